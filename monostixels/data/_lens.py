"""What the ``video`` and ``frames`` sources do to each stored frame before the pipeline sees it:
undistort it (when the intrinsics file has a ``distortion`` key), then resize it to the working size;
the intrinsics of the result, and the user's mask carried along.

Undistortion keeps the intrinsics file's camera matrix as the new one (``newCameraMatrix = K``, not
``getOptimalNewCameraMatrix``): the undistorted frame has the file's focal lengths and principal
point, so the numbers a user calibrated are the numbers the pipeline uses. With barrel distortion
(``k1 < 0``, dashcams) every output pixel then has a source pixel and the outer rim of the stored
frame is cropped; with pincushion distortion, or beyond the radius where the distortion polynomial
folds back, output pixels have no source: they are black and ignored (:attr:`FrameWarp.ignore`).
``getOptimalNewCameraMatrix(alpha=0)`` would keep a little more field of view but changes the
focal lengths (unequally in x and y) and still leaves a few pixels without a source.

Order: undistort at the stored size (the remap tables are computed once), then resize (area
interpolation); the intrinsics are scaled with the resize (pixel centres at integers:
``u' + 0.5 = s (u + 0.5)``).

The camera of a ``video`` or ``frames`` source (:func:`lens_camera`): its intrinsics from a file, or,
approximate, from a horizontal field of view (:func:`intrinsics_from_hfov`); an intrinsics file wins
over ``data.hfov_deg`` (a warning says the field of view is not used). The working size
(:func:`working_size`): ``resize`` = ``"auto"`` (about :data:`AUTO_PIXELS`, never upscaled), None,
a factor or ``[W, H]`` pixels.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.core.geometry import Camera
from monostixels.data._camera_files import check_intrinsics_size, make_camera, read_distortion, read_intrinsics_file
from monostixels.data._readers import read_mask_file

__all__ = ["FrameWarp", "AUTO_PIXELS", "intrinsics_from_hfov", "working_size", "lens_camera"]

logger = logging.getLogger(__name__)

#: Samples of the radius (normalised image coordinates) on which the distortion polynomial is checked
#: for a fold (where the distorted radius stops growing with the undistorted one).
_FOLD_SAMPLES = 4096
#: ``resize="auto"``: frames are scaled to about this many pixels (0.5 MP, e.g. 942x530 from 720p or
#: 1080p): flow, semantics and the solver take time in proportion to the pixels, and KITTI's 1242x375
#: (0.47 MP), the size the defaults are tuned at, is about as many.
AUTO_PIXELS = 500_000
#: ``resize="auto"`` keeps frames of up to this factor above :data:`AUTO_PIXELS` as they are (960x540 is
#: 0.52 MP): a resample that small costs sharpness for little time.
_AUTO_KEEP = 1.1


def intrinsics_from_hfov(width: int, height: int, hfov_deg: float) -> tuple[float, float, float, float]:
    """Approximate pinhole intrinsics ``(fx, fy, cx, cy)`` (pixels) from a horizontal field of view.

    Convention: pixel centres at integer coordinates, so the image centre is ``((W-1)/2, (H-1)/2)``;
    square pixels (``fy = fx``); no distortion. ``fx = (W / 2) / tan(hfov / 2)``.

    Raises:
        InputError: ``hfov_deg`` not in (0, 180).
    """
    if not (0.0 < float(hfov_deg) < 180.0) or not math.isfinite(float(hfov_deg)):
        raise InputError(f"data.hfov_deg: horizontal field of view must be in (0, 180) degrees, got {hfov_deg}")
    fx = (width / 2.0) / math.tan(math.radians(float(hfov_deg)) / 2.0)
    return fx, fx, (width - 1) / 2.0, (height - 1) / 2.0


def working_size(resize: Any, W: int, H: int) -> tuple[int, int]:
    """(H, W) pixels after ``resize`` of ``W x H`` frames: None (as stored), ``"auto"`` (about
    :data:`AUTO_PIXELS`, even sizes, never upscaled), a factor, or ``[W, H]`` pixels.

    Raises:
        InputError: anything else, a factor that is not positive, a size that is not positive.
    """
    if resize is None:
        return H, W
    if isinstance(resize, str):
        if resize.strip().lower() != "auto":
            raise InputError(f"data.resize: expected auto, a factor or [W, H] pixels, got {resize!r}")
        if W * H <= AUTO_PIXELS * _AUTO_KEEP:
            return H, W
        s = math.sqrt(AUTO_PIXELS / (W * H))
        # Even sizes: video encoders (the overlay video) and 2x pyramids want them.
        return max(2, 2 * round(H * s / 2)), max(2, 2 * round(W * s / 2))
    if isinstance(resize, (int, float)) and not isinstance(resize, bool):
        f = float(resize)
        if not (f > 0 and math.isfinite(f)):
            raise InputError(f"data.resize: factor must be positive, got {resize}")
        return max(1, round(H * f)), max(1, round(W * f))
    try:
        w, h = (int(x) for x in resize)
    except (TypeError, ValueError) as e:
        raise InputError(f"data.resize: expected auto, a factor or [W, H] pixels, got {resize!r}") from e
    if w < 1 or h < 1:
        raise InputError(f"data.resize: [W, H] must be positive, got {resize!r}")
    return h, w


def lens_camera(intrinsics: str | Path | None, hfov_deg: float | None, size_in: tuple[int, int],
                size: tuple[int, int], camera_height: float, pitch: float, mask: str | Path | None = None,
                what: str = "video", frames_what: str = "the video's frames") -> tuple[Camera, str, "FrameWarp"]:
    """The camera of frames undistorted and resized from ``size_in`` to ``size`` ((H, W) pixels), where its
    intrinsics came from, and the warp that makes the frames (with the user's mask, read and checked
    against ``size_in``).

    Args:
        intrinsics: intrinsics file (pixels of the stored frames; its ``distortion`` undistorts them).
            It wins over ``hfov_deg`` (a warning says ``hfov_deg`` is not used).
        hfov_deg: horizontal field of view (degrees), used without a file: :func:`intrinsics_from_hfov`.
        size_in: (H, W) of the stored frames.
        size: (H, W) of the frames handed on (:func:`working_size`).
        camera_height: metres above the road; pitch: radians, positive = looking down.
        mask: the user's mask image (non-zero = ignore) of ``size_in``, or None.
        what: the source's name for the messages (``"video"``, ``"frames"``); frames_what: its frames'.

    Returns:
        (camera at ``size``, the intrinsics' source: the file's path or ``"hfov D deg (approximate)"``, warp).

    Raises:
        InputError: neither a file nor ``hfov_deg`` (both options named), a malformed file, a file that
            states another image size, ``hfov_deg`` out of (0, 180), a mask of another size.
    """
    H0, W0 = size_in
    distortion = None
    if intrinsics is not None:
        source = str(intrinsics)
        if hfov_deg is not None:
            logger.warning("%s: data.hfov_deg=%g not used: the intrinsics file %s gives the camera", what,
                           float(hfov_deg), intrinsics)
        fx, fy, cx, cy = read_intrinsics_file(intrinsics)
        distortion = read_distortion(intrinsics)
        check_intrinsics_size(intrinsics, size_in, frames_what)
    elif hfov_deg is not None:
        source = f"hfov {float(hfov_deg):g} deg (approximate)"
        fx, fy, cx, cy = intrinsics_from_hfov(W0, H0, float(hfov_deg))
        logger.warning("%s: intrinsics from a horizontal field of view of %g deg: approximate (principal "
                       "point at the centre, no distortion); depths scale with the focal length", what, float(hfov_deg))
    else:
        raise InputError(f"{what}: no intrinsics: set data.intrinsics=FILE (fx fy cx cy) or data.hfov_deg=DEGREES "
                         f"(horizontal field of view, approximate)")
    user_mask = None if mask is None else read_mask_file(mask, size_in)
    warp = FrameWarp((fx, fy, cx, cy), distortion, size_in, size, user_mask)
    return make_camera(*warp.intrinsics, camera_height, pitch), source, warp


class FrameWarp:
    """Undistortion and resizing of one camera's frames, with the tables computed once.

    Args:
        intrinsics: ``(fx, fy, cx, cy)`` pixels of the stored frames (of the undistorted image when
            ``distortion`` is given: OpenCV's model).
        distortion: OpenCV coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``, or None (no
            undistortion; all zeros alike).
        size_in: (H, W) of the stored frames.
        size_out: (H, W) of the frames handed on (the working size).
        mask: (H, W) bool at ``size_in``, True = ignore (the user's ``data.mask``), or None.

    Attributes:
        intrinsics: ``(fx, fy, cx, cy)`` of the frames :meth:`image` returns (pixels).
        ignore: (H', W') torch bool at ``size_out``, True = ignore: the user's mask undistorted and
            resized (nearest neighbour) and the pixels without a source; None when there are neither.
    """

    def __init__(self, intrinsics: Sequence[float], distortion: np.ndarray | None, size_in: tuple[int, int],
                 size_out: tuple[int, int], mask: np.ndarray | None = None) -> None:
        fx, fy, cx, cy = (float(v) for v in intrinsics)
        self.size_in = (int(size_in[0]), int(size_in[1]))
        self.size_out = (int(size_out[0]), int(size_out[1]))
        H0, W0 = self.size_in
        H, W = self.size_out
        self._maps: tuple[np.ndarray, np.ndarray] | None = None
        no_source: np.ndarray | None = None  # (H0, W0) bool, undistorted pixels without a source
        if distortion is not None and np.any(np.asarray(distortion) != 0):
            d = np.asarray(distortion, dtype=np.float64).ravel()
            K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
            mx, my = cv2.initUndistortRectifyMap(K, d, None, K, (W0, H0), cv2.CV_32FC1)
            no_source = (mx < 0) | (mx > W0 - 1) | (my < 0) | (my > H0 - 1) | _beyond_fold(d, K, (H0, W0))
            if mask is not None:
                # Nearest neighbour; outside the stored frame = ignore.
                mask = cv2.remap(mask.astype(np.uint8), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                                 borderValue=1).astype(bool)
            # Fixed-point tables: the per-frame remap takes less time than with float ones.
            self._maps = cv2.convertMaps(mx, my, cv2.CV_16SC2)
            logger.info("lens: undistorting %dx%d frames (distortion %s, camera matrix kept); %.2f %% of the pixels "
                        "have no source and are ignored", W0, H0, np.array2string(d, precision=4),
                        100.0 * float(no_source.mean()))
            if not no_source.any():
                no_source = None
        ignore = mask
        if no_source is not None:
            ignore = no_source if ignore is None else ignore | no_source
        if ignore is not None and (H, W) != (H0, W0):
            # Nearest neighbour for the mask; a working pixel partly without a source is ignored.
            resized = cv2.resize(mask.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST).astype(bool) \
                if mask is not None else np.zeros((H, W), bool)
            if no_source is not None:
                resized |= cv2.resize(no_source.astype(np.float32), (W, H), interpolation=cv2.INTER_AREA) > 0
            ignore = resized
        self.ignore: torch.Tensor | None = None if ignore is None else torch.from_numpy(np.ascontiguousarray(ignore))
        sx, sy = W / W0, H / H0
        self.intrinsics = (fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5)

    @property
    def undistorts(self) -> bool:
        """Whether frames are undistorted (a non-zero distortion was given)."""
        return self._maps is not None

    @property
    def changes_frames(self) -> bool:
        """Whether :meth:`image` changes a frame (it undistorts or resizes)."""
        return self._maps is not None or self.size_out != self.size_in

    def image(self, img: np.ndarray) -> np.ndarray:
        """A stored frame undistorted and resized.

        Args:
            img: (H, W, C) uint8 or float32 at ``size_in`` (any channel order: channels are kept).

        Returns:
            (H', W', C) of the same dtype at ``size_out``.
        """
        if img.shape[:2] != self.size_in:
            raise ValueError(f"FrameWarp: frame is {img.shape[1]}x{img.shape[0]}, expected "
                             f"{self.size_in[1]}x{self.size_in[0]}")
        if self._maps is not None:
            img = cv2.remap(img, self._maps[0], self._maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        if img.shape[:2] != self.size_out:
            img = cv2.resize(img, (self.size_out[1], self.size_out[0]), interpolation=cv2.INTER_AREA)
        return img

    def ignore_mask(self) -> torch.Tensor | None:
        """A copy of :attr:`ignore` for one frame pair (consumers may change theirs), or None."""
        return None if self.ignore is None else self.ignore.clone()


def _beyond_fold(d: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: undistorted pixels whose radius lies beyond the first fold of the radial model.

    Past the radius where ``r_d(r) = r (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)``
    stops growing, the model maps two radii to one distorted radius: the remap would fill those pixels
    with a mirrored copy of the image, so they count as without a source. Tangential terms are small
    and left out of this check.
    """
    H, W = size
    k = np.zeros(8)
    k[: d.size] = d
    k1, k2, _, _, k3, k4, k5, k6 = k
    u = (np.arange(W) - K[0, 2]) / K[0, 0]
    v = (np.arange(H) - K[1, 2]) / K[1, 1]
    r = np.sqrt(u[None, :] ** 2 + v[:, None] ** 2)
    rs = np.linspace(0.0, float(r.max()), _FOLD_SAMPLES)
    r2 = rs * rs
    den = 1 + k4 * r2 + k5 * r2 ** 2 + k6 * r2 ** 3
    rd = rs * (1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3) / np.where(den > 0, den, np.nan)
    bad = ~(np.diff(rd) > 0) | ~np.isfinite(rd[1:])
    if not bad.any():
        return np.zeros((H, W), bool)
    return r >= rs[int(np.argmax(bad))]
