"""The config groups' schemas (monostixels/config_schema.py): Hydra refuses an unknown key and a value of the
wrong type when it composes the package config, naming the key; every packaged option composes; the
settings come out as the schema's dataclass."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from monostixels._checks import InputError
from monostixels.config_schema import SCHEMAS
from monostixels.pipeline import load_config

CONF = Path(__file__).resolve().parents[1] / "conf"


def _hydra_compose(overrides: list[str]):
    with initialize_config_module(config_module="monostixels.conf", version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


@pytest.mark.parametrize("override, key", [("movers.no_such_key=1", "movers.no_such_key"),
                                           ("solver.cell_rows=abc", "solver.cell_rows"),
                                           ("prior.beta_mc=big", "prior.beta_mc"),
                                           ("temporal.enabled=maybe", "temporal.enabled"),
                                           ("motion=mono", None)])
def test_hydra_refuses_unknown_keys_and_wrong_types(override, key):
    """Hydra itself refuses them at composition (its error names the key); load_config says it in one line."""
    if key is None:  # a valid choice composes
        assert OmegaConf.to_object(_hydra_compose([override]).motion).step == 4
        return
    with pytest.raises(ConfigCompositionException) as info:
        _hydra_compose([override])
    assert key in f"{info.value} {info.value.__cause__}"
    with pytest.raises(InputError, match=rf"^{key}: (unknown setting|expected)"):
        load_config([override])


@pytest.mark.parametrize("overrides, key, choices", [
    (["solver.dtype=float16"], "solver.dtype", "float32, float64"),
    (["solver.backend=cuda"], "solver.backend", "auto, eager, cpp"),
    (["solver.top_refine_objects=static"], "solver.top_refine_objects", "dynamic, all"),
    (["output.rerun_colors=rainbow"], "output.rerun_colors", "class, depth"),
    (["data=kitti2015", "data.previous=10"], "data.previous", "auto, 11, 09"),
    (["data=kitti2015", "data.split=val"], "data.split", "training, testing"),
    (["data=camvid", "data.split=training"], "data.split", "train, val, test"),
    (["flow=dis", "flow.confidence=harris"], "flow.confidence", "constant, structure_tensor"),
    (["flow=deepflow", "flow.matches=sift"], "flow.matches", "dis, none"),
    (["data=kitti_raw", "data.oxts=gps"], "data.oxts", "velocity, position"),
])
def test_a_name_that_is_none_of_a_settings_choices_is_refused_naming_it(overrides, key, choices):
    """The choices among names are Choice fields of the schemas: Hydra refuses any other name when it composes
    the config, and load_config (as the command line) says so in one line naming the key."""
    with pytest.raises(ConfigCompositionException):
        _hydra_compose(overrides)
    with pytest.raises(InputError, match=rf"^{key}: expected one of {choices}, got ") as info:
        load_config(overrides)
    assert "\n" not in str(info.value)


def test_a_choice_of_digits_reads_from_the_command_line_and_from_a_dict():
    """``data.previous=11`` reaches OmegaConf as an int: it is the member that number spells, as ``"11"`` is."""
    from monostixels.data.sources import KittiPrevious, data_params

    assert data_params(load_config(["data=kitti2015", "data.previous=11"]).data).previous is KittiPrevious["11"]
    assert data_params({"name": "kitti2015", "previous": "09"}).previous is KittiPrevious["09"]
    assert str(KittiPrevious["11"]) == "11" and KittiPrevious["11"] == "11"


def test_a_key_added_on_the_command_line_is_refused_where_it_is_read():
    """``+group.key=...`` is Hydra's explicit request to add a key: it composes, and the group's settings refuse it."""
    from monostixels._checks import config_params
    from monostixels.post.movers import MoverCheckParams

    cfg = load_config(["+movers.no_such_key=1"])
    with pytest.raises(InputError, match=r"^movers.no_such_key: unknown setting; known: enabled, "):
        config_params(MoverCheckParams, cfg.movers, "movers")


def _schemas_by_group() -> dict[str, dict[str, type]]:
    """``{group: {name in the ConfigStore: schema}}`` of :data:`SCHEMAS` (several for data, flow, ...)."""
    groups: dict[str, dict[str, type]] = {}
    for group, name, schema in SCHEMAS:
        groups.setdefault(group, {})[name] = schema
    return groups


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


def test_every_option_of_a_schema_group_composes_to_its_schema():
    for group, schemas in _schemas_by_group().items():
        assert _options(group), group
        for option in _options(group):
            node = load_config([f"{group}={option}"])[group]
            schema = OmegaConf.get_type(node)
            assert schema in schemas.values(), (group, option, schema)
            for key in OmegaConf.missing_keys(node):  # mandatory: semantic=onnx's model, motion=file's path
                OmegaConf.update(node, key.split(".", 1)[1], "given.file")
            assert isinstance(OmegaConf.to_object(node), schema)


def test_the_yaml_options_keep_only_choices():
    """A group's YAML options list a schema (or another option of the group) first; prior/default,
    solver/default, ... take the defaults."""
    import yaml

    for group, schemas in _schemas_by_group().items():
        for option in _options(group):
            data = yaml.safe_load((CONF / group / f"{option}.yaml").read_text()) or {}
            first = data.get("defaults", [None])[0]
            assert first in schemas or (CONF / group / f"{first}.yaml").is_file(), (group, option)
    assert set(yaml.safe_load((CONF / "solver" / "default.yaml").read_text())) == {"defaults"}


def test_cli_names_a_refused_setting_in_one_line(tmp_path):
    p = subprocess.run([sys.executable, "-c", "from monostixels.cli import main; main()", "eval", "solver.cell_rows=abc"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert p.returncode == 1
    lines = [ln for ln in p.stderr.splitlines() if "error:" in ln]
    assert lines == ["monostixels eval: error: solver.cell_rows: expected an integer, got 'abc'"], p.stderr
    assert "Traceback" not in p.stderr


#: An unknown key and a value of the wrong type in each group whose schemas came with the consolidation
#: (data, camera, flow, semantic, motion=gt/file, eval, output, batch, calibrate): the overrides, the option
#: the one-line error names and what it says, and the command whose group it is.
REFUSED = [
    (["data=video", "data.no_such_key=1"], "data.no_such_key", "unknown setting; known: name, path, ", "run"),
    (["data=video", "data.hfov_deg=wide"], "data.hfov_deg", "expected a number, got 'wide'", "run"),
    (["camera.roll=0.1"], "camera.roll", "unknown setting; known: height, pitch", "run"),
    (["camera.height=high"], "camera.height", "expected a number, got 'high'", "run"),
    (["flow=dis", "flow.bands=2"], "flow.bands", "unknown setting; known: name, ", "run"),  # deepflow's, not dis's
    (["flow=dis", "flow.scale=half"], "flow.scale", "expected a number, got 'half'", "run"),
    (["semantic=gt", "semantic.model=m.onnx"], "semantic.model", "unknown setting; known: name, confidence", "run"),
    (["semantic=fcn8s", "semantic.focal_px=wide"], "semantic.focal_px", "expected a number, got 'wide'", "run"),
    (["motion=gt", "motion.path=poses.txt"], "motion.path", "unknown setting; known: name", "run"),
    (["motion=file", "motion.offset=[a,0,0]"], "motion.offset[0]", "expected a number, got 'a'", "run"),
    (["eval.max_dist=80"], "eval.max_dist", "unknown setting; known: max_depth, ", "eval"),
    (["eval.max_depth=far"], "eval.max_depth", "expected a number, got 'far'", "eval"),
    (["output.rerun_fps=10"], "output.rerun_fps", "unknown setting; known: rerun, ", "run"),
    (["output.rerun=maybe"], "output.rerun", "expected true or false, got 'maybe'", "run"),
    (["batch.workers=4"], "batch.workers", "unknown setting; known: inputs, ", "batch"),
    (["batch.cpus_per_clip=two"], "batch.cpus_per_clip", "expected an integer, got 'two'", "batch"),
    (["calibrate.squares=[10,7]"], "calibrate.squares", "unknown setting; known: images, board, out, size", "calibrate"),
    (["calibrate.board=[a,6]"], "calibrate.board[0]", "expected an integer, got 'a'", "calibrate"),
]


@pytest.mark.parametrize("overrides, key, says, command", REFUSED, ids=[r[1] + ("?" if "unknown" in r[2] else "=") for r in REFUSED])
def test_every_group_refuses_an_unknown_key_and_a_wrong_type(overrides, key, says, command):
    with pytest.raises(InputError) as info:
        load_config(overrides)
    assert str(info.value).startswith(f"{key}: {says}"), str(info.value)


@pytest.mark.parametrize("group, option, wrong", [
    *(("data", name, "data.frames=many") for name in ("camvid", "ddad", "frames", "kitti2015", "kitti_raw",
                                                       "synthetic", "video")),
    *(("flow", name, "flow.sigma=big") for name in ("deepflow", "deepflow_fast", "deepflow_fb", "dis", "dis_refine",
                                                     "gt", "raft")),
    ("semantic", "gt", "semantic.confidence=high"), ("semantic", "none", "semantic.prior_overrides.alpha_dyn=big"),
    ("semantic", "fcn8s", "semantic.scale=half"), ("semantic", "fcn8s_synthetic", "semantic.runtime=[onnx]"),
    ("semantic", "onnx", "semantic.pad_to=x"), ("semantic", "cityscapes19", "semantic.softmax=maybe"),
    ("motion", "file", "motion.offset=abc"), ("motion", "gt", None), ("motion", "mono", "motion.step=x"),
])
def test_every_option_refuses_an_unknown_key_and_a_wrong_type(group, option, wrong):
    with pytest.raises(InputError, match=rf"^{group}\.no_such_key: unknown setting; known: \w"):
        load_config([f"{group}={option}", f"{group}.no_such_key=1"])
    if wrong is not None:  # motion=gt has no setting but its name
        key = wrong.split("=")[0].replace(".", r"\.")
        with pytest.raises(InputError, match=rf"^{key}: expected "):
            load_config([f"{group}={option}", wrong])


@pytest.mark.parametrize("overrides, key, says, command", REFUSED, ids=[r[1] + ("?" if "unknown" in r[2] else "=") for r in REFUSED])
def test_cli_refuses_an_unknown_key_and_a_wrong_type_of_every_group_in_one_line(tmp_path, overrides, key, says, command):
    p = subprocess.run([sys.executable, "-c", "from monostixels.cli import main; main()", command, *overrides],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert p.returncode == 1, p.stderr
    lines = [ln for ln in p.stderr.splitlines() if "error:" in ln]
    assert len(lines) == 1 and lines[0].startswith(f"monostixels {command}: error: {key}: {says}"), p.stderr
    assert "Traceback" not in p.stderr


def test_a_library_dict_reads_through_the_option_schema_by_its_name():
    """A dict (a library user's, or batch's config rebuilt from a plain dict) takes the option's defaults
    for the keys it lacks and is refused the same way as the composed option."""
    from monostixels.data.sources import VideoDataConfig, data_params
    from monostixels.inputs.flow_config import DeepFlowConfig, flow_params
    from monostixels.inputs.motion_track import motion_params

    composed = OmegaConf.to_object(load_config(["flow=deepflow"]).flow)
    assert flow_params({"name": "deepflow"}) == composed and isinstance(composed, DeepFlowConfig)
    assert flow_params(OmegaConf.create(OmegaConf.to_container(load_config(["flow=deepflow_fast"]).flow))).scale == 0.5
    assert data_params({"name": "video", "path": "c.mp4"}) == VideoDataConfig(path="c.mp4")
    with pytest.raises(InputError, match=r"^data\.hfov_deg: expected a number, got 'wide'$"):
        data_params({"name": "video", "hfov_deg": "wide"})
    with pytest.raises(InputError, match=r"^flow\.name: unknown option 'farneback'; choose one of gt, "):
        flow_params({"name": "farneback"})
    with pytest.raises(InputError, match=r"^motion\.path: motion=file needs a poses file"):
        motion_params(load_config(["motion=file"]).motion)
