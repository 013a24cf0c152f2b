"""The batched solver against the loop reference, exhaustive enumeration and exact planar scenes."""
from __future__ import annotations

import math

import pytest
import torch

from monostixels._checks import InputError
from monostixels.core.classes import DYNAMIC_OBJECT, GROUND, SKY, STATIC_OBJECT
from monostixels.core.energy import PriorParams
from monostixels.core.geometry import Camera, Motion, intrinsics, rotation_yaw
from tests.reference import column_energy, exhaustive_column, reference_column
from monostixels.core.columns import prepare_columns
from monostixels.core.solver import SolverConfig, solve, solve_columns

from tests import _planes


def random_problem(seed: int, *, H: int = 12, W: int = 10, sem: bool = True, stride: int = 1,
                   zero_structure: bool = False, degenerate: bool = False):
    """A random small problem: random flow, covariance, scores, camera, motion and priors."""
    g = torch.Generator().manual_seed(seed)
    rnd = lambda: float(torch.rand(1, generator=g))  # noqa: E731
    K = intrinsics(50 + 10 * rnd(), 45 + 10 * rnd(), 4.3, 3.1 + rnd())
    cam = Camera(K, height=1.2 + rnd())
    t = torch.tensor([0.1 * rnd() - 0.05, 0.02 * rnd(), 0.5 + rnd()], dtype=torch.float64)
    if degenerate:
        t = t * 1e-3
    mot = Motion(rotation_yaw(0.02 * (rnd() - 0.5)), t)
    flow = torch.randn(1, 2, H, W, generator=g, dtype=torch.float64) * 2
    cov = torch.eye(2, dtype=torch.float64) * (0.3 + torch.rand(1, H, W, 1, 1, generator=g, dtype=torch.float64))
    scores = torch.softmax(torch.randn(1, 10, H, W, generator=g, dtype=torch.float64) * 2, 1) if sem else None
    cfg = SolverConfig.from_yaml(column_width=5, cell_rows=2, dtype="float64", hypothesis_stride=stride)
    prm = PriorParams(**{k: 5 * rnd() for k in PriorParams.names()})
    if zero_structure:
        for k in ("alpha_grav_below", "beta_grav_below", "alpha_grav_above", "beta_grav_above",
                  "alpha_ord", "beta_ord", "alpha_flat", "beta_flat"):
            setattr(prm, k, 0.0)
    prob = prepare_columns(flow, cov, scores, [cam], [mot], cfg)
    return prob, prm, cfg


@pytest.mark.parametrize("backend", ["eager", "auto"])
@pytest.mark.parametrize("seed", range(56))
def test_batched_equals_reference(seed, backend):
    """Same optimal energy (relative 1e-5) as the loop reference, with random priors.

    ``auto`` is the fused C++ kernel where it builds (tests/test_solver_fast.py), else eager.
    """
    prob, prm, cfg = random_problem(seed, sem=seed % 3 != 0, stride=1 + seed % 3, degenerate=seed % 7 == 0)
    cfg = SolverConfig.from_yaml(**{**cfg.__dict__, "backend": backend})
    sol = solve_columns(prob, prm, cfg)
    for c in range(prob.num_columns):
        e_ref, stixels = reference_column(prob, c, prm, cfg)
        assert math.isclose(float(sol.energy[c]), e_ref, rel_tol=1e-5, abs_tol=1e-8), (c, float(sol.energy[c]), e_ref)
        # The reported per-stixel costs add up to the column energy.
        m = sol.col == c
        assert math.isclose(float(sol.cost[m].sum()), e_ref, rel_tol=1e-5, abs_tol=1e-8)


@pytest.mark.parametrize("seed", range(8))
def test_solution_energy_reevaluates(seed):
    """The returned labelled segmentation has exactly the reported energy under column_energy."""
    prob, prm, cfg = random_problem(100 + seed, sem=True)
    sol = solve_columns(prob, prm, cfg)
    for c in range(prob.num_columns):
        _, ref = reference_column(prob, c, prm, cfg)
        segs = [(s.b, s.t, s.type, s.cls, s.h) for s in ref]
        assert math.isclose(column_energy(prob, c, prm, cfg, segs), float(sol.energy[c]), rel_tol=1e-9, abs_tol=1e-9)
        m = sol.col == c
        assert [int(x) for x in sol.b[m]] == [s.b for s in ref]
        assert [int(x) for x in sol.type[m]] == [s.type for s in ref]


