"""Build and call the fused C++ column DP and its preparation ops (``monostixels/core/csrc/column_dp.cpp``).

The kernel is compiled at first use with :func:`torch.utils.cpp_extension.load` (g++ and ninja)
and cached in torch's extension directory (``$TORCH_EXTENSIONS_DIR``, default
``~/.cache/torch_extensions``); later processes load the cached library in milliseconds.
Nothing is downloaded. Without a compiler, or when the build fails, :func:`available` returns
False after logging ONE warning, and the solver falls back to its eager path.

Builds are serialised with an ``flock`` on the build folder, which the kernel releases when a
process dies. torch's own ``lock`` file is not released that way: a build that was killed (a
timeout, a stopped machine) leaves it behind, and every later process would wait for it forever.
Found while holding our lock, it can only be such a leftover and is removed.
"""
from __future__ import annotations

import contextlib
import fcntl
import hashlib
import logging
import os
import platform
import re
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import torch

__all__ = ["available", "loaded", "build_flags", "march", "MARCH_ENV", "column_dp", "cell_sums", "cell_means_checked", "hypotheses", "geometry",
           "semantic_prefix", "build_error", "CHECK_FINITE",
           "CHECK_NONNEGATIVE", "CHECK_POSITIVE_DEFINITE"]

logger = logging.getLogger(__name__)

_SOURCE = Path(__file__).with_name("csrc") / "column_dp.cpp"
#: The environment variable that chooses the instruction set the kernel is built for (gcc's
#: ``-march``): e.g. ``x86-64-v3`` (AVX2) for a build to run on any recent x86-64, ``native`` (the
#: default) for this CPU's. The cached build's name carries it.
MARCH_ENV = "MONOSTIXELS_MARCH"
_DEFAULT_MARCH = "native"
#: No fast-math and no FMA contraction: the kernel must round exactly like the eager torch ops.
#: -fno-trapping-math (FP exceptions are never inspected) lets gcc vectorise the branch-free loops.
_CFLAGS = ["-O3", "-ffp-contract=off", "-fno-fast-math", "-fno-trapping-math", "-fopenmp"]
#: at::parallel_for is an OpenMP pragma in the headers: without -fopenmp it runs on one thread. The
#: extension then uses the libgomp.so.1 that torch has already loaded (same soname): one runtime.
_LDFLAGS = ["-fopenmp"]
#: Order of the scalar parameters the kernel reads (``Params`` in column_dp.cpp).
PARAM_ORDER = ("beta_mc", "alpha_grav_below", "beta_grav_below", "alpha_grav_above", "beta_grav_above",
               "alpha_ord", "beta_ord", "alpha_flat", "beta_flat", "alpha_F", "delta_F", "alpha_dyn")

#: Value checks of :func:`cell_means_checked` (``CellCheck`` in column_dp.cpp): all finite; and every
#: pixel >= 0; and every pixel a positive definite 2 x 2 matrix (4 channels, (B, H, W, 2, 2) memory).
CHECK_FINITE, CHECK_NONNEGATIVE, CHECK_POSITIVE_DEFINITE = 1, 2, 3
_NO_CHECK = 0

_lock = threading.Lock()
_state: dict[str, object] = {"tried": False, "ok": False, "error": None}


def _cpu_tag() -> str:
    """A short tag of this CPU: ``-march=native`` builds must not be shared across CPU models."""
    try:
        info = Path("/proc/cpuinfo").read_text()
        flags = next((ln for ln in info.splitlines() if ln.startswith("flags")), "")
        model = next((ln for ln in info.splitlines() if ln.startswith("model name")), "")
    except OSError:
        flags = model = ""
    return hashlib.sha1(f"{platform.machine()}|{model}|{flags}".encode()).hexdigest()[:8]


def march() -> str:
    """The ``-march`` of the kernel's build: ``$MONOSTIXELS_MARCH``, else ``native``."""
    value = os.environ.get(MARCH_ENV, "").strip() or _DEFAULT_MARCH
    if not re.fullmatch(r"[A-Za-z0-9_.+-]+", value):
        raise ValueError(f"{MARCH_ENV}: a gcc -march value such as native or x86-64-v3, got {value!r}")
    return value


def build_flags() -> list[str]:
    """The compiler flags of the kernel's build (the benchmarks record them)."""
    return [_CFLAGS[0], f"-march={march()}", *_CFLAGS[1:]]


def _extensions_root() -> Path:
    """torch's extension folder: ``$TORCH_EXTENSIONS_DIR``, else torch's default (``~/.cache/torch_extensions``
    with a ``py<ver>_<cpu|cuXY>`` folder), where :func:`torch.utils.cpp_extension.load` itself would build."""
    from torch.utils import cpp_extension

    root = os.environ.get("TORCH_EXTENSIONS_DIR")
    if root:
        return Path(root)
    accel = f"cu{torch.version.cuda.replace('.', '')}" if torch.version.cuda else "cpu"
    return Path(cpp_extension.get_default_build_root()) / f"py{sys.version_info.major}{sys.version_info.minor}_{accel}"


