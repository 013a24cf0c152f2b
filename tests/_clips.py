"""Tiny clips for the `run` / `batch` end-to-end tests (rendered frames as a video or an image
folder), the CLI call they use, and a way to hide an optional extra.

A clip is 4 frames of a rendered pair at a quarter of KITTI's size (94 x 310): previous, current,
previous, current. So its 3 frame pairs all have real camera motion (forward, back, forward) and
the camera returns to where it was every second frame.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

#: Fast but real inputs: OpenCV DIS flow, no semantics, monocular ego-motion.
FAST = ["flow=dis", "semantic=none", "motion=mono"]
#: Frame rate written into the test videos.
FPS = 10.0


def _frames(seed: int) -> tuple[list[np.ndarray], torch.Tensor]:
    from monostixels.data.synthetic import render_pair

    pair = render_pair(seed, scale=0.25)
    bgr = [cv2.cvtColor((im.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR)
           for im in (pair.image_prev, pair.image, pair.image_prev, pair.image)]
    return bgr, pair.camera.K


def _write_intrinsics(path: Path, K: torch.Tensor) -> Path:
    path.write_text(f"fx: {float(K[0, 0])}\nfy: {float(K[1, 1])}\ncx: {float(K[0, 2])}\ncy: {float(K[1, 2])}\n")
    return path


def write_video_clip(path: Path, seed: int = 3) -> Path:
    """A 4-frame mp4 at ``path`` and its intrinsics beside it (``<stem>.intrinsics.yaml``); returns that file."""
    frames, K = _frames(seed)
    H, W = frames[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), FPS, (W, H))
    for f in frames:
        vw.write(f)
    vw.release()
    return _write_intrinsics(path.with_name(path.stem + ".intrinsics.yaml"), K)


def write_frames_clip(folder: Path, seed: int = 5) -> Path:
    """The same 4 frames as PNGs in ``folder`` with ``intrinsics.yaml``; returns the folder."""
    frames, K = _frames(seed)
    folder.mkdir(parents=True, exist_ok=True)
    for k, f in enumerate(frames):
        cv2.imwrite(str(folder / f"{k:04d}.png"), f)
    _write_intrinsics(folder / "intrinsics.yaml", K)
    return folder


def cli(args: list[str], cwd: Path, env: dict[str, str] | None = None, check: bool = True) -> subprocess.CompletedProcess:
    """Run ``monostixels ARGS`` in ``cwd`` on one thread (as a Ray worker with one CPU runs a clip)."""
    full = {**os.environ, "OMP_NUM_THREADS": "1", **(env or {})}
    p = subprocess.run([sys.executable, "-m", "monostixels.cli", *args], cwd=cwd, env=full,
                       capture_output=True, text=True, timeout=900)
    if check and p.returncode != 0:
        raise AssertionError(f"monostixels {' '.join(args)} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
    return p


def hide_module(monkeypatch, name: str) -> None:
    """Make ``import NAME`` (and its submodules) fail, as where its optional extra is not installed."""
    import builtins

    real = builtins.__import__

    def fake(module, *args, **kwargs):
        if module == name or module.startswith(name + "."):
            raise ImportError(f"No module named {name!r}")
        return real(module, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake)
