"""Long-lived helper threads: each call site's pool, kept per calling thread.

The pipeline runs work side by side where the libraries release the GIL (the semantic net beside the
flow, the backward flow beside the forward one, the covariance beside the backend). A pool made for
each call starts and ends threads every frame; over hours of video that churns the allocator's
per-thread arenas. :func:`helper_pool` hands out one pool per call site and calling thread, made at
its first use and kept: the same concurrency as a pool per call (a site never waits for another
site's work, and the thread reading pairs ahead has pools of its own), with a bounded set of threads.
"""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

__all__ = ["helper_pool"]

_local = threading.local()


def helper_pool(site: str, workers: int = 1) -> ThreadPoolExecutor:
    """The pool of ``workers`` threads of call site ``site`` for the calling thread (made at its first use).

    Use it where a ``with ThreadPoolExecutor(...)`` block would be, without the ``with``: the pool is not
    shut down after the block. Work submitted must not wait on other work of the same site and thread.
    """
    pools = getattr(_local, "pools", None)
    if pools is None:
        pools = _local.pools = {}
    pool = pools.get((site, workers))
    if pool is None:
        pool = pools[(site, workers)] = ThreadPoolExecutor(max_workers=workers,
                                                           thread_name_prefix=f"monostixels-{site}")
    return pool
