"""The package's layout keeps data flowing one way: the product path never imports ``monostixels.eval``."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "monostixels"
#: Modules that may import the evaluation: the evaluation itself and the command line (`monostixels eval`).
_MAY_IMPORT_EVAL = ("eval/", "cli.py")


def _imported_modules(path: Path, root: Path = PACKAGE.parent) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``path`` (a module under ``root``), relative ones resolved."""
    package = list(path.relative_to(root).parts[:-1])  # the module's package (an __init__'s own)
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            mod = ".".join(base + ([node.module] if node.module else []))
            # `from monostixels import eval` imports the sub-package too.
            found += [(node.lineno, f"{mod}.{a.name}") for a in node.names] + [(node.lineno, mod)]
    return found


def _product_modules() -> list[Path]:
    files = sorted(PACKAGE.rglob("*.py"))
    return [f for f in files if not str(f.relative_to(PACKAGE)).startswith(_MAY_IMPORT_EVAL)]


def test_the_scan_sees_every_kind_of_import(tmp_path):
    # The scanner itself: absolute, from-, relative and sub-package imports of eval are all caught.
    pkg = tmp_path / "monostixels" / "inputs"
    pkg.mkdir(parents=True)
    src = pkg / "x.py"
    src.write_text("import monostixels.eval.metrics\nfrom ..eval import metrics\nfrom monostixels import eval\n"
                   "from monostixels.post.sfm import triangulate\n")
    mods = [m for _, m in _imported_modules(src, tmp_path)]
    assert "monostixels.eval.metrics" in mods and "monostixels.eval" in mods
    assert sum(m == "monostixels.eval" or m.startswith("monostixels.eval.") for m in mods) >= 3


@pytest.mark.parametrize("path", _product_modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_product_path_does_not_import_eval(path: Path):
    bad = [(line, m) for line, m in _imported_modules(path) if m == "monostixels.eval" or m.startswith("monostixels.eval.")]
    assert not bad, f"{path.relative_to(PACKAGE.parent)} imports the evaluation: {bad}"


def test_the_sfm_baseline_lives_in_the_product_path():
    assert (PACKAGE / "post" / "sfm.py").is_file() and not (PACKAGE / "eval" / "sfm.py").exists()


#: Sub-packages by stage, in the order data flows through them (README, "Layout"), and some of their modules.
_STAGES = {
    "inputs": ("flow", "semantic", "motion", "static_regions"),
    "core": ("geometry", "classes", "energy", "columns", "solver", "stixels", "_dp_cpp"),
    "post": ("movers", "boundaries", "sfm"),
    "sequence": ("runner", "stream", "tracking"),
    "output": ("viz", "bev", "scene3d", "viewer", "io"),
}
#: The only modules at the top: the per-pair computation, the entry points, the config groups' schemas
#: (they gather every stage's settings) and private helpers.
_TOP = {"__init__", "pipeline", "cli", "batch", "config_schema", "_checks", "_cpu", "_paths", "_pools", "_threads",
        "_torchvision"}


def test_modules_sit_in_the_sub_package_of_their_stage():
    for stage, modules in _STAGES.items():
        for m in modules:
            assert (PACKAGE / stage / f"{m}.py").is_file(), f"{stage}/{m}.py"
    assert (PACKAGE / "core" / "csrc" / "column_dp.cpp").is_file()
    top = {f.stem for f in PACKAGE.glob("*.py")}
    assert top == _TOP, f"modules at the top of the package that belong to a stage: {sorted(top - _TOP)}"


#: Most lines of one module of the package: past it a module holds more than one concern.
_MAX_MODULE_LINES = 800


def test_no_module_is_over_the_line_limit():
    long = {str(f.relative_to(PACKAGE)): n for f in sorted(PACKAGE.rglob("*.py"))
            if (n := len(f.read_text().splitlines())) > _MAX_MODULE_LINES}
    assert not long, f"modules over {_MAX_MODULE_LINES} lines (split them by concern): {long}"


def test_no_sub_package_has_the_name_of_an_ignored_folder():
    # .gitignore's unanchored folders (the commands' `outputs/`, `runs/`, ...) are ignored at every
    # depth, and the wheel test's source copy leaves them out too: a sub-package of such a name would
    # be neither committed nor shipped.
    ignored = {ln.strip().rstrip("/") for ln in (PACKAGE.parent / ".gitignore").read_text().splitlines()
               if ln.strip().endswith("/") and not ln.strip().startswith(("/", "#")) and "*" not in ln}
    clash = sorted(str(d.relative_to(PACKAGE)) for d in PACKAGE.rglob("*")
                   if d.is_dir() and d.name in ignored - {"__pycache__"})
    assert ignored and not clash, f"sub-packages named like ignored folders: {clash}"
