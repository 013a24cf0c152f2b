"""The fused C++ column DP (solver.backend=cpp) against the eager path and the loop reference."""
from __future__ import annotations

import dataclasses
import logging
import math

import pytest
import torch

from monostixels import _dp_cpp
from monostixels import solver as solver_mod
from monostixels.data.synthetic import render_pair
from monostixels.energy import PriorParams
from monostixels.inputs.semantic import gt_scores
from monostixels.reference import reference_column
from monostixels.solver import SolverConfig, solve, solve_columns

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
    with caplog.at_level(logging.WARNING, logger="monostixels._dp_cpp"):
        for _ in range(3):
            assert torch.equal(solve_columns(prob, prm, _with(cfg, backend="auto")).energy, expected)
    warnings = [r for r in caplog.records if r.name == "monostixels._dp_cpp"]
    assert len(warnings) == 1 and "no C++ compiler (test)" in warnings[0].getMessage()
    with pytest.raises(RuntimeError, match="solver.backend=cpp.*no C\\+\\+ compiler"):
        solve_columns(prob, prm, _with(cfg, backend="cpp"))


def test_backend_setting_is_checked():
    from monostixels._checks import InputError

    with pytest.raises(InputError, match="solver.backend: one of auto, eager, cpp"):
        SolverConfig.from_yaml(backend="gpu")


@needs_kernel
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cell_sums_identical_to_torch(dtype):
    """The kernel's cell sums equal solver._block_sum's torch adds bit for bit, partial cells included."""
    g = torch.Generator().manual_seed(0)
    for shape in [(2, 3, 37, 23), (1, 10, 64, 101), (1, 1, 7, 9)]:
        x = (torch.randn(*shape, generator=g) * 100).to(dtype)
        for r, w in [(3, 5), (1, 1), (5, 4), (4, 7), (40, 40)]:
            a = solver_mod._block_sum(x, r, w, use_cpp=False)
            b = solver_mod._block_sum(x, r, w, use_cpp=True)
            assert a.shape == b.shape == (shape[0], shape[1], -(-shape[2] // r), -(-shape[3] // w))
            assert torch.equal(a, b), (shape, r, w)
    # The partial top cell and last column sum the pixels they have (no averaging, no dropping).
    ones = torch.ones(1, 1, 7, 9, dtype=dtype)
    assert solver_mod._block_sum(ones, 3, 4, use_cpp=True)[0, 0].tolist() == [[12, 12, 3]] * 2 + [[4, 4, 1]]