@pytest.mark.parametrize("seed", range(4))
def test_dp_is_exact_without_structural_priors(seed):
    """Without predecessor-dependent priors the DP optimum equals exhaustive enumeration."""
    prob, prm, cfg = random_problem(200 + seed, H=8, W=5, stride=2, zero_structure=True)
    sol = solve_columns(prob, prm, cfg)
    assert math.isclose(float(sol.energy[0]), exhaustive_column(prob, 0, prm, cfg), rel_tol=1e-9)


def test_dp_never_below_exhaustive():
    """With structural priors the DP is an approximation: never better than exhaustive search."""
    prob, prm, cfg = random_problem(300, H=8, W=5, stride=2)
    sol = solve_columns(prob, prm, cfg)
    assert float(sol.energy[0]) >= exhaustive_column(prob, 0, prm, cfg) - 1e-9


def test_soft_dp_converges_to_hard():
    prob, prm, cfg = random_problem(7, sem=True)
    hard = solve_columns(prob, prm, cfg).energy
    gaps = []
    for tau in (1.0, 0.1, 0.01, 0.001):
        soft = solve_columns(prob, prm, SolverConfig.from_yaml(**{**cfg.__dict__, "tau": tau})).energy
        assert bool((soft <= hard + 1e-9).all())  # a soft-min is below the min
        gaps.append(float((hard - soft).abs().max()))
    assert gaps[-1] < 0.02 and gaps == sorted(gaps, reverse=True)


def test_soft_dp_gradcheck():
    """Gradients of the soft optimal energy w.r.t. prior parameters (float64 finite differences)."""
    prob, prm0, cfg = random_problem(11, sem=True)
    cfg = SolverConfig.from_yaml(**{**cfg.__dict__, "tau": 0.5})
    names = ["beta_mc", "alpha_grav_above", "beta_grav_below", "alpha_ord", "beta_flat", "alpha_F", "alpha_L", "delta_F", "delta_L"]

    def energy(*vals):
        prm = PriorParams(**{**prm0.__dict__, **dict(zip(names, vals))})
        return solve_columns(prob, prm, cfg).energy.sum()

    x = tuple(torch.tensor(float(getattr(prm0, k)), dtype=torch.float64, requires_grad=True) for k in names)
    assert torch.autograd.gradcheck(energy, x, eps=1e-6, atol=1e-5, rtol=1e-4)
    # beta_mc counts stixels: its gradient is the expected number of stixels (>= columns).
    g = torch.autograd.grad(energy(*x), x[0])[0]
    assert float(g) >= prob.num_columns - 1e-6


# -------------------------------------------------------------------------------------- planar scene
@pytest.fixture(scope="module", params=[1, 3], ids=["r1", "r3"])
def planar(request):
    flow, cov, scores, truth = _planes.build_scene()
    cfg = SolverConfig.from_yaml(column_width=_planes.WS, cell_rows=request.param, dtype="float64")
    prm = PriorParams.from_yaml()
    st = solve(flow, cov, scores, _planes.CAM, _planes.MOTION, prm, cfg)
    return st, truth, cfg


def _column(st, c):
    m = st.column == c
    return {k: getattr(st, k)[m] for k in ("v_top", "v_bottom", "type", "cls", "inverse_depth", "motion")}


