"""Monocular ego-motion (``motion=mono``) on real KITTI raw drives against their ground truth.

Any ``kitti_raw`` root works: ../shared/data/kitti_raw_lidar (drive 0023, ground truth from the
GPS/IMU records, ``oxts/``) or ../shared/data/kitti_raw (drive 0028, ``poses_cam0.txt`` of KITTI
odometry sequence 08, whose vertical translation drifts: read the horizontal ``dir_xz`` there).
Runs the flow backend and the ``mono`` estimator with the sequence prior (as ``monostixels eval``
does) on each consecutive pair; prints per-pair errors, the medians and the largest scale error
(docs/conventions.md, section 4.5 ``motion``).

Command (repository root):
    nice -n 10 python -m benchmarks.motion_kitti [--root ../shared/data/kitti_raw_lidar] [--flow deepflow|dis] [--no-sequence-prior]
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from monostixels.build import build_source
from monostixels.inputs.flow import estimate_flow
from monostixels.eval.metrics import motion_errors
from monostixels.build import Purpose, build_pipeline
from monostixels.pipeline import load_config

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default=str(SHARED / "kitti_raw_lidar"))
    ap.add_argument("--flow", default="deepflow")
    ap.add_argument("--semantic", default="none", help="semantic config (none: no semantics)")
    ap.add_argument("--no-sequence-prior", action="store_true", help="each pair alone (motion.sequence_prior=false)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    cfg = load_config(["data=kitti_raw", f"data.root={args.root}", f"flow={args.flow}", f"semantic={args.semantic}",
                       "motion=mono", f"motion.sequence_prior={str(not args.no_sequence_prior).lower()}"])
    pipe = build_pipeline(cfg, Purpose.EVAL)
    from monostixels.inputs.semantic import estimate_semantics
    from monostixels.sequence.runner import motion_track_for

    track = motion_track_for(cfg.motion)  # the sequence layer's speed prior over the drive's pairs

    rows = []
    for pair in build_source(cfg):
        fr = estimate_flow(pair, cfg.flow)
        est = pipe.motion_for(pair, fr, estimate_semantics(pair, cfg.semantic), track=track)
        if pair.motion is None or est.degenerate:
            print(f"{pair.name}: {est.reason}")
            continue
        e = motion_errors(est.motion, pair.motion)
        rows.append(e)
        print(f"{pair.name}: rot {e['rot_err_deg']:.4f} deg  dir {e['trans_dir_err_deg']:.3f} deg  "
              f"dir_xz {e['trans_dir_err_xz_deg']:.3f} deg  scale {e['scale_rel_err']:.4f}  "
              f"|t_gt| {pair.motion.translation_norm:.3f} m  |t| {float(est.motion.t.norm()):.3f} m  | {est.reason}")
    if not rows:
        raise SystemExit("no pair with ground-truth motion")
    med = {k: float(np.median([r[k] for r in rows])) for k in rows[0]}
    print(f"pairs {len(rows)} (ground truth: {pair.meta.get('motion_source')})  median rot_err_deg {med['rot_err_deg']:.4f}  "
          f"trans_dir_err_deg {med['trans_dir_err_deg']:.3f}  trans_dir_err_xz_deg {med['trans_dir_err_xz_deg']:.3f}  "
          f"scale_rel_err {med['scale_rel_err']:.4f}  scale_rel_err_max {max(r['scale_rel_err'] for r in rows):.4f}")


if __name__ == "__main__":
    main()
