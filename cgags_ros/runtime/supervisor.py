"""
A supervised registration process: typed jobs in, typed answers out, with a time limit.

A pathological input that makes the pipeline loop costs one job (the process is killed
past the time limit and a fresh one started), and a process that dies (the OOM killer, a
native crash in a library, ``kill -9``), idle or busy, is replaced; the caller keeps
registering. The node runs a stream's jobs through one (``runtime.registration_timeout`` >
0) and, while it tracks, its periodic checks through a second at a lower OS priority
(:mod:`.checks`); any other caller that must survive a bad pair can use one too.

Built on public API only: one ``multiprocessing`` spawn-context
:class:`~multiprocessing.Process` and a :func:`~multiprocessing.Pipe` per process, which
runs a :class:`~.process.ChildSession`. One job is in flight at a time, so the caller's own
thread sends it, polls the pipe until the answer or the time limit, and receives: no
thread reads answers. A pipe that ends (the process died) fails the job in flight.

A pipe holds 64 kB: sending a scan (megabytes) waits until the process has read it. For a
process at a lower priority, which reads only when the CPU is idle, that wait would fall on
the caller; with ``spill_dir`` its jobs' clouds are written to files there (``/dev/shm``:
memory) and only their names cross the pipe, so sending never waits.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from typing import Any

from .jobs import Answer, HELD, Job, PrepareMap
from .process import Child, ChildDied, remove_files, spill, TargetNotHeld
from .procfs import rss_mb
from ..errors import CgagsError
from ..refusal import RefusalCode

WARM_UP_LIMIT_S = 300.0  # with a cold numba cache the warm-up compiles the numba code first


class RegistrationTimeout(CgagsError):
    """A job ran past its time limit and its process was killed (a fresh one started)."""

    code = RefusalCode.TIMEOUT


class ProcessCrashed(CgagsError):
    """The registration process died while it ran a job; a fresh one was started."""

    code = RefusalCode.PROCESS_CRASHED


@dataclasses.dataclass
class _InFlight:
    job: Job
    deadline: float  # monotonic seconds
    too_long: str  # what the timeout says
    spilled: list[str]  # the files of its clouds, removed when it ends


class Supervisor:
    """
    Runs jobs in one spawned process, supervised, with a time limit (see the module doc).

    :param timeout_s: the time limit of a job (``runtime.registration_timeout``).
    :param name: the process's name. :param niceness: added to its OS niceness (a lower
        priority: global work that must not take the CPU from a stream).
    :param spill_dir: send the jobs' clouds through files in this folder, not the pipe.

    The process keeps the last target: a job whose target is the same array object as the
    last completed job's is sent with :data:`~.jobs.HELD` instead (the node never writes to
    a decoded cloud); ``targets_sent`` counts the targets that crossed the pipe. A process
    found dead before a job is sent (it died idle) is replaced and the job runs on the fresh
    one; one that dies during a job is replaced and the job fails with
    :class:`ProcessCrashed`. :meth:`supervise` replaces a dead idle process early, so that
    the next job does not wait for the fresh one's start-up. ``crashes`` counts deaths,
    ``restarts`` every replacement (crashes and timeouts). :attr:`in_flight` from the moment
    a job is sent until its answer is received.

    Two threads use the process: the caller's (its jobs: :meth:`run`, :meth:`submit`,
    :meth:`collect`, :meth:`restart`; the engine thread) and another that supervises it
    (:meth:`supervise`, :attr:`ready` and :meth:`close`; the node's executor). Each holds
    one lock while it uses or replaces the process. :meth:`health` takes no lock.
    """

    def __init__(self, timeout_s: float, name: str = 'cgags-registration', niceness: int = 0,
                 spill_dir: str | None = None):
        self.timeout_s = timeout_s
        self.name, self.niceness, self.spill_dir = name, niceness, spill_dir
        self.crashes = 0
        self.restarts = 0
        self.targets_sent = 0
        self._lock = threading.Lock()  # held while the process is used (a job, a replacement)
        self._child: Child | None = None
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
            except ChildDied:
                pass  # supervise() or the next job replaces it
            finally:
                self._lock.release()
        return child.warm

    @property
    def alive(self) -> bool:
        """Tell whether the process runs (False after close, or once it died)."""
        child = self._child
        return child is not None and child.alive

    @property
    def in_flight(self) -> bool:
        """Tell whether a job was submitted and its answer not yet collected."""
        return self._flight is not None

    def health(self, prefix: str = 'registration') -> dict[str, Any]:
        """Return the process's counters and resident memory, for /diagnostics."""
        pid = self.pid
        return {f'{prefix}.pid': pid or 0, f'{prefix}.alive': self.alive,
                f'{prefix}.ready': self.ready,
                f'{prefix}.crashes': self.crashes, f'{prefix}.restarts': self.restarts,
                f'memory.{prefix}_rss_mb': round(rss_mb(pid) or 0.0, 1) if pid else 0.0}

    def wait_ready(self) -> None:
        """Wait for the warm-up; raise :class:`ProcessCrashed` if it failed or did not end."""
        with self._lock:
            child = self._child
            if child is None:
                return
            try:
                warm = child.wait_warm(WARM_UP_LIMIT_S)
            except ChildDied:
                raise ProcessCrashed('the registration process failed to start (it died)') \
                    from None
        if not warm:
            raise ProcessCrashed('the registration process failed to start (not ready after '
                                 f'{WARM_UP_LIMIT_S:g} s)')
        if child.warm_error is not None:
            raise ProcessCrashed('the registration process failed to start '
                                 f'({child.warm_error!r})')

    # ------------------------------------------------------------------ jobs

    def run(self, job: Job, timeout_s: float | None = None) -> Answer:
        """
        Run ``job`` in the process; return its answer.

        :param timeout_s: its time limit (default ``timeout_s``).
        :raises RegistrationTimeout: past the limit (the process is restarted).
        :raises ProcessCrashed: the process died during the job (it is replaced).
        :raises CgagsError: what the job raised (bad input, an unusable map, ...).
        """
        for attempt in (0, 1):
            self.submit(job, timeout_s)
            try:
                answer = None
                while answer is None:  # a poll may end a hair before the deadline: poll again
                    answer = self.collect(None)
                return answer
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
                    f'registration took longer than runtime.registration_timeout = {limit:g} s')
        with self._lock:
            if self._flight is not None:
                raise RuntimeError('a job is already in flight')
            for attempt in (0, 1):
                child = self._warm_child()
                sent, spilled = self._with_held_target(job), []
                if self.spill_dir is not None:
                    sent, spilled = spill(sent, self.spill_dir)
                try:
                    child.conn.send(sent)
                    break
                except (EOFError, OSError):  # it died idle since the check: a fresh one
                    remove_files(spilled)
                    if attempt:
                        raise ProcessCrashed('the registration process died before the job '
                                             'was sent; restarted') from None
                    self._crashed()
            self._flight = _InFlight(job, time.monotonic() + limit, too_long, spilled)

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
            except ChildDied:
                self._end_flight()
                if not self._closed:
                    self._crashed()
                what = ('loading the map (out of memory?)' if isinstance(flight.job, PrepareMap)
                        else 'this pair (killed, out of memory or a native crash)')
                raise ProcessCrashed(f'the registration process died during {what}; '
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
        if self._flight is not None:
            remove_files(self._flight.spilled)
        self._flight = None

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

    def _warm_child(self) -> Child:
        """Return the process once warm; one found dead (it died idle) is replaced first."""
        child = self._child
        if child is None:
            raise RegistrationTimeout('the registration process is shut down')
        if not child.alive:  # nothing of a job is lost
            self._crashed()
            child = self._child
        try:
            child.wait_warm(WARM_UP_LIMIT_S)
        except ChildDied:  # died warming up: the job goes to a fresh one
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
        self._child = Child(self.name, self.niceness)

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
