"""The fused C++ column DP (solver.backend=cpp) against the eager path and the loop reference."""
from __future__ import annotations

import dataclasses
import logging
import math

import pytest
import torch

from monostixels.core import _dp_cpp
from monostixels.core import columns as columns_mod
from monostixels.core import solver as solver_mod
from monostixels.data.synthetic import render_pair
from monostixels.core.energy import PriorParams
from monostixels.inputs.semantic import gt_scores
from tests.reference import reference_column
from monostixels.core.solver import SolverConfig, solve, solve_columns

from tests.test_solver import random_problem

needs_kernel = pytest.mark.skipif(not _dp_cpp.available(), reason=f"C++ kernel not built: {_dp_cpp.build_error()}")

SOLUTION_FIELDS = ("col", "b", "t", "type", "cls", "p", "p_ground", "tau", "cost", "energy")
WORLD_FIELDS = ("column", "v_top", "v_bottom", "type", "cls", "inverse_depth", "motion", "cost", "energy")


def _with(cfg: SolverConfig, **kw) -> SolverConfig:
    return SolverConfig.from_yaml(**{**cfg.__dict__, **kw})


def _as_dtype(prob, dtype: torch.dtype):
    """The same column problem with every floating tensor cast to ``dtype``."""
    return dataclasses.replace(prob, **{
        f.name: getattr(prob, f.name).to(dtype) for f in dataclasses.fields(prob)
        if isinstance(getattr(prob, f.name), torch.Tensor) and getattr(prob, f.name).is_floating_point()})


@needs_kernel
@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("seed", range(24))
def test_cpp_bit_identical_to_eager(seed, dtype):
    """Random problems (with/without semantics, hypothesis strides, degenerate motion): same bits."""
    prob, prm, cfg = random_problem(seed, sem=seed % 3 != 0, stride=1 + seed % 3, degenerate=seed % 7 == 0)
    prob = _as_dtype(prob, getattr(torch, dtype))
    cfg = _with(cfg, dtype=dtype)
    eager = solve_columns(prob, prm, _with(cfg, backend="eager"))
    fast = solve_columns(prob, prm, _with(cfg, backend="cpp"))
    for k in SOLUTION_FIELDS:
        assert torch.equal(getattr(eager, k), getattr(fast, k)), k


@needs_kernel
@pytest.mark.parametrize("seed", range(16))
def test_cpp_equals_reference(seed):
    """Same optimal energy as the loop reference (relative 1e-5), taller columns than above."""
    prob, prm, cfg = random_problem(500 + seed, H=20, sem=seed % 2 == 0, stride=1 + seed % 2, degenerate=seed == 5)
    sol = solve_columns(prob, prm, _with(cfg, backend="cpp"))
    for c in range(prob.num_columns):
        e_ref, _ = reference_column(prob, c, prm, cfg)
        assert math.isclose(float(sol.energy[c]), e_ref, rel_tol=1e-5, abs_tol=1e-8), (c, float(sol.energy[c]), e_ref)
        assert math.isclose(float(sol.cost[sol.col == c].sum()), e_ref, rel_tol=1e-5, abs_tol=1e-8)


@needs_kernel
@pytest.mark.parametrize("semantic", [True, False], ids=["sem", "nosem"])
def test_cpp_identical_stixels_on_synthetic_frame(semantic):
    """A rendered street scene (quarter size, float32, default settings): identical stixel worlds."""
    pair = render_pair(3, scale=0.25)
    H, W = pair.size
    flow = pair.gt.flow.float()
    cov = (0.5**2) * torch.eye(2).expand(H, W, 2, 2).contiguous()
    scores = gt_scores(pair.gt.labels, confidence=0.9) if semantic else None
    prior = PriorParams.from_yaml()
    worlds = {}
    for backend in ("eager", "cpp"):
        cfg = SolverConfig.from_yaml(cell_rows=2, backend=backend)
        worlds[backend] = solve(flow, cov, scores, pair.camera, pair.motion, prior, cfg)
    assert len(worlds["cpp"]) > 2 * worlds["cpp"].num_columns  # a real scene, not all-ground columns
    assert len({int(t) for t in worlds["cpp"].type}) >= 3
    for k in WORLD_FIELDS:
        assert torch.equal(getattr(worlds["eager"], k), getattr(worlds["cpp"], k)), k


