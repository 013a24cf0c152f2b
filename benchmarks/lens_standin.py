"""A distorted dashcam with a bonnet, made from the shared highway clip: the calibrated-lens path end to end.

Users' dashcams have wide, barrel-distorted lenses, a bonnet in view and an intrinsics file from
``monostixels calibrate``. No such clip with a known speed is shared; this makes one. The shared
highway clip (960x540, taken as a pinhole view of ``--clip-hfov`` 58 deg) is seen through the lens that
``monostixels calibrate`` finds on ``../shared/data/dashcam/camera_cal`` (1280x720, k1 -0.256): each
pixel of the distorted frame is undistorted with that file's K and distortion
(``cv2.undistortPoints``) to a viewing ray and sampled from the clip along it. The frame then has
exactly the calibrated camera's projection; rays the clip does not cover are black (about 25 px a side
once undistorted). A dark, speckled bonnet is painted over the lowest 70 (sides) to 115 (middle) rows,
as in the bonnet stand-in of docs/experiments.md. Then the clip runs as a user would run it
(``data.intrinsics=FILE``, ``data.mask=auto``) and is scored by :func:`benchmarks.dashcam.measure`.

The calibrated camera's field of view (fx 1159 px over 1280 px: 57.8 deg) is the clip's guessed 58 deg,
so the clip's scene keeps its size: the speed should come out as on the shared clip (25-30 m/s at
``camera.height=1.4``), with no warning and under 1 % false movers.

Commands (repository root; about 3 minutes on 2 cores)::

    monostixels calibrate calibrate.images='../shared/data/dashcam/camera_cal/*.jpg' calibrate.board=[9,6] \\
        calibrate.size=[1280,720] calibrate.out=runs/lens/intrinsics.yaml
    python -m benchmarks.lens_standin --intrinsics runs/lens/intrinsics.yaml --out runs/lens/standin.mp4 \\
        --json runs/lens/standin.json --referee ../shared/models/espnetv2_cityscapes_640x1024.onnx \\
        data.step=2 data.frames=40 camera.height=1.4

Measured (2026-12-07): docs/results.md, "A distorted lens with a bonnet".
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from benchmarks.dashcam import add_report_arguments, measure, write_report
from monostixels._checks import InputError
from monostixels.data._camera_files import read_distortion, read_intrinsics_file, read_intrinsics_size
from monostixels.data._lens import intrinsics_from_hfov

__all__ = ["standin_maps", "bonnet_mask", "write_standin", "main"]

logger = logging.getLogger(__name__)

#: The painted bonnet's height at the image's sides and at its middle (rows of a 720-row frame).
BONNET_ROWS = (70, 115)


def standin_maps(K: np.ndarray, distortion: np.ndarray, size: tuple[int, int], clip_size: tuple[int, int],
                 clip_hfov_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` tables that make a distorted frame of ``size`` from a pinhole clip frame.

    Args:
        K: (3, 3) the calibrated camera matrix (pixels of ``size``); distortion: OpenCV's coefficients.
        size: (H, W) of the distorted frames; clip_size: (H, W) of the clip's frames.
        clip_hfov_deg: the clip's horizontal field of view (its principal point at the centre).

    Returns:
        (map_x, map_y): (H, W) float32 clip pixel of each distorted pixel (outside the clip: no source).
    """
    H, W = size
    # The clip's camera as `data.hfov_deg` gives it to the pipeline.
    fx, fy, cx, cy = intrinsics_from_hfov(clip_size[1], clip_size[0], clip_hfov_deg)
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays = cv2.undistortPoints(np.stack([u.ravel(), v.ravel()], -1)[:, None, :], K, distortion)[:, 0, :]
    map_x = (fx * rays[:, 0] + cx).reshape(H, W).astype(np.float32)
    map_y = (fy * rays[:, 1] + cy).reshape(H, W).astype(np.float32)
    return map_x, map_y


def bonnet_mask(H: int, W: int, low: float, high: float) -> np.ndarray:
    """(H, W) bool: a bonnet whose top edge rises from ``low`` rows at the sides to ``high`` at the middle."""
    u = np.arange(W)
    height = low + (high - low) * (1 - ((u - W / 2) / (W / 2)) ** 2)
    return np.arange(H)[:, None] >= (H - height)[None, :]


def write_standin(clip: Path, intrinsics: Path, out: Path, clip_hfov_deg: float = 58.0) -> int:
    """Write the distorted clip with its bonnet (module docstring); returns the number of frames.

    Raises:
        InputError: an unreadable clip, an intrinsics file without ``distortion`` or without ``width`` and
            ``height`` (the calibrated size), a video that cannot be written.
    """
    fx, fy, cx, cy = read_intrinsics_file(intrinsics)
    dist = read_distortion(intrinsics)
    if dist is None:
        raise InputError(f"{intrinsics}: no 'distortion' key: the stand-in needs a calibrated lens")
    size = read_intrinsics_size(intrinsics)
    if size is None:
        raise InputError(f"{intrinsics}: no 'width' and 'height' (the calibrated image size)")
    H, W = size
    cap = cv2.VideoCapture(str(clip))
    if not cap.isOpened():
        raise InputError(f"--clip: cannot read the video {clip}")
    fps = cap.get(cv2.CAP_PROP_FPS) or 25.0
    Wc, Hc = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    map_x, map_y = standin_maps(K, dist, (H, W), (Hc, Wc), clip_hfov_deg)
    bonnet = bonnet_mask(H, W, *(r * H / 720 for r in BONNET_ROWS))
    # The same speckle in every frame (it does not move), smooth at the pixel scale as real paint is.
    speckle = (255 * (0.15 + 0.35 * (np.random.default_rng(5).random((H, W)) > 0.7))).astype(np.uint8)
    paint = cv2.GaussianBlur(speckle, (5, 5), 0)[bonnet][:, None]
    out.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"mp4v"), fps, (W, H))
    if not writer.isOpened():
        raise InputError(f"--out: cannot write the video {out}")
    n = 0
    with tqdm(total=int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) or None, desc="stand-in", unit="frame") as bar:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            img = cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            img[bonnet] = paint
            writer.write(img)
            n += 1
            bar.update()
    writer.release()
    logger.info("wrote %s: %d frames of %dx%d", out, n, W, H)
    return n


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clip", type=Path, default=Path("../shared/data/dashcam/highway_solid_white_right.mp4"),
                    help="the pinhole clip the stand-in is made from")
    ap.add_argument("--clip-hfov", type=float, default=58.0, help="its horizontal field of view (degrees)")
    ap.add_argument("--intrinsics", type=Path, required=True, help="an intrinsics file with distortion, width, height")
    ap.add_argument("--out", type=Path, required=True, help="write the stand-in video here")
    add_report_arguments(ap)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    torch.set_grad_enabled(False)
    try:
        write_standin(args.clip, args.intrinsics, args.out, args.clip_hfov)
    except InputError as e:
        ap.exit(2, f"lens_standin: error: {e}\n")
    write_report(measure([f"data.path={args.out}", f"data.intrinsics={args.intrinsics}", *args.overrides], args.referee),
                 args.json)


if __name__ == "__main__":
    main()
