"""Split a compiled (nogil) kernel's rows over threads: the front end's one thread pool."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
import threading
from typing import Callable

CHUNK = 512  # rows per task, so that threads finish close together

_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_pool_lock = threading.Lock()


def run_chunks(task: Callable[[int, int], None], n: int, workers: int,
               chunk: int = CHUNK) -> None:
    """
    Run ``task(a, b)`` over the rows [0, n) in chunks of ``chunk``, on ``workers`` threads.

    ``task`` must release the GIL (a ``nogil`` numba kernel) and write disjoint rows; the
    result then does not depend on ``workers``.
    """
    if workers <= 1 or n <= chunk:
        task(0, n)
        return
    global _pool, _pool_size
    with _pool_lock:
        if _pool is None or _pool_size < workers:
            _pool = ThreadPoolExecutor(workers, thread_name_prefix='cgags_frontend')
            _pool_size = workers
        pool = _pool
    bounds = list(range(0, n, chunk)) + [n]
    for part in [pool.submit(task, a, b) for a, b in zip(bounds[:-1], bounds[1:])]:
        part.result()