def test_soft_dp_and_gradients_stay_eager(monkeypatch):
    """tau > 0, or priors that require gradients, never reach the kernel (it has no backward)."""
    calls = []
    monkeypatch.setattr(solver_mod, "_solve_columns_cpp", lambda *a: calls.append(1))
    prob, prm, cfg = random_problem(3)
    solve_columns(prob, prm, _with(cfg, tau=0.5, backend="cpp"))
    grad_prm = dataclasses.replace(prm, beta_mc=torch.tensor(float(prm.beta_mc), dtype=torch.float64, requires_grad=True))
    e = solve_columns(prob, grad_prm, _with(cfg, backend="auto")).energy.sum()
    e.backward()
    assert calls == [] and grad_prm.beta_mc.grad is not None


def test_build_failure_falls_back_with_one_warning(monkeypatch, caplog):
    """No compiler / failed build: backend=auto solves eagerly after ONE warning; backend=cpp is an error."""
    monkeypatch.setattr(_dp_cpp, "_state", {"tried": False, "ok": False, "error": None})

    def broken_build() -> None:
        raise RuntimeError("no C++ compiler (test)")

    monkeypatch.setattr(_dp_cpp, "_build", broken_build)
    prob, prm, cfg = random_problem(4)
    expected = solve_columns(prob, prm, _with(cfg, backend="eager")).energy
    with caplog.at_level(logging.WARNING, logger="monostixels.core._dp_cpp"):
        for _ in range(3):
            assert torch.equal(solve_columns(prob, prm, _with(cfg, backend="auto")).energy, expected)
    warnings = [r for r in caplog.records if r.name == "monostixels.core._dp_cpp"]
    assert len(warnings) == 1 and "no C++ compiler (test)" in warnings[0].getMessage()
    with pytest.raises(RuntimeError, match="solver.backend=cpp.*no C\\+\\+ compiler"):
        solve_columns(prob, prm, _with(cfg, backend="cpp"))


