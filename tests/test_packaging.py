"""A non-editable install (a wheel) carries the configs and the shipped models, and `run` uses them."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from omegaconf import OmegaConf

REPO = Path(__file__).resolve().parents[1]


def _shipped_model_paths() -> set[str]:
    """Every ``models/...`` file a config of conf/ names and the checkout holds."""
    found = set()
    for f in (REPO / "conf").rglob("*.yaml"):
        for value in re.findall(r"^\s*\w+:\s*(models/\S+)\s*$", f.read_text(), flags=re.M):
            if (REPO / value).is_file():
                found.add(value)
    return found


#: Not part of a source tree: local environments, build and run outputs.
_NOT_SOURCE = (".venv", ".git", "build", "*.egg-info", "outputs", "runs", "multirun", "__pycache__", ".pytest_cache")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    # Built from a copy of the source tree, as from a fresh clone: setuptools builds in the tree
    # (build/), and a stale build/ of the checkout would put files in the wheel that no longer exist.
    src = tmp_path_factory.mktemp("src") / "monostixels"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(*_NOT_SOURCE))
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(out),
                    str(src)], check=True, capture_output=True, timeout=600)
    (whl,) = out.glob("monostixels-*.whl")
    return whl


@pytest.fixture(scope="module")
def installed(wheel: Path, tmp_path_factory) -> Path:
    target = tmp_path_factory.mktemp("site")
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(target), str(wheel)],
                   check=True, capture_output=True, timeout=600)
    return target


def _python(code: str, target: Path, cwd: Path) -> str:
    env = {**os.environ, "PYTHONPATH": str(target)}
    out = subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_wheel_holds_the_default_models_and_every_config(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    # the semantic nets of run (preset=fast), preset=accurate and demo
    defaults = {"models/fcn8s_real_int8.onnx", "models/fcn8s_real.onnx", "models/fcn8s_synthetic.onnx"}
    assert defaults <= _shipped_model_paths()
    for model in _shipped_model_paths():
        assert f"monostixels/{model}" in names, model
    configs = {str(f.relative_to(REPO)) for f in (REPO / "conf").rglob("*.yaml")}
    assert configs and all(f"monostixels/{c}" in names for c in configs)
    assert "monostixels/models/MODEL_CARD.md" in names
    # Nothing but the source: every module of the wheel is a file of the checkout.
    roots = {"conf": REPO / "conf", "models": REPO / "models"}
    for n in names:
        if n.startswith("monostixels/") and n.endswith(".py"):
            rel = Path(n).relative_to("monostixels")
            src = roots[rel.parts[0]].joinpath(*rel.parts[1:]) if rel.parts[0] in roots else REPO / "monostixels" / rel
            assert src.is_file(), n


def test_config_found_in_non_editable_install(installed: Path, tmp_path: Path) -> None:
    code = ("import monostixels; from monostixels.pipeline import load_config; "
            "c = load_config(['solver.cell_rows=5']); print(monostixels.__file__, c.solver.cell_rows, c.prior.beta_mc)")
    path, rows, beta = _python(code, installed, tmp_path).split()
    assert path.startswith(str(installed)) and rows == "5"
    assert float(beta) > 0


def test_installed_package_finds_its_models_and_run_uses_the_real_image_net(installed: Path, tmp_path: Path) -> None:
    # Outside the checkout, relative `models/...` paths resolve to the installed copies.
    code = ("from monostixels.inputs.semantic import resolve_model_path; "
            "print(resolve_model_path('models/fcn8s_real.onnx'))")
    assert _python(code, installed, tmp_path).strip().startswith(str(installed / "monostixels" / "models"))
    env = {**os.environ, "PYTHONPATH": str(installed)}
    p = subprocess.run([sys.executable, "-m", "monostixels.cli", "run", "--cfg", "job"], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert "not found" not in p.stderr  # no fall-back to semantic=none
    semantic = OmegaConf.create(p.stdout).semantic
    assert semantic.name == "fcn8s" and semantic.model == "models/fcn8s_real_int8.onnx"
