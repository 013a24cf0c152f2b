"""Learn the stixel priors by gradient descent through the soft-min DP.

Loss (a structured-perceptron / max-margin style loss, LeCun et al. 2006 "energy-based learning"):
for every column of every training frame,

    L_c(θ) = E_θ(y*_c; noisy inputs) - softmin_y E_θ(y; noisy inputs)        (>= ~0)

where ``y*`` is the *target labelling* (segmentation, types, classes, depths) and the second term
is the optimal energy of the soft DP (``solver.tau > 0``), differentiable in the prior parameters.
Minimising it lowers the energy of the target relative to every competing labelling, i.e. makes
the target the DP's answer on the noisy inputs (DeepFlow flow) the pipeline really sees.

Target labelling: the hard-DP solution on the *ground-truth* inputs of the same frame (gt flow,
gt semantics, gt motion), which reproduces the synthetic ground-truth depth to ~4 % rel
(`monostixels eval flow=gt semantic=gt motion=gt`). Its energy under the noisy inputs is computed
by :func:`labelling_energy`, a vectorised evaluation of the solver's energy for a given labelling
(it equals the DP's optimum when given the DP's own solution: tests/test_sweep.py).

``delta_F`` is held fixed (the energy's scale: the loss is homogeneous in the parameters), every
learned parameter is kept positive through ``θ = exp(w)``, and a small quadratic penalty on
``log θ - log θ_default`` keeps the parameters from running off along directions the few training
frames do not constrain. Which parameters are learned is ``train.learn`` (conf/train_priors.yaml:
``beta_mc`` and the structural priors; see the comment there for why not the data-term weights).
The result is written to ``conf/prior/learned.yaml`` with the keys of
``conf/prior/default.yaml``.

Usage (from the repository root)::

    nice -n 10 python -m train.priors                       # conf/train_priors.yaml
    nice -n 10 python -m train.priors train.steps=60 data.frames=8

Seeds: training frames are synthetic source seed 1 (the tuning split), never 0 (benchmark) or 2
(validation).
"""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from monostixels.core.classes import DYNAMIC_OBJECT, GROUND, SKY, STATIC_OBJECT
import monostixels.config_schema  # noqa: F401 - registers the groups' schemas (main composes the package config)
from monostixels.core.energy import PriorParams, gravity, ordering_from_depths
from monostixels.core.geometry import ground_basis, pixel_rays
from monostixels.core.columns import ColumnProblem, _row_costs, beyond_horizon, prepare_columns
from monostixels.core.solver import ColumnSolution, SolverConfig, solve_columns
from monostixels._checks import one_line_errors

__all__ = ["labelling_energy", "perceptron_loss", "build_problems", "learn_priors", "write_prior_yaml",
           "priors_from_sweep", "subsample_columns", "main"]

logger = logging.getLogger(__name__)

CONFIG_NAME = "train_priors"
#: Header of the written yaml file.
_YAML_HEADER = (
    "# Learned stixel priors: gradient descent through the soft-min DP, written by\n"
    "# `python -m train.priors` (train/priors.py; settings in conf/train_priors.yaml).\n"
    "# Keys and units: PriorConfig (monostixels/core/energy.py). Use: monostixels eval prior=learned\n"
)


