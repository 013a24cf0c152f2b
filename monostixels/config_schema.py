"""The schemas of the config groups, registered with Hydra's ConfigStore.

Each group below has one settings dataclass, its schema, or (``data``, ``flow``, ``semantic``, ``motion``,
whose options differ in their keys) one per option, chosen by the option's ``name``. The defaults live
there, and every YAML option of the group (conf/<group>/*.yaml) lists its schema first in its defaults
list (``defaults: [base_<group or name>, _self_]``, or another option of the group), then chooses or
overrides values. Hydra then refuses an unknown key or a value of the wrong type when it composes the
config (``movers.no_such_key=1``, ``solver.cell_rows=abc``, ``data.hfov_deg=wide``) or a name that is none of
a setting's choices (a :class:`monostixels._checks.Choice` field: ``flow.preset``, ``flow.matches_preset``,
``flow.size``, ``flow.runtime``, ``flow.precision``, ``flow.confidence``, ``semantic.runtime``, ``solver.dtype``,
``solver.backend``, ``solver.top_refine_objects``, ``output.rerun_colors``, ``data.split`` of kitti2015 and
camvid, ``data.previous``, ``data.oxts``, ``flow.matches``), and the code takes the
settings as the dataclass (:func:`monostixels._checks.config_params`, or
:func:`monostixels._checks.option_params` by ``name``), also from a plain dict or a config rebuilt from one.

Importing this module registers the schemas; the package config (``pkg://monostixels.conf``) imports it
when it is loaded, so every place that composes it (:func:`monostixels.pipeline.load_config`, the command
line, train/) has them. It gathers every stage's settings, so it sits above them all, below the command line.

=============  ===================================================================  ============================
group          schema                                                               registered as
=============  ===================================================================  ============================
movers         :class:`monostixels.post.movers.MoverCheckParams`                    ``movers/base_movers``
solver         :class:`monostixels.core.solver.SolverConfig`                        ``solver/base_solver``
prior          :class:`monostixels.core.energy.PriorConfig`                         ``prior/base_prior``
stream         :class:`monostixels.sequence.stream.StreamParams`                    ``stream/base_stream``
keyframes      :class:`monostixels.sequence.runner.KeyframeParams`                  ``keyframes/base_keyframes``
temporal       :class:`monostixels.sequence.tracking.TrackParams`                   ``temporal/base_temporal``
ttc            :class:`monostixels.sequence.ttc.TtcParams`                          ``ttc/base_ttc``
motion (mono)  :class:`monostixels.inputs.motion_track.MonoMotionConfig`            ``motion/base_mono``
motion (gt)    :class:`monostixels.inputs.motion.GtMotionConfig`                    ``motion/base_gt``
motion (file)  :class:`monostixels.inputs.motion.FileMotionConfig`                  ``motion/base_file``
data           :class:`monostixels.data.sources.SyntheticDataConfig`,               ``data/base_synthetic``,
               ``Kitti2015DataConfig``, ``KittiRawDataConfig``, ``DdadDataConfig``,  ``data/base_kitti2015``, ...
               ``FramesDataConfig``, ``VideoDataConfig``, ``CamVidDataConfig``      (``data/base_<name>``)
camera         :class:`monostixels.data.sources.CameraConfig`                       ``camera/base_camera``
flow           :class:`monostixels.inputs.flow_config.GtFlowConfig`,                ``flow/base_<name>``
               ``DisFlowConfig``, ``DeepFlowConfig``, ``RaftFlowConfig``            (gt, dis, deepflow, raft)
semantic       :class:`monostixels.inputs.semantic.GtSemanticConfig`,               ``semantic/base_<name>``
               ``NoSemanticConfig``, ``Fcn8sSemanticConfig``, ``OnnxSemanticConfig``  (gt, none, fcn8s, onnx)
eval           :class:`monostixels.pipeline.EvalConfig`                             ``eval/base_eval``
output         :class:`monostixels.output.viewer.OutputConfig`                      ``output/base_output``
batch          :class:`monostixels.batch.BatchConfig`                               ``batch/base_batch``
calibrate      :class:`monostixels.data.calibration.CalibrateConfig`                ``calibrate/base_calibrate``
=============  ===================================================================  ============================
"""
from __future__ import annotations

