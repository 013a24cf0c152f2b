"""The road plane between two frames: its pixels, its flow's homography and the photometric scale search.

Used by :func:`monostixels.inputs.motion.estimate_mono` for the metric scale of the camera's
translation (steps 4a and 4c of that module's docstring):

- :func:`ground_candidates`: pixels whose viewing ray meets the configured ground ahead;
- :func:`ground_system` and :func:`fit_ground`: the ground homography ``K (R + t̂ m^T) K^-1`` is
  linear in ``m = (s / h) n``; RANSAC and least squares over the flow of those pixels;
- :func:`photometric_ground`: the previous image warped onto the current one by the ground
  homography, its metric length and road normal searched for the least median grey difference
  (a 1-D grid over the length, then a pattern search), with the grid's candidates evaluated in
  threads; :func:`photometric_inputs` prepares its grey images and pixels.

Convention (docs/conventions.md, section 2): ``X_prev = R X_cur + t``; pixels ``(u, v)``, metres.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import torch

from monostixels._pools import helper_pool
from monostixels.inputs.confidence import to_gray
from monostixels.inputs.motion_base import MonoParams

#: Semantic class id of road (classes.CLASS_NAMES): the plane the mounting height refers to.
ROAD_CLASS = 0


def rays(K: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Viewing rays (N, 3) with z = 1 of pixels (N, 2)."""
    return np.c_[pts, np.ones(len(pts))] @ np.linalg.inv(K).T


def ground_candidates(K: np.ndarray, n: np.ndarray, height: float, pts: np.ndarray, prm: MonoParams,
                       lateral: bool = True) -> np.ndarray:
    """Mask (N,) of pixels whose ray meets the reference ground ahead within the road region.

    ``lateral=False`` drops the corridor of ``ground_half_width``: with semantic road labels the
    road pixels are known wherever they are, and a vehicle ahead can block the corridor.
    """
    r = rays(K, pts)
    rn = r @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.where(rn > 1e-6, height / rn, np.inf)  # X = lam r on the ground n^T X = h
    X = r * np.where(np.isfinite(lam), lam, 0.0)[:, None]
    near = np.isfinite(lam) & (X[:, 2] < prm.ground_max_distance)
    return near & (np.abs(X[:, 0]) < prm.ground_half_width) if lateral else near


