"""
Split a compiled (nogil) function's rows over threads: the package's one thread pool.

The front end (FPFH, descriptor index) and the core (compatibility graph) run their
compiled functions on it; every task writes disjoint rows, so results do not depend on the
number of threads.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
import os
import threading
from typing import Callable, MutableMapping, Sequence, TypeVar

T = TypeVar('T')
R = TypeVar('R')

CHUNK = 512  # rows per task, so that threads finish close together
# Threads a registration uses by default: the machine's cores, at most four.
DEFAULT_WORKERS = max(1, min(4, os.cpu_count() or 1))

_pool: ThreadPoolExecutor | None = None
_pool_size = 0
# Any of the pipeline's threads may ask for the pool first: a pair's own, or a task beside it.
_pool_lock = threading.Lock()


def run_chunks(task: Callable[[int, int], None], n: int, workers: int,
               chunk: int = CHUNK) -> None:
    """
    Run ``task(a, b)`` over the rows [0, n) in chunks of ``chunk``, on ``workers`` threads.

    ``task`` must release the GIL (a ``nogil`` numba function) and write disjoint rows; the
    result then does not depend on ``workers``.
    """
    if workers <= 1 or n <= chunk:
        task(0, n)
        return
    pool = _shared_pool(workers)
    bounds = list(range(0, n, chunk)) + [n]
    for part in [pool.submit(task, a, b) for a, b in zip(bounds[:-1], bounds[1:])]:
        part.result()


def run_split(task: Callable[[int, int], None], bounds: Sequence[int]) -> None:
    """
    Run ``task(a, b)`` for each consecutive pair of ``bounds``, all at once (one thread each).

    The caller runs the last range itself, so k ranges occupy k threads and short tasks
    (a millisecond) pay one hand-off each, not a queue. Same contract as :func:`run_chunks`.
    """
    ranges = list(zip(bounds[:-1], bounds[1:]))
    if len(ranges) <= 1:
        for a, b in ranges:
            task(a, b)
        return
    pool = _shared_pool(len(ranges) - 1)
    parts = [pool.submit(task, a, b) for a, b in ranges[:-1]]
    task(*ranges[-1])
    for part in parts:
        part.result()


def quiet_idle_threads(environ: MutableMapping[str, str] = os.environ) -> None:
    """
    Make the idle threads of OpenMP (Open3D) and OpenBLAS sleep instead of spin.

    For the entry points that run the pipeline (the tools, the node, its registration
    process), before numpy and Open3D load: the libraries read these variables once, when
    they load, and a spawned process inherits them. OpenMP's idle threads spin by default
    and, on a loaded machine, each of ICP's short parallel loops then waits for a
    descheduled thread; OpenBLAS's workers likewise spin after each threaded call and take
    the CPU from Open3D. Passive waiting costs nothing measurable on an idle machine
    (docs/design.md). A value the user set wins.
    """
    environ.setdefault('OMP_WAIT_POLICY', 'PASSIVE')
    environ.setdefault('OPENBLAS_THREAD_TIMEOUT', '20')


def in_background(task: Callable[[], T], enabled: bool = True) -> Callable[[], T]:
    """
    Start ``task()`` on a thread of its own; return a function that waits for its result.

    The returned function re-raises what ``task`` raised. With ``enabled`` False the task
    runs at once, in this thread (what it raises is still raised by the returned function).
    A thread of its own, not the shared pool: the task may itself split compiled work over the
    pool (:func:`run_split`), and waiting inside a pool thread for tasks queued behind it
    would deadlock a one-thread pool.
    """
    outcome: list = []

    def run() -> None:
        try:
            outcome.append((True, task()))
        except BaseException as exc:  # noqa: BLE001 - handed to the caller
            outcome.append((False, exc))

    thread = threading.Thread(target=run, name='cgags_background', daemon=True)
    if enabled:
        thread.start()
    else:
        run()

    def wait() -> T:
        if enabled:
            thread.join()
        ok, value = outcome[0]
        if not ok:
            raise value
        return value

    return wait


def map_ordered(task: Callable[[T], R], items: Sequence[T], workers: int) -> list[R]:
    """
    Return ``[task(x) for x in items]``, the items dealt over ``workers`` threads.

    For independent tasks that spend most of their time outside the GIL (k-d tree queries,
    numpy on large arrays, Open3D): this thread takes a share too, so ``workers`` threads
    run in all. The results, in the items' order, do not depend on ``workers``. Each share
    runs on a thread of its own, as :func:`in_background`: a task may use the pool.
    """
    items = list(items)
    n = max(1, min(workers, len(items)))
    out: list = [None] * len(items)

    def share(k: int) -> Callable[[], None]:
        def run() -> None:
            for i in range(k, len(items), n):
                out[i] = task(items[i])
        return run

    waits = [in_background(share(k)) for k in range(1, n)]
    try:
        share(0)()
    finally:
        for wait in waits:
            wait()
    return out


def _shared_pool(workers: int) -> ThreadPoolExecutor:
    global _pool, _pool_size
    with _pool_lock:
        # Sized for the largest caller from the start (the pool starts threads only as
        # tasks need them), so the core's one extra thread and the front end's pool are the
        # same pool rather than a smaller one left behind when a larger one replaces it.
        if _pool is None or _pool_size < workers:
            _pool_size = max(workers, DEFAULT_WORKERS)
            _pool = ThreadPoolExecutor(_pool_size, thread_name_prefix='cgags_worker')
        return _pool