def labelling_energy(prob: ColumnProblem, lab: ColumnSolution, prm: PriorParams, cfg: SolverConfig) -> torch.Tensor:
    """Energy (C,) of a given labelling of every column of ``prob``, as the solver defines it.

    Args:
        prob: the column problem (C columns, n cells) whose data terms are evaluated.
        lab: a labelling of the same column/cell grid (e.g. :func:`solve_columns` on another
            problem of the same frames): per stixel ``col, b, t, type, cls, p, p_ground, tau``,
            sorted by column then bottom cell, tiling every column.
        prm: prior parameters (floats or 0-d tensors; differentiable).
        cfg: solver settings (dtype, min/max depth).

    Returns:
        (C,) energy: flow + semantic data terms of every cell under the labelled plane/motion,
        plus ``beta_mc`` per stixel and the structural priors (flatness, gravity, ordering).
    """
    dt = cfg.torch_dtype
    prm = prm.as_tensors(dt)
    C, n = prob.num_columns, prob.num_cells
    p_min = 1.0 / cfg.max_depth
    lengths = lab.t - lab.b + 1
    if int(lengths.sum()) != C * n:
        raise ValueError("labelling_energy: the labelling does not tile the problem's columns")
    cell = lambda x: x.repeat_interleave(lengths, dim=0).reshape((C, n) + tuple(x.shape[1:]))  # noqa: E731
    T_c, p_c, cls_c = cell(lab.type), cell(lab.p.to(dt)), cell(lab.cls)
    tau_c = cell(lab.tau.to(dt))

    # Flow term: predicted point H x of every cell under its stixel's homography (columns.flow_prefix).
    ray = pixel_rays(prob.K[:, None], prob.u[:, None], prob.v[None, :])  # C x n x 3
    a = ((prob.K @ prob.R)[:, None] @ ray[..., None])[..., 0]
    cK = (prob.K @ prob.t[..., None])[..., 0][:, None]  # C x 1 x 3
    s_g = (ray * prob.n_g[:, None]).sum(-1)
    s_o = (ray * prob.n_obj[:, None]).sum(-1)
    kbt = ((prob.K @ ground_basis(prob.n_g))[:, None] @ tau_c[..., None])[..., 0]  # C x n x 3
    zero = torch.zeros_like(s_g)
    lin = torch.where(T_c == GROUND, p_c * s_g, torch.where(T_c == STATIC_OBJECT, p_c * s_o, zero))
    Hx = a + lin[..., None] * cK + torch.where((T_c == DYNAMIC_OBJECT)[..., None], s_o[..., None] * kbt, 0 * kbt)
    e_cell = _row_costs(prob, Hx[:, None], prm)[:, 0]  # C x n, weighted by rows and delta_F
    impossible = ((T_c == GROUND) & (s_g <= 0)) | ((T_c == SKY) & (s_g > 0))
    e_cell = beyond_horizon(e_cell, impossible, prob, prm)
    e_cell = e_cell + torch.where(T_c == DYNAMIC_OBJECT, prm.alpha_dyn * prob.rows, zero)
    if prob.nll is not None:
        nll = prob.nll.gather(2, cls_c[..., None])[..., 0]
        e_cell = e_cell + torch.minimum(nll, prm.alpha_L) * prob.rows * prm.delta_L
    energy = e_cell.sum(1)

    # Structural priors of every stixel given its predecessor (the virtual ground at the camera
    # height for the first stixel of a column), exactly as in the DP.
    first = lab.b == 0
    p_ref = (1.0 / prob.h_cam)[lab.col].to(dt)
    prev_T = torch.where(first, torch.full_like(lab.type, GROUND), lab.type.roll(1))
    prev_p = torch.where(first, p_ref, lab.p.to(dt).roll(1))
    prev_g = torch.where(first, p_ref, lab.p_ground.to(dt).roll(1))
    p = lab.p.to(dt)
    is_obj = (lab.type == STATIC_OBJECT) | (lab.type == DYNAMIC_OBJECT)
    prev_obj = (prev_T == STATIC_OBJECT) | (prev_T == DYNAMIC_OBJECT)
    safe_p = torch.where(p > 0, p, torch.ones_like(p))
    dh_flat = 1.0 / prev_g - 1.0 / safe_p
    flat = prm.alpha_flat + prm.beta_flat * dh_flat * dh_flat
    ray_b = pixel_rays(prob.K[lab.col], prob.u[lab.col], prob.v_edge[lab.b])
    q = (ray_b * prob.n_g[lab.col]).sum(-1) / (ray_b * prob.n_obj[lab.col]).sum(-1)
    grav = gravity(1.0 / prev_g - q / safe_p, prm)
    ordv = ordering_from_depths(1.0 / prev_p.clamp(min=p_min) - 1.0 / safe_p, prm)
    obj = torch.where(prev_obj, torch.minimum(grav, ordv), grav)
    s = torch.where(lab.type == GROUND, flat, torch.where(is_obj, obj, torch.zeros_like(flat)))
    s = s + prm.beta_mc
    s = torch.where(lab.type == SKY, torch.zeros_like(s) + prm.beta_mc, s)
    return energy + torch.zeros(C, dtype=dt).index_add(0, lab.col, s)


def perceptron_loss(prob: ColumnProblem, target: ColumnSolution, prm: PriorParams, cfg: SolverConfig) -> torch.Tensor:
    """Mean over columns of (target energy - soft optimal energy) / cells; ``cfg.tau > 0``."""
    e_target = labelling_energy(prob, target, prm, cfg)
    e_soft = solve_columns(prob, prm, cfg).energy
    return ((e_target - e_soft) / prob.num_cells).mean()


def _load(overrides: list[str]) -> DictConfig:
    """The package config (conf/config.yaml) with ``overrides``, inside or outside a Hydra app."""
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():  # under @hydra.main: same conf/ search path
        return hydra.compose(config_name="config", overrides=overrides)
    from monostixels.pipeline import load_config

    return load_config(overrides)


