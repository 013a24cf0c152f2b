"""The result type: a multi-layer stixel world, its dense maps and its serialisation."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, Mapping

import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.core.classes import CLASS_NAMES, SKY, TYPE_NAMES
from monostixels.core.geometry import object_normals, pixel_rays
from monostixels.core.status import FrameStatus

__all__ = ["StixelWorld", "paint_index_map", "neighbours", "segment_lower_median"]

_TENSOR_FIELDS = ("column", "v_top", "v_bottom", "type", "cls", "inverse_depth", "motion", "cost", "tau")
#: Fields of sequences (present when the stream set them).
_OPTIONAL_FIELDS = ("track_id", "velocity", "ttc_s", "ttc_warning", "pose")


def neighbours(column: torch.Tensor, v_top: torch.Tensor, v_bottom: torch.Tensor) -> torch.Tensor:
    """(N, N) bool: stixels ``i`` and ``j`` stand in adjacent columns and share a row.

    Args:
        column, v_top, v_bottom: (N,) integer stixel columns and inclusive pixel rows.

    The neighbourhood of the stixels of one object (a moving object is wider than one column): the
    movers' isolated-stixel check, the tracks' object groups and the pictures' mover groups.
    """
    c = column.long()
    return (((c[:, None] - c[None, :]).abs() == 1) & (v_top[:, None] <= v_bottom[None, :])
            & (v_top[None, :] <= v_bottom[:, None]))


def segment_lower_median(values: torch.Tensor, seg: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """Per-segment lower median (S,) of ``values`` (N,) with non-decreasing segment ids ``seg`` (N,)
    and segment sizes ``counts`` (S,); NaN where a segment holds a NaN (as ``torch.median``) or is empty.

    The segments are laid out as the rows of an (S, max count) array padded with ``+inf`` and sorted
    along the rows (cheaper than sorting all values and then the segment ids): the
    order statistics, and so the medians, are the same.
    """
    S = counts.numel()
    out = torch.full((S,), math.nan, dtype=values.dtype)
    if values.numel() == 0:
        return out
    start = torch.cumsum(counts, 0) - counts
    nan = torch.isnan(values)
    rows = torch.full((S, int(counts.max())), math.inf, dtype=values.dtype)
    rows[seg, torch.arange(values.numel()) - start[seg]] = values.masked_fill(nan, math.inf)
    srt = rows.sort(dim=1).values
    med = srt[torch.arange(S), torch.div(counts - 1, 2, rounding_mode="floor").clamp(min=0)]
    nan_in = torch.zeros(S, dtype=torch.bool)
    nan_in[seg[nan]] = True
    return torch.where((counts > 0) & ~nan_in, med, out)


def paint_index_map(column: torch.Tensor, v_top: torch.Tensor, v_bottom: torch.Tensor, column_width: int,
                    image_size: tuple[int, int]) -> torch.Tensor:
    """Index (H, W) int64 of the stixel covering each pixel, -1 where none.

    Args:
        column, v_top, v_bottom: (N,) stixel columns and inclusive pixel rows (``v_top <= v_bottom``).
        column_width: ``w_s`` pixels. image_size: ``(H, W)``.

    Raises:
        InputError: lengths differ, ``v_bottom < v_top``, or rows / columns outside the image.
    """
    H, W = image_size
    col, top, bot = (torch.as_tensor(x).long().reshape(-1) for x in (column, v_top, v_bottom))
    n = col.numel()
    if not (top.numel() == n and bot.numel() == n):
        raise InputError(f"stixels: column, v_top, v_bottom differ in length ({n}, {top.numel()}, {bot.numel()})")
    ncols = -(-W // column_width)
    if n and bool((bot < top).any()):
        raise InputError("stixels: v_bottom < v_top for some stixel (rows are inclusive, v grows downward)")
    if n and (int(top.min()) < 0 or int(bot.max()) >= H or int(col.min()) < 0 or int(col.max()) >= ncols):
        raise InputError(f"stixels: rows or columns outside the image ({H} rows, {ncols} columns of width {column_width})")
    cell = torch.full((H, ncols), -1, dtype=torch.long)  # one entry per (row, stixel column)
    lengths = bot - top + 1
    ids = torch.repeat_interleave(torch.arange(n), lengths)
    starts = torch.cumsum(lengths, 0) - lengths
    rows = top[ids] + (torch.arange(ids.numel()) - starts[ids])
    cell[rows, col[ids]] = ids
    # Each stixel column repeated column_width times (a broadcast copy, several times faster than
    # gathering the columns by index), the last one cut at the image's edge.
    return cell[:, :, None].expand(H, ncols, column_width).reshape(H, ncols * column_width)[:, :W].contiguous()


@dataclass
class StixelWorld:
    """Stixels of one frame: a flat table of N stixels, sorted by column, then bottom to top.

    Convention: column ``c`` spans pixels ``u`` in ``[c w_s, min((c+1) w_s, W))``; rows are pixel
    rows with ``v`` downward, ``v_top <= v_bottom``, both inclusive. A stixel lies on the plane
    ``p n^T X = 1`` (``p`` = ``inverse_depth``, 1/metres): ground ``n = n_g``, objects ``n`` = the
    column's horizontal viewing direction, sky ``p = 0``.

    Attributes:
        column_width: ``w_s`` in pixels.
        image_size: ``(H, W)`` pixels.
        K: intrinsics (3, 3). ground_normal: ``n_g`` (3,).
        column, v_top, v_bottom, type, cls: (N,) int64.
        inverse_depth: (N,) 1/metres. motion: (N, 3) metres, ``Δ`` of dynamic stixels (0 otherwise).
        cost: (N,) energy of each stixel (data + prior terms). tau: (N, 2) ``(t̃x, t̃y)`` of dynamic stixels.
        energy: (C,) optimal energy of every column.
        status: what is known about the frame beside its stixels (:class:`~monostixels.core.status.FrameStatus`:
            the camera motion's status, the post-processing's counts); ``stixels.json`` writes it as ``flags``.

    On sequences (:mod:`monostixels.sequence`: ``TrackedFrame.world()``) also, else None:
        track_id: (N,) int64 track of each object stixel (-1: ground, sky, untracked).
        velocity: (N, 3) world velocity, m/s (world = the sequence's first camera; 0: ground, sky).
        ttc_s: (N,) time to collision, seconds (inf: not closing; ground and sky inf).
        ttc_warning: (N,) bool, closing within ``ttc.warn_s`` inside the camera's path.
        pose: (4, 4) camera-to-world of the frame. pair_info: the pair solved (``current``,
            ``previous`` frame names, ``frames_back``, ``dt_s``, ``driven_m``).
    """

    column_width: int
    image_size: tuple[int, int]
    K: torch.Tensor
    ground_normal: torch.Tensor
    column: torch.Tensor
    v_top: torch.Tensor
    v_bottom: torch.Tensor
    type: torch.Tensor
    cls: torch.Tensor
    inverse_depth: torch.Tensor
    motion: torch.Tensor
    cost: torch.Tensor
    tau: torch.Tensor
    energy: torch.Tensor
    status: FrameStatus = field(default_factory=FrameStatus)
    track_id: torch.Tensor | None = None
    velocity: torch.Tensor | None = None
    ttc_s: torch.Tensor | None = None
    ttc_warning: torch.Tensor | None = None
    pose: torch.Tensor | None = None
    pair_info: dict[str, Any] | None = None

    # ------------------------------------------------------------------ derived quantities
    def __len__(self) -> int:
        return int(self.column.numel())

    @property
    def flags(self) -> Mapping[str, Any]:
        """The ``flags`` of ``stixels.json`` (read only; :meth:`FrameStatus.to_flags
        <monostixels.core.status.FrameStatus.to_flags>`): set :attr:`status` instead."""
        return MappingProxyType(self.status.to_flags())

    @property
    def num_columns(self) -> int:
        W = self.image_size[1]
        return -(-W // self.column_width)

    @property
    def compactness(self) -> int:
        """Number of values needed to represent the depth: 3 per stixel (paper, section Metric)."""
        return 3 * len(self)

    def normals(self) -> torch.Tensor:
        """Plane normal (N, 3) of each stixel (ground: ``n_g``; objects: column direction)."""
        K = self.K.double()
        ng = self.ground_normal.double()
        W = self.image_size[1]
        u0 = self.column.double() * self.column_width
        u1 = torch.clamp(u0 + self.column_width, max=W)
        uc = (u0 + u1 - 1) / 2
        n_obj = object_normals(K, ng, uc)
        is_ground = (self.type == 0)[:, None]
        return torch.where(is_ground, ng.expand_as(n_obj), n_obj)

    @property
    def depth(self) -> torch.Tensor:
        """Representative depth z (N,) of each stixel: at its bottom-centre pixel, inf for sky (metres)."""
        H, W = self.image_size
        u0 = self.column.double() * self.column_width
        uc = (u0 + torch.clamp(u0 + self.column_width, max=W) - 1) / 2
        v = torch.where(self.type == 0, self.v_bottom, (self.v_top + self.v_bottom) // 2).double()
        ray = pixel_rays(self.K.double(), uc, v)
        z = 1.0 / (self.inverse_depth.double() * (ray * self.normals()).sum(-1))
        return torch.where(self.type == SKY, torch.full_like(z, float("inf")), z).float()

    def depth_map(self) -> torch.Tensor:
        """Dense depth z (H, W) in metres from ray-plane intersection per pixel.

        Sky pixels are ``inf``; ground pixels above the horizon (the ray never meets the plane)
        get a negative depth: both are invalid estimates that evaluation clamps.
        """
        H, W = self.image_size
        idx = self.index_map()
        K = self.K.double()
        # The viewing ray K^-1 (u, v, 1) (geometry.pixel_rays, z = 1) dotted with the stixel's normal,
        # written out per component (x n_x + y n_y + n_z): the same float64 numbers as the (H, W, 3)
        # product summed over its last axis, without building it.
        fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
        u = torch.arange(W, dtype=torch.float64)
        y = ((torch.arange(H, dtype=torch.float64) - cy) / fy)[:, None]  # H x 1
        x = (u[None, :] - cx - skew * y) / fx  # H x W
        ng = self.ground_normal.double()
        n_obj = object_normals(K, ng, u)  # W x 3: every pixel uses its own column direction
        safe = idx.clamp(min=0)
        typ = self.type[safe]
        p = self.inverse_depth.double()[safe]
        ground = typ == 0
        nx, ny, nz = (torch.where(ground, ng[i], n_obj[None, :, i]) for i in range(3))
        z = 1.0 / (p * (x * nx + y * ny + nz))
        z = torch.where(typ == SKY, torch.full_like(z, float("inf")), z)
        z = torch.where(idx < 0, torch.full_like(z, float("nan")), z)
        return z.float()

    def index_map(self) -> torch.Tensor:
        """Index (H, W) int64 of the stixel covering each pixel (-1 where none)."""
        return paint_index_map(self.column, self.v_top, self.v_bottom, self.column_width, self.image_size)

    def semantic_map(self) -> torch.Tensor:
        """Class id (H, W) int64 of every pixel (255 where no stixel)."""
        idx = self.index_map()
        out = self.cls[idx.clamp(min=0)]
        return torch.where(idx < 0, torch.full_like(out, 255), out)

    def type_map(self) -> torch.Tensor:
        """Stixel type (H, W) int64 of every pixel (-1 where no stixel)."""
        idx = self.index_map()
        out = self.type[idx.clamp(min=0)]
        return torch.where(idx < 0, torch.full_like(out, -1), out)

    def column_stixels(self, c: int) -> list[dict[str, Any]]:
        """The stixels of column ``c`` bottom to top, as dicts (see :meth:`to_dict`)."""
        return [s for s in self.to_dict()["stixels"] if s["column"] == c]

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict: frame metadata and one entry per stixel."""
        depth = self.depth
        stixels = []
        for i in range(len(self)):
            stixels.append({
                "column": int(self.column[i]),
                "v_bottom": int(self.v_bottom[i]),
                "v_top": int(self.v_top[i]),
                "type": TYPE_NAMES[int(self.type[i])],
                "class": CLASS_NAMES[int(self.cls[i])],
                "inverse_depth": float(self.inverse_depth[i]),
                "depth": float(depth[i]) if torch.isfinite(depth[i]) else None,
                "motion": [float(x) for x in self.motion[i]],
                "tau": [float(x) for x in self.tau[i]],
                "cost": float(self.cost[i]),
            })
            if self.track_id is not None:
                stixels[-1]["track_id"] = int(self.track_id[i])
            if self.velocity is not None:
                stixels[-1]["velocity"] = [float(x) for x in self.velocity[i]]
            if self.ttc_s is not None:
                # JSON has no infinity: null = not closing (as a sky stixel's depth is null).
                ttc = float(self.ttc_s[i])
                stixels[-1]["ttc_s"] = ttc if math.isfinite(ttc) else None
            if self.ttc_warning is not None:
                stixels[-1]["ttc_warning"] = bool(self.ttc_warning[i])
        extra: dict[str, Any] = {}
        if self.pose is not None:
            extra["pose"] = self.pose.double().tolist()
        if self.pair_info is not None:
            extra["pair"] = dict(self.pair_info)
        return {
            "format": "monostixels/1",
            "column_width": self.column_width,
            "image_size": list(self.image_size),
            "K": self.K.double().tolist(),
            "ground_normal": self.ground_normal.double().tolist(),
            "energy": [float(e) for e in self.energy],
            "flags": self.status.to_flags(),
            "compactness": self.compactness,
            **extra,
            "stixels": stixels,
        }

    def save_json(self, path: str | Path) -> None:
        """Write :meth:`to_dict` as JSON."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_dict(), indent=1))

    @staticmethod
    def from_dict(d: dict[str, Any]) -> "StixelWorld":
        """Inverse of :meth:`to_dict`."""
        if d.get("format") != "monostixels/1":
            raise InputError(f"stixels: unknown format {d.get('format')!r}, expected 'monostixels/1'")
        st = d["stixels"]
        L = lambda k, dt=torch.long: torch.tensor([s[k] for s in st], dtype=dt)  # noqa: E731
        return StixelWorld(
            column_width=int(d["column_width"]),
            image_size=(int(d["image_size"][0]), int(d["image_size"][1])),
            K=torch.tensor(d["K"], dtype=torch.float64),
            ground_normal=torch.tensor(d["ground_normal"], dtype=torch.float64),
            column=L("column"), v_top=L("v_top"), v_bottom=L("v_bottom"),
            type=torch.tensor([TYPE_NAMES.index(s["type"]) for s in st], dtype=torch.long),
            cls=torch.tensor([CLASS_NAMES.index(s["class"]) for s in st], dtype=torch.long),
            inverse_depth=L("inverse_depth", torch.float64),
            motion=torch.tensor([s["motion"] for s in st], dtype=torch.float64).reshape(-1, 3),
            cost=L("cost", torch.float64),
            tau=torch.tensor([s["tau"] for s in st], dtype=torch.float64).reshape(-1, 2),
            energy=torch.tensor(d["energy"], dtype=torch.float64),
            status=FrameStatus.from_flags(d.get("flags", {})),
            track_id=L("track_id") if st and "track_id" in st[0] else None,
            velocity=(torch.tensor([s["velocity"] for s in st], dtype=torch.float64).reshape(-1, 3)
                      if st and "velocity" in st[0] else None),
            ttc_s=(torch.tensor([math.inf if s["ttc_s"] is None else s["ttc_s"] for s in st], dtype=torch.float64)
                   if st and "ttc_s" in st[0] else None),
            ttc_warning=L("ttc_warning", torch.bool) if st and "ttc_warning" in st[0] else None,
            pose=torch.tensor(d["pose"], dtype=torch.float64) if "pose" in d else None,
            pair_info=dict(d["pair"]) if "pair" in d else None,
        )

    @staticmethod
    def load_json(path: str | Path) -> "StixelWorld":
        """Read a file written by :meth:`save_json`."""
        path = Path(path)
        try:
            d = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise InputError(f"stixels file {path}: cannot read ({e})") from e
        return StixelWorld.from_dict(d)

    def save_npz(self, path: str | Path) -> None:
        """Write all fields as arrays to a ``.npz`` file (flags as a JSON string)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {k: getattr(self, k).detach().cpu().numpy() for k in _TENSOR_FIELDS}
        arrays |= {k: getattr(self, k).detach().cpu().numpy() for k in _OPTIONAL_FIELDS if getattr(self, k) is not None}
        if self.pair_info is not None:
            arrays["pair"] = np.array(json.dumps(self.pair_info))
        np.savez(
            path, column_width=self.column_width, image_size=np.array(self.image_size),
            K=self.K.detach().cpu().numpy(), ground_normal=self.ground_normal.detach().cpu().numpy(),
            energy=self.energy.detach().cpu().numpy(), flags=json.dumps(self.status.to_flags()), **arrays,
        )

    @staticmethod
    def load_npz(path: str | Path) -> "StixelWorld":
        """Read a file written by :meth:`save_npz`."""
        try:
            z = np.load(Path(path), allow_pickle=False)
        except (OSError, ValueError) as e:
            raise InputError(f"stixels file {path}: cannot read ({e})") from e
        t = {k: torch.from_numpy(z[k]) for k in _TENSOR_FIELDS}
        t |= {k: torch.from_numpy(z[k]) for k in _OPTIONAL_FIELDS if k in z.files}
        if "pair" in z.files:
            t["pair_info"] = json.loads(str(z["pair"]))
        return StixelWorld(
            column_width=int(z["column_width"]), image_size=tuple(int(x) for x in z["image_size"]),
            K=torch.from_numpy(z["K"]), ground_normal=torch.from_numpy(z["ground_normal"]),
            energy=torch.from_numpy(z["energy"]), status=FrameStatus.from_flags(json.loads(str(z["flags"]))), **t,
        )
