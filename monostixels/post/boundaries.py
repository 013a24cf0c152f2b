"""Moving objects' tops at pixel rows: the DP's semantic term, re-read row by row at the boundary.

The DP places stixel boundaries on cell edges (``solver.cell_rows`` rows). Where a moving object
meets the background above it (sky, or a farther object), the cell that straddles the boundary
holds both; DeepFlow smooths its flow across the motion boundary, and the cell often goes to the
background. Its object pixels then get the background's depth (a car 6 m away read as a house
80 m away: a relative error of ~10 per pixel), so these few pixels carry a large share of the
movers' depth error (docs/experiments.md, "Tops of movers").

After the DP (and the mover check), each such boundary moves to the row, within ``rows`` rows of
the DP's, that minimises the semantic term of the two stixels over those rows at pixel-row
resolution: ``min(-log s_c(v), alpha_L)`` per row, ``s_c(v)`` the class score averaged over the
column's pixels of row ``v`` (the DP's term, per cell), the lower stixel's class below the
boundary and the upper one's above. The flow term is left out: across a motion boundary it is
the smoothed flow that put the cell on the wrong side. Depths, types and classes stay as the DP
chose them; only ``v_top`` of the object and ``v_bottom`` of the stixel above change, so a
dynamic stixel keeps its ground contact. The stixels' ``cost`` and the world's ``energy`` remain
those of the DP's cell-level solution.
"""
from __future__ import annotations

import dataclasses

import torch

from monostixels._checks import InputError, check_shape
from monostixels.core.classes import DYNAMIC_OBJECT, NUM_CLASSES, SKY, STATIC_OBJECT
from monostixels.core.solver_config import REFINE_OBJECTS
from monostixels.core.stixels import StixelWorld

__all__ = ["REFINE_OBJECTS", "row_class_cost", "refine_object_tops"]



