"""Bird's-eye view of a stixel world: occupancy, free space and the camera's field of view, in metres.

Convention: the view lies in the road plane. Its axes are those of
:func:`monostixels.core.geometry.ground_basis`: ``x`` to the right (camera x projected onto the road),
``z`` forward (camera z projected), both metres, the camera at the origin. An object stixel
``p n^T X = 1`` (``n`` its column's horizontal viewing direction) stands at horizontal distance
``d = 1 / p``; its footprint is the segment of that vertical plane between the rays of its
column's two pixel edges. Free space in a column runs from the camera to its first object
stixel from the bottom, or to the farthest ground it sees.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.core.classes import DYNAMIC_OBJECT, GROUND, STATIC_OBJECT
from monostixels.core.geometry import ground_basis, object_normals, pixel_rays
from monostixels.core.stixels import StixelWorld
from monostixels.output.viz import (_ARROW_MIN_COLUMNS, COLORMAP_MAX_DEPTH_M, COLORMAP_MIN_DEPTH_M, MOTION_ARROW_FRAMES, _draw_arrow,
                             depth_colormap, draw_notes, frame_notes, mover_groups)

__all__ = ["BevView", "stixel_footprints", "free_space", "bev_image"]

#: Colours of the view (RGB): outside the field of view, seen but not known free, free space, grid.
_UNSEEN_RGB = (35, 35, 35)
_SEEN_RGB = (85, 85, 85)
_FREE_RGB = (200, 200, 200)
_GRID_RGB = (130, 130, 130)
_MOVER_RGB = (255, 255, 255)
#: Text size of the view's labels (1 = for a 1242 px wide image): the view is small and is shown enlarged.
_TEXT_SCALE = 0.75


@dataclass(frozen=True)
class BevView:
    """The metric window of a bird's-eye view and its pixel grid.

    Attributes:
        forward_m: range ahead of the camera shown, metres (the camera sits on the bottom edge).
        lateral_m: range to each side, metres.
        px_per_m: pixels per metre.
        grid_m: spacing of the distance grid, metres.
    """

    forward_m: float = 50.0
    lateral_m: float = 25.0
    px_per_m: float = 8.0
    grid_m: float = 10.0

    def __post_init__(self) -> None:
        for k in ("forward_m", "lateral_m", "px_per_m", "grid_m"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"BevView.{k}: must be a positive number, got {v}")

    @property
    def size(self) -> tuple[int, int]:
        """(H, W) pixels."""
        return round(self.forward_m * self.px_per_m), round(2 * self.lateral_m * self.px_per_m)

    def to_pixel(self, x: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Pixel coordinates (..., 2) as (column, row) of road points ``x``, ``z`` (...) in metres.

        Convention: pixel centres at integers; ``x = 0`` is the middle column, ``z = 0`` the bottom edge.
        """
        H, W = self.size
        col = W / 2 - 0.5 + np.asarray(x, dtype=np.float64) * self.px_per_m
        row = H - 0.5 - np.asarray(z, dtype=np.float64) * self.px_per_m
        return np.stack([col, row], axis=-1)


def _frame(world: StixelWorld) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """K (3, 3), n_g (3,) and the road basis B (3, 2), float64."""
    K, ng = world.K.double(), world.ground_normal.double()
    return K, ng, ground_basis(ng)


def _column_edges(world: StixelWorld) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel ``u`` of the left and right edge (N,) of each stixel's column (pixel centres at integers)."""
    W, w = world.image_size[1], world.column_width
    u0 = world.column.double() * w
    return u0 - 0.5, torch.clamp(u0 + w, max=W) - 0.5