def test_killed_build_leaves_no_lock_that_blocks(tmp_path, caplog):
    """A build killed mid-way (torch's ``lock`` file left behind) does not make later builds wait forever."""
    import signal
    import subprocess
    import sys

    build_dir = tmp_path / "monostixels_column_dp_x"
    # A process that holds the build lock, writes torch's baton file as a build does, and is killed.
    code = ("import sys, time; from pathlib import Path; from monostixels.core._dp_cpp import build_lock\n"
            "d = Path(sys.argv[1])\n"
            "with build_lock(d):\n"
            "    (d / 'lock').touch(); print('building', flush=True); time.sleep(600)\n")
    p = subprocess.Popen([sys.executable, "-c", code, str(build_dir)], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "building"
        p.send_signal(signal.SIGKILL)
        p.wait(timeout=30)
    finally:
        p.kill()
    assert (build_dir / "lock").exists()
    with caplog.at_level(logging.WARNING, logger="monostixels.core._dp_cpp"):
        with _dp_cpp.build_lock(build_dir):
            assert not (build_dir / "lock").exists()
    assert any("did not finish" in r.getMessage() for r in caplog.records)


def test_backend_setting_is_checked():
    from monostixels._checks import InputError

    # The schema's choice (SolverBackend): OmegaConf refuses any other name, naming the key.
    with pytest.raises(InputError, match="^solver.backend: expected one of auto, eager, cpp, got 'gpu'"):
        SolverConfig.from_yaml(backend="gpu")


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cell_sums_identical_to_torch(dtype):
    """The kernel's cell sums equal columns._block_sum's torch adds bit for bit, partial cells included."""
    g = torch.Generator().manual_seed(0)
    for shape in [(2, 3, 37, 23), (1, 10, 64, 101), (1, 1, 7, 9)]:
        x = (torch.randn(*shape, generator=g) * 100).to(dtype)
        for r, w in [(3, 5), (1, 1), (5, 4), (4, 7), (40, 40)]:
            a = columns_mod._block_sum(x, r, w, use_cpp=False)
            b = columns_mod._block_sum(x, r, w, use_cpp=True)
            assert a.shape == b.shape == (shape[0], shape[1], -(-shape[2] // r), -(-shape[3] // w))
            assert torch.equal(a, b), (shape, r, w)
    # The partial top cell and last column sum the pixels they have (no averaging, no dropping).
    ones = torch.ones(1, 1, 7, 9, dtype=dtype)
    assert columns_mod._block_sum(ones, 3, 4, use_cpp=True)[0, 0].tolist() == [[12, 12, 3]] * 2 + [[4, 4, 1]]


# ------------------------------------------------------------ preparation in the kernel (same bits)
def _cast(prob, dtype: torch.dtype):
    return _as_dtype(prob, dtype) if dtype != torch.float64 else prob


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("seed", range(12))
def test_cpp_preparation_identical_to_torch(seed, dtype):
    """Per-cell geometry, hypothesis sets (with g = K B tau) and semantic prefix: the kernel's bits."""
    prob, prm, cfg = random_problem(700 + seed, H=11 + seed, W=9 + 2 * seed, sem=seed % 4 != 0,
                                    degenerate=seed % 5 == 0)
    prob = _cast(prob, dtype)
    cfg = _with(cfg, dtype="float64" if dtype == torch.float64 else "float32", standing_hypotheses=seed % 3 != 0)
    geo_t, geo_c = columns_mod.column_geometry(prob), columns_mod.column_geometry(prob, cpp=True)
    for k in ("ray", "a", "cK", "s_g", "s_o", "q"):
        assert torch.equal(getattr(geo_t, k), getattr(geo_c, k)), k
    hyp_t = columns_mod.hypotheses(prob, _with(cfg, backend="eager"), geo_t)
    hyp_c = columns_mod.hypotheses(prob, _with(cfg, backend="cpp"), geo_c)
    for k in ("p_ground", "p_object", "tau", "B"):
        assert torch.equal(getattr(hyp_t, k), getattr(hyp_c, k)), k
    g_t = columns_mod.flow_geometry(prob, hyp_t, geo_t)[-1]
    assert hyp_t.g is None and torch.equal(g_t, hyp_c.g)
    # Cells without a fit were replaced (reference ground, farthest depth, tau = 0): repeats exist.
    assert len(set(hyp_c.p_ground[0].tolist())) < hyp_c.p_ground.shape[1]
    prm_t = prm.as_tensors(dtype)
    for margin in ((5.0, 5.0), (5.0, math.inf), (math.inf, 2.0), (math.inf, math.inf)):
        L_t, cls_t = columns_mod.semantic_prefix(prob, prm_t, dtype, margin[0], geo_t, ground_margin_deg=margin[1])
        L_c, cls_c = columns_mod.semantic_prefix(prob, prm_t, dtype, margin[0], geo_c, cpp=True, ground_margin_deg=margin[1])
        assert cls_t == cls_c and torch.equal(L_t, L_c), margin


def test_fit_threshold_is_geometrys():
    import inspect

    from monostixels.core.geometry import solve_dynamic_dof, solve_static_dof

    for f in (solve_static_dof, solve_dynamic_dof):
        assert inspect.signature(f).parameters["eps"].default == columns_mod._FIT_EPS


@needs_kernel
@pytest.mark.parametrize("semantic", [True, False], ids=["sem", "nosem"])
def test_cpp_identical_on_flat_scene_with_ties(semantic):
    """Zero flow, uniform scores, no structural priors: most hypotheses repeat and many energies tie."""
    prob, prm, cfg = random_problem(31, H=16, W=10, sem=semantic, zero_structure=True)
    prob = dataclasses.replace(prob, flow=torch.zeros_like(prob.flow),
                               nll=None if prob.nll is None else torch.full_like(prob.nll, math.log(10)))
    eager = solve_columns(prob, prm, _with(cfg, backend="eager"))
    fast = solve_columns(prob, prm, _with(cfg, backend="cpp"))
    for k in SOLUTION_FIELDS:
        assert torch.equal(getattr(eager, k), getattr(fast, k)), k


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cell_means_layouts_and_value_checks(dtype):
    """Planar and per-pixel-interleaved inputs give _block_sum's bits divided by the count, in
    (B, C, n, ch) memory; the same pass catches one bad value anywhere (whole vectors and the rest)."""
    g = torch.Generator().manual_seed(1)
    B, H, W, r, w = 2, 23, 41, 3, 5  # W % 16 and W % 8 != 0: the pixels after the last whole vector
    n, C = -(-H // r), -(-W // w)
    count = (torch.clamp(H - torch.arange(n) * r, max=r)[:, None] * torch.clamp(W - torch.arange(C) * w, max=w)).to(dtype)
    planar = torch.rand(B, 10, H, W, generator=g).to(dtype)
    a = torch.randn(B, H, W, 2, 2, generator=g).to(dtype)
    cov = a @ a.transpose(-1, -2) + 0.1 * torch.eye(2, dtype=dtype)  # positive definite
    inter = cov.permute(0, 3, 4, 1, 2).reshape(B, 4, H, W)
    pairs = torch.randn(B, H, W, 2, generator=g).to(dtype).permute(0, 3, 1, 2)  # 2 interleaved channels
    for x, check in [(planar, _dp_cpp.CHECK_NONNEGATIVE), (inter, _dp_cpp.CHECK_POSITIVE_DEFINITE),
                     (pairs, _dp_cpp.CHECK_FINITE)]:
        means, ok = _dp_cpp.cell_means_checked(x, r, w, count, check)
        ref = columns_mod._block_sum(x.contiguous(), r, w) / count
        assert ok and means.shape == (B, C, n, x.shape[1]) and means.is_contiguous()
        assert torch.equal(means, ref.permute(0, 3, 2, 1))
    for (b, v, u) in [(0, 0, 0), (1, 22, 40), (1, 7, 33), (0, 11, 17)]:
        bad = planar.clone()
        bad[b, 4, v, u] = -1e-6
        assert not _dp_cpp.cell_means_checked(bad, r, w, count, _dp_cpp.CHECK_NONNEGATIVE)[1]
        for i, j, val in [(0, 0, -0.5), (1, 1, 0.0), (0, 1, 1e3)]:
            c = cov.clone()
            c[b, v, u, i, j] = val
            if i != j:
                c[b, v, u, j, i] = val  # symmetric, det < 0
            x = c.permute(0, 3, 4, 1, 2).reshape(B, 4, H, W)
            assert not _dp_cpp.cell_means_checked(x, r, w, count, _dp_cpp.CHECK_POSITIVE_DEFINITE)[1], (b, v, u, i, j)
        p = pairs.clone()
        p[b, 1, v, u] = float("nan")
        assert not _dp_cpp.cell_means_checked(p, r, w, count, _dp_cpp.CHECK_FINITE)[1]


@pytest.mark.parametrize("backend", ["eager", "cpp"])
def test_bad_values_named_on_both_backends(backend):
    """The value checks run after the cell sums now; the errors are the same as before, on both paths."""
    if backend == "cpp" and not _dp_cpp.available():
        pytest.skip(f"C++ kernel not built: {_dp_cpp.build_error()}")
    from monostixels._checks import InputError

    from tests.test_solver import _good

    flow, cov, sc, cam, mot = _good()
    cfg, prm = SolverConfig.from_yaml(cell_rows=2, backend=backend), PriorParams.from_yaml()
    cases = []
    f = flow.clone()
    f[1, 11, 9] = float("inf")
    cases.append(((f, cov, sc), "flow: 1 non-finite"))
    c = cov.clone()
    c[5, 9, 0, 1] = c[5, 9, 1, 0] = 2.0
    cases.append(((flow, c, sc), "positive definite"))
    s = sc.clone()
    s[3, 0, 0] = -0.01
    cases.append(((flow, cov, s), "non-negative"))
    s = sc.clone()
    s[9, 11, 9] = float("nan")
    cases.append(((flow, cov, s), "semantic scores: 1 non-finite"))
    for (fl, cv, scores), msg in cases:
        with pytest.raises(InputError, match=msg):
            solve(fl, cv, scores, cam, mot, prm, cfg)
    # Finite values whose cell sum overflows fail the fast check only: the full check passes them.
    f = flow.clone()
    f[0, 0, :2] = 3e38
    assert len(solve(f, cov, sc, cam, mot, prm, cfg)) > 0


@needs_kernel
def test_cpp_batch_of_frames_identical_to_eager_and_single_frames():
    """Three frames in one batch (the cell means read image after image): the same worlds as
    solving each frame alone, and as the eager path."""
    pairs = [render_pair(s, scale=0.25) for s in (1, 2, 3)]
    H, W = pairs[0].size
    flows = [p.gt.flow.float() for p in pairs]
    covs = [(0.5**2) * torch.eye(2).expand(H, W, 2, 2).contiguous() for _ in pairs]
    scores = [gt_scores(p.gt.labels, confidence=0.9) for p in pairs]
    cams, mots, prior = [p.camera for p in pairs], [p.motion for p in pairs], PriorParams.from_yaml()
    worlds = {b: solver_mod.solve_batch(flows, covs, scores, cams, mots, prior, SolverConfig.from_yaml(cell_rows=2, backend=b))
              for b in ("eager", "cpp")}
    cfg = SolverConfig.from_yaml(cell_rows=2, backend="cpp")
    for k in range(len(pairs)):
        alone = solve(flows[k], covs[k], scores[k], cams[k], mots[k], prior, cfg)
        for f in WORLD_FIELDS:
            assert torch.equal(getattr(worlds["cpp"][k], f), getattr(alone, f)), (k, f)
            assert torch.equal(getattr(worlds["cpp"][k], f), getattr(worlds["eager"][k], f)), (k, f)