def subsample_columns(prob: ColumnProblem, stride: int, offset: int = 0) -> ColumnProblem:
    """Every ``stride``-th column of ``prob`` (columns are independent DP problems).

    More frames at the same cost: neighbouring columns are strongly correlated, distinct frames
    are not.
    """
    if stride <= 1:
        return prob
    idx = torch.arange(offset % stride, prob.num_columns, stride)
    per_column = ("K", "R", "t", "n_g", "n_obj", "h_cam", "u", "flow", "cov_inv", "logdet", "nll", "degenerate",
                  "frame", "column")
    kw = {f: getattr(prob, f) for f in ColumnProblem.__dataclass_fields__}
    for f in per_column:
        if kw[f] is not None:
            kw[f] = kw[f][idx]
    return ColumnProblem(**kw)


def build_problems(cfg: DictConfig) -> tuple[ColumnProblem, ColumnProblem]:
    """The noisy (training-input) and ground-truth column problems of the training frames.

    Args:
        cfg: the train_priors config (``data``, ``inputs``, ``solver`` nodes).

    Returns:
        (noisy, gt) problems on the same column/cell grid, all frames batched.
    """
    from monostixels.data.synthetic import render_pair
    from monostixels.inputs.flow import estimate_flow
    from monostixels.inputs.semantic import estimate_semantics
    from monostixels.pipeline import Pipeline
    from monostixels.build import pipeline_settings

    pipes = {k: Pipeline(pipeline_settings(_load(list(cfg.inputs[k])))) for k in ("noisy", "gt")}
    scfg = SolverConfig.from_yaml(**OmegaConf.to_container(cfg.solver, resolve=True))  # type: ignore[arg-type]
    per = {k: {"flow": [], "cov": [], "sem": [], "cam": [], "mot": []} for k in pipes}
    for i in tqdm(range(int(cfg.data.frames)), desc="inputs", unit="frame"):
        pair = render_pair(int(cfg.data.seed) * 100_000 + i, scale=float(cfg.data.scale),
                           density=float(cfg.data.density))
        for k, pipe in pipes.items():
            fl = estimate_flow(pair, pipe.flow_cfg)
            sem = estimate_semantics(pair, pipe.semantic_cfg)
            mot = pipe.motion_for(pair, fl, sem)
            d = per[k]
            d["flow"].append(fl.flow)
            d["cov"].append(fl.cov)
            d["sem"].append(sem)
            d["cam"].append(pair.camera)
            d["mot"].append(mot.motion)
    out = []
    for k in ("noisy", "gt"):
        d = per[k]
        sem = torch.stack(d["sem"]) if d["sem"][0] is not None else None
        prob = prepare_columns(torch.stack(d["flow"]), torch.stack(d["cov"]), sem, d["cam"], d["mot"], scfg)
        out.append(subsample_columns(prob, int(cfg.data.get("column_stride", 1))))
    return out[0], out[1]


def learn_priors(noisy: ColumnProblem, gt: ColumnProblem, init: PriorParams, learn: list[str], *, tau: float,
                 steps: int, lr: float, reg: float, solver: dict[str, Any], min_value: float = 1e-3) -> tuple[PriorParams, list[float]]:
    """Adam on ``w`` with ``θ = exp(w)`` (positive, relative steps) for the parameters in ``learn``; the rest stay at ``init``.

    Args:
        noisy, gt: problems from :func:`build_problems`.
        init: starting (and regularisation-centre) parameters.
        learn: names of the learned parameters.
        tau: soft-min temperature of the DP (energy units).
        steps, lr: Adam steps and learning rate (on ``w``).
        reg: weight of ``sum (log θ - log θ_init)^2``.
        solver: solver settings (dict) for both problems.
        min_value: floor of a learned parameter's initial value (log 0 is -inf).

    Returns:
        (learned parameters, loss per step).
    """
    hard = SolverConfig.from_yaml(**{**solver, "tau": 0.0})
    soft = SolverConfig.from_yaml(**{**solver, "tau": float(tau)})
    with torch.no_grad():
        target = solve_columns(gt, init, hard)
    dt = soft.torch_dtype
    log0 = {k: math.log(max(float(getattr(init, k)), min_value)) for k in learn}
    w = {k: torch.tensor(v, dtype=dt, requires_grad=True) for k, v in log0.items()}
    opt = torch.optim.Adam(list(w.values()), lr=lr)
    losses: list[float] = []
    for step in tqdm(range(steps), desc="priors", unit="step"):
        prm = PriorParams(**{**init.__dict__, **{k: torch.exp(v) for k, v in w.items()}})
        loss = perceptron_loss(noisy, target, prm, soft)
        penalty = sum((w[k] - log0[k]) ** 2 for k in learn)
        total = loss + reg * penalty
        opt.zero_grad()
        total.backward()
        opt.step()
        losses.append(loss.item())
        logger.info("step %d: loss %.4f penalty %.4f %s", step, float(loss), float(penalty),
                    {k: round(float(getattr(prm, k)), 3) for k in learn})
    final = PriorParams(**{**init.__dict__, **{k: float(torch.exp(v)) for k, v in w.items()}})
    return final, losses


