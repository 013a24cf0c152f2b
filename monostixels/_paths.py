"""Where the package finds the files its config names: the shipped models and a user's own.

The repository's ``models/`` folder is installed as the package ``monostixels.models`` (see
pyproject.toml), so a config path ``models/NAME`` means the shipped file in every kind of
install: the checkout's ``models/`` in an editable install, ``site-packages/monostixels/models/``
from a wheel. A user points to other weights with an absolute path, or a path relative to the
working directory (``semantic.model=/path/net.onnx``, ``flow.weights=my/raft.pt``).
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

__all__ = ["REPO_ROOT", "shipped_models_dir", "path_candidates", "find_file"]

#: The folder that holds the ``monostixels`` package: the repository root in an editable install.
REPO_ROOT = Path(__file__).resolve().parents[1]
#: First part of a config path that names a shipped model.
_MODELS = "models"


def shipped_models_dir() -> Path | None:
    """The folder of the shipped models (``monostixels.models``), or None where it is not installed."""
    spec = importlib.util.find_spec(f"monostixels.{_MODELS}")
    locations = list(spec.submodule_search_locations or []) if spec is not None else []
    for loc in locations:
        if Path(loc).is_dir():
            return Path(loc)
    fallback = REPO_ROOT / _MODELS  # a checkout on sys.path without an install
    return fallback if fallback.is_dir() else None


def path_candidates(path: str | Path) -> list[Path]:
    """Where a config path may point, in the order tried.

    An absolute path is taken as it is. A relative one is tried against the working directory,
    then, for ``models/...``, against the shipped models, then against the repository root.
    """
    p = Path(str(path)).expanduser()
    if p.is_absolute():
        return [p]
    out = [Path.cwd() / p]
    shipped = shipped_models_dir()
    if shipped is not None and p.parts and p.parts[0] == _MODELS:
        out.append(shipped.joinpath(*p.parts[1:]))
    out.append(REPO_ROOT / p)
    return list(dict.fromkeys(out))


def find_file(path: str | Path) -> Path | None:
    """The first existing file among :func:`path_candidates`, resolved; None if there is none."""
    for c in path_candidates(path):
        if c.is_file():
            return c.resolve()
    return None