def _on_plane(K: torch.Tensor, ng: torch.Tensor, n: torch.Tensor, d: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Point (N, 3) of the vertical plane ``n^T X = d`` on the horizontal ray of column ``u`` (N,)."""
    e = object_normals(K, ng, u)
    return (d / (e * n).sum(-1))[:, None] * e


def stixel_footprints(world: StixelWorld) -> np.ndarray:
    """Footprint of every stixel on the road, (N, 2, 2): (left, right) edge x (x, z), metres.

    Object stixels only; ground and sky stixels (and objects without a finite distance) are NaN.
    """
    K, ng, B = _frame(world)
    p = world.inverse_depth.double()
    obj = ((world.type == STATIC_OBJECT) | (world.type == DYNAMIC_OBJECT)) & (p > 0)
    d = 1.0 / torch.where(obj, p, torch.ones_like(p))
    n = world.normals().double()
    ul, ur = _column_edges(world)
    out = torch.stack([_on_plane(K, ng, n, d, ul) @ B, _on_plane(K, ng, n, d, ur) @ B], dim=1)
    return torch.where(obj[:, None, None], out, torch.full_like(out, float("nan"))).numpy()


def _first_objects(world: StixelWorld) -> np.ndarray:
    """(N,) bool: the lowest object stixel of each column (stixels run bottom to top within a column)."""
    obj = ((world.type == STATIC_OBJECT) | (world.type == DYNAMIC_OBJECT)) & (world.inverse_depth > 0)
    first = np.zeros(len(world), dtype=bool)
    seen: set[int] = set()
    for i in torch.nonzero(obj).flatten().tolist():
        c = int(world.column[i])
        if c not in seen:
            seen.add(c)
            first[i] = True
    return first


def free_space(world: StixelWorld, max_range_m: float = float("inf")) -> np.ndarray:
    """Free horizontal distance (C,) per column, metres: to its first object stixel from the bottom,
    else to the farthest ground point it sees (capped at ``max_range_m``); 0 where it sees neither."""
    K, ng, _ = _frame(world)
    C, W, w = world.num_columns, world.image_size[1], world.column_width
    col = world.column.long()
    typ = world.type
    p = world.inverse_depth.double()
    free = np.zeros(C)
    # Farthest ground: the top row of each ground stixel, on its plane n_g^T X = 1 / p.
    u0 = world.column.double() * w
    uc = (u0 + torch.clamp(u0 + w, max=W) - 1) / 2
    ray = pixel_rays(K, uc, world.v_top.double())
    down = (ray * ng).sum(-1)
    gnd = (typ == GROUND) & (p > 0) & (down > 0)
    X = (1.0 / (p * down.clamp(min=1e-12)))[:, None] * ray
    horiz = (X - (X @ ng)[:, None] * ng).norm(dim=-1)
    for i in torch.nonzero(gnd).flatten().tolist():
        free[col[i]] = max(free[col[i]], float(horiz[i]))
    # The first object from the bottom ends it.
    for i in np.flatnonzero(_first_objects(world)):
        free[col[i]] = 1.0 / float(p[i])
    return np.minimum(free, max_range_m)


def bev_image(
    world: StixelWorld,
    view: BevView = BevView(),
    *,
    min_depth: float = COLORMAP_MIN_DEPTH_M,
    max_depth: float = COLORMAP_MAX_DEPTH_M,
    moving: np.ndarray | None = None,
    motion: torch.Tensor | np.ndarray | None = None,
    notes: Sequence[str] = (),
) -> np.ndarray:
    """Draw the bird's-eye view of a stixel world (see the module docstring for the axes).

    The camera's field of view (the rays of the image's left and right edges) is drawn over the
    unseen background, free space in light grey, each object stixel as its footprint in the colour
    of its depth (as :func:`monostixels.output.viz.stixel_depth_overlay`), moving objects outlined in white
    with an arrow of their motion on the road over :data:`monostixels.output.viz.MOTION_ARROW_FRAMES`
    frames, a distance grid every ``view.grid_m`` metres, and frame notes top left.

    Args:
        world: the stixels of one frame.
        view: metric window and resolution.
        min_depth, max_depth: colour-map range, metres.
        moving: (N,) bool, the stixels drawn as moving; default the dynamic ones.
        motion: (N, 3) motion of each stixel between the two frames (camera frame, metres); default
            ``world.motion``.
        notes: more lines for the top-left box.

    Returns:
        (H, W, 3) uint8 RGB, ``(H, W) = view.size``.
    """
    import cv2

    H, W = view.size
    K, ng, B = _frame(world)
    rgb = np.empty((H, W, 3), np.uint8)
    rgb[:] = _UNSEEN_RGB
    far = 4.0 * (view.forward_m + view.lateral_m)  # beyond the window in every direction
    cam = view.to_pixel(0.0, 0.0)
    Wimg = world.image_size[1]
    fov = object_normals(K, ng, torch.tensor([-0.5, Wimg - 0.5], dtype=torch.float64)) @ B  # 2 x 2 (x, z)
    wedge = view.to_pixel(far * fov[:, 0].numpy(), far * fov[:, 1].numpy())
    cv2.fillPoly(rgb, [np.round(np.vstack([cam, wedge])).astype(np.int32)], _SEEN_RGB, cv2.LINE_AA)
    # Free space, column by column: the wedge between its edge rays up to its free distance.
    free = free_space(world, max_range_m=far)
    cols = torch.arange(world.num_columns, dtype=torch.float64)
    w = world.column_width
    el = object_normals(K, ng, cols * w - 0.5)
    er = object_normals(K, ng, torch.clamp(cols * w + w, max=Wimg) - 0.5)
    nc = object_normals(K, ng, (cols * w + torch.clamp(cols * w + w, max=Wimg) - 1) / 2)
    f = torch.from_numpy(free)
    pl = ((f / (el * nc).sum(-1))[:, None] * el) @ B
    pr = ((f / (er * nc).sum(-1))[:, None] * er) @ B
    for c in np.flatnonzero(free > 0):
        quad = np.vstack([cam, view.to_pixel(*pl[c].numpy()), view.to_pixel(*pr[c].numpy())])
        cv2.fillConvexPoly(rgb, np.round(quad).astype(np.int32), _FREE_RGB, cv2.LINE_AA)
    # Distance grid with labels.
    font, fs, th = cv2.FONT_HERSHEY_SIMPLEX, 0.5 * _TEXT_SCALE, 1
    for z in np.arange(view.grid_m, view.forward_m + 1e-9, view.grid_m):
        row = int(round(view.to_pixel(0.0, z)[1]))
        cv2.line(rgb, (0, row), (W - 1, row), _GRID_RGB, 1)
        cv2.putText(rgb, f"{z:g} m", (3, row - 3), font, fs, (230, 230, 230), th, cv2.LINE_AA)
    for x in np.arange(-np.floor(view.lateral_m / view.grid_m) * view.grid_m, view.lateral_m + 1e-9, view.grid_m):
        colx = int(round(view.to_pixel(x, 0.0)[0]))
        cv2.line(rgb, (colx, 0), (colx, H - 1), _GRID_RGB, 1)
    # Occupancy: object footprints in their depth colour, each column's first object (the obstacle)
    # bold, the objects seen above it thin; movers outlined.
    foot = stixel_footprints(world)
    colours = depth_colormap(world.depth.double().numpy()[None], min_depth=min_depth, max_depth=max_depth)[0]
    groups = mover_groups(world, moving)
    members = np.zeros(len(world), dtype=bool)
    if groups:
        members[np.concatenate(groups)] = True
    first = _first_objects(world)
    bold = max(2, round(0.4 * view.px_per_m))
    order = np.argsort(-np.nan_to_num(foot[:, 0, 1], nan=-1.0))  # far first: near ones drawn on top
    for i in order:
        if not np.isfinite(foot[i]).all():
            continue
        a, b = (tuple(int(round(v)) for v in view.to_pixel(*foot[i, j])) for j in (0, 1))
        thick = bold if first[i] else max(1, bold // 2)
        if members[i]:
            cv2.line(rgb, a, b, _MOVER_RGB, thick + 2, cv2.LINE_AA)
        cv2.line(rgb, a, b, tuple(int(c) for c in colours[i]), thick, cv2.LINE_AA)
    if groups:
        mot = (world.motion if motion is None else torch.as_tensor(np.asarray(motion))).double().reshape(-1, 3)
        if mot.shape[0] != len(world):
            raise InputError(f"motion: expected ({len(world)}, 3), got {tuple(mot.shape)}")
        on_road = (mot @ B).numpy()
        for g in groups:
            if world.column[g].unique().numel() < _ARROW_MIN_COLUMNS:
                continue
            centre = np.nanmean(foot[g].reshape(-1, 2), axis=0)
            if not np.isfinite(centre).all():
                continue
            tip = centre + MOTION_ARROW_FRAMES * on_road[g].mean(0)
            _draw_arrow(rgb, view.to_pixel(*centre), view.to_pixel(*tip), max(1, bold // 2))
    # The camera: a small triangle pointing forward.
    s = max(4, round(0.8 * view.px_per_m))
    tri = np.array([[cam[0], cam[1] - 1.6 * s], [cam[0] - s, cam[1]], [cam[0] + s, cam[1]]])
    cv2.fillConvexPoly(rgb, np.round(tri).astype(np.int32), (255, 255, 255), cv2.LINE_AA)
    draw_notes(rgb, [*frame_notes(world), *notes], scale=_TEXT_SCALE)
    return rgb
