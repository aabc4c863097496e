"""
``register_clouds`` in a supervised child process, with a time limit.

A pathological input that makes the pipeline loop costs one pair (the child is killed past
the time limit and a fresh one started), and a child that dies (the OOM killer, a native
crash in a library, ``kill -9``), idle or busy, is replaced; the caller keeps registering.
The node runs every pair through it (``worker.registration_timeout`` > 0); any other caller that
must survive a bad pair can too.

Built on public API only: one ``multiprocessing`` spawn-context :class:`~multiprocessing.Process`
and a :func:`~multiprocessing.Pipe` per child. Jobs go down the pipe one at a time; a thread
of this process reads the answers into :class:`concurrent.futures.Future` objects and, when
the pipe ends (the child died), fails the job in flight.
"""

from __future__ import annotations

import collections
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
import dataclasses
import multiprocessing
import os
import pickle
import signal
import threading
from typing import Any, Callable

import numpy as np

from ..config.pipeline import PipelineConfig
from ..errors import CgagsError
from ..parallel import quiet_idle_threads
from ..refusal import RefusalCode

RegisterFn = Callable[..., Any]  # register_any(source, target, *, config[, stamp]) -> result

WARM_UP_LIMIT_S = 300.0  # with a cold numba cache the warm-up compiles the numba code first


class RegistrationTimeout(CgagsError):
    """A registration ran past ``worker.registration_timeout`` and its process was killed."""

    code = RefusalCode.TIMEOUT


class WorkerCrashed(CgagsError):
    """The registration process died while it registered a pair; a fresh one was started."""

    code = RefusalCode.WORKER_CRASHED


_child_target: Any = None  # in the registration process: the last target
_map_holder: Any = None  # in the process that runs the pipeline: the map of a map.file


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
    from .map import MapHolder

    if _map_holder is None:
        _map_holder = MapHolder()
    return _map_holder.get(target.path, config, target.cache_dir)


def register_any(source: np.ndarray, target: Any, *, config: PipelineConfig,
                 stamp: float | None = None) -> Any:
    """
    Run ``register_clouds`` onto an array or a :class:`MapRef` (in this process).

    With ``stamp`` (the scan's header stamp, seconds) the scan is the next of a stream:
    this process's :class:`~.tracking.Tracker` registers it (:func:`~.stream.register_stream`),
    falling back to ``register_clouds``. For a map the result's ``map_info`` holds the map's
    summary (cache hit or miss, points, load time).
    """
    if stamp is not None:
        from .stream import register_stream

        return register_stream(source, _resolve(target, config), config=config, stamp=stamp)
    from . import register_clouds

    return register_clouds(source, _resolve(target, config), config=config)


def prepare_map(ref: MapRef, config: PipelineConfig) -> dict[str, Any]:
    """Load (or read from the cache) the map of ``ref`` in this process; return its summary."""
    return _resolve(ref, config).info()


class _TargetNotHeld(Exception):
    """The registration process holds no target (it was restarted): send it again."""


def _register_in_child(source: np.ndarray, target: np.ndarray | None, *,
                       config: PipelineConfig, stamp: float | None = None) -> Any:
    """
    Run :func:`register_any` in the registration process.

    ``target=None`` reuses the target sent last, so an unchanged (latched) target crosses
    the pipe once, not every pair.
    """
    global _child_target
    if target is not None:
        _child_target = target
    elif _child_target is None:
        raise _TargetNotHeld()
    # the parent needs no Open3D
    return register_any(source, _child_target, config=config, stamp=stamp)


def _serve(conn: Any) -> None:
    """
    Run in the child: warm up and answer, then run each job of the pipe and answer it.

    Every answer is ``(ok, value)``: the job's return value or the exception it raised.
    The parent decides when the child ends (it kills it, or closes the pipe), so a Ctrl-C
    meant for the parent's terminal does not end a registration here.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from . import warm_up

    # Warm-up: the pipeline imported (Open3D) and every stage run once on a small synthetic
    # pair, so that no start-up cost is counted against a real pair's limit.
    ok, value = _run(warm_up, (), {})
    answer = _pickled(ok, None if ok else value)
    while True:
        try:
            conn.send_bytes(answer)
            fn, args, kwargs = conn.recv()
        except (EOFError, OSError):
            return  # the parent is gone or closed the pipe
        answer = _pickled(*_run(fn, args, kwargs))


def _run(fn: Callable[..., Any], args: tuple, kwargs: dict) -> tuple[bool, Any]:
    try:
        return True, fn(*args, **kwargs)
    except Exception as exc:  # noqa: BLE001 - sent back, raised in the parent
        return False, exc


def _pickled(ok: bool, value: Any) -> bytes:
    """Return the answer ``(ok, value)`` as bytes for the pipe, or an error that pickles."""
    try:
        return pickle.dumps((ok, value), protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as exc:  # noqa: BLE001 - an answer that does not pickle
        return pickle.dumps((False, CgagsError(
            f'the registration process cannot send back {value!r}: {exc!r}')))


def rss_mb(pid: int | None = None) -> float | None:
    """Return the resident memory of process ``pid`` (default: this one) in MB, if known."""
    try:
        with open(f"/proc/{pid or 'self'}/statm", encoding='ascii') as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None  # not Linux, or the process is gone
    return pages * os.sysconf('SC_PAGE_SIZE') / 1e6


def running(pid: int) -> bool:
    """Tell whether process ``pid`` exists and is not a zombie (dead, not yet reaped)."""
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


class _ChildDied(Exception):
    """The child's pipe ended: the process is gone."""


