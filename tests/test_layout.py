"""The package's layout keeps data flowing one way: layers that import only from the layers below them, no
import cycle, and the product path never imports ``monostixels.eval``."""
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
    # The pipeline computes the SfM baseline (`eval` and `demo` show it): its triangulation is product code.
    defines = [_module_name(f) for f in sorted(PACKAGE.rglob("*.py"))
               if any(isinstance(n, ast.FunctionDef) and n.name == "triangulate" for n in ast.walk(ast.parse(f.read_text())))]
    assert defines and not [m for m in defines if m.startswith("monostixels.eval")], defines


#: The package's layers, lowest first (README, "Layout"): a module imports only from its own layer and the
#: layers before it. Each layer: its name in the README's layout block and the sub-packages or top-level
#: modules (without ``.py``; ``__init__`` is the package's own) it holds.
_LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("_*.py", ("__init__", "_checks", "_config", "_paths", "_pools", "_threads", "_torchvision")),
    ("core/", ("core", "_cpu")),  # _cpu reports the solver kernel's build beside the CPU's
    ("data/", ("data",)),
    ("inputs/", ("inputs",)),
    ("post/", ("post",)),
    ("pipeline.py", ("pipeline",)),
    ("sequence/", ("sequence",)),
    ("output/", ("output",)),
    ("build.py", ("build",)),  # the source, runner and writers of a command, from the config parsed once
    ("eval/", ("eval",)),
    ("batch.py", ("batch",)),
    ("config_schema.py", ("config_schema",)),  # it gathers the settings of every layer below
    ("cli.py", ("cli",)),
)


def _module_name(path: Path, root: Path = PACKAGE.parent) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _import_graph(package: Path = PACKAGE) -> dict[str, dict[str, int]]:
    """{module: {module of the package it imports: first line}} of every module under ``package``. An
    imported name counts as its module; imports inside functions and TYPE_CHECKING blocks count too."""
    files = {_module_name(f, package.parent): f for f in sorted(package.rglob("*.py"))}
    graph: dict[str, dict[str, int]] = {}
    for name, path in files.items():
        edges: dict[str, int] = {}
        for line, imported in sorted(_imported_modules(path, package.parent)):
            while imported and imported not in files:
                imported = imported.rpartition(".")[0]
            if imported and imported != name:
                edges.setdefault(imported, line)
        graph[name] = edges
    return graph


def _layer(module: str) -> int:
    """Index in :data:`_LAYERS` of a module of the package (``monostixels.core.solver``: core's)."""
    parts = module.split(".")
    key = parts[1] if len(parts) > 1 else "__init__"
    found = [i for i, (_, members) in enumerate(_LAYERS) if key in members]
    assert found, f"{module} is in no layer: add it to _LAYERS (tests/test_layout.py) and to the README's layout"
    return found[0]


def _cycle(graph: dict[str, dict[str, int]]) -> list[str] | None:
    """One import cycle of ``graph``, as the modules along it (the first again at the end), or None."""
    state: dict[str, int] = {}  # 1: on the path being walked, 2: done
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        path.append(m)
        for n in sorted(graph.get(m, {})):
            if state.get(n) == 1:
                return path[path.index(n):] + [n]
            if n not in state and (found := visit(n)):
                return found
        path.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return None


def test_the_graph_sees_imports_inside_functions_and_type_checking_blocks(tmp_path):
    pkg = tmp_path / "monostixels"
    (pkg / "core").mkdir(parents=True)
    (pkg / "post").mkdir()
    for f in ("__init__.py", "core/__init__.py", "post/__init__.py", "post/boundaries.py"):
        (pkg / f).write_text("")
    (pkg / "core" / "solver.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ..post import boundaries\n"
        "def f():\n    from monostixels.post.boundaries import REFINE\n")
    graph = _import_graph(pkg)
    assert graph["monostixels.core.solver"] == {"monostixels.post": 3, "monostixels.post.boundaries": 3}
    assert _layer("monostixels.core.solver") < _layer("monostixels.post.boundaries")
    assert _cycle({"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b": 1}, "b": {}}) is None


