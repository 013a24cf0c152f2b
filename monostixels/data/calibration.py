"""Camera calibration from chessboard views (``monostixels calibrate``).

OpenCV's method (Zhang's, as in OpenCV's calibration tutorial): ``findChessboardCorners`` per image,
``cornerSubPix`` to refine the corners, ``calibrateCamera`` over all views with a board, giving the
pinhole intrinsics and five distortion coefficients ``k1, k2, p1, p2, k3``. The result is written as
an intrinsics file in the format :func:`monostixels.data._camera_files.read_intrinsics_file` reads, with the
``distortion`` key (:func:`monostixels.data._camera_files.read_distortion`), so that ``data=video`` and
``data=frames`` undistort with it.

Convention: ``board = (columns, rows)`` counts *inner* corners (where four squares meet), as OpenCV's
``patternSize``: the common printed board of 10 x 7 squares has 9 x 6. Pixel centres at integers
(OpenCV), so the intrinsics are those of the images as stored. The command's settings: the config group
``calibrate`` (:class:`CalibrateConfig`).
"""
from __future__ import annotations

import glob
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Sequence

import cv2
import numpy as np

from monostixels._checks import InputError
from monostixels.data._readers import IMAGE_EXTENSIONS

__all__ = ["CalibrateConfig", "Calibration", "MIN_BOARDS", "calibrate_images", "calibration_lines", "find_board",
           "write_intrinsics_file"]

logger = logging.getLogger(__name__)


@dataclass
class CalibrateConfig:
    """The settings of ``monostixels calibrate``: the schema of the config group ``calibrate``
    (monostixels.config_schema).

    Attributes:
        images: the chessboard views: a glob (quote it against the shell) or a folder; 10-20 views of the board
            at varied angles covering the whole image (the corners matter most for the distortion), at least
            :data:`MIN_BOARDS` of them showing the board.
        board: inner corners ``[columns, rows]``, where four squares meet (a board of 10 x 7 squares has [9, 6]).
        out: the intrinsics file written (fx, fy, cx, cy and distortion ``[k1, k2, p1, p2, k3]``), for
            ``data.intrinsics``.
        size: ``[W, H]``: use only the images of this size (the others are skipped and listed); None = all,
            of one size.
    """

    images: Optional[str] = None
    board: List[int] = field(default_factory=lambda: [9, 6])
    out: str = "intrinsics.yaml"
    size: Optional[List[int]] = None

#: Fewest views with a board found that a calibration accepts: Zhang's method needs three views of a
#: plane for the intrinsics; the distortion coefficients want more (10-20 views at varied angles and
#: positions across the image, see :data:`_RECOMMENDED_BOARDS`).
MIN_BOARDS = 3
#: Below this many boards a warning says the calibration may be poor.
_RECOMMENDED_BOARDS = 10
#: A reprojection error above this (pixels) gets a warning: the board size, or some detections, are wrong.
_RMS_WARN_PX = 2.0
#: ``cornerSubPix`` half window (pixels): at most this (OpenCV tutorial's 11) and at most a third of the
#: corner spacing, so that the window never reaches a neighbouring corner.
_SUBPIX_HALF_WINDOW = 11
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)