def write_prior_yaml(prm: PriorParams, path: str | Path, note: str = "", header: str | None = None) -> Path:
    """Write ``prm`` as a ``prior`` config file: the schema (``base_prior``) and every parameter, in the
    order of :class:`~monostixels.core.energy.PriorConfig`."""
    path = Path(path)
    lines = [(_YAML_HEADER if header is None else header).rstrip("\n")]
    if note:
        lines += [f"# {ln}" for ln in note.splitlines()]
    lines += ["# Every parameter is written, equal to the schema's default or not: the set as found, kept",
              "# whatever the defaults (PriorConfig, monostixels/core/energy.py) become.",
              "defaults:", "  - base_prior", "  - _self_", ""]
    lines += [f"{k}: {round(v, 4)}" for k, v in prm.to_dict().items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def priors_from_sweep(results: str | Path, base: str = "default") -> PriorParams:
    """The best parameters of a Hydra Optuna sweep (``optimization_results.yaml``) over ``conf/prior/<base>.yaml``."""
    import yaml

    res = yaml.safe_load(Path(results).read_text())
    best = {k.split(".", 1)[1]: float(v) for k, v in res["best_params"].items() if k.startswith("prior.")}
    return PriorParams.from_yaml(base, **best)


@hydra.main(config_path="../conf", config_name=CONFIG_NAME, version_base="1.3")
@one_line_errors("train.priors")
def main(cfg: DictConfig) -> None:
    """Build the training problems, learn the priors, write ``cfg.out``.

    With ``+from_sweep=<sweep dir>/optimization_results.yaml`` it instead writes the sweep's best
    parameters (over conf/prior/default.yaml) to ``cfg.out`` (e.g. ``out=conf/prior/tuned.yaml``).
    """
    logging.getLogger("monostixels").setLevel(logging.WARNING)
    if cfg.get("from_sweep"):
        import yaml

        src = Path(hydra.utils.to_absolute_path(str(cfg.from_sweep)))
        res = yaml.safe_load(src.read_text())
        out = Path(hydra.utils.to_absolute_path(str(cfg.out)))
        header = ("Swept stixel priors: best trial of `monostixels eval --multirun +sweep=priors`\n"
                  f"(conf/sweep/priors.yaml), objective overall rel {res['best_value']:.4f} on the tuning frames;\n"
                  "keys not swept are those of conf/prior/default.yaml.")
        write_prior_yaml(priors_from_sweep(src), out, header="\n".join(f"# {ln}" for ln in header.splitlines()))
        print(f"wrote {out} from {src}")
        return
    t0 = time.perf_counter()
    noisy, gt = build_problems(cfg)
    t_inputs = time.perf_counter() - t0
    init = PriorParams.from_yaml(str(cfg.init))
    solver = {**SolverConfig.from_yaml(**OmegaConf.to_container(cfg.solver, resolve=True)).__dict__,  # type: ignore[arg-type]
              "dtype": str(cfg.train.dtype)}
    prm, losses = learn_priors(noisy, gt, init, list(cfg.train.learn), tau=float(cfg.train.tau),
                               steps=int(cfg.train.steps), lr=float(cfg.train.lr), reg=float(cfg.train.reg),
                               solver=solver)
    note = (f"{cfg.data.frames} frames of synthetic seed {cfg.data.seed} at scale {cfg.data.scale}, inputs "
            f"{' '.join(cfg.inputs.noisy)}; tau {cfg.train.tau}, {cfg.train.steps} Adam steps (lr {cfg.train.lr}), "
            f"reg {cfg.train.reg}; loss {losses[0]:.4f} -> {losses[-1]:.4f}.")
    out = Path(hydra.utils.to_absolute_path(str(cfg.out)))
    write_prior_yaml(prm, out, note)
    print(f"learned priors: loss {losses[0]:.4f} -> {losses[-1]:.4f} in {len(losses)} steps "
          f"(inputs {t_inputs:.0f} s, total {time.perf_counter() - t0:.0f} s); wrote {out}")
    for k in cfg.train.learn:
        print(f"  {k:<18} {float(getattr(init, k)):9.3f} -> {float(getattr(prm, k)):9.3f}")


if __name__ == "__main__":
    main()
