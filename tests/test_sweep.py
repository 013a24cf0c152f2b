"""The Optuna prior sweep end to end, and the learned-prior loss (train/priors.py)."""
from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

from monostixels.core.energy import PriorParams
from monostixels.core.solver import SolverConfig, solve_columns
from tests.test_solver import random_problem
from train.priors import labelling_energy, perceptron_loss, write_prior_yaml

REPO = Path(__file__).resolve().parents[1]
def _installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:  # the parent namespace package hydra_plugins is absent
        return False


_HAS_SWEEPER = _installed("hydra_plugins.hydra_optuna_sweeper") and _installed("hydra_plugins.hydra_joblib_launcher")
#: Tiny inputs of the end-to-end sweep: one frame at 0.2 x KITTI size with ground-truth inputs.
_TINY = ["data.frames=1", "data.scale=0.2", "flow=gt", "semantic=gt", "motion=gt"]


def _monostixels(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    code = "import sys; from monostixels.cli import main; sys.argv = ['monostixels', *sys.argv[1:]]; main()"
    return subprocess.run([sys.executable, "-c", code, *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=600)


@pytest.mark.slow
@pytest.mark.skipif(not _HAS_SWEEPER, reason="hydra-optuna-sweeper / hydra-joblib-launcher not installed "
                    "(pip install -e '.[sweep]')")
def test_two_trial_sweep_end_to_end(tmp_path):
    """`monostixels eval --multirun +sweep=priors` runs 2 Optuna trials and reports the best one."""
    sweep_dir = tmp_path / "sweep"
    r = _monostixels(["eval", "--multirun", "+sweep=priors", "hydra.sweeper.n_trials=2", *_TINY,
                      "prior.beta_mc=interval(5,40)", f"hydra.sweep.dir={sweep_dir}",
                      f"outputs={tmp_path / 'out'}"], cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    # Both trials ran (one job directory each, with different sampled priors).
    trials = sorted(p for p in sweep_dir.iterdir() if p.is_dir())
    assert [p.name for p in trials] == ["0", "1"]
    sampled = []
    for p in trials:
        ov = yaml.safe_load((p / ".hydra" / "overrides.yaml").read_text())
        sampled.append({o.split("=")[0]: float(o.split("=")[1]) for o in ov if o.startswith("prior.")})
    assert sampled[0] != sampled[1]
    assert all(5 <= s["prior.beta_mc"] <= 40 for s in sampled)
    res = yaml.safe_load((sweep_dir / "optimization_results.yaml").read_text())
    best = res["best_params"]
    assert set(best) == set(sampled[0]) and best in sampled
    assert 0 < res["best_value"] < 1
    # The reported best value is the objective of a plain eval with the best parameters.
    out = tmp_path / "best.json"
    r = _monostixels(["eval", *_TINY, "data.seed=1", *[f"{k}={v}" for k, v in best.items()], f"out={out}",
                      f"outputs={tmp_path / 'out'}", f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    rel = json.loads(out.read_text())["methods"]["monostixels"]["overall"]["rel"]
    assert math.isclose(rel, res["best_value"], rel_tol=1e-6)


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5, 6, 8, 9])
def test_labelling_energy_of_dp_solution_is_dp_energy(seed):
    """The vectorised labelling energy re-evaluates the DP's own optimum exactly (random priors)."""
    prob, prm, cfg = random_problem(seed, sem=seed % 3 != 0, stride=1 + seed % 3)
    sol = solve_columns(prob, prm, cfg)
    e = labelling_energy(prob, sol, prm, cfg)
    assert torch.allclose(e, sol.energy, rtol=1e-9, atol=1e-9)


def test_perceptron_loss_zero_at_generating_priors():
    """Loss ~0 when the target is optimal under the priors; > 0 under priors that prefer another labelling."""
    prob, prm, cfg = random_problem(21, sem=True)
    target = solve_columns(prob, prm, cfg)
    soft = SolverConfig.from_yaml(**{**cfg.__dict__, "tau": 1e-3})
    assert abs(float(perceptron_loss(prob, target, prm, soft))) < 1e-3
    other = PriorParams(**{**prm.__dict__, "beta_mc": 10 * float(prm.beta_mc) + 20.0})
    assert float(perceptron_loss(prob, target, other, soft)) > 0.05


def test_perceptron_loss_gradcheck():
    """Gradients of the loss w.r.t. the priors match finite differences (soft DP, float64)."""
    prob, prm0, cfg = random_problem(22, sem=True)
    target = solve_columns(prob, prm0, cfg)
    soft = SolverConfig.from_yaml(**{**cfg.__dict__, "tau": 0.5})
    names = ["beta_mc", "alpha_grav_above", "beta_flat", "alpha_L", "delta_L"]

    def loss(*vals):
        prm = PriorParams(**{**prm0.__dict__, **dict(zip(names, vals))})
        return perceptron_loss(prob, target, prm, soft)

    x = tuple(torch.tensor(float(getattr(prm0, k)) * 1.3 + 0.1, dtype=torch.float64, requires_grad=True) for k in names)
    assert torch.autograd.gradcheck(loss, x, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_written_prior_yaml_loads(tmp_path):
    """write_prior_yaml gives a prior option (the schema, then every parameter) that composes back to the
    same values; the written options of conf/prior/ have that form."""
    from omegaconf import OmegaConf

    from monostixels.core.energy import PriorConfig

    prm = PriorParams.from_yaml("default", beta_mc=31.5)
    path = write_prior_yaml(prm, tmp_path / "p.yaml", note="test")
    written = yaml.safe_load(path.read_text())
    assert written.pop("defaults") == ["base_prior", "_self_"] and list(written) == PriorParams.names()
    back = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(PriorConfig), written)).params()
    assert back.to_dict() == pytest.approx(prm.to_dict(), rel=1e-4)
    for name in ("tuned", "learned"):
        f = REPO / "conf" / "prior" / f"{name}.yaml"
        if f.exists():
            assert list(yaml.safe_load(f.read_text())) == ["defaults", *PriorParams.names()], f