def test_every_module_sits_in_a_layer():
    for module in _import_graph():
        _layer(module)


def test_no_import_runs_against_the_layers():
    against = [f"{m} (line {line}) imports {n}" for m, edges in sorted(_import_graph().items())
               for n, line in sorted(edges.items()) if _layer(n) > _layer(m)]
    layers = [name for name, _ in _LAYERS]
    assert not against, f"imports from a higher layer (layers, lowest first: {layers}):\n" + "\n".join(against)


def test_the_package_has_no_import_cycle():
    cycle = _cycle(_import_graph())
    assert cycle is None, f"import cycle: {' -> '.join(cycle or [])}"


def test_the_per_pair_pipeline_imports_nothing_of_the_sequence_layer():
    # The sequence layer owns what is carried between frames; the pipeline computes a pair from what it is given.
    graph = _import_graph()
    assert not [m for m in graph["monostixels.pipeline"] if m.split(".")[:2] == ["monostixels", "sequence"]]


def test_the_readme_states_the_layers_in_order():
    text = (PACKAGE.parent / "README.md").read_text()
    block = text[text.index("## Layout"):]
    block = block[block.index("```") + 3:]
    block = block[:block.index("```")]
    # Each layer starts a line of the block (after its indent), lowest first.
    heads = [ln.split()[0] for ln in block.splitlines() if ln.strip()]
    layers = [name for name, _ in _LAYERS]
    assert [h for h in heads if h in layers] == layers, heads


#: Modules below the builder that may hold a config itself: the config's own helpers, which compose it
#: (``_config``: load_config, load_group) and turn its nodes into the settings' dataclasses with one-line errors
#: (``_checks``: config_params, option_params); the builder calls them, every other module takes the settings.
_MAY_TAKE_THE_CONFIG = ("monostixels._config", "monostixels._checks")
#: What a schema dataclass below the builder may import of omegaconf: the marker of a required value (``???``).
_SCHEMA_NAMES = {"MISSING"}


def _config_uses(path: Path) -> list[str]:
    """Where ``path`` imports omegaconf (but :data:`_SCHEMA_NAMES`) or annotates a parameter or a return with
    ``DictConfig`` (also in a string annotation), as ``line: what``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [f"{node.lineno}: import {a.name}" for a in node.names if a.name.split(".")[0] == "omegaconf"]
        elif isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").split(".")[0] == "omegaconf":
            found += [f"{node.lineno}: from {node.module} import {a.name}" for a in node.names if a.name not in _SCHEMA_NAMES]
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            args = node.args
            notes = [a.annotation for a in (*args.posonlyargs, *args.args, *args.kwonlyargs, args.vararg, args.kwarg)
                     if a is not None and a.annotation is not None] + ([node.returns] if node.returns else [])
            found += [f"{n.lineno}: {node.name}(... {ast.unparse(n)})" for n in notes if "DictConfig" in ast.unparse(n)]
    return sorted(found, key=lambda u: int(u.split(":")[0]))


def test_the_config_scan_sees_imports_and_annotations(tmp_path):
    src = tmp_path / "x.py"
    src.write_text("from omegaconf import MISSING\nimport omegaconf\nfrom omegaconf import DictConfig, OmegaConf\n"
                   "def f(cfg: 'DictConfig | None', n: int) -> None:\n    from omegaconf.errors import ValidationError\n"
                   "def g(*, cfg: Any) -> DictConfig: ...\n")
    assert [u.split(":")[0] for u in _config_uses(src)] == ["2", "3", "3", "4", "5", "6"]


def test_nothing_below_the_builder_takes_a_config():
    # The builder (build.py) parses the composed config once into typed settings and hands them down: a module
    # below it that took the config would parse it again, its own way (issue 55, "one direction through the code").
    builder = _layer("monostixels.build")
    uses = {m: u for m, f in ((_module_name(f), f) for f in sorted(PACKAGE.rglob("*.py")))
            if _layer(m) < builder and m not in _MAY_TAKE_THE_CONFIG and (u := _config_uses(f))}
    assert not uses, f"modules below build.py that read the config itself (take the settings instead): {uses}"


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
