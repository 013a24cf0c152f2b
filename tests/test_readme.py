"""The README and docs/ stay true: set-up commands in step with CI, every command shown names real
commands, config groups, keys, modules and flags, every link resolves, and the pages stay short and
free of the project's own history (which lives in docs/experiments.md)."""
from __future__ import annotations

import importlib.util
import re
import shlex
from functools import lru_cache
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md")), REPO / "models" / "MODEL_CARD.md"]
_README_MAX_LINES = 300


def _readme_commands() -> list[str]:
    text = (REPO / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.S)
    return [line.strip() for line in blocks[0].splitlines() if line.strip() and not line.startswith("#")]


def test_readme_starts_with_the_two_fresh_machine_commands():
    cmds = _readme_commands()
    assert len(cmds) == 2
    assert cmds[0].startswith("python3 -m venv .venv") and cmds[0].endswith("monostixels demo")
    assert "pip install torch==2.13.0" in cmds[0] and "pip install torch==2.13.0" in cmds[1]
    assert cmds[1].endswith("python -m pytest -q")


def test_ci_runs_the_readme_test_command():
    ci = (REPO / ".ci" / "run").read_text()
    want = _readme_commands()[1].replace("pip install ", "pip install -q ")
    assert want in ci


# ------------------------------------------------------------------------------------------------
# Commands shown on the pages.

def _shown_commands(page: Path) -> list[str]:
    """Commands of the page's ```bash blocks (continuation lines joined, comments dropped) and of its
    inline code spans that start with ``monostixels`` or ``python`` (after env settings and ``nice``)."""
    text = page.read_text()
    cmds = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = re.sub(r"\s+#\s.*$", "", line).strip()
            if line and not line.startswith("#"):
                cmds.append(line)
    prose = re.sub(r"```.*?```", "", text, flags=re.S).replace("\n", " ")
    cmds += [c for c in re.findall(r"`([^`]+)`", prose) if re.match(r"([A-Z_]+=\S+ )*(nice -n \d+ )?(monostixels|python) \S", c)]
    return cmds


def _words(cmd: str) -> list[list[str]]:
    """The simple commands of a shell line (split at ``&&``), without env assignments and ``nice``."""
    out = []
    for part in cmd.split("&&"):
        w = shlex.split(part)
        while w and (re.match(r"^[A-Z_]+=", w[0]) or w[0] == "nice"):
            w = w[3:] if w[0] == "nice" and len(w) > 2 and w[1] == "-n" else w[1:]
        if w:
            out.append(w)
    return out


@lru_cache(maxsize=None)
def _compose(config_name: str, overrides: tuple[str, ...]) -> None:
    """Compose a config of conf/ with overrides: raises on an unknown group, option or key."""
    from hydra import compose, initialize_config_module

    with initialize_config_module(config_module="monostixels.conf", version_base="1.3"):
        compose(config_name=config_name, overrides=list(overrides))


#: A value the page leaves to the reader: data=..., <date>, PATH, X.
_PLACEHOLDER = re.compile(r"^(\.\.\.|.*<.*>.*|[A-Z]+)$")


def _overrides(args: list[str]) -> tuple[str, ...]:
    # Hydra's own keys (hydra.*, hydra/launcher=...) belong to Hydra and its plugins.
    return tuple(a for a in args if "=" in a and not a.startswith(("-", "hydra"))
                 and not _PLACEHOLDER.match(a.split("=", 1)[1]))


def _script_flags(source: Path) -> set[str]:
    """The flags a script declares, with those of the benchmark modules it imports (shared options such as
    benchmarks.dashcam.add_report_arguments)."""
    text = source.read_text()
    flags = set(re.findall(r"add_argument\(\s*\"(--[\w-]+)\"", text))
    for module in re.findall(r"^from benchmarks\.(\w+) import", text, re.M):
        flags |= set(re.findall(r"add_argument\(\s*\"(--[\w-]+)\"", (REPO / "benchmarks" / f"{module}.py").read_text()))
    return flags


