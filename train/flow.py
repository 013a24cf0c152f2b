"""Train RAFT-small on rendered street scenes and real frames, then export it (Hydra; conf/train_flow.yaml).

Run from the repository root (CPU work: be nice to other users of the machine)::

    nice -n 10 python -m train.flow                 # train (resumes run_dir/ckpt.pt), then export
    python -m train.flow export_only=true           # only export the last checkpoint to models/
    nice -n 10 python -m train.flow export.onnx=null  # train only (the weights; export later as above)

The shipped weights add RAFT's convex upsampler to those, trained alone on the frozen body
(``mask_hidden``, ``trainable``; models/MODEL_CARD.md), then fine-tune the whole network at the scale
``flow=raft`` runs at (0.75 of KITTI's size: the half-size pool upscaled 1.23-1.74x). The whole
chain, each stage from the last one's weights, the last writing ``models/``::

    nice -n 10 python -m train.flow out_weights=runs/train_flow/raft_small.pt export.onnx=runs/train_flow/raft_small.onnx
    nice -n 10 python -m train.flow mask_hidden=128 trainable=mask_predictor \
        init_weights=runs/train_flow/raft_small.pt run_dir=runs/train_flow_convex \
        out_weights=runs/train_flow_convex/raft_small.pt export.onnx=runs/train_flow_convex/raft_small.onnx \
        'stages=[{steps: 2500, lr: 4.0e-4, warmup: 100, real_fraction: 0.2}]'
    nice -n 10 python -m train.flow mask_hidden=128 trainable=all \
        init_weights=runs/train_flow_convex/raft_small.pt run_dir=runs/train_flow_s075 \
        'stages=[{steps: 1500, lr: 1.0e-4, warmup: 100, real_fraction: 0.35}]' 'augment.scale_log2=[0.3,0.8]'

Data:

- **Synthetic** (supervised): ``synthetic.pairs`` scene pairs of the built-in renderer, source seed
  ``synthetic.source_seed`` (>= 20; evaluation uses source seeds 0-2, tuning 5-16, flow
  validation ``val.source_seed``), at ``synthetic.scale`` of KITTI's 1242x375 (the resolution the
  flow stage runs RAFT at); odd pairs with randomised appearance. Both directions of every pair are
  used (the renderer's flow is current -> previous; the reverse pair's target comes from the
  reverse render, see :func:`render_pool`). Rendered once into shards under ``run_dir``.
- **Real** (distillation, RAFT fine-tuning stage): the frames ``real.sources`` names (drive 0028,
  DDAD scene_01, KITTI 2015 000000 — never the LiDAR drive 0023, the real evaluation), resized so
  the focal length is ``real.focal_px`` (KITTI at half size); targets are DeepFlow's forward-backward
  checked flow (``conf/flow/deepflow.yaml``) on the pixels whose round trip closes within
  ``real.max_fb_px``, both directions. Computed once and cached.

Schedule (RAFT, Teed & Deng 2020, scaled to a CPU): ``stages`` run one after the other, each with
AdamW, a linear warm-up and a linear decay to zero, and its own share of real samples
(``real_fraction``): a long synthetic stage, then a shorter fine-tuning stage that mixes in the real
frames at a lower learning rate (RAFT's Chairs -> Things -> KITTI). Loss: RAFT's sequence loss
(L1 end-point error of every recurrent update weighted ``gamma^(N - i - 1)``) on valid pixels.
Augmentation as RAFT: colour jitter (sometimes different for the two images), random scale,
occluding patches in the second image (eraser), horizontal flips, random crops.

Checkpoints (model, optimiser, step, history) every ``ckpt_every`` steps to ``run_dir/ckpt.pt``,
and a copy at the end of each stage (``stage{k}.pt``); a new run with the same ``run_dir`` resumes.
Every ``val.every`` steps the EPE on held-out renders is logged. At the end the weights go to
``out_weights`` (float16) and ONNX (:func:`monostixels.inputs.raft.export_onnx`), with an INT8 copy
(``export.int8``, :func:`monostixels.inputs.raft.quantize_onnx`; the activation ranges from the
first pairs of the real sources at the scale ``flow=raft`` runs at).

Convention: ``image1`` = current, ``image2`` = previous, output current -> previous (``x_prev = x + f``).
"""
from __future__ import annotations