@contextlib.contextmanager
def build_lock(build_dir: Path) -> Iterator[None]:
    """Hold the build folder's flock; a torch ``lock`` file found meanwhile is a killed build's leftover."""
    build_dir.mkdir(parents=True, exist_ok=True)
    with open(build_dir / ".monostixels.flock", "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)  # waits for a live builder only; a dead one's flock is gone
        try:
            stale = build_dir / "lock"
            if stale.exists():
                logger.warning("solver: removing %s, left by a C++ kernel build that did not finish", stale)
                stale.unlink(missing_ok=True)
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _build() -> None:
    from torch.utils import cpp_extension

    # The name carries the hash of the source and the flags (the -march among them) and the CPU tag,
    # so an edited kernel, another instruction set or another CPU gets its own cached build instead
    # of a stale or illegal-instruction one.
    cflags = build_flags()
    src_hash = hashlib.sha1(_SOURCE.read_bytes() + " ".join(cflags + _LDFLAGS).encode()).hexdigest()[:8]
    name = f"monostixels_column_dp_{src_hash}_{_cpu_tag()}"
    build_dir = _extensions_root() / name
    with build_lock(build_dir):
        cpp_extension.load(
            name=name,
            sources=[str(_SOURCE)],
            extra_cflags=cflags,
            extra_ldflags=_LDFLAGS,
            build_directory=str(build_dir),
            is_python_module=False,
            verbose=False,
        )


def available() -> bool:
    """Whether the compiled kernel is loaded (builds it on the first call; thread-safe)."""
    with _lock:
        if not _state["tried"]:
            _state["tried"] = True
            try:
                _build()
                _state["ok"] = all(hasattr(torch.ops.monostixels, op) for op in ("column_dp", "cell_sums", "hypotheses", "geometry",
                                                                     "semantic_prefix"))
            except Exception as exc:  # noqa: BLE001 - any build/load failure means: use the eager path
                _state["error"] = f"{type(exc).__name__}: {exc}"
                logger.warning("solver: the C++ column DP could not be built or loaded (%s); using the "
                               "eager torch path (same results, ~50x slower). Set solver.backend=eager "
                               "to silence this.", str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        return bool(_state["ok"])


def loaded() -> bool:
    """Whether the kernel is loaded already (never builds it; :func:`available` does)."""
    return bool(_state["ok"])


def build_error() -> str | None:
    """Why the kernel is not available (None when it is, or before the first :func:`available`)."""
    return _state["error"]  # type: ignore[return-value]


def column_dp(*args: object) -> list[torch.Tensor]:
    """The hard DP and its back-tracking: (col, b, t, type, cls, p, p_ground, tau, cost, energy) of
    ``solver.ColumnSolution``; arguments as in ``column_dp.cpp`` (see ``solver._solve_columns_cpp``)."""
    return torch.ops.monostixels.column_dp(*args)


def cell_sums(x: torch.Tensor, r: int, w: int) -> torch.Tensor:
    """Cell sums (B, ch, n, C) of x (B, ch, H, W); the same bits as ``columns._block_sum``."""
    return torch.ops.monostixels.cell_sums(x, r, w, _NO_CHECK, None)[0]


def cell_means_checked(x: torch.Tensor, r: int, w: int, count: torch.Tensor, check: int) -> tuple[torch.Tensor, bool]:
    """Cell means (B, C, n, ch) (the sums of :func:`cell_sums` divided by ``count`` (n, C)) and,
    from the same pass, whether the values pass ``check`` (``CHECK_*``).

    False only says that some value may be bad (a sum can also overflow): the caller then runs
    its full checks, which name the problem.
    """
    means, ok = torch.ops.monostixels.cell_sums(x, r, w, check, count)
    return means, bool(ok)


def hypotheses(*args: object) -> list[torch.Tensor]:
    """Hypothesis sets (p_ground, p_object, tau, g = K B tau) for hypothesis_stride 1 (see ``columns.hypotheses``)."""
    return torch.ops.monostixels.hypotheses(*args)


def geometry(*args: object) -> list[torch.Tensor]:
    """Per-cell (ray, a, s_g, s_o, q) of every column (see ``columns.column_geometry``)."""
    return torch.ops.monostixels.geometry(*args)


def semantic_prefix(*args: object) -> torch.Tensor:
    """Prefix-summed semantic cost (C, 10, n + 1) (see ``columns.semantic_prefix``)."""
    return torch.ops.monostixels.semantic_prefix(*args)