class _Child:
    """One spawned registration process, its pipe, and the thread that reads its answers."""

    def __init__(self) -> None:
        # Spawn, not fork: forking a process that runs DDS threads is unsafe. The child
        # inherits this environment and loads numpy before any code of ours runs in it.
        quiet_idle_threads()
        context = multiprocessing.get_context('spawn')
        self.conn, child_end = context.Pipe()
        self.process = context.Process(target=_serve, args=(child_end,),
                                       name='cgags-registration', daemon=True)
        self.process.start()
        child_end.close()  # the child's copy alone keeps it open: its death ends the pipe
        self.warm: Future = Future()  # the first answer is the warm-up's
        self._waiting: collections.deque[Future] = collections.deque([self.warm])
        self._lock = threading.Lock()
        self.ended = False
        self._reader = threading.Thread(target=self._read, name='registration-answers',
                                        daemon=True)
        self._reader.start()

    @property
    def alive(self) -> bool:
        """Tell whether the process still runs (by pid: a zombie counts as dead)."""
        return not self.ended and running(self.process.pid)

    def submit(self, fn: Callable[..., Any], args: tuple, kwargs: dict) -> Future:
        """Send one job; return the future of its answer. :raises _ChildDied: it is gone."""
        future: Future = Future()
        with self._lock:
            if self.ended:
                raise _ChildDied()
            self._waiting.append(future)
        try:
            self.conn.send((fn, args, kwargs))
        except BaseException as exc:
            # Nothing was sent (a job that does not pickle) or the pipe is broken: no
            # answer will come for this future.
            with self._lock:
                if future in self._waiting:
                    self._waiting.remove(future)
            if isinstance(exc, (EOFError, OSError)):
                raise _ChildDied() from None
            raise
        return future

    def _read(self) -> None:
        while True:
            try:
                ok, value = self.conn.recv()
            except (EOFError, OSError):
                break
            except Exception as exc:  # noqa: BLE001 - an answer that does not unpickle
                ok, value = False, CgagsError(f'unreadable answer of the registration '
                                              f'process: {exc!r}')
            with self._lock:
                future = self._waiting.popleft() if self._waiting else None
            if future is None:
                continue
            if ok:
                future.set_result(value)
            else:
                future.set_exception(value)
        with self._lock:
            self.ended = True
            waiting, self._waiting = list(self._waiting), collections.deque()
        for future in waiting:
            future.set_exception(_ChildDied())

    def kill(self) -> None:
        """End the process now (a job in flight fails) and release the pipe."""
        self.process.kill()
        self.process.join(5.0)
        self._reader.join(5.0)  # the pipe ended with the process
        self.conn.close()


