"""Flow quality of the backends on the built-in synthetic benchmark (table in docs/results.md).

EPE (mean end-point error, px) and Fl-all (KITTI outlier rule: error > 3 px and > 5 % of the
true flow) over pixels with valid ground-truth flow, and seconds per frame of the flow
computation alone (the covariance, shared by all backends, is timed separately), on synthetic
evaluation source seed 0 at full KITTI resolution 1242x375.

Command (repository root; the RAFT rows read models/raft_small.pt / .onnx, conf/flow/raft.yaml):

    nice -n 10 python -m benchmarks.flow_quality --frames 20

Results (2026-12-02), ``--frames 20`` at 1242x375, idle machine, the backends as configured in
conf/flow/ (DeepFlow and RAFT with 4 full-size refinement passes; RAFT at 0.75 of the size with its
convex upsampler); ``--cache`` lets the backends run in separate calls (``--backends deepflow,dis``
then ``--backends raft,raft_onnx``):

    | backend   | EPE (px) | Fl-all (%) | seconds / frame |
    |-----------|---------:|-----------:|----------------:|
    | deepflow  |     1.12 |        5.2 |            0.73 |
    | dis       |     1.42 |        6.7 |            0.04 |
    | raft      |     1.17 |        4.5 |            0.79 |
    | raft_onnx |     1.17 |        4.5 |            1.20 |
    structure-tensor covariance: 0.02 s / frame

``raft_onnx``'s graph runs a pair both ways as one batch (the pipeline's forward-backward check);
one direction alone costs it that time. ``--pipeline`` adds the flow stage as the pipeline runs it
(``estimate_flow``: both directions where ``fb_consistency`` is on, refinements, covariance);
``--frames 6 --backends raft,raft_onnx,deepflow --pipeline``, idle machine, 2026-12-02: raft 1.70,
raft_onnx 1.31, deepflow 1.47 s a frame. ``raft_int8`` is the INT8 copy (``models/raft_small_int8.onnx``,
what ``flow=raft`` runs on a CPU): 2026-12-03, ``--frames 20 --backends raft_onnx,raft_int8,deepflow
--pipeline`` on a host twice as slow, EPE 1.17 / 1.22 / 1.12 px, seconds 2.46 / 1.49 / 1.48, pipeline
2.62 / 1.91 / 2.73.

RAFT = models/raft_small.pt / .onnx (models/MODEL_CARD.md: ``python -m train.flow``, 5000 steps, the upsampler's 2500 and 1500 at the running scale).
``deepflow`` is guided by DIS's matches (``flow.matches=dis``): OpenCV's DeepFlow alone is the
variational part without DeepMatching and loses the large near-field displacements of the road.
"""
from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf
from tqdm import tqdm

from monostixels.core.energy import load_config_group
from monostixels.data.synthetic import SyntheticSource
from monostixels.inputs.confidence import flow_covariance
from monostixels.inputs.flow import compute_flow, confidence_params, estimate_flow, flow_metrics
from monostixels.inputs.flow_backends import resolve_path


def main() -> None:
    ap = argparse.ArgumentParser(description="EPE / Fl-all / seconds of the flow backends on synthetic frames")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0, help="synthetic source seed (evaluation: 0, 1, 2)")
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--backends", default="deepflow,dis,raft,raft_onnx,raft_int8")
    ap.add_argument("--cache", default=None,
                    help="folder for rendered frames and per-backend results (lets backends run in separate calls; "
                         "the table then lists every backend measured there)")
    ap.add_argument("--pipeline", action="store_true",
                    help="also time the flow stage as the pipeline runs it (estimate_flow: both directions where "
                         "the backend's fb_consistency is on, the refinement and the covariance)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    cfgs = {}
    for b in args.backends.split(","):
        if b in ("raft", "raft_onnx", "raft_int8"):  # the same weights in torch, ONNX Runtime, and its INT8 copy
            cfg = OmegaConf.create(load_config_group("flow", "raft"))
            cfg.runtime = "torch" if b == "raft" else "onnx"
            if b == "raft_int8":
                w = Path(cfg.weights)
                cfg.onnx = str(w.with_name(w.stem + "_int8.onnx"))
        else:
            cfg = OmegaConf.create(load_config_group("flow", b))
        if cfg.name == "raft":
            needed = cfg.onnx if cfg.runtime == "onnx" else cfg.weights
            if not resolve_path(needed).is_file():
                print(f"skipping {b}: {needed} not found (train it with `python -m train.flow`)")
                continue
        cfgs[b] = cfg

    src = SyntheticSource(args.frames, seed=args.seed, scale=args.scale)
    cache = Path(args.cache) if args.cache else None
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
    rows: dict[str, dict[str, list[float]]] = {b: {"epe": [], "fl_all": [], "seconds": [], "pipeline": []} for b in cfgs}
    cov_seconds = []
    size = None
    for i in tqdm(range(len(src)), desc="frames"):
        frame_file = None if cache is None else cache / f"frame_s{args.seed}_x{args.scale}_{i:03d}.pt"
        if frame_file is not None and frame_file.is_file():
            pair = torch.load(frame_file, weights_only=False)
        else:
            pair = src[i]
            if frame_file is not None:
                torch.save(pair, frame_file)
        size = pair.size
        for b, cfg in cfgs.items():
            t0 = time.perf_counter()
            flow = compute_flow(pair.image, pair.image_prev, cfg)
            rows[b]["seconds"].append(time.perf_counter() - t0)
            m = flow_metrics(flow, pair.gt.flow, pair.gt.flow_valid)
            rows[b]["epe"].append(m["epe"])
            rows[b]["fl_all"].append(m["fl_all"])
            if args.pipeline:
                t0 = time.perf_counter()
                estimate_flow(pair, cfg)
                rows[b]["pipeline"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        flow_covariance(pair.image, confidence_params(load_config_group("flow", "deepflow")))
        cov_seconds.append(time.perf_counter() - t0)

    if cache is not None:
        res_file = cache / f"results_s{args.seed}_x{args.scale}_n{args.frames}.json"
        stored = json.loads(res_file.read_text()) if res_file.is_file() else {}
        stored.update(rows)
        stored["_size"] = list(size)
        stored["_cov_seconds"] = stored.get("_cov_seconds", []) + cov_seconds
        res_file.write_text(json.dumps(stored))
        rows = {k: v for k, v in stored.items() if not k.startswith("_")}
        cov_seconds = stored["_cov_seconds"]
    print(f"\n{len(src)} synthetic frames (source seed {args.seed}), {size[1]}x{size[0]}; "
          "EPE and Fl-all averaged over frames, seconds = flow only, median per frame\n")
    print("| backend | EPE (px) | Fl-all (%) | seconds / frame | pipeline seconds / frame |")
    print("|---|---:|---:|---:|---:|")
    for b, r in rows.items():
        pipe = f"{np.median(r['pipeline']):.2f}" if r.get("pipeline") else "-"
        print(f"| {b} | {np.mean(r['epe']):.2f} | {100 * np.mean(r['fl_all']):.1f} | {np.median(r['seconds']):.2f} | {pipe} |")
    print(f"\nstructure-tensor covariance: {np.median(cov_seconds):.2f} s / frame (all backends)")


if __name__ == "__main__":
    main()
