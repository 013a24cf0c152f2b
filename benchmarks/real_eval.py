"""Sweep the `semantic=none` type choice (``prior.alpha_dyn``) on real and synthetic frames.

Runs :func:`monostixels.eval.evaluate.evaluate` (the code behind ``monostixels eval``) once per
value of ``prior.alpha_dyn`` on one data configuration, and prints the headline numbers of each
report. The optical flow does not depend on the priors, so it is computed once per frame pair and
cached on disk (``--cache``); every later value only re-runs motion, solver and metrics. The
reports are identical to ``monostixels eval`` with the same overrides (same flow, same code path).

Commands (repository root, 2 shared cores: keep torch single-threaded):
    OMP_NUM_THREADS=1 nice -n 10 python -m benchmarks.real_eval --alpha 0 0.5 1 2 -- \
        data=ddad data.root=../shared/data/ddad_dgp flow=deepflow semantic=none motion=gt
    OMP_NUM_THREADS=1 nice -n 10 python -m benchmarks.real_eval --alpha 0 0.5 1 2 -- \
        data=kitti_raw data.root=../shared/data/kitti_raw flow=deepflow semantic=none motion=mono \
        data.only_labelled=true
    OMP_NUM_THREADS=1 nice -n 10 python -m benchmarks.real_eval --alpha 0 0.5 1 2 -- \
        data=synthetic data.frames=4 flow=gt semantic=none motion=gt
"""
from __future__ import annotations

import argparse
import hashlib
import json
import logging
import tempfile
from pathlib import Path
from typing import Any

import torch

import monostixels.pipeline as pipeline_module
from monostixels.data.base import FramePair
from monostixels.eval.evaluate import evaluate, write_report
from monostixels.inputs.flow import FlowResult, estimate_flow
from monostixels.pipeline import load_config

__all__ = ["cached_flow", "summary", "main"]

logger = logging.getLogger(__name__)

#: Default folder of the flow cache (one .pt file per frame pair and flow configuration).
DEFAULT_CACHE = Path(tempfile.gettempdir()) / "monostixels_flow_cache"


def cached_flow(cache: Path):
    """A drop-in for :func:`estimate_flow` that stores each result under ``cache``.

    The key is the pair's name, image size and a checksum of its pixels, the full flow config and
    a checksum of the flow and data-source code, so a different backend, setting or code version
    never reuses a stale result.
    """

    # The flow code (backends, confidence, and the data sources that make gt flow) is part of the
    # key: a cached result of older code is never reused.
    pkg = Path(pipeline_module.__file__).parent
    code = hashlib.sha1(b"".join(p.read_bytes() for d in ("inputs", "data") for p in sorted((pkg / d).glob("*.py"))))
    code = code.hexdigest()[:12]

    def _estimate(pair: FramePair, cfg: Any) -> FlowResult:
        from omegaconf import OmegaConf

        cfg_txt = json.dumps(OmegaConf.to_container(cfg, resolve=True) if hasattr(cfg, "keys") else str(cfg),
                             sort_keys=True)
        img_sum = float(pair.image[:, ::17, ::17].sum())  # cheap guard against name collisions
        key = hashlib.sha1(f"{pair.name}|{tuple(pair.size)}|{img_sum:.4f}|{cfg_txt}|{code}".encode()).hexdigest()[:16]
        path = cache / f"{key}.pt"
        if path.exists():
            d = torch.load(path)
            return FlowResult(flow=d["flow"], cov=d["cov"], seconds=d["seconds"], backend=d["backend"])
        res = estimate_flow(pair, cfg)
        cache.mkdir(parents=True, exist_ok=True)
        torch.save({"flow": res.flow, "cov": res.cov, "seconds": res.seconds, "backend": res.backend}, path)
        return res

    return _estimate


def ground_from_motion() -> None:
    """Experimental (a proposal, not the package's behaviour): with ``motion=mono``, solve with the
    ground normal fitted by the motion estimator instead of ``camera.ground_normal``.

    The ``mono`` estimator fits the road plane to get the metric scale (``fit_ground``) but keeps
    the fitted normal to itself; this patch records it and swaps it into the pair's camera before
    the solver runs (``Pipeline.motion_for`` runs before ``solve``).
    """
    import dataclasses

    import numpy as np

    import monostixels.inputs.motion as motion_module

    fit = motion_module.fit_ground
    last: dict[str, np.ndarray] = {}

    def _fit(*a: Any, **k: Any) -> tuple[np.ndarray, np.ndarray]:
        m, inl = fit(*a, **k)
        last["m"] = m
        return m, inl

    motion_module.fit_ground = _fit
    orig = pipeline_module.Pipeline.motion_for

    def motion_for(self: Any, pair: FramePair, flow: FlowResult, semantic: torch.Tensor | None, *args: Any,
                   **kwargs: Any) -> Any:
        last.clear()
        est = orig(self, pair, flow, semantic, *args, **kwargs)
        if "m" in last and not est.degenerate:
            n = torch.as_tensor(last["m"] / np.linalg.norm(last["m"]), dtype=pair.camera.K.dtype)
            pair.camera = dataclasses.replace(pair.camera, ground_normal=n)
        return est

    pipeline_module.Pipeline.motion_for = motion_for


def summary(report: dict) -> dict[str, Any]:
    """The headline numbers: rel per split for both methods, bottoms, motion, compactness."""
    out: dict[str, Any] = {"frames": report["frames"]}
    for m in ("monostixels", "sfm"):
        for s in ("overall", "static", "moving"):
            r = report["methods"][m].get(s)
            if r:
                out[f"{m}.{s}.rel"] = r["rel"]
                out[f"{m}.{s}.d1.25"] = r["d1.25"]
                out[f"{m}.{s}.n"] = r["n"]
    out["compactness"] = report["methods"]["monostixels"]["compactness"]
    if "bottoms" in report:
        out.update({f"bottoms.{k}": v for k, v in report["bottoms"].items()})
    if "motion" in report:
        out.update({f"motion.{k}": v for k, v in report["motion"].items()})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--alpha", type=float, nargs="+", default=[0.0, 0.5, 1.0, 2.0],
                    help="values of prior.alpha_dyn to evaluate")
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help="flow cache folder")
    ap.add_argument("--out", type=Path, default=None, help="folder for one JSON report per value")
    ap.add_argument("--ground-from-motion", action="store_true",
                    help="experimental: solve with the ground normal fitted by motion=mono")
    ap.add_argument("overrides", nargs="*", help="config overrides as for `monostixels eval`")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    from monostixels.build import build_source

    pipeline_module.estimate_flow = cached_flow(args.cache)  # the Pipeline looks it up at call time
    if args.ground_from_motion:
        ground_from_motion()
    rows = []
    for a in args.alpha:
        cfg = load_config([*args.overrides, f"prior.alpha_dyn={a}"])
        report = evaluate(cfg, build_source(cfg), dataset=str(cfg.data.name), progress=False)
        if args.out is not None:
            write_report(report, args.out / f"alpha_dyn_{a:g}.json")
        s = summary(report)
        rows.append((a, s))
        print(f"alpha_dyn={a:g}: " + "  ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}"
                                                 for k, v in s.items()), flush=True)


if __name__ == "__main__":
    main()