import logging
import math
import shutil
import time
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from monostixels._checks import InputError, one_line_errors
from monostixels.data.synthetic import SOURCE_SEED_STRIDE, render_pair
from monostixels.inputs.raft import RAFT_MIN_SIZE, RAFT_MULTIPLE, RaftFlow, build_raft, export_onnx, load_raft_weights, mask_hidden_of, quantize_onnx

logger = logging.getLogger("train.flow")

__all__ = ["main", "Sample", "render_pool", "real_pool", "augment", "sample_batch", "sequence_loss", "export",
           "calibration_pairs", "validate"]

#: A training sample: images (3, H, W) uint8 current and previous, flow (2, H, W) float16 current ->
#: previous (px), valid (H, W) bool.
Sample = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


def _u8(image: torch.Tensor) -> torch.Tensor:
    return (image.clamp(0, 1) * 255 + 0.5).to(torch.uint8)


def _pack(cur: torch.Tensor, prev: torch.Tensor, flow: torch.Tensor, valid: torch.Tensor) -> Sample:
    return _u8(cur), _u8(prev), flow.half(), valid.bool()


def _render_sample(scene: int, scale: float, appearance: int | None) -> list[Sample]:
    """Both directions of one synthetic pair: (cur, prev) with the renderer's flow, and (prev, cur)
    with the flow of the same scene rendered with the motion inverted (``render_pair(reverse=True)``
    does not exist: the reverse target is the forward flow pushed through the forward flow, kept
    only where that is consistent, see below)."""
    p = render_pair(scene, scale=scale, appearance_seed=appearance)
    out = [_pack(p.image, p.image_prev, p.gt.flow, p.gt.flow_valid)]
    # Reverse direction: a pixel x of the current image lands on x + f(x) in the previous one, so
    # the previous image's pixel nearest to x + f(x) flows back by -f(x). Splat to the nearest
    # pixel, keep one-to-one hits of valid vectors only (occluded pixels get no target).
    f, v = p.gt.flow, p.gt.flow_valid
    H, W = v.shape
    vv, uu = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    up = (uu + f[0]).round().long()
    vp = (vv + f[1]).round().long()
    inside = v & (up >= 0) & (up < W) & (vp >= 0) & (vp < H)
    idx = (vp * W + up)[inside]
    back = torch.zeros(2, H * W)
    hits = torch.zeros(H * W)
    back[0].index_put_((idx,), -f[0][inside], accumulate=True)
    back[1].index_put_((idx,), -f[1][inside], accumulate=True)
    hits.index_put_((idx,), torch.ones_like(idx, dtype=torch.float32), accumulate=True)
    ok = hits == 1
    # Sub-pixel: the splat target is off by the rounding of x + f (< 0.5 px per axis); correct it
    # to first order by the offset between the pixel and the exact landing point.
    frac_u = torch.zeros(H * W)
    frac_v = torch.zeros(H * W)
    frac_u.index_put_((idx,), ((uu + f[0]) - up)[inside], accumulate=True)
    frac_v.index_put_((idx,), ((vv + f[1]) - vp)[inside], accumulate=True)
    back[0] += frac_u
    back[1] += frac_v
    back = torch.where(ok[None], back, torch.zeros(()))
    out.append(_pack(p.image_prev, p.image, back.view(2, H, W), ok.view(H, W)))
    return out


