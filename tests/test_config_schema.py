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
