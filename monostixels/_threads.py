"""One thread budget for the whole process: torch, OpenCV and every ONNX Runtime session (config key ``threads``).

The pipeline runs several Python threads side by side (the next pair's flow and the semantic net
ahead of time, the photometric search's workers, the two flow directions), and each library below
them brings its own pool: torch's OpenMP team, OpenCV's pthreads pool, ONNX Runtime's intra- and
inter-op pools. Left to their defaults each pool takes every core and *spins* while idle (OpenMP
by default, OpenCV's pool for up to 10000 pause iterations, ONNX Runtime's intra-op threads), so on
a 2-core machine the spinning threads of one library take the cores the others wait for: the CPU
time per frame grows with no gain in speed, and more so the busier the machine.

:func:`set_threads` (applied once at start-up from the config key ``threads``; ``auto`` = the cores
this process may use: ``len(os.sched_getaffinity(0))``, or a container's CPU quota where lower) gives torch and OpenCV that many threads;
:func:`onnx_session_options` gives each ONNX Runtime session as many intra-op threads, one inter-op
thread, sequential execution and no spinning. :func:`quiet_spinning` (called on ``import monostixels``,
before torch and OpenCV load) makes idle OpenMP and OpenCV threads sleep instead of spinning; both
read their setting once, when they load, and a value the user exported is kept.

Set ``MONOSTIXELS_SPIN=1`` in the environment to leave every library's spinning as it is (the
comparison in docs/results.md, "Speed").
"""
from __future__ import annotations

import logging
import math
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

__all__ = ["available_cores", "resolve_threads", "set_threads", "set_opencv_threads", "torch_threads", "threads",
           "onnx_session_options",
           "thread_counts", "auto_threads", "ensure_threads", "cgroup_cpu_limit", "quiet_spinning", "spinning"]

logger = logging.getLogger(__name__)

#: Environment settings that make idle pool threads sleep: OpenMP's (torch) and OpenCV's pthreads pool
#: (its busy-wait loops, counted in iterations; OpenCV's defaults 2000 / 10000 / 16).
_SLEEP_ENV = {
    "OMP_WAIT_POLICY": "PASSIVE",
    "OPENCV_THREAD_POOL_ACTIVE_WAIT_WORKER": "0",
    "OPENCV_THREAD_POOL_ACTIVE_WAIT_MAIN": "0",
    "OPENCV_THREAD_POOL_ACTIVE_WAIT_PAUSE_LIMIT": "0",
}
#: ``MONOSTIXELS_SPIN=1``: keep the libraries' spinning (for measuring what turning it off gains).
_SPIN_ENV = "MONOSTIXELS_SPIN"

#: The process's thread count once :func:`set_threads` ran (None: not yet).
_applied: int | None = None


def spinning() -> bool:
    """Whether the libraries' idle threads are left spinning (``MONOSTIXELS_SPIN=1``)."""
    return os.environ.get(_SPIN_ENV, "0") not in ("", "0", "false", "False")


def quiet_spinning() -> None:
    """Idle OpenMP and OpenCV threads sleep (environment defaults; a value already set is kept).

    Effective only before torch and OpenCV are loaded: ``import monostixels`` calls it first thing.
    """
    if spinning():
        return
    for key, value in _SLEEP_ENV.items():
        os.environ.setdefault(key, value)


def cgroup_cpu_limit(root: Path = Path("/sys/fs/cgroup")) -> int | None:
    """Whole CPUs of the container's CPU quota (cgroup v2 ``cpu.max``, v1 ``cpu.cfs_quota_us``), None = no quota.

    A container limited to 2 CPUs on a 64-core host sees 64 cores in its affinity: each library would
    start 64 threads that share 2 CPUs' worth of time slices.
    """
    try:
        v2 = root / "cpu.max"
        if v2.is_file():
            quota, period = (v2.read_text().split() + ["100000"])[:2]
            if quota == "max":
                return None
            return max(1, math.ceil(int(quota) / int(period)))
        quota_f, period_f = root / "cpu" / "cpu.cfs_quota_us", root / "cpu" / "cpu.cfs_period_us"
        if quota_f.is_file() and period_f.is_file():
            quota, period = int(quota_f.read_text()), int(period_f.read_text())
            return None if quota <= 0 or period <= 0 else max(1, math.ceil(quota / period))
    except (OSError, ValueError):  # unreadable or unexpected: no quota known
        return None
    return None


def available_cores() -> int:
    """The cores this process may use: its CPU affinity (``os.cpu_count()`` where unknown), or a
    container's CPU quota where that is lower (:func:`cgroup_cpu_limit`)."""
    try:
        cores = max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not Linux
        cores = max(1, os.cpu_count() or 1)
    quota = cgroup_cpu_limit()
    return min(cores, quota) if quota is not None else cores


