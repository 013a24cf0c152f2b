"""Train RAFT-small on synthetic frame pairs, then export it to ONNX (Hydra; conf/train_flow.yaml).

Run from the repository root (it is CPU work: be nice to other users of the machine):

    nice -n 10 python -m train.flow                       # train (resumes runs/train_flow/ckpt.pt)
    nice -n 10 python -m train.flow steps=4000 max_minutes=null
    python -m train.flow export_only=true                 # only export models/raft_small_synthetic.pt

Data: ``cfg.pairs`` scene pairs of the built-in renderer, synthetic source seed ``cfg.source_seed``
(>= 20 for the flow net; evaluation uses source seeds 0, 1, 2), rendered once at
``cfg.scale`` into an in-memory pool; every step draws a batch of random crops with random
horizontal flips (flow x negated). Loss: RAFT's sequence loss (L1 end-point error of every
recurrent update, weighted ``gamma^(N - i - 1)``) on pixels with valid ground-truth flow.
Optimiser: AdamW, linear warm-up then linear decay. A checkpoint (model, optimiser, step, pool
description) is written every ``ckpt_every`` steps to ``run_dir/ckpt.pt``; a new run with the same
``run_dir`` resumes from it. At the end the state dict goes to ``out_weights`` and the network
(``export.updates`` recurrent steps) is exported to ONNX at ``export.height x export.width``.

Convention: the network is trained as flow.py uses it — ``image1`` = current, ``image2`` =
previous, output current -> previous (``x_prev = x + f``).
"""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from monostixels.data.synthetic import SOURCE_SEED_STRIDE, render_pair
from monostixels.inputs.raft import RAFT_MIN_SIZE, RAFT_MULTIPLE, RaftFlow, build_raft, export_onnx, load_raft_weights

logger = logging.getLogger("train.flow")

__all__ = ["main", "render_pool", "sample_batch", "sequence_loss", "export"]


def render_pool(cfg: DictConfig) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]:
    """Render ``cfg.pairs`` synthetic pairs: (image_cur, image_prev (3, H, W), flow (2, H, W), valid (H, W)).

    The pool is cached in ``run_dir`` (rendering is the slow part of a resume)."""
    cache = Path(cfg.run_dir) / f"pool_s{cfg.source_seed}_n{cfg.pairs}_x{cfg.scale}_r{int(bool(cfg.randomise_appearance))}.pt"
    if cache.is_file():
        logger.info("training pairs from %s", cache)
        return torch.load(cache, weights_only=True)
    pool = []
    for i in tqdm(range(int(cfg.pairs)), desc="render training pairs", leave=False):
        scene = int(cfg.source_seed) * SOURCE_SEED_STRIDE + i
        # Odd pairs get randomised appearance (colours, textures, lighting) for robustness.
        app = scene if (cfg.randomise_appearance and i % 2 == 1) else None
        p = render_pair(scene, scale=float(cfg.scale), appearance_seed=app)
        pool.append((p.image, p.image_prev, p.gt.flow, p.gt.flow_valid))
    torch.save(pool, cache)
    return pool


def sample_batch(pool, batch_size: int, crop: tuple[int, int], gen: torch.Generator):
    """A batch of random crops (B, 3, h, w) x2, flow (B, 2, h, w), valid (B, h, w) with random h-flips."""
    h, w = crop
    cur, prev, flo, val = [], [], [], []
    for _ in range(batch_size):
        a, b, f, v = pool[int(torch.randint(len(pool), (1,), generator=gen))]
        H, W = a.shape[-2:]
        y = int(torch.randint(H - h + 1, (1,), generator=gen))
        x = int(torch.randint(W - w + 1, (1,), generator=gen))
        sl = (slice(None), slice(y, y + h), slice(x, x + w))
        a, b, f, v = a[sl], b[sl], f[sl].clone(), v[y:y + h, x:x + w]
        if bool(torch.rand((), generator=gen) < 0.5):
            # Mirror both images; the flow's x component changes sign.
            a, b, f, v = a.flip(-1), b.flip(-1), f.flip(-1), v.flip(-1)
            f[0] = -f[0]
        cur.append(a); prev.append(b); flo.append(f); val.append(v)
    return torch.stack(cur), torch.stack(prev), torch.stack(flo), torch.stack(val)