def test_planar_scene_segmentation_and_depths(planar):
    st, truth, cfg = planar
    r = cfg.cell_rows
    for tr in truth:
        col = _column(st, tr["column"])
        obj = tr["obj"]
        want_type = DYNAMIC_OBJECT if obj.cls >= 6 else STATIC_OBJECT
        is_obj = col["type"] == want_type
        assert int(is_obj.sum()) == 1, (tr["column"], col)
        k = int(torch.nonzero(is_obj)[0])
        # Boundaries within one cell.
        assert abs(int(col["v_bottom"][k]) - tr["foot_v"]) <= r
        assert abs(int(col["v_top"][k]) - tr["top_v"]) <= r
        assert int(col["type"][0]) == GROUND and int(col["type"][-1]) in (SKY, want_type)
        assert int(col["cls"][k]) == obj.cls
        depth = 1 / float(col["inverse_depth"][k])
        # A depth from the ground contact has its row at a cell boundary: at r = 1 within half a
        # row of the true contact; at larger r within one cell (the ground-ray depth changes by
        # z^2 / (f h) per row).
        rows_err = 0.5 if r == 1 else r
        contact_tol = rows_err * obj.dist / (float(_planes.K[1, 1]) * _planes.CAM.height)
        if want_type == STATIC_OBJECT:
            # From the flow (1 %) or from the standing hypothesis (the contact's tolerance).
            assert abs(depth / obj.dist - 1) < max(0.01, contact_tol), (tr["column"], depth, obj.dist)
        else:
            tol = 0.02 if r == 1 else contact_tol
            assert abs(depth / obj.dist - 1) < tol, (tr["column"], depth, obj.dist)
            delta = torch.tensor(obj.delta, dtype=torch.float64)
            assert float((col["motion"][k] - delta).norm()) < 0.05, (tr["column"], col["motion"][k], delta)
        # Ground below the object at the camera height.
        assert abs(1 / float(col["inverse_depth"][0]) - _planes.CAM.height) < 0.01 * _planes.CAM.height


def test_planar_scene_depth_map(planar):
    """Dense depth from ray-plane intersection equals the analytic depth on the objects."""
    st, truth, cfg = planar
    depth = st.depth_map()
    for tr in truth[::3]:
        c, obj = tr["column"], tr["obj"]
        if obj.cls >= 6 and cfg.cell_rows > 1:
            continue  # dynamic depth: quantised by the cell of the ground contact (see above)
        v = (tr["foot_v"] + tr["top_v"]) // 2
        uc = c * _planes.WS + 2
        ray = torch.linalg.inv(_planes.K) @ torch.tensor([uc, v, 1.0], dtype=torch.float64)
        from monostixels.core.geometry import object_normals

        n_o = object_normals(_planes.K, _planes.CAM.ground_normal.double(), torch.tensor(uc, dtype=torch.float64))
        z_true = obj.dist / float(ray @ n_o)
        # 2 %, or the ground contact's cell quantisation where the depth comes from the scene model
        # (a standing hypothesis: far objects, whose flow barely depends on their depth).
        rows_err = 0.5 if cfg.cell_rows == 1 else cfg.cell_rows
        tol = max(0.02, rows_err * obj.dist / (float(_planes.K[1, 1]) * _planes.CAM.height))
        assert abs(float(depth[v, uc]) / z_true - 1) < tol


def test_planar_scene_float32_matches_float64():
    flow, cov, scores, _ = _planes.build_scene()
    st = {}
    for dt in ("float32", "float64"):
        cfg = SolverConfig.from_yaml(column_width=_planes.WS, cell_rows=3, dtype=dt)
        dtype = torch.float32 if dt == "float32" else torch.float64
        st[dt] = solve(flow.to(dtype), cov.to(dtype), scores.to(dtype), _planes.CAM, _planes.MOTION,
                       PriorParams.from_yaml(), cfg)
    assert torch.equal(st["float32"].type, st["float64"].type)
    assert torch.equal(st["float32"].v_bottom, st["float64"].v_bottom)
    assert torch.allclose(st["float32"].inverse_depth, st["float64"].inverse_depth, rtol=1e-3)