def auto_threads() -> int:
    """What ``threads: auto`` means: :func:`available_cores`, or ``OMP_NUM_THREADS`` where the
    environment sets a lower count (a Ray worker with one CPU, a user's own limit: honoured as before)."""
    cores = available_cores()
    env = os.environ.get("OMP_NUM_THREADS", "").strip()
    return min(cores, int(env)) if env.isdigit() and int(env) > 0 else cores


def resolve_threads(value: Any) -> int:
    """The thread count a ``threads`` setting means: ``auto`` / None / 0 = :func:`auto_threads`, else an int >= 1."""
    from monostixels._checks import InputError

    if value is None or (isinstance(value, str) and value.strip().lower() == "auto"):
        return auto_threads()
    if isinstance(value, str) and value.strip().isdigit():
        value = int(value.strip())
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise InputError(f"threads: 'auto' or a whole number >= 1 (threads of torch, OpenCV and ONNX Runtime), "
                         f"got {value!r}")
    return value if value > 0 else auto_threads()


def set_threads(value: Any = "auto") -> int:
    """Give torch, OpenCV and the ONNX Runtime sessions created from now on ``value`` threads; returns the count.

    Args:
        value: the config key ``threads`` (``auto``: :func:`available_cores`; or a whole number >= 1).

    Torch's inter-op pool (used only by ``torch.jit.fork``, never by the package) gets one thread where
    it has not started yet; the package's own parallelism is its Python threads.
    """
    global _applied
    import cv2
    import torch

    n = resolve_threads(value)
    torch.set_num_threads(n)
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:  # allowed once, before any inter-op work: already set or started
        logger.debug("torch inter-op threads already fixed at %d", torch.get_num_interop_threads())
    cv2.setNumThreads(n)
    if _applied != n:
        logger.debug("threads: %d (torch, OpenCV, ONNX Runtime intra-op)%s", n, "; spinning left on" if spinning() else "")
    _applied = n
    return n


def set_opencv_threads(n: int | None) -> int:
    """OpenCV's pool at ``n`` threads (None: the process's :func:`threads`); returns the count.

    A pipeline whose flow runs in a thread of its own beside other work (``Pipeline(overlap=True)``: the
    semantic net, and on a stream the solver of the pair before) gives OpenCV one thread less than the
    budget (one on 2 cores): that work keeps a core busy, and on it the pool's share of DIS and the
    refinement only waits and hands off. OpenCV's flows are bit-identical with one thread or more.
    """
    import cv2

    count = threads() if n is None else max(1, int(n))
    cv2.setNumThreads(count)
    return count


@contextmanager
def torch_threads(n: int) -> Iterator[int]:
    """Torch's intra-op pool at ``n`` threads (at least one) inside the block, its count before restored after.

    The sequence layer's overlapped stream (``stream.overlap``) keeps every core busy with its own threads:
    the sequence layer's, which estimates the motion and solves a pair, and the next pair's flow beside it.
    An intra-op pool in the first then only hands work back and forth on cores that are taken (and the
    photometric search's workers, as many as torch's threads, do the same): it gets one thread less than
    the budget there, as OpenCV's pool does beside the flow (:func:`set_opencv_threads`).
    """
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(max(1, int(n)))
    try:
        yield torch.get_num_threads()
    finally:
        torch.set_num_threads(before)


def threads() -> int:
    """The process's thread count: the one :func:`set_threads` applied, else :func:`available_cores`."""
    return _applied if _applied is not None else available_cores()


def ensure_threads(value: Any = "auto") -> int:
    """:func:`set_threads` unless it already ran in this process (library use: a :class:`Pipeline` built
    without the command line); returns the count in use."""
    return _applied if _applied is not None else set_threads(value)


def onnx_session_options(intra_op: int = 0) -> Any:
    """``onnxruntime.SessionOptions`` for a session of the package.

    Args:
        intra_op: intra-op threads (0 = the process's :func:`threads`).

    One inter-op thread and sequential execution (the graphs are chains; parallel branches would
    only add a second pool), and no spinning: an idle intra-op thread otherwise busy-waits on a core
    the flow or the solver needs (``MONOSTIXELS_SPIN=1`` keeps ONNX Runtime's default).
    """
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(intra_op) if intra_op and intra_op > 0 else threads()
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    if not spinning():
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        opts.add_session_config_entry("session.inter_op.allow_spinning", "0")
    return opts


def thread_counts() -> dict[str, int]:
    """Threads in use: torch's intra-op, OpenCV's pool, and what an ONNX Runtime session of the package gets."""
    import cv2
    import torch

    return {"torch": torch.get_num_threads(), "opencv": cv2.getNumThreads(), "onnxruntime": threads()}
