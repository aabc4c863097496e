"""
The registration worker: ``register_clouds`` in a supervised child process.

ROS-free by itself, but it exists for the node: a pathological input that makes the
pipeline loop costs one pair (the child is killed past the time limit), and a child that
dies (the OOM killer, a native crash in a library, ``kill -9``), idle or busy, is replaced
by a fresh one; the node keeps registering.
"""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from concurrent.futures.process import BrokenProcessPool
import dataclasses
import multiprocessing
import os
import threading
from typing import Any, Callable

import numpy as np

from ..config.pipeline import PipelineConfig
from ..errors import CgagsError
from ..refusal import RefusalCode

RegisterFn = Callable[..., Any]  # register_clouds(source, target, *, config) -> PipelineResult

WARM_UP_LIMIT_S = 300.0  # with a cold numba cache the warm-up compiles the numba code first


class RegistrationTimeout(CgagsError):
    """A registration ran past ``registration_timeout`` and its process was killed."""

    code = RefusalCode.TIMEOUT


class WorkerCrashed(CgagsError):
    """The registration process died while it registered a pair; a fresh one was started."""

    code = RefusalCode.WORKER_CRASHED


_child_target: Any = None  # in the registration process: the last target
_map_holder: Any = None  # in the process that runs the pipeline: the map of a map_file


@dataclasses.dataclass(frozen=True)
class MapRef:
    """
    A target that is a map file: the process running the pipeline loads its features.

    :ivar path: the map file (PLY, PCD, NPY, XYZ/CSV/TXT), metres, map frame.
    :ivar cache_dir: feature cache directory ('' disables the cache).
    """

    path: str
    cache_dir: str = ''


def _resolve(target: Any, config: PipelineConfig) -> Any:
    """Return ``target``, or for a :class:`MapRef` the map's prepared features."""
    if not isinstance(target, MapRef):
        return target
    global _map_holder
    from ..pipeline.map import MapHolder

    if _map_holder is None:
        _map_holder = MapHolder()
    return _map_holder.get(target.path, config, target.cache_dir)


def register_any(source: np.ndarray, target: Any, *, config: PipelineConfig) -> Any:
    """
    Run ``register_clouds`` onto an array or a :class:`MapRef` (in this process).

    For a map the result's ``map_info`` holds the map's summary (cache hit or miss, points,
    load time).
    """
    from ..pipeline import register_clouds

    return register_clouds(source, _resolve(target, config), config=config)


def prepare_map(ref: MapRef, config: PipelineConfig) -> dict[str, Any]:
    """Load (or read from the cache) the map of ``ref`` in this process; return its summary."""
    return _resolve(ref, config).info()


class _TargetNotHeld(Exception):
    """The registration process holds no target (it was restarted): send it again."""


def _register_in_child(source: np.ndarray, target: np.ndarray | None, *,
                       config: PipelineConfig) -> Any:
    """
    Run ``register_clouds`` in the registration process.

    ``target=None`` reuses the target sent last, so an unchanged (latched) target crosses
    the pipe once, not every pair.
    """
    global _child_target
    if target is not None:
        _child_target = target
    elif _child_target is None:
        raise _TargetNotHeld()
    return register_any(source, _child_target, config=config)  # the parent needs no Open3D


def _warm_up_in_child() -> Any:
    from ..pipeline import warm_up

    return warm_up()


def rss_mb(pid: int | None = None) -> float | None:
    """Return the resident memory of process ``pid`` (default: this one) in MB, if known."""
    try:
        with open(f"/proc/{pid or 'self'}/statm", encoding='ascii') as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None  # not Linux, or the process is gone
    return pages * os.sysconf('SC_PAGE_SIZE') / 1e6