@dataclass
class Calibration:
    """Intrinsics and lens distortion of one camera from chessboard views.

    Attributes:
        fx, fy, cx, cy: pinhole intrinsics (pixels of the images as stored).
        distortion: ``(k1, k2, p1, p2, k3)``, OpenCV's order and model (barrel: ``k1 < 0``).
        rms_px: RMS reprojection error of the board corners (pixels).
        size: (H, W) of the images (pixels).
        board: (columns, rows) inner corners.
        images: every image the pattern matched (of the calibrated size), sorted.
        boards: the images where the board was found (used by the calibration).
        no_board: the images where it was not found.
        other_size: images skipped for their size (only with ``size`` given to :func:`calibrate_images`).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...]
    rms_px: float
    size: tuple[int, int]
    board: tuple[int, int]
    images: list[Path] = field(default_factory=list)
    boards: list[Path] = field(default_factory=list)
    no_board: list[Path] = field(default_factory=list)
    other_size: list[Path] = field(default_factory=list)

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def find_board(gray: np.ndarray, board: tuple[int, int]) -> np.ndarray | None:
    """The inner corners of a chessboard in an image, refined to sub-pixel accuracy.

    Args:
        gray: (H, W) uint8 image.
        board: (columns, rows) inner corners.

    Returns:
        (columns * rows, 2) float32 corner pixels (``u, v``), row by row in OpenCV's order; None when
        the whole board is not found.
    """
    found, corners = cv2.findChessboardCorners(gray, board, flags=cv2.CALIB_CB_ADAPTIVE_THRESH
                                               + cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not found:
        return None
    pts = corners.reshape(board[1], board[0], 2)
    spacing = min(np.linalg.norm(np.diff(pts, axis=0), axis=2).min(), np.linalg.norm(np.diff(pts, axis=1), axis=2).min())
    half = int(max(2, min(_SUBPIX_HALF_WINDOW, spacing / 3)))
    corners = cv2.cornerSubPix(gray, corners, (half, half), (-1, -1), _SUBPIX_CRITERIA)
    return corners.reshape(-1, 2)


def calibrate_images(images: str | Path | Sequence[str | Path], board: Sequence[int] = (9, 6),
                     size: Sequence[int] | None = None) -> Calibration:
    """Calibrate a camera from images of a chessboard.

    Args:
        images: a glob pattern (``"camera_cal/*.jpg"``), a folder (its image files) or a list of files.
        board: (columns, rows) inner corners of the board (9 x 6 for a board of 10 x 7 squares).
        size: ``(W, H)``: use only the images of this size (the others are skipped and listed);
            None = all images, which must then have one size.

    Returns:
        The :class:`Calibration` (write it with :func:`write_intrinsics_file`).

    Raises:
        InputError: no image matches (the pattern named), an unreadable image, images of different
            sizes (without ``size``), no image of ``size``, a bad ``board``, fewer than
            :data:`MIN_BOARDS` images with the board found, or a calibration that does not converge.
    """
    what = _describe(images)
    try:
        cols, rows = (int(v) for v in board)
    except (TypeError, ValueError):
        raise InputError(f"calibrate.board: expected [columns, rows] inner corners, e.g. [9, 6], got {board!r}") from None
    if cols < 3 or rows < 3:
        raise InputError(f"calibrate.board: needs at least 3 x 3 inner corners, got [{cols}, {rows}]")
    files = _image_files(images, what)
    grays = {p: _read_gray(p) for p in files}
    sizes: dict[tuple[int, int], list[Path]] = {}
    for p, g in grays.items():
        sizes.setdefault((g.shape[1], g.shape[0]), []).append(p)
    other: list[Path] = []
    W, H = next(iter(sizes))
    if size is not None:
        try:
            want = tuple(int(v) for v in size)
        except (TypeError, ValueError):
            raise InputError(f"calibrate.size: expected [W, H] pixels, got {size!r}") from None
        if want not in sizes:
            raise InputError(f"calibrate.images: {what} has no image of {want[0]}x{want[1]} (calibrate.size); "
                             f"sizes: {_sizes_text(sizes)}")
        other = [p for s, ps in sizes.items() if s != want for p in ps]
        for p in other:
            logger.warning("calibrate: %s skipped: %dx%d, not %dx%d (calibrate.size)", p, grays[p].shape[1],
                           grays[p].shape[0], *want)
        files = sizes[want]
        W, H = want
    elif len(sizes) > 1:
        common = max(sizes, key=lambda s: len(sizes[s]))
        raise InputError(f"calibrate.images: {what} holds images of different sizes ({_sizes_text(sizes)}); "
                         f"intrinsics hold for one size: set calibrate.size=[{common[0]},{common[1]}] to use only "
                         f"those, or remove the others")
    grid = np.zeros((rows * cols, 3), np.float32)
    grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2)  # row by row, as findChessboardCorners orders them
    found: list[Path] = []
    missed: list[Path] = []
    corners: list[np.ndarray] = []
    for p in files:
        c = find_board(grays[p], (cols, rows))
        if c is None:
            logger.warning("calibrate: no %dx%d board found in %s", cols, rows, p)
            missed.append(p)
            continue
        found.append(p)
        corners.append(c.reshape(-1, 1, 2))
    if len(found) < MIN_BOARDS:
        raise InputError(f"calibrate.images: a {cols}x{rows} board (inner corners, calibrate.board) found in "
                         f"{len(found)} of the {len(files)} images of {what}; a calibration needs at least "
                         f"{MIN_BOARDS} (10-20 recommended)")
    if len(found) < _RECOMMENDED_BOARDS:
        logger.warning("calibrate: only %d views with a board; %d or more, at varied angles and across the whole "
                       "image, give a reliable distortion", len(found), _RECOMMENDED_BOARDS)
    rms, K, dist, _, _ = cv2.calibrateCamera([grid] * len(found), corners, (W, H), None, None)
    dist = np.asarray(dist, dtype=np.float64).ravel()
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist)) and K[0, 0] > 0 and K[1, 1] > 0
            and math.isfinite(rms)):
        raise InputError(f"calibrate: the calibration of {what} did not converge (fx={K[0, 0]}, fy={K[1, 1]}, "
                         f"RMS {rms}); check calibrate.board and the views")
    if rms > _RMS_WARN_PX:
        logger.warning("calibrate: RMS reprojection error %.2f px is high (a wrong calibrate.board, blurred or "
                       "mis-detected views?)", rms)
    return Calibration(fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                       distortion=tuple(float(v) for v in dist[:5]), rms_px=float(rms), size=(H, W),
                       board=(cols, rows), images=list(files), boards=found, no_board=missed, other_size=other)


def write_intrinsics_file(cal: Calibration, path: str | Path) -> Path:
    """Write a calibration as an intrinsics file (YAML) that ``data.intrinsics`` reads.

    Keys ``fx, fy, cx, cy`` (pixels), ``distortion: [k1, k2, p1, p2, k3]`` and ``width``, ``height``
    (the image size they hold for); comments say where it came from (views, RMS error). Parent folders
    are created.

    Returns:
        The path written.
    """
    p = Path(path).expanduser()
    p.parent.mkdir(parents=True, exist_ok=True)
    H, W = cal.size
    lines = [
        "# Camera intrinsics from `monostixels calibrate` (OpenCV calibrateCamera): pixels of "
        f"{W}x{H} images,",
        f"# {len(cal.boards)} views of a {cal.board[0]}x{cal.board[1]} chessboard (inner corners), "
        f"RMS reprojection error {cal.rms_px:.3f} px.",
        "# distortion: OpenCV's order k1, k2, p1, p2, k3 (frames are undistorted with it).",
        f"fx: {cal.fx!r}",
        f"fy: {cal.fy!r}",
        f"cx: {cal.cx!r}",
        f"cy: {cal.cy!r}",
        f"distortion: [{', '.join(repr(v) for v in cal.distortion)}]",
        "# The image size these hold for: frames of another size are refused.",
        f"width: {W}",
        f"height: {H}",
    ]
    p.write_text("\n".join(lines) + "\n")
    return p


def calibration_lines(cal: Calibration, path: Path) -> list[str]:
    """What ``monostixels calibrate`` prints of calibration ``cal`` written to ``path``: the boards found, the
    RMS reprojection error (pixels), the images left out, the intrinsics and the distortion."""
    H, W = cal.size
    k1, k2, p1, p2, k3 = cal.distortion
    lines = [f"calibrate: {cal.board[0]}x{cal.board[1]} board found in {len(cal.boards)} of {len(cal.images)} images "
             f"({W}x{H}); RMS reprojection error {cal.rms_px:.3f} px"]
    if cal.no_board:
        lines.append(f"  no board in: {', '.join(p.name for p in cal.no_board)}")
    if cal.other_size:
        lines.append(f"  skipped (not {W}x{H}): {', '.join(p.name for p in cal.other_size)}")
    lines.append(f"  fx {cal.fx:.2f}  fy {cal.fy:.2f}  cx {cal.cx:.2f}  cy {cal.cy:.2f} px; "
                 f"distortion k1 {k1:.4f} k2 {k2:.4f} p1 {p1:.5f} p2 {p2:.5f} k3 {k3:.4f}")
    lines.append(f"wrote {path} (use it: data.intrinsics={path})")
    return lines


def _describe(images: str | Path | Sequence[str | Path]) -> str:
    if isinstance(images, (str, Path)):
        return repr(str(images))
    return f"the {len(images)} listed files"


def _image_files(images: str | Path | Sequence[str | Path] | None, what: str) -> list[Path]:
    """Image files of a glob, a folder or a list, sorted by name (a list keeps its order)."""
    if images is None or (isinstance(images, (str, Path)) and str(images) == ""):
        raise InputError("calibrate.images: no images given (calibrate.images='DIR/*.jpg')")
    if isinstance(images, (str, Path)):
        pattern = str(Path(str(images)).expanduser())
        if Path(pattern).is_dir():
            pattern = str(Path(pattern) / "*")
        files = sorted(Path(f) for f in glob.glob(pattern))
    else:
        files = [Path(f).expanduser() for f in images]
        missing = [f for f in files if not f.is_file()]
        if missing:
            raise InputError(f"calibrate.images: file {missing[0]} does not exist")
    files = [f for f in files if f.is_file() and f.suffix.lower() in IMAGE_EXTENSIONS]
    if not files:
        raise InputError(f"calibrate.images: no image file matches {what} ({', '.join(IMAGE_EXTENSIONS)})")
    return files


def _read_gray(p: Path) -> np.ndarray:
    img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
    if img is None or img.size == 0:
        raise InputError(f"calibrate.images: cannot read {p} (not an image file OpenCV can decode, or corrupt)")
    return img


def _sizes_text(sizes: dict[tuple[int, int], list[Path]]) -> str:
    return ", ".join(f"{len(ps)} of {w}x{h}" + (f" ({', '.join(p.name for p in ps[:3])}{', ...' if len(ps) > 3 else ''})"
                                                 if len(ps) < max(len(v) for v in sizes.values()) else "")
                     for (w, h), ps in sorted(sizes.items(), key=lambda kv: -len(kv[1])))
