"""
The registration process: the session that runs its jobs, its side of the pipe, its clouds.

A :class:`ChildSession` is created with the process that runs the pipeline (the node's
registration process, or the node's own process when ``runtime.registration_timeout`` is 0)
and forgotten with it: a replaced process starts with no target, no map, no stream prior
and no relocalization in progress, and the next job says so (a map is loaded again, a
stream goes global, a sequence starts over). It holds:

- the target sent last (a job's target :data:`~.jobs.HELD` reuses it);
- the maps of ``MapRef`` targets (:class:`~cgags_ros.pipeline.map.MapHolder`);
- the stream's :class:`~cgags_ros.tracking.Tracker`;
- the relocalization over several scans in progress (:class:`~cgags_ros.relocalization.
  relocalizer.Relocalizer`).

The pipeline (Open3D) is imported when the first job runs.

:func:`serve` runs in the spawned process: it warms up, then answers each job with its
:class:`ChildSession`. :class:`Child` is the parent's handle on one such process: its pipe,
its warm-up, whether it still runs. :func:`spill` writes a job's clouds to files (see
:mod:`.supervisor` for why) and :func:`unspill` reads them back in the process.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import pickle
import signal
import tempfile
from typing import Any, Callable

import numpy as np

from .jobs import (Answer, CheckScan, CheckVerdict, HELD, Job, MapReady, MapRef, PairDone,
                   PrepareMap, RegisterPair, SequenceScan, Target, track, Tracked, TrackScan)
from .procfs import running
from ..config.pipeline import PipelineConfig
from ..errors import CgagsError
from ..parallel import quiet_idle_threads
from ..relocalization.sequence import StepAnswer


class TargetNotHeld(CgagsError):
    """A job asked for the held target, and this session holds none (it was restarted)."""


class ChildSession:
    """
    Runs jobs (:meth:`run`) and keeps the state they share (see the module doc).

    A :class:`~.jobs.Runner` of this process: nothing to supervise, no time limit.
    """

    def __init__(self) -> None:
        self._target: Any = None
        self._maps: Any = None
        self._tracker: Any = None
        self._relocalizer: Any = None

    def run(self, job: Job, timeout_s: float | None = None) -> Answer:
        """
        Run one job; return its typed answer.

        ``timeout_s`` is ignored: a call in this process cannot be interrupted.

        :raises CgagsError: as the job's pipeline.
        """
        if isinstance(job, PrepareMap):
            return MapReady(self._prepared(job.ref, job.config).info())
        target = self._resolve(job.target, job.config)
        if isinstance(job, TrackScan):
            return self._track(job, target)
        if isinstance(job, SequenceScan):
            return self._sequence_scan(job, target)
        from ..pipeline.register import register_clouds

        if isinstance(job, RegisterPair):
            return PairDone(register_clouds(job.source, target, config=job.config,
                                            hint=job.hint))
        if isinstance(job, CheckScan):
            result = register_clouds(job.source, target, config=job.config)
            return CheckVerdict(job.stamp, np.asarray(result.transform) if result.valid else None,
                                '' if result.valid else result.refusal.code.value)
        raise TypeError(f'not a job: {job!r}')

    def supervise(self) -> bool:
        """Tell that nothing was replaced: this process runs the jobs."""
        return False

    def health(self, prefix: str = 'registration') -> dict[str, Any]:
        """Return no /diagnostics keys: this process's are the node's."""
        return {}

    def close(self) -> None:
        """End nothing: this process runs the jobs (its state goes with this object)."""

    def _resolve(self, target: Target, config: PipelineConfig) -> Any:
        """Return the points or the prepared map a job's target stands for, and hold it."""
        if isinstance(target, str) and target == HELD:
            if self._target is None:
                raise TargetNotHeld('the registration process holds no target (restarted)')
            target = self._target
        self._target = target
        return self._prepared(target, config) if isinstance(target, MapRef) else target

    def _prepared(self, ref: MapRef, config: PipelineConfig) -> Any:
        if self._maps is None:
            from ..pipeline.map import MapHolder

            self._maps = MapHolder()
        return self._maps.get(ref.path, config, ref.cache_dir)

    def _track(self, job: TrackScan, target: Any) -> Tracked:
        if self._tracker is None:
            from ..tracking.tracker import Tracker

            self._tracker = Tracker()
        tracker = self._tracker

        def run() -> Any:
            if job.verdict is not None:
                tracker.apply_check(job.verdict.stamp, job.verdict.transform)
            return tracker.register(job.source, target, job.stamp, config=job.config,
                                    defer_checks=job.checks_beside)

        result, counts = track(tracker, run)
        return Tracked(result, counts, tracker.check_due)

    def _sequence_scan(self, job: SequenceScan, prepared: Any) -> StepAnswer:
        from ..relocalization.relocalizer import Relocalizer, SequenceConfig

        reloc = self._relocalizer
        if (job.restart or reloc is None or reloc.prepared is not prepared
                or reloc.config != job.config or reloc.sequence.max_scans != job.max_scans):
            reloc = self._relocalizer = Relocalizer(prepared, job.config,
                                                    SequenceConfig(max_scans=job.max_scans))
        odom = None if job.odom_from_sensor is None else np.asarray(job.odom_from_sensor)
        answer = reloc.add(job.source, odom, job.hint)
        return StepAnswer(answer.refusal, answer.results[-1], answer.confirmed, answer.done,
                          answer.transform, answer.map_from_odom, answer.scans_used,
                          len(answer.hypotheses))