def test_degenerate_motion_is_flagged_and_uses_scene_model():
    flow, cov, scores, truth = _planes.build_scene()
    still = Motion(torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    st = solve(torch.zeros_like(flow), cov, scores, _planes.CAM, still, PriorParams.from_yaml(),
               SolverConfig.from_yaml(column_width=_planes.WS, cell_rows=2, dtype="float64"))
    assert st.flags["degenerate_motion"] and "scene model" in st.flags["reason"]
    # Ground at the camera height; objects standing on it (depth from their foot).
    g = st.type == GROUND
    assert torch.allclose(1 / st.inverse_depth[g], torch.tensor(_planes.CAM.height, dtype=torch.float64))
    wall = [tr for tr in truth if tr["obj"].cls == 3][0]
    col = _column(st, wall["column"])
    k = int(torch.nonzero(col["type"] == STATIC_OBJECT)[0])
    assert abs(1 / float(col["inverse_depth"][k]) / wall["obj"].dist - 1) < 0.05


def test_ground_and_sky_keep_to_their_side_of_the_horizon():
    # A forward-moving camera and the flow of the ground plane's homography over the whole image:
    # above the horizon that flow is the plane's mirror image behind the camera, which no ground
    # can produce (on real images: noise near the focus of expansion that a far ground fits).
    from monostixels.core.geometry import apply_homography, homography

    H, W, cy = 60, 20, 24.5
    K = intrinsics(60.0, 60.0, 9.5, cy)
    cam = Camera(K, height=1.5)
    mot = Motion(torch.eye(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    Hg = homography(K, mot.R, mot.t, cam.ground_normal.double(), torch.tensor(1 / 1.5, dtype=torch.float64))
    up, vp = apply_homography(Hg, u, v)
    flow = torch.stack([up - u, vp - v])
    cov = (0.25 * torch.eye(2, dtype=torch.float64)).expand(H, W, 2, 2).clone()
    st = solve(flow, cov, None, cam, mot, PriorParams.from_yaml(),
               SolverConfig.from_yaml(column_width=5, cell_rows=2, dtype="float64"))
    g = st.type == GROUND
    assert bool(g.any())
    # Every ground stixel ends at the horizon (within one cell).
    assert float(st.v_top[g].min()) >= cy - 2
    # Zero flow everywhere (all far away): never sky below the horizon (far objects there).
    st0 = solve(torch.zeros_like(flow), cov, None, cam, mot, PriorParams.from_yaml(),
                SolverConfig.from_yaml(column_width=5, cell_rows=2, dtype="float64"))
    sky = st0.type == SKY
    assert not bool(sky.any()) or float(st0.v_bottom[sky].max()) <= cy + 2
    assert bool(((st0.type == STATIC_OBJECT) | (st0.type == DYNAMIC_OBJECT)).any())


# -------------------------------------------------------------------------------------- bad input
def _good():
    H, W = 12, 10
    return (torch.zeros(2, H, W), torch.eye(2).expand(H, W, 2, 2).clone(), torch.full((10, H, W), 0.1),
            Camera(intrinsics(50, 50, 5, 6)), Motion(torch.eye(3), torch.tensor([0.0, 0.0, 1.0])))


def test_bad_inputs_fail_clearly():
    flow, cov, sc, cam, mot = _good()
    cfg, prm = SolverConfig.from_yaml(cell_rows=2), PriorParams.from_yaml()
    nan_flow = flow.clone()
    nan_flow[0, 3, 4] = float("nan")
    with pytest.raises(InputError, match="flow: 1 non-finite"):
        solve(nan_flow, cov, sc, cam, mot, prm, cfg)
    with pytest.raises(InputError, match="semantic scores: expected \\(10, H, W\\)"):
        solve(flow, cov, sc[:9], cam, mot, prm, cfg)
    with pytest.raises(InputError, match="differ in size"):
        solve(flow, cov, torch.full((10, 12, 11), 0.1), cam, mot, prm, cfg)
    with pytest.raises(InputError, match="covariance"):
        solve(flow, cov[:, :5], sc, cam, mot, prm, cfg)
    with pytest.raises(InputError, match="positive definite"):
        solve(flow, torch.zeros_like(cov), sc, cam, mot, prm, cfg)
    with pytest.raises(InputError, match="not a rotation"):
        Motion(2 * torch.eye(3), torch.zeros(3))
    with pytest.raises(InputError, match="K: not a pinhole"):
        Camera(torch.zeros(3, 3))
    with pytest.raises(InputError, match="solver.cell_rows"):
        SolverConfig.from_yaml(cell_rows=0)
    with pytest.raises(InputError, match="solver.rows: unknown setting"):
        SolverConfig.from_yaml(rows=3)
    with pytest.raises(InputError, match="prior.beta_mc: expected a number, got 'big'"):
        PriorParams.from_yaml(beta_mc="big")
    with pytest.raises(InputError, match="prior.beta_mc: must be >= 0"):
        PriorParams.from_yaml(beta_mc=-1.0)


def test_image_sizes_not_multiple_of_cells():
    """Partial last column and partial top cell are kept, not dropped."""
    flow, cov, sc, cam, mot = _good()
    st = solve(flow[:, :11, :9], cov[:11, :9], sc[:, :11, :9], cam, mot, PriorParams.from_yaml(), SolverConfig.from_yaml(column_width=4, cell_rows=3))
    assert st.num_columns == 3
    for c in range(3):
        col = _column(st, c)
        assert int(col["v_bottom"].max()) == 10 and int(col["v_top"].min()) == 0
    assert bool((st.index_map() >= 0).all())


def _flow_fails(horizon_row: float, first: int, second: int):
    """A 40 x 10 image where no type fits the flow (noise of 40 px), the horizon at ``horizon_row``, and
    the net's scores: class ``first`` 0.6 everywhere, ``second`` 0.31. Returns the solver's inputs but
    its config and the rows' angle to the horizon (degrees, positive below)."""
    H, W = 40, 10
    K = intrinsics(50.0, 50.0, 4.5, horizon_row)
    cam = Camera(K, height=1.5)
    mot = Motion(torch.eye(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    g = torch.Generator().manual_seed(0)
    flow = 40.0 * torch.randn(2, H, W, generator=g, dtype=torch.float64)  # no type fits it
    cov = torch.eye(2, dtype=torch.float64).expand(H, W, 2, 2).clone()
    scores = torch.full((10, H, W), 0.01, dtype=torch.float64)
    scores[first] = 0.6
    scores[second] = 0.31
    below_deg = torch.rad2deg(torch.atan((torch.arange(H, dtype=torch.float64) - horizon_row) / 50.0))
    return flow, cov, scores, cam, mot, PriorParams.from_yaml(), below_deg


def test_no_sky_far_below_the_horizon():
    """Where the flow fails everywhere and the net reads the lower rows as sky (bright road), the sky
    no longer reaches down there: more than ``sky_horizon_margin_deg`` below the horizon it pays both
    caps. Off (``.inf``), the net's score decides and the bottom of the column is sky."""
    flow, cov, scores, cam, mot, prm, below_deg = _flow_fails(5.0, 9, 0)  # sky (class 9) first, road second
    deep = below_deg > 5.0  # rows more than 5 deg below the horizon
    for margin, sky_deep in ((5.0, False), (math.inf, True)):
        cfg = SolverConfig.from_yaml(column_width=5, cell_rows=2, dtype="float64", sky_horizon_margin_deg=margin)
        st = solve(flow, cov, scores, cam, mot, prm, cfg)
        sky = st.type_map() == SKY
        assert bool(sky[deep].any()) == sky_deep
    for bad in (-1.0, ".inf", None):
        with pytest.raises(InputError, match="sky_horizon_margin_deg"):
            SolverConfig.from_yaml(sky_horizon_margin_deg=bad)
    assert SolverConfig.from_yaml(sky_horizon_margin_deg="inf").sky_horizon_margin_deg == math.inf


def test_no_ground_far_above_the_horizon():
    """A vehicle that drives along with the camera has the sky's flow (none): the static types fail
    on it. Where the net reads it as road, ground no longer reaches more than
    ``ground_horizon_margin_deg`` above the horizon, where its depth would be negative: there it pays
    both caps and the sky (the net's second class) wins. Off (``.inf``), the net's score decides."""
    flow, cov, scores, cam, mot, prm, below_deg = _flow_fails(30.0, 0, 9)  # road first, sky (class 9) second
    high = below_deg < -5.0  # rows more than 5 deg above the horizon
    for margin, ground_high in ((5.0, False), (math.inf, True)):
        cfg = SolverConfig.from_yaml(column_width=5, cell_rows=2, dtype="float64", ground_horizon_margin_deg=margin)
        st = solve(flow, cov, scores, cam, mot, prm, cfg)
        ground = st.type_map() == GROUND
        assert bool(ground[high].any()) == ground_high
        if not ground_high:
            assert bool((st.type_map()[high] == SKY).all())
    for bad in (-1.0, ".inf", None):
        with pytest.raises(InputError, match="ground_horizon_margin_deg"):
            SolverConfig.from_yaml(ground_horizon_margin_deg=bad)