def row_class_cost(scores: torch.Tensor, column_width: int, alpha_L: float) -> torch.Tensor:
    """Semantic cost of every class per image row and stixel column.

    Args:
        scores: (10, H, W) class scores (probabilities).
        column_width: ``w_s`` pixels.
        alpha_L: cap of the cost per row (the prior's ``alpha_L``).

    Returns:
        (10, H, C) float64, ``C = ceil(W / w_s)``: ``min(-log mean_u s_c(v, u), alpha_L)`` over the
        column's pixels ``u`` (a last, narrower column over its own pixels).
    """
    check_shape(scores, (NUM_CLASSES, None, None), "semantic scores")
    _, H, W = scores.shape
    C = -(-W // column_width)
    which = torch.arange(W) // column_width
    summed = torch.zeros(NUM_CLASSES, H, C, dtype=torch.float64).index_add_(2, which, scores.double())
    mean = summed / torch.bincount(which, minlength=C).double()
    return (-mean.clamp(min=1e-12).log()).clamp(max=float(alpha_L))


def refine_object_tops(world: StixelWorld, scores: torch.Tensor, rows: int, depth_ratio: float,
                       alpha_L: float, objects: str = "dynamic") -> StixelWorld:
    """Move each object's top to the row of least semantic cost within ``rows`` rows (module docstring).

    A boundary moves where the stixel below is an object of ``objects`` and the one above is sky or
    an object more than ``depth_ratio`` times farther. Each stixel keeps at least one row: a
    boundary cannot pass the other boundary of either stixel, even where that one moves too (a
    stixel too thin for that keeps the DP's boundary). Ties keep the DP's boundary.

    Args:
        world: the stixels of one frame (rows at cell edges, as the solver gives them).
        scores: (10, H, W) the class scores the solver was given.
        rows: search half-width in pixel rows (0 = return ``world`` unchanged).
        depth_ratio: how much farther (>= 1) an object above must be for its boundary to move.
        alpha_L: the prior's cap of the semantic cost per row.
        objects: ``dynamic`` (the tops of dynamic object stixels) or ``all`` (static ones too).

    Returns:
        A new :class:`StixelWorld` with moved ``v_top`` / ``v_bottom``; everything else shared.
    """
    if not (isinstance(rows, int) and rows >= 0):
        raise InputError(f"solver.top_refine_rows: an integer >= 0, got {rows!r}")
    if not 1.0 <= depth_ratio < float("inf"):
        raise InputError(f"solver.top_refine_depth_ratio: a number >= 1, got {depth_ratio!r}")
    if objects not in REFINE_OBJECTS:
        raise InputError(f"solver.top_refine_objects: one of {', '.join(REFINE_OBJECTS)}, got {objects!r}")
    H, W = world.image_size
    check_shape(scores, (NUM_CLASSES, H, W), "semantic scores")
    if rows == 0 or len(world) < 2:
        return world
    col, typ, cls, p = world.column, world.type, world.cls, world.inverse_depth.double()
    top, bot = world.v_top.clone(), world.v_bottom.clone()
    # Stixels are sorted by column, bottom to top: k + 1 is the one above k in the same column.
    lo, up = torch.arange(len(world) - 1), torch.arange(1, len(world))
    is_obj = (typ == STATIC_OBJECT) | (typ == DYNAMIC_OBJECT)
    farther = is_obj[up] & (p[up] * depth_ratio < p[lo])
    movable = torch.isin(typ, torch.tensor(REFINE_OBJECTS[objects]))
    snap = (col[lo] == col[up]) & movable[lo] & ((typ[up] == SKY) | farther)
    if not bool(snap.any()):
        return world
    # A stixel's other boundary may move by up to `rows` as well: keep clear of it.
    top_moves = torch.zeros(len(world), dtype=torch.bool)
    bot_moves = torch.zeros(len(world), dtype=torch.bool)
    top_moves[lo[snap]] = True
    bot_moves[up[snap]] = True
    lo, up = lo[snap], up[snap]
    b = top[lo]  # the DP's boundary: first row of the object below
    first = top[up] + 1 + torch.where(top_moves[up], rows, 0)  # the stixel above keeps >= 1 row
    last = bot[lo] - torch.where(bot_moves[lo], rows, 0)  # the object keeps >= 1 row
    offsets = torch.arange(-rows, rows + 1)
    cand = b[:, None] + offsets[None, :]
    ok = (cand >= first[:, None]) & (cand <= last[:, None])
    # Cost over the window [b - rows, b + rows]: the upper class above the candidate, the lower below.
    w0, w1 = (b - rows).clamp(0, H), (b + rows + 1).clamp(0, H)
    c, cu, cl = col[lo].long(), cls[up].long(), cls[lo].long()
    cc = cand.clamp(0, H)
    # prefix[k, v]: cost of class/column pair k over rows 0 .. v - 1, for the pairs read only.
    pairs, inv = torch.unique(torch.cat([cu * world.num_columns + c, cl * world.num_columns + c]), return_inverse=True)
    prefix = _prefix_costs(scores, pairs // world.num_columns, pairs % world.num_columns, world.column_width, alpha_L)
    ku, kl = inv[: len(c)], inv[len(c):]
    above = prefix[ku[:, None], cc] - prefix[ku, w0][:, None]
    below = prefix[kl, w1][:, None] - prefix[kl[:, None], cc]
    total = torch.where(ok, above + below, torch.full_like(above, float("inf")))
    total = torch.where(offsets[None, :] == 0, total - 1e-9, total)
    best = cand.gather(1, total.argmin(1, keepdim=True))[:, 0]
    new_b = torch.where(ok[:, rows], best, b)
    top[lo] = new_b
    bot[up] = new_b - 1
    return dataclasses.replace(world, v_top=top, v_bottom=bot)


def _prefix_costs(scores: torch.Tensor, classes: torch.Tensor, columns: torch.Tensor, column_width: int,
                  alpha_L: float) -> torch.Tensor:
    """Prefix sums over rows (K, H + 1) float64 of :func:`row_class_cost` for K (class, column) pairs only.

    Bit-identical to the rows of ``row_class_cost(...).cumsum(1)``: each column's mean adds its pixels
    left to right in float64 as ``index_add_`` does, and a cumulative sum runs row by row either way.
    """
    _, H, W = scores.shape
    c0 = columns * column_width
    n = (torch.clamp(c0 + column_width, max=W) - c0).double()  # a last, narrower column
    summed = torch.zeros(len(classes), H, dtype=torch.float64)
    for j in range(column_width):
        u = c0 + j
        inside = u < W
        summed += torch.where(inside[:, None], scores[classes, :, u.clamp(max=W - 1)].double(), 0.0)
    cost = (-(summed / n[:, None]).clamp(min=1e-12).log()).clamp(max=float(alpha_L))
    return torch.cat([torch.zeros(len(classes), 1, dtype=torch.float64), cost.cumsum(1)], 1)