import sys
from typing import Sequence

from hydra.core.config_store import ConfigStore

from monostixels._checks import InputError
from monostixels._config import composition_error, load_config
from monostixels.batch import BatchConfig
from monostixels.core.energy import PriorConfig
from monostixels.core.solver import SolverConfig
from monostixels.data.calibration import CalibrateConfig
from monostixels.data.sources import DATA_SCHEMAS, CameraConfig
from monostixels.inputs.flow_config import FLOW_SCHEMAS
from monostixels.inputs.motion_track import MOTION_SCHEMAS
from monostixels.inputs.semantic import SEMANTIC_SCHEMAS
from monostixels.output.viewer import OutputConfig
from monostixels.pipeline import EvalConfig
from monostixels.post.movers import MoverCheckParams
from monostixels.sequence.runner import KeyframeParams
from monostixels.sequence.stream import StreamParams
from monostixels.sequence.tracking import TrackParams
from monostixels.sequence.ttc import TtcParams

__all__ = ["SCHEMAS", "register", "composition_error", "check_overrides", "refuse_bad_overrides"]

#: ``(group, name in the ConfigStore, schema)`` of every schema: one per group, or one per option (by its
#: ``name``) where the options of a group differ in their keys.
SCHEMAS: tuple[tuple[str, str, type], ...] = (
    ("movers", "base_movers", MoverCheckParams),
    ("solver", "base_solver", SolverConfig),
    ("prior", "base_prior", PriorConfig),
    ("stream", "base_stream", StreamParams),
    ("keyframes", "base_keyframes", KeyframeParams),
    ("temporal", "base_temporal", TrackParams),
    ("ttc", "base_ttc", TtcParams),
    *(("motion", f"base_{name}", schema) for name, schema in MOTION_SCHEMAS.items()),
    *(("data", f"base_{name}", schema) for name, schema in DATA_SCHEMAS.items()),
    ("camera", "base_camera", CameraConfig),
    *(("flow", f"base_{name}", schema) for name, schema in FLOW_SCHEMAS.items()),
    *(("semantic", f"base_{name}", schema) for name, schema in SEMANTIC_SCHEMAS.items()),
    ("eval", "base_eval", EvalConfig),
    ("output", "base_output", OutputConfig),
    ("batch", "base_batch", BatchConfig),
    ("calibrate", "base_calibrate", CalibrateConfig),
)


def register() -> None:
    """Store every schema of :data:`SCHEMAS` in Hydra's ConfigStore (again: the same nodes)."""
    cs = ConfigStore.instance()
    for group, name, schema in SCHEMAS:
        cs.store(group=group, name=name, node=schema)


def check_overrides(overrides: Sequence[str]) -> InputError | None:
    """Compose the package config with ``overrides`` as the command line would
    (:func:`monostixels.pipeline.load_config`); the one-line error of an unknown key or a wrong type among
    them, else None (the config composes, or fails for a reason Hydra reports itself)."""
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        return None
    try:
        load_config(overrides)
    except InputError as e:
        return e
    except Exception:  # noqa: BLE001 - not ours to report: Hydra's own run reports it
        return None
    return None

register()


def refuse_bad_overrides(cmd: str, flags: list[str], overrides: list[str]) -> None:
    """``monostixels CMD``'s ``overrides`` checked before Hydra composes them: an override of a group with a
    schema (monostixels.config_schema) that Hydra refuses (an unknown key, a value of the wrong type): one line
    naming the option and exit 1, as for any bad input (Hydra itself would print its composition error over
    several lines). Sweeps (their overrides are ranges) are left to Hydra."""
    if {"--multirun", "-m"} & set(flags):
        return
    groups = {g for g, _, _ in SCHEMAS}
    if not any(o.lstrip("+~").split("=", 1)[0].split(".", 1)[0] in groups for o in overrides):
        return  # the packaged options compose (tests/test_config_schema.py): only a user's value can fail
    error = check_overrides([*overrides, f"command={cmd}"])
    if error is not None:
        print(f"monostixels {cmd}: error: {error}", file=sys.stderr)
        sys.exit(1)
