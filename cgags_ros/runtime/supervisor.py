"""
A supervised registration process: typed jobs in, typed answers out, with a time limit.

A pathological input that makes the pipeline loop costs one job (the process is killed
past the time limit and a fresh one started), and a process that dies (the OOM killer, a
native crash in a library, ``kill -9``), idle or busy, is replaced; the caller keeps
registering. The node runs a stream's jobs through one (``worker.registration_timeout`` >
0) and, while it tracks, its periodic checks through a second at a lower OS priority
(:mod:`.checks`); any other caller that must survive a bad pair can use one too.

Built on public API only: one ``multiprocessing`` spawn-context
:class:`~multiprocessing.Process` and a :func:`~multiprocessing.Pipe` per process, which
runs a :class:`~.session.ChildSession`. One job is in flight at a time, so the caller's own
thread sends it, polls the pipe until the answer or the time limit, and receives: no
thread reads answers. A pipe that ends (the process died) fails the job in flight.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import pickle
import signal
import threading
import time
from typing import Any, Callable

from .jobs import Answer, HELD, Job, PrepareMap
from .procfs import rss_mb, running
from .session import ChildSession, TargetNotHeld, warm_up
from ..errors import CgagsError
from ..parallel import quiet_idle_threads
from ..refusal import RefusalCode

WARM_UP_LIMIT_S = 300.0  # with a cold numba cache the warm-up compiles the numba code first


class RegistrationTimeout(CgagsError):
    """A job ran past its time limit and its process was killed (a fresh one started)."""

    code = RefusalCode.TIMEOUT


class WorkerCrashed(CgagsError):
    """The registration process died while it ran a job; a fresh one was started."""

    code = RefusalCode.WORKER_CRASHED


class _ChildDied(Exception):
    """The process's pipe ended: it is gone."""


def _serve(conn: Any, niceness: int) -> None:
    """
    Run in the process: warm up and answer, then run each job of the pipe and answer it.

    Every answer is ``(ok, value)``: the job's answer or the exception it raised. The parent
    decides when the process ends (it kills it, or closes the pipe), so a Ctrl-C meant for
    the parent's terminal does not end a registration here.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if niceness:
        os.nice(niceness)
    session = ChildSession()
    # Warm-up: the pipeline imported (Open3D) and every stage run once on a small synthetic
    # pair, so that no start-up cost is counted against a real job's limit.
    ok, value = _run(warm_up)
    answer = _pickled(ok, None if ok else value)
    while True:
        try:
            conn.send_bytes(answer)
            job = conn.recv()
        except (EOFError, OSError):
            return  # the parent is gone or closed the pipe
        answer = _pickled(*_run(lambda: session.run(job)))


def _run(fn: Callable[[], Any]) -> tuple[bool, Any]:
    try:
        return True, fn()
    except Exception as exc:  # noqa: BLE001 - sent back, raised in the parent
        return False, exc


def _pickled(ok: bool, value: Any) -> bytes:
    """Return the answer ``(ok, value)`` as bytes for the pipe, or an error that pickles."""
    try:
        return pickle.dumps((ok, value), protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as exc:  # noqa: BLE001 - an answer that does not pickle
        return pickle.dumps((False, CgagsError(
            f'the registration process cannot send back {value!r}: {exc!r}')))


class _Child:
    """One spawned process and its pipe; ``warm`` once its warm-up answered."""

    def __init__(self, name: str, niceness: int) -> None:
        # Spawn, not fork: forking a process that runs DDS threads is unsafe. The process
        # inherits this environment and loads numpy before any code of ours runs in it.
        quiet_idle_threads()
        context = multiprocessing.get_context('spawn')
        self.conn, child_end = context.Pipe()
        self.process = context.Process(target=_serve, args=(child_end, niceness), name=name,
                                       daemon=True)
        self.process.start()
        child_end.close()  # the process's copy alone keeps it open: its death ends the pipe
        self.warm = False
        self.warm_error: BaseException | None = None

    @property
    def alive(self) -> bool:
        """Tell whether the process still runs (by pid: a zombie counts as dead)."""
        return running(self.process.pid)

    def receive(self, timeout_s: float | None) -> tuple[bool, Any] | None:
        """Return the next answer ``(ok, value)``, None past ``timeout_s`` (or _ChildDied)."""
        try:
            if not self.conn.poll(timeout_s):
                return None
            return self.conn.recv()
        except (EOFError, OSError):
            raise _ChildDied() from None
        except Exception as exc:  # noqa: BLE001 - an answer that does not unpickle
            return False, CgagsError(f'unreadable answer of the registration process: {exc!r}')

    def wait_warm(self, timeout_s: float | None) -> bool:
        """Take the warm-up's answer if it came within ``timeout_s``; tell whether warm."""
        if not self.warm:
            answer = self.receive(timeout_s)
            if answer is not None:
                self.warm, self.warm_error = True, None if answer[0] else answer[1]
        return self.warm

    def kill(self) -> None:
        """End the process now and release the pipe."""
        self.process.kill()
        self.process.join(5.0)
        self.conn.close()


