"""
The registration process's state: one object that runs every job and holds what they share.

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
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .jobs import (Answer, CheckScan, CheckVerdict, HELD, Job, MapReady, MapRef, PairDone,
                   PrepareMap, RegisterPair, SequenceScan, Target, track, Tracked, TrackScan)
from ..config.pipeline import PipelineConfig
from ..errors import CgagsError
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
            return PairDone(register_clouds(job.source, target, config=job.config))
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
        answer = reloc.add(job.source, odom)
        return StepAnswer(answer.refusal, answer.results[-1], answer.confirmed, answer.done,
                          answer.transform, answer.map_from_odom, answer.scans_used,
                          len(answer.hypotheses))


def warm_up() -> None:
    """Import the pipeline (Open3D) and run every stage once, so no pair pays for it."""
    from ..pipeline.register import warm_up as pipeline_warm_up

    pipeline_warm_up()