def warm_up() -> None:
    """Import the pipeline (Open3D) and run every stage once, so no pair pays for it."""
    from ..pipeline.register import warm_up as pipeline_warm_up

    pipeline_warm_up()


class ChildDied(Exception):
    """The process's pipe ended: it is gone."""


@dataclasses.dataclass(frozen=True)
class Spilled:
    """An array a job carries, written to ``path`` (``.npy``) instead of the pipe."""

    path: str


CLOUDS = ('source', 'target')  # the fields of a job that may hold a cloud


def spill(job: Job, folder: str) -> tuple[Job, list[str]]:
    """Return ``job`` with its clouds written to files in ``folder``, and those files."""
    changes, paths = {}, []
    for name in CLOUDS:
        value = getattr(job, name, None)
        if isinstance(value, np.ndarray):
            fd, path = tempfile.mkstemp(suffix='.npy', prefix='cgags-job-', dir=folder)
            with os.fdopen(fd, 'wb') as f:
                np.save(f, value, allow_pickle=False)
            changes[name] = Spilled(path)
            paths.append(path)
    return (dataclasses.replace(job, **changes) if changes else job), paths


def unspill(job: Any) -> Any:
    """Return ``job`` with its spilled clouds read back (in the process)."""
    changes = {name: np.load(value.path, allow_pickle=False) for name in CLOUDS
               if isinstance(value := getattr(job, name, None), Spilled)}
    return dataclasses.replace(job, **changes) if changes else job


def spill_folder() -> str:
    """Return where spilled clouds go: ``/dev/shm`` (memory) when writable, else the temp dir."""
    shm = '/dev/shm'
    return shm if os.path.isdir(shm) and os.access(shm, os.W_OK) else tempfile.gettempdir()


def serve(conn: Any, niceness: int) -> None:
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
        answer = _pickled(*_run(lambda: session.run(unspill(job))))


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


class Child:
    """One spawned process and its pipe; ``warm`` once its warm-up answered."""

    def __init__(self, name: str, niceness: int) -> None:
        # Spawn, not fork: forking a process that runs DDS threads is unsafe. The process
        # inherits this environment and loads numpy before any code of ours runs in it.
        quiet_idle_threads()
        context = multiprocessing.get_context('spawn')
        self.conn, child_end = context.Pipe()
        self.process = context.Process(target=serve, args=(child_end, niceness), name=name,
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
        """Return the next answer ``(ok, value)``, None past ``timeout_s`` (or ChildDied)."""
        try:
            if not self.conn.poll(timeout_s):
                return None
            return self.conn.recv()
        except (EOFError, OSError):
            raise ChildDied() from None
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


def remove_files(paths: list[str]) -> None:
    for path in paths:
        try:
            os.remove(path)
        except OSError:
            pass  # already gone