def ground_system(K: np.ndarray, R: np.ndarray, t: np.ndarray, p_cur: np.ndarray, p_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear equations ``A m = b`` (2N, 3), (2N,) of ground pixels for ``H = K (R + t m^T) K^-1``.

    With ``y = K^-1 x``, ``a = K R y``, ``c = K t``: ``H x = a + c (m^T y)`` and ``x_prev × H x = 0``
    give ``(u' c_3 - c_1) y^T m = a_1 - u' a_3`` and the same in ``v'``; dividing by ``a_3``
    (≈ the third coordinate of ``H x``) makes the residuals close to pixels.
    """
    y = rays(K, p_cur)
    a = y @ (K @ R).T
    c = K @ t
    up, vp = p_prev[:, 0], p_prev[:, 1]
    w = 1.0 / a[:, 2:3]
    A = np.concatenate([y * ((up * c[2] - c[0])[:, None]) * w, y * ((vp * c[2] - c[1])[:, None]) * w])
    b = np.concatenate([(a[:, 0] - up * a[:, 2]) * w[:, 0], (a[:, 1] - vp * a[:, 2]) * w[:, 0]])
    return A, b


def tilt_deg(m: np.ndarray, n_g: np.ndarray) -> float:
    """Angle (degrees) between the plane vector ``m`` and the unit normal ``n_g``."""
    q = float(np.linalg.norm(m))
    return math.degrees(math.acos(np.clip(float(m @ n_g) / max(q, 1e-30), -1.0, 1.0)))


#: Residuals per block of the ground RANSAC's scoring (hypotheses x pixels): blocks of about 0.5 MB.
_RANSAC_CHUNK = 65536


def fit_ground(A: np.ndarray, b: np.ndarray, thr: float, rng: np.random.Generator, hypotheses: int = 300,
                n_g: np.ndarray | None = None, max_tilt: float = 180.0) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC (2 pixels = 4 equations per hypothesis) + least squares of ``A m = b``; returns m and inliers (N,).

    Hypotheses tilted more than ``max_tilt`` degrees from ``n_g`` are not scored: the road is
    near the configured plane, and a wall or a car side that happens to hold more of the
    candidate pixels must not win.
    """
    N = len(A) // 2
    A_u, A_v, b_u, b_v = A[:N], A[N:], b[:N], b[N:]  # the u and v equations of each pixel

    def residual(m: np.ndarray) -> np.ndarray:
        return np.hypot(A_u @ m - b_u, A_v @ m - b_v)

    # The hypotheses' pixel pairs drawn one hypothesis after the other, as they always were (the
    # generator's stream is the same), then fitted and scored all at once: a loop of 300 small fits
    # cost ~11 ms however few the pixels.
    pairs = np.array([rng.choice(N, size=2, replace=False) for _ in range(hypotheses)]).reshape(-1, 2)
    rows = np.concatenate([pairs, pairs + N], axis=1)  # (hypotheses, 4)
    # Each 4 x 3 system's least-squares solution (the pseudo-inverse with lstsq's cut-off, rcond=None;
    # given by position: numpy 1.x calls it rcond, 2.x rtol).
    ms = (np.linalg.pinv(A[rows], 4 * np.finfo(np.float64).eps) @ b[rows][..., None])[..., 0]
    keep = np.ones(len(ms), dtype=bool)
    if n_g is not None:
        q = np.maximum(np.linalg.norm(ms, axis=1), 1e-30)
        keep = np.degrees(np.arccos(np.clip(ms @ n_g / q, -1.0, 1.0))) <= max_tilt
    scored = np.nonzero(keep)[0]
    best = None
    if len(scored):
        counts = np.empty(len(scored), dtype=np.int64)
        chunk = max(1, _RANSAC_CHUNK // max(N, 1))  # residual blocks of about _RANSAC_CHUNK values
        for s in range(0, len(scored), chunk):
            Mc = ms[scored[s:s + chunk]].T  # (3, c)
            res = np.hypot(A_u @ Mc - b_u[:, None], A_v @ Mc - b_v[:, None])
            counts[s:s + chunk] = np.count_nonzero(res < thr, axis=0)
        # The first hypothesis with the most inliers (as the loop kept it), its fit as lstsq gives it.
        h = int(scored[int(np.argmax(counts))])
        best, *_ = np.linalg.lstsq(A[rows[h]], b[rows[h]], rcond=None)
    if best is None:  # no hypothesis within the tilt: the unconstrained fit, rejected by the caller
        best, *_ = np.linalg.lstsq(A, b, rcond=None)
    m = best
    for _ in range(3):
        inl = np.nonzero(residual(m) < thr)[0]
        if len(inl) < 3:
            break
        sel = np.concatenate([inl, inl + N])
        m, *_ = np.linalg.lstsq(A[sel], b[sel], rcond=None)
    return m, residual(m) < thr


#: Candidate metric translations (metres per frame) of the photometric scale search.
_SCALE_GRID_M = np.geomspace(0.02, 5.0, 96)


#: Step halvings of the photometric pattern search (from one grid step: a final step of 1/256 of it).
_PATTERN_ROUNDS = 8
#: Warm start of the photometric search (a prediction from the stream): every this-many-th scale of
#: the grid is read (the contrast's median, a minimum far away), and the scales within this many grid
#: steps (6 % each) of the prediction.
_WARM_GRID_STRIDE = 4
_WARM_GRID_HALF_WIDTH = 3
#: Least ratio of the refined to the grid contrast that the pattern search is taken to reach (a bound with
#: a margin): a warm grid contrast above ``photometric_sharp / 0.7`` is not refined.
PATTERN_MAX_GAIN = 0.7


#: Most threads of the photometric search: its grid is 96 costs, its pattern search asks for two at
#: a time.
_MAX_PHOTOMETRIC_WORKERS = 4


#: The road reverses t only where the reversed plane explains at least this share of its vectors: a road whose
#: flow failed (highway asphalt, pulled towards zero) fits a plane by chance with 2.5-7 % of its vectors under
#: either sign (the shared highway clip, 6 of 40 pairs), a real one with 44-52 % (the KITTI traffic drive's
#: frames 1-7). Chosen between those two clips; the synthetic renders and KITTI drives 0023 / 0028 never
#: reverse. docs/experiments.md, "Camera motion on unseen footage".
ROAD_SIGN_SHARE = 0.25
#: Most road vectors of that vote (:func:`road_sign_votes`).
_SIGN_VECTORS = 2000

def road_sign_votes(Kn: np.ndarray, n_g: np.ndarray, height: float, params: MonoParams, R: np.ndarray,
                     t: np.ndarray, p_cur: np.ndarray, p_prev: np.ndarray, base: np.ndarray,
                     lateral: bool) -> tuple[int, int, int] | None:
    """The road's vectors that a plane explains with the translation ``t`` and with ``-t``, and how many it has.

    The ground's flow is linear in ``m = (s / h) n`` (:func:`ground_system`); reversing ``t`` reverses
    ``m``. Each sign gets the RANSAC of the ground fit, its hypotheses within ``ground_max_tilt`` of the
    downward normal ``n_g``: the count of road vectors (``base`` & the ground ahead) within
    ``ground_threshold`` pixels of the best plane, or 0 where the fit leaves that cone. None with fewer than
    ``min_points`` road vectors. Each fit draws from its own generator (``params.seed``), so that the
    estimator's own stream is the same with or without this test.
    """
    gidx = np.nonzero(base & ground_candidates(Kn, n_g, height, p_cur, params, lateral=lateral))[0]
    if len(gidx) < params.min_points:
        return None
    n_road = len(gidx)
    # A vote needs no more than _SIGN_VECTORS evenly spread vectors (the RANSAC's scoring is most of its time).
    gidx = gidx[:: -(-n_road // _SIGN_VECTORS)]
    A, bb = ground_system(Kn, R, t, p_cur[gidx], p_prev[gidx])
    votes = []
    for sign in (1.0, -1.0):
        # Under -t the plane vector of the same flow is -m: the fit of -A (A is linear in t).
        m, ginl = fit_ground(sign * A, bb, params.ground_threshold, np.random.default_rng(params.seed), n_g=n_g,
                              max_tilt=params.ground_max_tilt)
        votes.append(int(ginl.sum()) if float(np.linalg.norm(m)) > 0 and tilt_deg(m, n_g) <= params.ground_max_tilt else 0)
    # Counted in the road's vectors (scaled up from the ones voting).
    return votes[0] * n_road // len(gidx), votes[1] * n_road // len(gidx), n_road


def _photometric_workers() -> int:
    """Threads of the photometric search: torch's thread count, which stands for the cores this
    process may use (``--threads`` of the benchmarks, ``torch.set_num_threads``), at most 4."""
    return max(1, min(_MAX_PHOTOMETRIC_WORKERS, torch.get_num_threads()))


def _grey(image: torch.Tensor) -> np.ndarray:
    """(3, H, W) RGB in [0, 1] -> (H, W) float32 grey, lightly smoothed (a wider basin for the search)."""
    # Clipped in numpy, then the covariance's grey conversion (numpy, the same float32 values as
    # torch's weighted channel sum), without torch's thread hand-offs.
    x = np.clip(image.detach().cpu().numpy().astype(np.float32, copy=False), 0.0, 1.0)
    g = to_gray(torch.from_numpy(x)).numpy()
    return cv2.GaussianBlur(g, (0, 0), 1.0)


#: :func:`_median` of an array of at least ``64 * _MEDIAN_STRIDE`` values first brackets the middle with
#: every this-many-th value.
_MEDIAN_STRIDE = 64


def _median(x: np.ndarray) -> float:
    """``float(np.median(x))`` of a non-empty 1-D array.

    The same value as numpy (the middle order statistic, or the mean of the two middle ones
    taken in ``x``'s dtype as ``np.mean`` takes it), faster on the costs of one photometric
    candidate (the search's largest part). A long array is first bracketed: the
    middle of every :data:`_MEDIAN_STRIDE`-th value, widened by three standard deviations of a
    sample median's rank and 4 more values on each side, gives ``[lo, hi]``; where the values below
    ``lo`` are fewer than the middle's rank and those up to ``hi`` more, only the eighth or so within
    the bracket is partitioned (else, rarely, the whole array). Either way the result is exact: the bracket
    only chooses which values are partitioned. ``np.median`` partitions the whole array at three
    positions (two middles and the end, for its NaN check).
    """
    n = len(x)
    if np.isnan(x).any():
        return math.nan
    k = n // 2
    if n >= 64 * _MEDIAN_STRIDE:
        s = np.sort(x[::_MEDIAN_STRIDE])
        m = len(s)
        w = int(1.5 * math.sqrt(m)) + 4  # the sample median's rank: standard deviation sqrt(m) / 2
        lo, hi = s[max(m // 2 - w, 0)], s[min(m // 2 + w, m - 1)]
        below = int(np.count_nonzero(x < lo))
        inside = x[(x >= lo) & (x <= hi)]
        # The middle order statistics are k (odd n) or k - 1 and k (even n), 0-based.
        if below <= k - (1 - n % 2) and k < below + len(inside):
            j = k - below
            if n % 2:
                return float(np.partition(inside, j)[j])
            part = np.partition(inside, [j - 1, j])
            return float(np.mean(np.array([part[j - 1], part[j]], dtype=x.dtype)))
    part = np.partition(x, k)
    if n % 2:
        return float(part[k])
    return float(np.mean(np.array([part[:k].max(), part[k]], dtype=x.dtype)))


def _sample(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples (N,) of ``img`` at (u, v) (maps are reshaped: OpenCV caps their sides at 32767)."""
    n = len(u)
    cols = 1024
    rows = -(-n // cols)
    mu = np.empty(rows * cols, dtype=np.float32)
    mv = np.empty(rows * cols, dtype=np.float32)
    mu[:n] = u
    mv[:n] = v
    mu[n:] = 0.0
    mv[n:] = 0.0
    return cv2.remap(img, mu.reshape(rows, cols), mv.reshape(rows, cols), cv2.INTER_LINEAR).reshape(-1)[:n]


def photometric_ground(cur: np.ndarray, prev: np.ndarray, K: np.ndarray, R: np.ndarray, t_unit: np.ndarray,
                        n_g: np.ndarray, height: float, pts: np.ndarray, max_tilt: float,
                        start: tuple[float, np.ndarray] | None = None,
                        unsharp: float = math.inf) -> tuple[float, np.ndarray, float] | None:
    """Metric length (m) of ``t_unit`` and road normal that best warp ``prev`` onto ``cur`` over ``pts``.

    The ground homography of a length ``s`` and normal ``n`` is ``K (R + s t̂ n^T / h) K^-1``; the
    cost is the median absolute grey difference over the ground pixels ``pts`` (N, 2) (robust to
    an object on them). A 1-D search over ``s`` with ``n = n_g`` finds the basin, then a pattern
    search refines ``(log s, n)`` with ``n`` within ``max_tilt`` degrees of ``n_g``.

    ``start = (s, n)``: a prediction (a stream's last pair at constant velocity). The 1-D search then
    reads only every :data:`_WARM_GRID_STRIDE`-th scale of its grid (enough for the median the
    contrast is measured against, and to see a minimum far from the prediction) and the scales within
    :data:`_WARM_GRID_HALF_WIDTH` grid steps of ``s``: where the best of those lies inside that window
    it is the grid's minimum, and the pattern search runs from it as from scratch (the same result,
    a third of the 1-D search's cost); else the whole grid is read. The pattern search is not started
    at the prediction itself: started there, it would keep each pair's scale near the last pair's, a
    bias the search from the grid does not have. ``unsharp``: with a start, a grid contrast
    above this is returned as it is, without the pattern search (the caller then takes another scale;
    it asks again without a start where it needs the refined minimum after all).

    Returns:
        ``(s, n (3,), contrast)``, contrast = best cost / median cost over the 1-D grid (lower is
        clearer), or None without a clear minimum.
    """
    y = rays(K, pts)
    a = y @ (K @ R).T
    c = K @ t_unit
    H, W = cur.shape
    ref = cur[pts[:, 1].astype(np.int64), pts[:, 0].astype(np.int64)]
    e1 = np.cross(n_g, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n_g, e1)  # n_g, e1 (sideways), e2 (forward): roll and pitch of the road plane

    def normal(x: np.ndarray) -> np.ndarray:
        n = n_g + x[1] * e1 + x[2] * e2
        return n / np.linalg.norm(n)

    # Per-component arrays and a cache of ``y @ n``/costs: the same float operations as on
    # (N, 3) arrays, fewer passes over memory (the search evaluates ~180 candidates per pair).
    a0, a1, a2 = (np.ascontiguousarray(a[:, i]) for i in range(3))
    c0, c1, c2 = (float(ci) for ci in c)
    yn_cache: dict[bytes, np.ndarray] = {}
    cost_cache: dict[bytes, float] = {}

    def cost(x: np.ndarray) -> float:
        key = x.tobytes()
        if key in cost_cache:
            return cost_cache[key]
        n = normal(x)
        if tilt_deg(n, n_g) > max_tilt:
            cost_cache[key] = math.inf
            return math.inf
        nkey = n.tobytes()
        yn = yn_cache.get(nkey)
        if yn is None:
            yn = y @ n
            if len(yn_cache) >= 8:  # the normals of one pattern-search step; bounded memory
                yn_cache.clear()
            yn_cache[nkey] = yn
        # k = exp(x0) y.n / h; (u, v) = (a0 + k c0, a1 + k c1) / (a2 + k c2): each product and sum of
        # the formula as written, into four arrays (fresh temporaries cost more than the arithmetic).
        k = np.multiply(yn, math.exp(x[0]))
        k /= height
        q2 = np.multiply(k, c2)
        q2 += a2
        u = np.multiply(k, c0)
        u += a0
        u /= q2
        v = np.multiply(k, c1, out=k)
        v += a1
        v /= q2
        # The usual case, every pixel in the previous image, from five reductions (a NaN fails them too).
        if q2.min() > 0 and u.min() >= 0 and u.max() <= W - 1 and v.min() >= 0 and v.max() <= H - 1:
            out = _median(np.abs(_sample(prev, u, v) - ref))
        else:
            inside = (q2 > 0) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
            n_in = int(np.count_nonzero(inside))
            if 2 * n_in < len(inside):  # fewer than half of the pixels land in the previous image
                out = math.inf
            else:
                out = _median(np.abs(_sample(prev, u[inside], v[inside]) - ref[inside]))
        cost_cache[key] = out
        return out

    # ``cost`` is a pure function of x: candidates the search will (or may) ask for next are
    # evaluated side by side into the cache (numpy and OpenCV release the GIL), and the search
    # below then runs as written, one candidate after the other, on cached values: the same
    # result as the sequential search, in less wall time.
    workers = _photometric_workers()
    pool = helper_pool("photometric", workers - 1) if workers > 1 else None

    def prefetch(xs: list[np.ndarray]) -> None:
        todo = [x for x in xs if x.tobytes() not in cost_cache]
        if pool is None or len(todo) < 2:
            return
        chunks = [todo[i::workers] for i in range(workers)]  # interleaved: the far scales are cheap
        futures = [pool.submit(lambda xs_: [cost(x_) for x_ in xs_], ch) for ch in chunks[1:] if ch]
        for x_ in chunks[0]:
            cost(x_)
        for fut in futures:
            fut.result()

    grid_step = math.log(_SCALE_GRID_M[1] / _SCALE_GRID_M[0])
    step = np.array([grid_step, 0.01, 0.01])  # 1 grid step, ~0.6 deg
    x = None
    if start is not None:
        # A sparse cover of the grid (for the contrast's median, and to see a minimum far from the
        # prediction) and the grid's scales within a window around the predicted one.
        k0 = int(round(math.log(start[0] / _SCALE_GRID_M[0]) / grid_step))
        window = range(max(k0 - _WARM_GRID_HALF_WIDTH, 0), min(k0 + _WARM_GRID_HALF_WIDTH + 1, len(_SCALE_GRID_M)))
        read = sorted(set(range(0, len(_SCALE_GRID_M), _WARM_GRID_STRIDE)) | set(window))
        grid = [np.array([math.log(_SCALE_GRID_M[k]), 0.0, 0.0]) for k in read]
        prefetch(grid)
        c_read = np.array([cost(g) for g in grid])
        fin = np.isfinite(c_read)
        if fin.sum() >= 8:
            kb = read[int(np.argmin(np.where(fin, c_read, np.inf)))]
            # The best scale read lies inside the window (not at its ends: the speed changed more than
            # the window allows) and is clear against the cover: the grid's minimum, as a full grid
            # would have found it; the pattern search then runs as from scratch.
            if window.start < kb < window.stop - 1 and 0 < kb < len(_SCALE_GRID_M) - 1:
                cover = np.array([c for k, c in zip(read, c_read) if k % _WARM_GRID_STRIDE == 0])
                costs, finite = cover, np.isfinite(cover)
                best = float(c_read[read.index(kb)])
                if best >= 0.6 * np.median(costs[finite]):
                    return None
                x = np.array([math.log(_SCALE_GRID_M[kb]), 0.0, 0.0])
                contrast = best / float(np.median(costs[finite]))
                if contrast > unsharp:
                    return math.exp(x[0]), n_g.copy(), contrast
    if x is None:
        grid = [np.array([math.log(s), 0.0, 0.0]) for s in _SCALE_GRID_M]
        prefetch(grid)
        costs = np.array([cost(g) for g in grid])
        finite = np.isfinite(costs)
        if finite.sum() < 8:
            return None
        k = int(np.argmin(np.where(finite, costs, np.inf)))
        # A clear minimum: well below the typical cost, and not at the end of the grid.
        if k in (0, len(_SCALE_GRID_M) - 1) or costs[k] >= 0.6 * np.median(costs[finite]):
            return None
        x = np.array([math.log(_SCALE_GRID_M[k]), 0.0, 0.0])
        best = costs[k]

    def trial(x: np.ndarray, d: int, sign: float) -> np.ndarray:
        out = x.copy()
        out[d] += sign * step[d]
        return out

    for _ in range(_PATTERN_ROUNDS):
        improved = True
        while improved:
            improved = False
            for d in range(3):
                # Both signs at once; when +1 improves, the -1 one was spare work of the other thread.
                prefetch([trial(x, d, 1.0), trial(x, d, -1.0)])
                for sign in (1.0, -1.0):
                    cand = trial(x, d, sign)
                    ct = cost(cand)
                    if ct < best:
                        x, best, improved = cand, ct, True
        step /= 2
    return math.exp(x[0]), normal(x), float(best / np.median(costs[finite]))


def photometric_inputs(images: tuple[torch.Tensor, torch.Tensor], road_scores: np.ndarray | None, K: np.ndarray,
                        n_g: np.ndarray, height: float, params: MonoParams,
                        rng: np.random.Generator,
                        ignore: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The grey images (current, previous) and ground pixels (N, 2) of :func:`photometric_ground`.

    The pixels are every second pixel that is road (``road_scores``: (10, H, W) class scores)
    or, without them, every second pixel of the road region ahead, less the ``ignore`` (H, W) pixels;
    at most ``photometric_pixels`` of them (a seeded subset drawn from ``rng``). They depend on the
    images, the semantics and the camera only, not on the flow.
    """
    H, W = images[0].shape[-2:]
    if road_scores is not None:
        dense_2 = np.argmax(road_scores[:, ::2, ::2], axis=0) == ROAD_CLASS
    else:
        dense_2 = np.ones(((H + 1) // 2, (W + 1) // 2), dtype=bool)
    vv, uu = np.nonzero(dense_2)  # every second pixel
    pts = np.c_[uu * 2, vv * 2].astype(np.float64)
    pts = pts[ground_candidates(K, n_g, height, pts, params, lateral=road_scores is None)]
    if ignore is not None:
        pts = pts[~ignore[pts[:, 1].astype(np.int64), pts[:, 0].astype(np.int64)]]
    if len(pts) > params.photometric_pixels:
        pts = pts[np.sort(rng.choice(len(pts), size=params.photometric_pixels, replace=False))]
    return _grey(images[0]), _grey(images[1]), pts