class IsolatedRegistration:
    """
    Run ``register_clouds`` in one spawned child process, supervised, with a time limit.

    Results and typed errors come back pickled. The child keeps the last target: a target
    that is the same array object as the previous call's is not sent again (the node never
    writes to a decoded cloud); ``targets_sent`` counts the targets that crossed the pipe.
    A stream's scans (``stamp`` given) are tracked by the child's own
    :class:`~.tracking.Tracker`, beside that target: a replaced child starts without a prior.

    Supervision: a child found dead before a pair is sent (it died idle) is replaced and
    the pair runs on the fresh one; a child that dies during a pair is replaced and that
    pair fails with :class:`WorkerCrashed`. :meth:`supervise` replaces a dead idle child
    early, so that the next pair does not wait for the fresh one's start-up. ``crashes``
    counts deaths, ``restarts`` every replacement (crashes and timeouts). ``busy`` is set
    from the moment a job (a pair, a map) is sent to the child until its answer.
    """

    def __init__(self, timeout_s: float):
        self.timeout_s = timeout_s
        self.crashes = 0
        self.restarts = 0
        self.targets_sent = 0
        self.busy = threading.Event()
        self._child: _Child | None = None
        self._closed = False
        self._calling = False  # a call is using the child (supervise() leaves it alone)
        self._lock = threading.Lock()  # guards the child between callers and supervise()
        self._sent_target: np.ndarray | None = None  # what the child holds (by identity)
        self._start()

    @property
    def pid(self) -> int | None:
        """Return the child's process id (None after close)."""
        child = self._child
        return None if child is None else child.process.pid

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
        child = self._child
        return child is not None and child.warm.done()

    def wait_ready(self) -> None:
        """Wait for the warm-up; raise :class:`WorkerCrashed` if it failed or did not end."""
        child = self._child
        if child is not None:
            self._wait_for_warm_up(child, strict=True)

    def supervise(self) -> bool:
        """Replace a child that died while idle; return True when one was replaced."""
        with self._lock:
            if self._closed or self._calling or self._child is None or self._alive():
                return False
            self._crashed()
            return True

    def __call__(self, source: np.ndarray, target: np.ndarray, *, config: PipelineConfig,
                 stamp: float | None = None) -> Any:
        """Run :func:`register_any` (``stamp``: a stream's scan, tracked) in the child."""
        def job() -> tuple[Any, tuple, dict]:
            # Asked once the child is known to be alive: a replaced child holds no target.
            held = target is self._sent_target
            # Only a completed call proves the child holds this target; after any failure
            # it is sent again.
            self._sent_target = None
            self.targets_sent += not held
            return (_register_in_child, (source, None if held else target),
                    {'config': config, 'stamp': stamp})

        try:
            result = self._in_child(
                job, self.timeout_s,
                'registration took longer than worker.registration_timeout = '
                f'{self.timeout_s:g} s',
                'during this pair (killed, out of memory or a native crash)')
        except _TargetNotHeld:  # not expected (a restart forgets what was sent); resend
            return self(source, target, config=config, stamp=stamp)
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
            self._calling = True
        try:
            future = self._send(job)
            self.busy.set()
            try:
                return future.result(timeout=timeout_s)
            except FutureTimeout:
                if future.done():
                    raise  # the job's own error, not the time limit
            self.restart()
            raise RegistrationTimeout(f'{too_long}; its process was restarted')
        except _ChildDied:
            with self._lock:
                if not self._closed:
                    self._crashed()
            raise WorkerCrashed(f'the registration process died {died}; restarted') from None
        finally:
            self.busy.clear()
            with self._lock:
                self._calling = False

    def _send(self, job: Callable[[], tuple[Any, tuple, dict]]) -> Future:
        """Send ``job()`` to the warm child; return the future of its answer."""
        child = self._warm_child()
        try:
            return child.submit(*job())
        except _ChildDied:  # died idle since the check: the job goes to a fresh child
            return self._warm_child(dead=child).submit(*job())

    def _warm_child(self, dead: _Child | None = None) -> _Child:
        """Return the child once warm; one found dead (it died idle) is replaced first."""
        with self._lock:
            if self._child is None:
                raise RegistrationTimeout('the registration process is shut down')
            if self._child is dead or not self._alive():  # nothing of this call is lost
                self._crashed()
            child = self._child
        self._wait_for_warm_up(child)
        return child

    def _wait_for_warm_up(self, child: _Child, strict: bool = False) -> None:
        try:
            child.warm.result(timeout=WARM_UP_LIMIT_S)
        except Exception as exc:  # noqa: BLE001 - not strict: it shows again on the real pair
            if strict:
                why = (f'not ready after {WARM_UP_LIMIT_S:g} s' if isinstance(exc, FutureTimeout)
                       else 'it died' if isinstance(exc, _ChildDied) else repr(exc))
                raise WorkerCrashed(f'the registration process failed to start ({why})') from None

    def _alive(self) -> bool:
        child = self._child
        return child is not None and child.alive

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
        self._sent_target = None
        self._child = _Child()

    def close(self) -> None:
        """Stop the child for good."""
        with self._lock:
            self._closed = True
            self._kill()

    def _kill(self) -> None:
        child, self._child = self._child, None
        if child is not None:
            child.kill()


def load_pipeline() -> RegisterFn:
    """Import the pipeline (and Open3D) now and warm it up; return :func:`register_any`."""
    from . import warm_up

    warm_up()  # pay Open3D's start-up now rather than on the first pair
    return register_any