def render_pool(cfg: DictConfig) -> list[Sample]:
    """The synthetic training samples (both directions of ``cfg.synthetic.pairs`` pairs).

    Rendered in shards of ``cfg.synthetic.shard`` pairs cached under ``run_dir`` (rendering is the
    slow part of a first start; an interrupted render resumes at the next shard)."""
    sc = cfg.synthetic
    n, shard = int(sc.pairs), int(sc.shard)
    root = Path(cfg.run_dir) / "pool"
    root.mkdir(parents=True, exist_ok=True)
    pool: list[Sample] = []
    for s0 in tqdm(range(0, n, shard), desc="synthetic shards", leave=False):
        s1 = min(n, s0 + shard)
        path = root / f"syn_s{int(sc.source_seed)}_x{float(sc.scale)}_{s0:05d}_{s1:05d}.pt"
        if path.is_file():
            pool += torch.load(path, weights_only=True)
            continue
        part: list[Sample] = []
        for i in range(s0, s1):
            scene = int(sc.source_seed) * SOURCE_SEED_STRIDE + i
            app = scene if (bool(sc.randomise_appearance) and i % 2 == 1) else None
            part += _render_sample(scene, float(sc.scale), app)
        tmp = path.with_suffix(".pt.tmp")
        torch.save(part, tmp)
        tmp.replace(path)
        pool += part
    return pool