def _running(pid: int) -> bool:
    """Tell whether process ``pid`` exists and is not a zombie."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f'/proc/{pid}/stat', encoding='ascii') as f:
            return f.read().rsplit(')', 1)[1].split()[0] not in ('Z', 'X')
    except (OSError, IndexError):
        return True  # no /proc: the signal test is all there is


class IsolatedRegistration:
    """
    Run ``register_clouds`` in one spawned child process, supervised, with a time limit.

    Spawn, not fork: forking a process that runs DDS threads is unsafe. Results and typed
    errors come back pickled. The child keeps the last target: a target that is the same
    array object as the previous call's is not sent again (the node never writes to a
    decoded cloud).

    Supervision: a child found dead before a pair is sent (it died idle) is replaced and
    the pair runs on the fresh one; a child that dies during a pair is replaced and that
    pair fails with :class:`WorkerCrashed`. :meth:`supervise` replaces a dead idle child
    early, so that the next pair does not wait for the fresh one's start-up. ``crashes``
    counts deaths, ``restarts`` every replacement (crashes and timeouts).
    """

    def __init__(self, timeout_s: float):
        self.timeout_s = timeout_s
        self.crashes = 0
        self.restarts = 0
        self._pool: Any = None
        self._closed = False
        self._busy = False
        self._lock = threading.Lock()  # guards the pool between the worker and supervise()
        self._sent_target: np.ndarray | None = None  # what the child holds (by identity)
        self._start()

    @property
    def pid(self) -> int | None:
        """Return the child's process id (None before it started or after close)."""
        processes = getattr(self._pool, '_processes', None) or {}
        return next(iter(processes), None)

    def health(self) -> dict[str, Any]:
        """Return the worker's counters and resident memory, for /diagnostics."""
        pid = self.pid
        return {'worker.pid': pid or 0, 'worker.alive': self._alive(),
                'worker.ready': self.ready,
                'worker.crashes': self.crashes, 'worker.restarts': self.restarts,
                'memory.worker_rss_mb': round(rss_mb(pid) or 0.0, 1) if pid else 0.0}

    @property
    def ready(self) -> bool:
        """Tell whether the child has finished its warm-up (a pair then starts at once)."""
        warm = self._warm
        return self._pool is not None and (warm is None or warm.done())

    def wait_ready(self) -> None:
        """Wait for the warm-up; raise :class:`WorkerCrashed` if it failed or did not end."""
        self._wait_for_warm_up(self._warm, strict=True)

    def supervise(self) -> bool:
        """Replace a child that died while idle; return True when one was replaced."""
        with self._lock:
            if self._closed or self._busy or self._pool is None or self._alive():
                return False
            self._crashed()
            return True

    def __call__(self, source: np.ndarray, target: np.ndarray, *, config: PipelineConfig) -> Any:
        def job() -> tuple[Any, tuple, dict]:
            # Asked once the child is known to be alive: a replaced child holds no target.
            held = target is self._sent_target
            # Only a completed call proves the child holds this target; after any failure
            # it is sent again.
            self._sent_target = None
            return self._fn, (source, None if held else target), {'config': config}

        try:
            result = self._in_child(
                job, self.timeout_s,
                f'registration took longer than registration_timeout = {self.timeout_s:g} s',
                'during this pair (killed, out of memory or a native crash)')
        except _TargetNotHeld:  # not expected (a restart forgets what was sent); resend
            return self(source, target, config=config)
        self._sent_target = target
        return result

    def prepare_map(self, ref: MapRef, config: PipelineConfig, timeout_s: float) -> dict:
        """
        Load the map of ``ref`` in the child (features from the cache or computed).

        :returns: the map's summary (:meth:`~cgags_ros.pipeline.map.PreparedMap.info`).
        :raises RegistrationTimeout: past ``timeout_s`` (the child is restarted).
        :raises WorkerCrashed: the child died while loading.
        :raises CgagsError: the map cannot be read or is empty.
        """
        return self._in_child(lambda: (prepare_map, (ref, config), {}), timeout_s,
                              f'loading the map took longer than {timeout_s:g} s',
                              'while loading the map (out of memory?)')

    def _in_child(self, job: Callable[[], tuple[Any, tuple, dict]], timeout_s: float,
                  too_long: str, died: str) -> Any:
        """
        Run ``fn(*args, **kwargs)`` of ``job()`` in the child, supervised; return the result.

        A child found dead first (idle) is replaced and the call runs on the fresh one
        after its warm-up. Past ``timeout_s`` the child is restarted and
        :class:`RegistrationTimeout` (``too_long``) raised; a child dying during the call is
        replaced and :class:`WorkerCrashed` (``died``) raised.
        """
        with self._lock:
            if self._pool is None:
                raise RegistrationTimeout('the registration process is shut down')
            if not self._alive():  # died while idle: nothing of this call is lost
                self._crashed()
            warm = self._warm
            self._busy = True
        try:
            self._wait_for_warm_up(warm)
            fn, args, kwargs = job()
            return self._submit(fn, *args, **kwargs).result(timeout=timeout_s)
        except FutureTimeout:
            self.restart()
            raise RegistrationTimeout(f'{too_long}; its process was restarted') from None
        except BrokenProcessPool:
            with self._lock:
                if not self._closed:
                    self._crashed()
            raise WorkerCrashed(f'the registration process died {died}; restarted') from None
        finally:
            with self._lock:
                self._busy = False

    def _submit(self, *args: Any, **kwargs: Any) -> Any:
        """Submit to the child; one that died since the last check (idle) is replaced."""
        with self._lock:
            if self._pool is None:
                raise RegistrationTimeout('the registration process is shut down')
            try:
                return self._pool.submit(*args, **kwargs)
            except BrokenProcessPool:
                self._crashed()
                warm = self._warm
        self._wait_for_warm_up(warm)
        with self._lock:
            if self._pool is None:
                raise RegistrationTimeout('the registration process is shut down')
            return self._pool.submit(*args, **kwargs)

    def _wait_for_warm_up(self, warm: Any, strict: bool = False) -> None:
        if warm is None:
            return
        try:
            warm.result(timeout=WARM_UP_LIMIT_S)
        except Exception as exc:  # noqa: BLE001 - not strict: it shows again on the real pair
            if strict:
                why = (f'not ready after {WARM_UP_LIMIT_S:g} s' if isinstance(exc, FutureTimeout)
                       else 'it died' if isinstance(exc, BrokenProcessPool) else repr(exc))
                raise WorkerCrashed(f'the registration process failed to start ({why})') from None
        with self._lock:
            if self._warm is warm:
                self._warm = None

    def _alive(self) -> bool:
        if self._pool is None or getattr(self._pool, '_broken', False):
            return False
        # By pid, not Process.is_alive(): once the pool's manager thread has reaped a dead
        # child, is_alive() in another thread reports it as running.
        return all(_running(pid) for pid in list(getattr(self._pool, '_processes', {})))

    def _crashed(self) -> None:
        self.crashes += 1
        self._replace()

    def restart(self) -> None:
        """Kill the child and start a fresh one (a registration in flight fails)."""
        with self._lock:
            self._replace()

    def _replace(self) -> None:
        self._kill()
        if not self._closed:
            self.restarts += 1
            self._start()

    def _start(self) -> None:
        self._fn = _register_in_child
        self._sent_target = None
        self._pool = ProcessPoolExecutor(max_workers=1,
                                         mp_context=multiprocessing.get_context('spawn'))
        # Warm-up: the child imports the pipeline (Open3D) and runs every stage once on a
        # small synthetic pair, so no start-up cost is counted against a real pair's limit.
        self._warm = self._pool.submit(_warm_up_in_child)

    def close(self) -> None:
        """Stop the child and the pool for good."""
        with self._lock:
            self._closed = True
            # Wait for the pool's manager thread: one still running at interpreter exit
            # races concurrent.futures' atexit hook, which then prints "OSError: handle is
            # closed". The child is killed first, so this returns at once.
            self._kill(wait=True)

    def _kill(self, wait: bool = False) -> None:
        pool, self._pool = self._pool, None
        if pool is None:
            return
        # ProcessPoolExecutor cannot cancel a running call: stop its process directly.
        for proc in list(getattr(pool, '_processes', {}).values()):
            proc.kill()
        pool.shutdown(wait=wait, cancel_futures=True)


def load_pipeline() -> RegisterFn:
    """Import the pipeline (and Open3D) now and warm it up; return :func:`register_any`."""
    from ..pipeline import warm_up

    warm_up()  # pay Open3D's start-up now rather than on the first pair
    return register_any