def _check(words: list[str]) -> None:
    from monostixels.cli import _COMMAND_DEFAULTS, COMMANDS

    head = words[0]
    if head == "monostixels":
        if len(words) > 1 and _PLACEHOLDER.match(words[1]):
            return  # `monostixels <command> --cfg job`
        assert len(words) > 1 and words[1] in COMMANDS, f"unknown command: {words[1:2]}"
        flags = [a for a in words[2:] if a.startswith("-")]
        assert set(flags) <= {"--multirun", "--cfg", "-m"}, flags
        given = _overrides([a for a in words[2:] if a not in ("--cfg", "job")])
        if {"--multirun", "-m"} & set(words):  # a sweep composes as its first point
            given = tuple(re.sub(r"^([^=]+=)([^,\[\]]+),.*$", r"\1\2", o) for o in given)
        keys = {o.split("=", 1)[0].lstrip("+~") for o in given}
        defaults = tuple(d for d in _COMMAND_DEFAULTS.get(words[1], ()) if d.split("=")[0] not in keys)
        _compose("config", defaults + given + (f"command={words[1]}",))  # as the command composes it
    elif head in ("python", "python3") and words[1:2] == ["-m"]:
        module = words[2]
        if module in ("venv", "pytest", "pip", "build"):
            return
        spec = importlib.util.find_spec(module)
        assert spec is not None and spec.origin, f"no module {module}"
        rest = words[3:]
        src = Path(spec.origin)
        hydra_name = re.search(r"config_name=(?:\"(\w+)\"|CONFIG_NAME)", src.read_text())
        if hydra_name:  # a Hydra app of conf/: its --config-name and overrides must compose
            default = hydra_name.group(1) or re.search(r"CONFIG_NAME = \"(\w+)\"", src.read_text()).group(1)
            name = rest[rest.index("--config-name") + 1] if "--config-name" in rest else default
            assert (REPO / "conf" / f"{name}.yaml").is_file(), name
            _compose(name, _overrides(rest))
        else:
            flags = {a.split("=")[0] for a in rest if a.startswith("--")}
            assert flags <= _script_flags(src), f"{module}: unknown flags {flags - _script_flags(src)}"
    elif head in ("python", "python3") and words[1].endswith(".py"):
        script = REPO / words[1]
        assert script.is_file(), words[1]
        flags = {a.split("=")[0] for a in words[2:] if a.startswith("--")}
        assert flags <= _script_flags(script), f"{words[1]}: unknown flags {flags - _script_flags(script)}"
    elif head == "pip":
        pyproject = (REPO / "pyproject.toml").read_text()
        for extra in re.findall(r"\.\[([\w,-]+)\]", " ".join(words)):
            for e in extra.split(","):
                assert re.search(rf"^{re.escape(e)} = \[", pyproject, flags=re.M), f"no extra [{e}] in pyproject.toml"


_COMMANDS = sorted({(p.relative_to(REPO).as_posix(), c) for p in PAGES for c in _shown_commands(p)})


def test_the_pages_show_commands():
    pages = {p for p, _ in _COMMANDS}
    assert {"README.md", "docs/results.md", "docs/usage.md", "docs/benchmarks.md"} <= pages
    assert sum(c.startswith("monostixels ") for _, c in _COMMANDS) >= 20


@pytest.mark.parametrize("page, cmd", _COMMANDS, ids=[f"{p}: {c[:60]}" for p, c in _COMMANDS])
def test_shown_command_exists(page: str, cmd: str):
    for words in _words(cmd):
        _check(words)


@pytest.mark.parametrize("cmd, wrong", [
    ("monostixels fly data=synthetic", "unknown command"),
    ("monostixels eval flow=nonexistent", "nonexistent"),
    ("monostixels run data=frames data.no_such_key=1", "no_such_key"),
    ("python -m benchmarks.flow_quality --no-such-flag", "unknown flags"),
    ("python -m train.semantic --config-name no_such_config", "no_such_config"),
    ("python benchmarks/no_such_script.py", "no_such_script"),
    ("pip install -e '.[no-such-extra]'", "no extra"),
])
def test_the_check_catches_stale_commands(cmd: str, wrong: str):
    with pytest.raises(Exception, match=wrong):
        for words in _words(cmd):
            _check(words)


# ------------------------------------------------------------------------------------------------
# Links, length, history.

def _anchor(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(REPO).as_posix())
def test_links_resolve(page: Path):
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"https?://", target):
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        assert dest.exists(), f"{page.name}: link to missing {target}"
        if anchor and dest.suffix == ".md":
            anchors = {_anchor(h) for h in re.findall(r"^#+ (.+)$", dest.read_text(), flags=re.M)}
            assert anchor in anchors, f"{page.name}: no section #{anchor} in {path or page.name}"


def test_readme_is_a_short_product_page():
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= _README_MAX_LINES
    for name in ("method.md", "results.md", "experiments.md", "benchmarks.md"):
        assert (REPO / "docs" / name).is_file() and f"docs/{name}" in text, name


@pytest.mark.parametrize("path", [*PAGES, *sorted((REPO / "conf").rglob("*.yaml"))],
                         ids=lambda p: p.relative_to(REPO).as_posix())
def test_no_history_by_issue_number(path: Path):
    # Work is referred to by topic and date (docs/experiments.md), never by the tracker's numbers.
    text = path.read_text()
    assert not re.search(r"\bissues? #?\d+", text, flags=re.I), path
    assert not re.search(r"^#+ .*\b(issue|#\d+)", text, flags=re.I | re.M), path