def sequence_loss(preds: list[torch.Tensor], flow: torch.Tensor, valid: torch.Tensor, gamma: float, max_flow: float):
    """RAFT sequence loss: sum_i gamma^(N-i-1) mean_valid |pred_i - flow|_1; also the final EPE (px)."""
    valid = valid & (flow.norm(dim=1) < max_flow)
    n = len(preds)
    denom = valid.sum().clamp_min(1)
    loss = flow.new_zeros(())
    for i, p in enumerate(preds):
        l1 = (p - flow).abs().sum(1)
        loss = loss + gamma ** (n - i - 1) * (l1 * valid).sum() / denom
    epe = ((preds[-1].detach() - flow).norm(dim=1) * valid).sum() / denom
    return loss, float(epe)


def export(cfg: DictConfig) -> None:
    """Export ``cfg.out_weights`` to ONNX (``cfg.export``)."""
    model = load_raft_weights(cfg.out_weights, cfg.size)
    path = export_onnx(RaftFlow(model, int(cfg.export.updates)), cfg.export.onnx, int(cfg.export.height), int(cfg.export.width))
    logger.info("ONNX written: %s (%.1f MB)", path, path.stat().st_size / 1e6)


def _lr_factor(step: int, warmup: int, steps: int) -> float:
    if step < warmup:
        return (step + 1) / warmup
    return max(0.0, (steps - step) / max(1, steps - warmup))


@hydra.main(config_path="../conf", config_name="train_flow", version_base=None)
def main(cfg: DictConfig) -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    if cfg.export_only:
        export(cfg)
        return
    torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(int(cfg.seed))
    crop = (int(cfg.crop[0]), int(cfg.crop[1]))
    if any(c % RAFT_MULTIPLE or c < RAFT_MIN_SIZE for c in crop):
        raise ValueError(f"crop: both sides must be multiples of {RAFT_MULTIPLE} and >= {RAFT_MIN_SIZE}, got {crop}")

    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    ckpt_path = run_dir / "ckpt.pt"
    model = build_raft(cfg.size)
    opt = torch.optim.AdamW(model.parameters(), lr=float(cfg.lr), weight_decay=float(cfg.weight_decay))
    step, history = 0, []
    if cfg.resume and ckpt_path.is_file():
        ck = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optim"])
        step, history = int(ck["step"]), list(ck.get("history", []))
        logger.info("resumed from %s at step %d", ckpt_path, step)
    gen = torch.Generator().manual_seed(int(cfg.seed) + step)

    run_dir.mkdir(parents=True, exist_ok=True)
    crop_ok = crop[0] <= round(375 * float(cfg.scale)) and crop[1] <= round(1242 * float(cfg.scale))
    if not crop_ok:
        raise ValueError(f"crop {crop} larger than the rendered images at scale {cfg.scale}")
    pool = render_pool(cfg)

    def save() -> None:
        tmp = ckpt_path.with_suffix(".pt.tmp")
        torch.save({"model": model.state_dict(), "optim": opt.state_dict(), "step": step, "history": history,
                    "config": OmegaConf.to_container(cfg, resolve=True)}, tmp)
        tmp.replace(ckpt_path)

    t0 = time.time()
    model.train()
    steps = int(cfg.steps)
    bar = tqdm(total=steps, initial=step, desc="train RAFT-small")
    ema = None
    while step < steps:
        if cfg.max_minutes is not None and time.time() - t0 > 60.0 * float(cfg.max_minutes):
            logger.info("time limit of %s minutes reached at step %d", cfg.max_minutes, step)
            break
        for g in opt.param_groups:
            g["lr"] = float(cfg.lr) * _lr_factor(step, int(cfg.warmup), steps)
        a, b, f, v = sample_batch(pool, int(cfg.batch_size), crop, gen)
        preds = model(2 * a - 1, 2 * b - 1, num_flow_updates=int(cfg.train_updates))
        loss, epe = sequence_loss(preds, f, v, float(cfg.gamma), float(cfg.max_flow))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), float(cfg.grad_clip))
        opt.step()
        step += 1
        ema = epe if ema is None else 0.95 * ema + 0.05 * epe
        history.append((step, float(loss), epe))
        bar.update(1)
        bar.set_postfix(loss=f"{float(loss):.2f}", epe=f"{ema:.2f}")
        if step % int(cfg.ckpt_every) == 0:
            save()
    bar.close()
    save()
    model.eval()
    out = Path(cfg.out_weights)
    out.parent.mkdir(parents=True, exist_ok=True)
    # float16 on disk (loaded back into float32 parameters): keeps all shipped models under 25 MB.
    torch.save({k: v.half() if v.is_floating_point() else v for k, v in model.state_dict().items()}, out)
    logger.info("step %d, training EPE (ema) %.2f px; weights written: %s", step, ema if ema is not None else math.nan, out)
    export(cfg)


if __name__ == "__main__":
    main()