def _resize_image(image: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    return F.interpolate(image[None], size=size, mode="area")[0] if image.shape[-2:] != size else image


def real_pool(cfg: DictConfig) -> list[Sample]:
    """Distillation samples of the real frames (module docstring), cached in ``run_dir/pool``."""
    rc = cfg.real
    path = Path(cfg.run_dir) / "pool" / f"real_f{float(rc.focal_px)}_fb{float(rc.max_fb_px)}.pt"
    if path.is_file():
        return torch.load(path, weights_only=True)
    from monostixels.core.energy import load_config_group
    from monostixels.build import build_source
    from monostixels.inputs.confidence import fb_consistency_error
    from monostixels.inputs.flow import compute_flow
    from monostixels.inputs.flow_config import flow_params

    teacher = flow_params(load_config_group("flow", "deepflow"))
    crop_h, crop_w = int(cfg.crop[0]), int(cfg.crop[1])
    pool: list[Sample] = []
    for src_cfg in rc.sources:
        d = OmegaConf.to_container(src_cfg, resolve=True)
        if "0023" in str(d.get("root", "")) or "lidar" in str(d.get("root", "")):
            raise InputError(f"real.sources: {d.get('root')} is the LiDAR evaluation drive; never train on it")
        src = build_source(d)
        for pair in tqdm(src, desc=f"teacher flow {d['name']}", leave=False):
            H, W = pair.size
            fx = float(pair.camera.K[0, 0])
            s = min(1.0, max(float(rc.focal_px) / fx, crop_h / H, crop_w / W))
            size = (round(H * s), round(W * s))
            # The teacher runs at twice the target resolution (at most full size), then area-downscaled.
            ts = min(1.0, 2.0 * s)
            tsize = (round(H * ts), round(W * ts))
            a, b = _resize_image(pair.image, tsize), _resize_image(pair.image_prev, tsize)
            fwd = compute_flow(a, b, teacher)
            bwd = compute_flow(b, a, teacher)
            for cur, prev, f, g in ((a, b, fwd, bwd), (b, a, bwd, fwd)):
                err = fb_consistency_error(f, g)
                ok = (err < float(rc.max_fb_px)).float()
                small_f = _resize_image(f, size) * (size[1] / tsize[1])
                small_ok = _resize_image(ok[None], size)[0] > 0.999
                pool.append(_pack(_resize_image(cur, size), _resize_image(prev, size), small_f, small_ok))
            logger.info("teacher %s at %dx%d: %.0f %% trusted", pair.name, size[1], size[0],
                        100 * float(pool[-1][3].float().mean()))
    tmp = path.with_suffix(".pt.tmp")
    torch.save(pool, tmp)
    tmp.replace(path)
    return pool


def _colour_jitter(img: torch.Tensor, gen: torch.Generator, strength: float) -> torch.Tensor:
    """Brightness, contrast, saturation, per-channel gain and gamma on a (3, H, W) image in [0, 1]."""
    def u(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((), generator=gen))
    s = strength
    img = img * u(1 - 0.4 * s, 1 + 0.4 * s)
    mean = img.mean()
    img = (img - mean) * u(1 - 0.4 * s, 1 + 0.4 * s) + mean
    grey = img.mean(0, keepdim=True)
    img = (img - grey) * u(1 - 0.4 * s, 1 + 0.4 * s) + grey
    img = img * torch.tensor([u(1 - 0.1 * s, 1 + 0.1 * s) for _ in range(3)])[:, None, None]
    return img.clamp(0, 1) ** u(1 - 0.3 * s, 1 + 0.3 * s)


def augment(sample: Sample, crop: tuple[int, int], gen: torch.Generator, aug: DictConfig | dict[str, Any]
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """One augmented crop: cur, prev (3, h, w) float [0, 1], flow (2, h, w), valid (h, w) bool.

    Random scale ``2^U(scale_log2)`` (flow vectors scaled with the image; valid pixels by nearest
    sampling, so a resampled vector never mixes a valid and an invalid one), random crop, colour
    jitter (asymmetric with probability ``asym_prob``), eraser patches in the previous image
    (RAFT: occlusions the network must fill in), horizontal flip (flow x negated).
    """
    a, b, f, v = sample
    a, b, f = a.float() / 255, b.float() / 255, f.float()
    h, w = crop
    H, W = a.shape[-2:]
    lo, hi = aug["scale_log2"]
    smin = max(h / H, w / W) * 1.001
    s = max(smin, 2.0 ** (lo + (hi - lo) * float(torch.rand((), generator=gen))))
    if abs(s - 1.0) > 1e-3:
        size = (max(h, round(H * s)), max(w, round(W * s)))
        sy, sx = size[0] / H, size[1] / W
        a = F.interpolate(a[None], size=size, mode="bilinear", align_corners=False)[0]
        b = F.interpolate(b[None], size=size, mode="bilinear", align_corners=False)[0]
        f = F.interpolate(f[None], size=size, mode="nearest")[0] * torch.tensor([sx, sy])[:, None, None]
        v = F.interpolate(v[None, None].float(), size=size, mode="nearest")[0, 0] > 0.5
        H, W = size
    y = int(torch.randint(H - h + 1, (1,), generator=gen))
    x = int(torch.randint(W - w + 1, (1,), generator=gen))
    a, b = a[:, y:y + h, x:x + w], b[:, y:y + h, x:x + w]
    f, v = f[:, y:y + h, x:x + w].clone(), v[y:y + h, x:x + w]
    strength = float(aug["colour"])
    if float(torch.rand((), generator=gen)) < float(aug["asym_prob"]):
        a, b = _colour_jitter(a, gen, strength), _colour_jitter(b, gen, strength)
    else:
        state = gen.get_state()
        a = _colour_jitter(a, gen, strength)
        gen.set_state(state)
        b = _colour_jitter(b, gen, strength)
    if float(torch.rand((), generator=gen)) < float(aug["eraser_prob"]):
        b = b.clone()
        mean = b.mean((1, 2))
        for _ in range(int(torch.randint(1, 3, (1,), generator=gen))):
            ey, ex = int(torch.randint(h, (1,), generator=gen)), int(torch.randint(w, (1,), generator=gen))
            dy, dx = (int(torch.randint(25, 60, (1,), generator=gen)) for _ in range(2))
            b[:, ey:ey + dy, ex:ex + dx] = mean[:, None, None]
    if float(torch.rand((), generator=gen)) < 0.5:
        a, b, f, v = a.flip(-1), b.flip(-1), f.flip(-1), v.flip(-1)
        f[0] = -f[0]
    return a, b, f, v


def sample_batch(pools: list[list[Sample]], weights: list[float], batch_size: int, crop: tuple[int, int],
                 gen: torch.Generator, aug: DictConfig | dict[str, Any]):
    """A batch (B, 3, h, w) x2, flow (B, 2, h, w), valid (B, h, w): each item from pool ``k`` with
    probability ``weights[k]``, augmented by :func:`augment`."""
    w = torch.tensor(weights, dtype=torch.float64)
    items = []
    for _ in range(batch_size):
        k = int(torch.multinomial(w, 1, generator=gen))
        pool = pools[k]
        items.append(augment(pool[int(torch.randint(len(pool), (1,), generator=gen))], crop, gen, aug))
    return tuple(torch.stack(t) for t in zip(*items))


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


def validation_pairs(cfg: DictConfig) -> list[Sample]:
    """Held-out renders (source seed ``val.source_seed``, whole images), cached in ``run_dir/pool``."""
    vc = cfg.val
    path = Path(cfg.run_dir) / "pool" / f"val_s{int(vc.source_seed)}_n{int(vc.pairs)}_x{float(cfg.synthetic.scale)}.pt"
    if path.is_file():
        return torch.load(path, weights_only=True)
    pool = []
    for i in range(int(vc.pairs)):
        p = render_pair(int(vc.source_seed) * SOURCE_SEED_STRIDE + i, scale=float(cfg.synthetic.scale))
        pool.append(_pack(p.image, p.image_prev, p.gt.flow, p.gt.flow_valid))
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(pool, path)
    return pool


def validate(model: torch.nn.Module, pairs: list[Sample], updates: int) -> float:
    """Mean EPE (px) over the valid pixels of whole held-out images, ``updates`` recurrent steps (float32,
    on the model's device)."""
    from monostixels.inputs.raft import pad_images

    was = model.training
    model.eval()
    dev = next(model.parameters()).device
    errs = []
    with torch.inference_mode():
        for a, b, f, v in pairs:
            (pa, pb), (H, W) = pad_images(a[None].float() / 255, b[None].float() / 255)
            pa, pb = pa.to(dev), pb.to(dev)
            out = model(2 * pa - 1, 2 * pb - 1, num_flow_updates=updates)[-1][0, :, :H, :W].cpu()
            errs.append(float((out - f.float()).norm(dim=0)[v].mean()))
    model.train(was)
    return float(np.mean(errs))


def calibration_pairs(cfg: DictConfig) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Image pairs (3, h, w) in [0, 1] for the INT8 copy's activation ranges: the first
    ``export.calibration_per_source`` pairs of each of ``real.sources`` (the training's real frames, never
    drive 0023), each at ``export.calibration_scale`` of its size (where ``flow=raft`` runs the network)."""
    from monostixels.build import build_source

    per, scale = int(cfg.export.calibration_per_source), float(cfg.export.calibration_scale)
    pairs = []
    for src_cfg in cfg.real.sources:
        d = OmegaConf.to_container(src_cfg, resolve=True)
        if "0023" in str(d.get("root", "")) or "lidar" in str(d.get("root", "")):
            raise InputError(f"real.sources: {d.get('root')} is the LiDAR evaluation drive; never calibrate on it")
        for k, pair in enumerate(build_source(d)):
            if k >= per:
                break
            H, W = pair.size
            size = (round(H * scale), round(W * scale))
            pairs.append((_resize_image(pair.image.float(), size), _resize_image(pair.image_prev.float(), size)))
    return pairs


def export(cfg: DictConfig) -> None:
    """Export ``cfg.out_weights`` to ONNX (``cfg.export``), and with ``export.int8`` its INT8 copy beside it
    (``<name>_int8.onnx``, the file ``flow.precision=int8`` looks for beside the weights). With
    ``export.onnx: null`` only the weights are kept (a run to be exported later with ``export_only``)."""
    if not cfg.export.onnx:
        if cfg.export_only:
            raise InputError("export_only=true needs export.onnx: the ONNX file to write")
        logger.info("no ONNX export (export.onnx is null): the weights are %s", cfg.out_weights)
        return
    model = load_raft_weights(cfg.out_weights, cfg.size)
    path = export_onnx(RaftFlow(model, int(cfg.export.updates)), cfg.export.onnx, int(cfg.export.height),
                       int(cfg.export.width), half_weights=bool(cfg.export.get("half_weights", False)))
    logger.info("ONNX written: %s (%.1f MB)", path, path.stat().st_size / 1e6)
    if cfg.export.get("int8", False):
        quantize_onnx(path, path.with_name(path.stem + "_int8.onnx"), calibration_pairs(cfg))


def _lr_factor(step: int, warmup: int, steps: int) -> float:
    """Linear warm-up over ``warmup`` steps, then linear decay to zero at ``steps`` (RAFT's one-cycle, linear)."""
    if step < warmup:
        return (step + 1) / warmup
    return max(0.0, (steps - step) / max(1, steps - warmup))


def _device(cfg: DictConfig) -> tuple[torch.device, bool]:
    """The training device (``cfg.device``: cpu | cuda | auto) and whether bf16 autocast is on (``cfg.amp``)."""
    name = str(cfg.get("device", "cpu"))
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name not in ("cpu", "cuda"):
        raise InputError(f"device: cpu, cuda or auto, got {name!r}")
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("device=cuda: torch sees no CUDA device here (device=cpu or device=auto)")
    amp = str(cfg.get("amp", "none"))
    if amp not in ("none", "bf16"):
        raise InputError(f"amp: none or bf16, got {amp!r}")
    return torch.device(name), amp == "bf16"


def _stage_at(stages: list[dict[str, Any]], step: int) -> tuple[int, int]:
    """(index of the stage that ``step`` belongs to, the stage's first global step); (len, total) when done."""
    start = 0
    for k, st in enumerate(stages):
        if step < start + int(st["steps"]):
            return k, start
        start += int(st["steps"])
    return len(stages), start


def write_weights(model: torch.nn.Module, out: Path) -> None:
    """The state dict as float16 (loaded back into float32 parameters): keeps shipped models small."""
    out.parent.mkdir(parents=True, exist_ok=True)
    torch.save({k: (v.half() if v.is_floating_point() else v).cpu() for k, v in model.state_dict().items()}, out)


@hydra.main(config_path="../conf", config_name="train_flow", version_base=None)
@one_line_errors("train.flow")
def main(cfg: DictConfig) -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    run_dir = Path(cfg.run_dir)
    ckpt_path = run_dir / "ckpt.pt"
    if cfg.export_only:
        if ckpt_path.is_file():
            ck = torch.load(ckpt_path, map_location="cpu", weights_only=False)
            model = build_raft(cfg.size, mask_hidden_of(ck["model"]))
            model.load_state_dict(ck["model"])
            write_weights(model, Path(cfg.out_weights))
        export(cfg)
        return
    torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(int(cfg.seed))
    crop = (int(cfg.crop[0]), int(cfg.crop[1]))
    if any(c % RAFT_MULTIPLE or c < RAFT_MIN_SIZE for c in crop):
        raise InputError(f"crop: both sides must be multiples of {RAFT_MULTIPLE} and >= {RAFT_MIN_SIZE}, got {crop}")
    stages = [dict(s) for s in OmegaConf.to_container(cfg.stages, resolve=True)]
    total = sum(int(s["steps"]) for s in stages)

    run_dir.mkdir(parents=True, exist_ok=True)
    dev, bf16 = _device(cfg)
    # On the device before the optimiser is made: its state (and a resumed one) then lives there too.
    model = build_raft(cfg.size, int(cfg.get("mask_hidden", 0))).to(dev)
    trainable = str(cfg.get("trainable", "all"))
    if trainable == "mask_predictor":
        # The convex upsampler alone, on a trained body: the 1/8-resolution flow stays what it was, and a
        # step costs about a quarter (no backward pass through the body).
        if getattr(model, "mask_predictor", None) is None:
            raise InputError("trainable=mask_predictor: the model has no convex upsampler (set mask_hidden > 0)")
        for name, prm in model.named_parameters():
            prm.requires_grad_(name.startswith("mask_predictor."))
    elif trainable != "all":
        raise InputError(f"trainable: all or mask_predictor, got {trainable!r}")
    params = [q for q in model.parameters() if q.requires_grad]
    opt = torch.optim.AdamW(params, lr=float(stages[0]["lr"]), weight_decay=float(cfg.weight_decay), eps=1e-8)
    step, history, val_history = 0, [], []
    if cfg.resume and ckpt_path.is_file():
        ck = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optim"])
        step, history = int(ck["step"]), list(ck.get("history", []))
        val_history = list(ck.get("val_history", []))
        logger.info("resumed from %s at step %d", ckpt_path, step)
    elif cfg.init_weights:
        init = load_raft_weights(cfg.init_weights, cfg.size).state_dict()
        missing, unexpected = model.load_state_dict(init, strict=False)
        # Only a head the initial weights lack may start from scratch (a convex upsampler added to a
        # bilinear RAFT-small); anything else is the wrong architecture.
        if unexpected or any(not k.startswith("mask_predictor.") for k in missing):
            raise InputError(f"init_weights: {cfg.init_weights!r} does not fit the configured RAFT-{cfg.size} "
                             f"(missing {missing[:3]}, unexpected {unexpected[:3]})")
        logger.info("initialised from %s%s", cfg.init_weights,
                    f" (convex upsampler from scratch: {len(missing)} tensors)" if missing else "")
    gen = torch.Generator().manual_seed(int(cfg.seed) + step)

    synthetic = render_pool(cfg)
    needs_real = any(float(s.get("real_fraction", 0.0)) > 0 for s in stages[_stage_at(stages, step)[0]:])
    real = real_pool(cfg) if needs_real else []
    val_pairs = validation_pairs(cfg)
    logger.info("pools: %d synthetic samples, %d real samples, %d validation pairs", len(synthetic), len(real),
                len(val_pairs))

    def save(path: Path = ckpt_path) -> None:
        tmp = path.with_suffix(".pt.tmp")
        torch.save({"model": model.state_dict(), "optim": opt.state_dict(), "step": step, "history": history,
                    "val_history": val_history, "config": OmegaConf.to_container(cfg, resolve=True)}, tmp)
        tmp.replace(path)

    t0 = time.time()
    model.train()
    bar = tqdm(total=total, initial=step, desc="train RAFT-small", mininterval=30)
    ema = None
    while step < total:
        if cfg.max_minutes is not None and time.time() - t0 > 60.0 * float(cfg.max_minutes):
            logger.info("time limit of %s minutes reached at step %d", cfg.max_minutes, step)
            break
        k, start = _stage_at(stages, step)
        st = stages[k]
        for g in opt.param_groups:
            g["lr"] = float(st["lr"]) * _lr_factor(step - start, int(st["warmup"]), int(st["steps"]))
        frac = float(st.get("real_fraction", 0.0)) if real else 0.0
        a, b, f, v = sample_batch([synthetic, real] if frac > 0 else [synthetic], [1 - frac, frac] if frac > 0 else [1.0],
                                  int(cfg.batch_size), crop, gen, cfg.augment)
        a, b, f, v = (t.to(dev, non_blocking=True) for t in (a, b, f, v))
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=bf16):
            preds = model(2 * a - 1, 2 * b - 1, num_flow_updates=int(cfg.train_updates))
        # The loss in float32 whatever the forward ran in (bf16 keeps 3 significant digits).
        loss, epe = sequence_loss([q.float() for q in preds], f, v, float(cfg.gamma), float(cfg.max_flow))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, float(cfg.grad_clip))
        opt.step()
        step += 1
        ema = epe if ema is None else 0.98 * ema + 0.02 * epe
        history.append((step, loss.item(), epe))
        bar.update(1)
        bar.set_postfix(stage=k, loss=f"{loss.item():.2f}", epe=f"{ema:.2f}")
        if step % int(cfg.val.every) == 0 or step == total:
            val = validate(model, val_pairs, int(cfg.val.updates))
            val_history.append((step, val))
            logger.info("step %d (stage %d, %.1f h): training EPE (ema) %.2f px, validation EPE %.3f px", step, k,
                        (time.time() - t0) / 3600, ema, val)
        if step % int(cfg.ckpt_every) == 0:
            save()
        k_next, _ = _stage_at(stages, step)
        if k_next != k:
            save()
            shutil.copyfile(ckpt_path, run_dir / f"stage{k}.pt")
            logger.info("stage %d done at step %d: %s", k, step, run_dir / f"stage{k}.pt")
    bar.close()
    save()
    if step < total:
        return
    model.eval()
    write_weights(model, Path(cfg.out_weights))
    logger.info("step %d, training EPE (ema) %.2f px; weights written: %s", step, ema if ema is not None else math.nan,
                cfg.out_weights)
    export(cfg)


if __name__ == "__main__":
    main()