@dataclasses.dataclass
class _InFlight:
    job: Job
    deadline: float  # monotonic seconds
    too_long: str  # what the timeout says


class Supervisor:
    """
    Runs jobs in one spawned process, supervised, with a time limit (see the module doc).

    :param timeout_s: the time limit of a job (``worker.registration_timeout``).
    :param name: the process's name. :param niceness: added to its OS niceness (a lower
        priority: global work that must not take the CPU from a stream).

    The process keeps the last target: a job whose target is the same array object as the
    last completed job's is sent with :data:`~.jobs.HELD` instead (the node never writes to
    a decoded cloud); ``targets_sent`` counts the targets that crossed the pipe. A process
    found dead before a job is sent (it died idle) is replaced and the job runs on the fresh
    one; one that dies during a job is replaced and the job fails with
    :class:`WorkerCrashed`. :meth:`supervise` replaces a dead idle process early, so that
    the next job does not wait for the fresh one's start-up. ``crashes`` counts deaths,
    ``restarts`` every replacement (crashes and timeouts). ``busy`` is set from the moment a
    job is sent until its answer is received. One caller at a time; :meth:`health`,
    :meth:`supervise` and :attr:`ready` may be called from any thread.
    """

    def __init__(self, timeout_s: float, name: str = 'cgags-registration', niceness: int = 0):
        self.timeout_s = timeout_s
        self.name, self.niceness = name, niceness
        self.crashes = 0
        self.restarts = 0
        self.targets_sent = 0
        self.busy = threading.Event()
        self._lock = threading.Lock()  # held while the process is used (a job, a replacement)
        self._child: _Child | None = None
        self._closed = False
        self._held: Any = None  # the target the process holds (by identity)
        self._flight: _InFlight | None = None
        self._start()

    # ------------------------------------------------------------------ state

    @property
    def pid(self) -> int | None:
        """Return the process id (None after close)."""
        child = self._child
        return None if child is None else child.process.pid

    @property
    def ready(self) -> bool:
        """Tell whether the process has finished its warm-up (a job then starts at once)."""
        child = self._child
        if child is None:
            return False
        if not child.warm and self._lock.acquire(blocking=False):
            try:
                child.wait_warm(0.0)
            except _ChildDied:
                pass  # supervise() or the next job replaces it
            finally:
                self._lock.release()
        return child.warm

    @property
    def in_flight(self) -> bool:
        """Tell whether a job was submitted and its answer not yet collected."""
        return self._flight is not None

    def health(self, prefix: str = 'worker') -> dict[str, Any]:
        """Return the process's counters and resident memory, for /diagnostics."""
        pid = self.pid
        child = self._child
        return {f'{prefix}.pid': pid or 0,
                f'{prefix}.alive': child is not None and child.alive,
                f'{prefix}.ready': self.ready,
                f'{prefix}.crashes': self.crashes, f'{prefix}.restarts': self.restarts,
                f'memory.{prefix}_rss_mb': round(rss_mb(pid) or 0.0, 1) if pid else 0.0}

    def wait_ready(self) -> None:
        """Wait for the warm-up; raise :class:`WorkerCrashed` if it failed or did not end."""
        with self._lock:
            child = self._child
            if child is None:
                return
            try:
                warm = child.wait_warm(WARM_UP_LIMIT_S)
            except _ChildDied:
                raise WorkerCrashed('the registration process failed to start (it died)') \
                    from None
        if not warm:
            raise WorkerCrashed('the registration process failed to start (not ready after '
                                f'{WARM_UP_LIMIT_S:g} s)')
        if child.warm_error is not None:
            raise WorkerCrashed('the registration process failed to start '
                                f'({child.warm_error!r})')

    # ------------------------------------------------------------------ jobs

    def run(self, job: Job, timeout_s: float | None = None) -> Answer:
        """
        Run ``job`` in the process; return its answer.

        :param timeout_s: its time limit (default ``timeout_s``).
        :raises RegistrationTimeout: past the limit (the process is restarted).
        :raises WorkerCrashed: the process died during the job (it is replaced).
        :raises CgagsError: what the job raised (bad input, an unusable map, ...).
        """
        for attempt in (0, 1):
            self.submit(job, timeout_s)
            try:
                return self.collect(None)
            except TargetNotHeld:  # not expected (a restart forgets what was sent): resend
                if attempt:
                    raise
                self._held = None
        raise AssertionError('unreachable')

    def submit(self, job: Job, timeout_s: float | None = None) -> None:
        """Send ``job`` to the warm process and return; :meth:`collect` takes its answer."""
        limit = self.timeout_s if timeout_s is None else timeout_s
        too_long = (f'loading the map took longer than {limit:g} s'
                    if isinstance(job, PrepareMap) else
                    f'registration took longer than worker.registration_timeout = {limit:g} s')
        with self._lock:
            if self._flight is not None:
                raise RuntimeError('a job is already in flight')
            for attempt in (0, 1):
                child = self._warm_child()
                sent = self._with_held_target(job)
                try:
                    child.conn.send(sent)
                    break
                except (EOFError, OSError):  # it died idle since the check: a fresh one
                    if attempt:
                        raise WorkerCrashed('the registration process died before the job '
                                            'was sent; restarted') from None
                    self._crashed()
            self._flight = _InFlight(job, time.monotonic() + limit, too_long)
            self.busy.set()

    def collect(self, wait_s: float | None = 0.0) -> Answer | None:
        """
        Return the answer of the job in flight, or None when it has not landed yet.

        :param wait_s: how long to wait for it (None: until it lands or its limit passes).
        :raises: as :meth:`run`, once the job has ended.
        """
        with self._lock:
            flight, child = self._flight, self._child
            if flight is None or child is None:
                raise RuntimeError('no job in flight')
            left = flight.deadline - time.monotonic()
            wait = max(left, 0.0) if wait_s is None else min(max(left, 0.0), wait_s)
            try:
                answer = child.receive(wait)
            except _ChildDied:
                self._end_flight()
                if not self._closed:
                    self._crashed()
                what = ('loading the map (out of memory?)' if isinstance(flight.job, PrepareMap)
                        else 'this pair (killed, out of memory or a native crash)')
                raise WorkerCrashed(f'the registration process died during {what}; '
                                    'restarted') from None
            if answer is None:
                if time.monotonic() < flight.deadline:
                    return None
                self._end_flight()
                self._replace()
                raise RegistrationTimeout(f'{flight.too_long}; its process was restarted')
            self._end_flight()
            ok, value = answer
            if not ok:
                raise value
            target = getattr(flight.job, 'target', None)
            if target is not None and not isinstance(target, str):
                self._held = target  # a completed job proves the process holds it
            return value

    def _end_flight(self) -> None:
        self._flight = None
        self.busy.clear()

    def _with_held_target(self, job: Job) -> Job:
        """Return ``job`` with :data:`HELD` for a target the process already holds."""
        target = getattr(job, 'target', None)
        if target is None or isinstance(target, str):
            return job
        held, self._held = target is self._held, None  # only an answer proves it is held
        self.targets_sent += not held
        return dataclasses.replace(job, target=HELD) if held else job

    # ------------------------------------------------------------------ supervision

    def supervise(self) -> bool:
        """Replace a process that died while idle; return True when one was replaced."""
        if not self._lock.acquire(blocking=False):
            return False  # a job or a replacement is using it
        try:
            child = self._child
            if self._closed or self._flight is not None or child is None or child.alive:
                return False
            self._crashed()
            return True
        finally:
            self._lock.release()

    def _warm_child(self) -> _Child:
        """Return the process once warm; one found dead (it died idle) is replaced first."""
        child = self._child
        if child is None:
            raise RegistrationTimeout('the registration process is shut down')
        if not child.alive:  # nothing of a job is lost
            self._crashed()
            child = self._child
        try:
            child.wait_warm(WARM_UP_LIMIT_S)
        except _ChildDied:  # died warming up: the job goes to a fresh one
            self._crashed()
            child = self._child
            child.wait_warm(WARM_UP_LIMIT_S)
        return child

    def _crashed(self) -> None:
        self.crashes += 1
        self._replace()

    def restart(self) -> None:
        """Kill the process and start a fresh one (a job in flight is lost)."""
        with self._lock:
            self._end_flight()
            self._replace()

    def _replace(self) -> None:
        self._kill()
        if not self._closed:
            self.restarts += 1
            self._start()

    def _start(self) -> None:
        self._held = None
        self._child = _Child(self.name, self.niceness)

    def close(self) -> None:
        """Stop the process for good (a job in flight ends at once)."""
        self._closed = True
        child = self._child
        if child is not None:
            child.process.kill()  # ends a job in flight, which releases the lock
        with self._lock:
            self._end_flight()
            self._kill()

    def _kill(self) -> None:
        child, self._child = self._child, None
        if child is not None:
            child.kill()
