"""
The jobs the registration process runs, one type a kind, the typed answer of each, their counts.

The engine chooses the kind once (:meth:`~cgags_ros.engine.engine.RegistrationEngine`),
a :class:`Runner` runs it (a :class:`~.supervisor.Supervisor`'s registration process, or a
:class:`~.process.ChildSession` in this process), and the answer's type says what came
back; every answer to a registration carries its
:class:`~cgags_ros.pipeline.result.PipelineResult` (:func:`result_of`).

- :class:`RegisterPair` -> :class:`PairDone`: one pair through ``register_clouds`` (a scan
  on a map with the :class:`~cgags_ros.pipeline.hint.Hint` of a relocalization, if any).
- :class:`TrackScan` -> :class:`Tracked`: a stream's next scan through the session's
  :class:`~cgags_ros.tracking.Tracker`, which may ask for a periodic check beside it.
- :class:`CheckScan` -> :class:`CheckVerdict`: that check, a global registration of a
  tracked scan, answered with the pose alone (the checks' lane, :mod:`.checks`).
- :class:`SequenceScan` -> :class:`~cgags_ros.relocalization.sequence.StepAnswer`: one scan
  of a relocalization over several scans, on the map (with its hint, if any).
- :class:`PrepareMap` -> :class:`MapReady`: load a map's features.

Targets are an array (metres, the target's frame), a :class:`MapRef` (the process loads
and keeps the map), or :data:`HELD`: the target the session was sent last, so a latched
target crosses the pipe once. Light to import (numpy, no Open3D): the node's own process
builds jobs and reads answers without loading the pipeline.

A stream is tracked (:func:`tracks`: continuous mode, tracking on) when its scans are
:class:`TrackScan` jobs. Its Tracker lives where registration runs, beside the target, and a
replaced process starts a fresh one. So each :class:`Tracked` answer carries what the scan
added to its Tracker's counts (:func:`track`), and the engine's :class:`StreamCounts` adds
them up across restarts.
"""

from __future__ import annotations

from collections import Counter
import dataclasses
from typing import Any, Callable, Protocol, Union

import numpy as np

from ..config.pipeline import PipelineConfig
from ..pipeline.hint import Hint
from ..pipeline.result import PipelineResult
from ..relocalization.sequence import StepAnswer

HELD = 'held'  # a job's target: the one the session holds (sent by an earlier job)
# The Tracker's counts /diagnostics always carries (the others appear once they happen).
SHOWN = ('tracked', 'global', 'tracking_failures', 'periodic_checks')


@dataclasses.dataclass(frozen=True)
class MapRef:
    """
    A target that is a map file: the process running the job loads (and keeps) its features.

    :ivar path: the map file (PLY, PCD, NPY, XYZ/CSV/TXT), metres, map frame.
    :ivar cache_dir: feature cache directory ('' disables the cache).
    """

    path: str
    cache_dir: str = ''


Target = Union[np.ndarray, MapRef, str]  # an array, a map, or HELD


@dataclasses.dataclass(frozen=True)
class RegisterPair:
    """
    Register ``source`` (N, 3, metres, its sensor frame) onto ``target`` globally.

    :ivar hint: with a map target, where the source's sensor is believed to be: only the
        map's places it covers are searched (None: everywhere).
    """

    source: np.ndarray
    target: Target
    config: PipelineConfig
    hint: Hint | None = None


@dataclasses.dataclass(frozen=True)
class CheckVerdict:
    """
    A periodic global check of a tracked scan, run in the other lane, as it landed.

    :ivar stamp: the checked scan's stamp, seconds.
    :ivar transform: the global result (4x4, source -> target), or None when it refused.
    :ivar code: why it refused (a ``RefusalCode`` value), '' when valid.
    """

    stamp: float
    transform: np.ndarray | None
    code: str = ''


@dataclasses.dataclass(frozen=True)
class CheckScan:
    """Register a tracked scan ``source`` (stamped ``stamp``, s) globally: its check."""

    source: np.ndarray
    target: Target
    config: PipelineConfig
    stamp: float


@dataclasses.dataclass(frozen=True)
class TrackScan:
    """
    Register a stream's next scan with the session's Tracker.

    :ivar stamp: the scan's header stamp, seconds.
    :ivar checks_beside: periodic checks run in a second lane: a scan whose check is due is
        tracked, and :class:`Tracked` says the check is due instead of running it here.
    :ivar verdict: a check that landed since the last scan, applied before this one.
    """

    source: np.ndarray
    target: Target
    config: PipelineConfig
    stamp: float
    checks_beside: bool = False
    verdict: CheckVerdict | None = None


@dataclasses.dataclass(frozen=True)
class SequenceScan:
    """
    Add a scan to the session's relocalization over several scans on ``target``'s map.

    :ivar odom_from_sensor: 4x4 pose of the sensor in the odometry frame at the scan's
        stamp (metres); None: no odometry, the scan is judged alone and the sequence starts
        over.
    :ivar max_scans: scans after which an unconfirmed answer is refused.
    :ivar restart: forget the scans so far first.
    :ivar hint: where the scan's sensor is believed to be in the map (None: anywhere).
    """

    source: np.ndarray
    target: Target
    config: PipelineConfig
    odom_from_sensor: np.ndarray | None
    max_scans: int
    restart: bool
    hint: Hint | None = None


@dataclasses.dataclass(frozen=True)
class PrepareMap:
    """Load the map of ``ref`` (features from the cache or computed) and keep it."""

    ref: MapRef
    config: PipelineConfig


@dataclasses.dataclass
class PairDone:
    """The answer to :class:`RegisterPair`: the pipeline's result."""

    result: PipelineResult


@dataclasses.dataclass
class Tracked:
    """
    The answer to :class:`TrackScan`.

    :ivar result: the scan's result (``path`` 'tracked' or 'global').
    :ivar counts: what this scan added to the Tracker's counts (and the verdict applied).
    :ivar check_due: a periodic check of this scan is due: run it in the other lane.
    """

    result: PipelineResult
    counts: dict[str, int]
    check_due: bool = False


MapSummary = dict[str, Union[str, int, float, list[float], None]]  # PreparedMap.info()


@dataclasses.dataclass
class MapReady:
    """The answer to :class:`PrepareMap`: the map's summary (``PreparedMap.info()``)."""

    info: MapSummary


Job = Union[RegisterPair, TrackScan, SequenceScan, PrepareMap, CheckScan]
Answer = Union[PairDone, Tracked, StepAnswer, MapReady, CheckVerdict]


def result_of(answer: Answer) -> PipelineResult:
    """
    Return the registration an answer to a pair, a tracked scan or a sequence's scan carries.

    :raises TypeError: the answer of a map load or a check, which carries none.
    """
    if isinstance(answer, (MapReady, CheckVerdict)):
        raise TypeError(f'{type(answer).__name__} carries no registration')
    return answer.result


def tracks(mode: str, config: PipelineConfig) -> bool:
    """Tell whether a stream in node mode ``mode`` is tracked (continuous, tracking on)."""
    return mode == 'continuous' and config.tracking.enabled


def track(tracker: Any, run: Callable[[], Any]) -> tuple[Any, dict[str, int]]:
    """Run ``run()`` (a call of ``tracker``); return its value and what it added to the counts."""
    before = tracker.counts()
    value = run()
    return value, {k: v - before.get(k, 0) for k, v in tracker.counts().items()
                   if v != before.get(k, 0)}


class StreamCounts:
    """
    The Tracker's counts, added up from each scan's share.

    One thread adds (the engine thread); :meth:`statistics` may be read from any: the
    counts are replaced whole, never changed in place, so no lock is needed.
    """

    def __init__(self) -> None:
        self._counts: Counter[str] = Counter({name: 0 for name in SHOWN})

    def add(self, counts: dict[str, int]) -> None:
        """Add what one scan counted."""
        total = self._counts.copy()
        total.update(counts)
        self._counts = total

    def statistics(self) -> dict[str, int]:
        """Return ``tracking.<count>`` for /diagnostics."""
        return {f'tracking.{k}': v for k, v in sorted(self._counts.items())}


class Runner(Protocol):
    """
    What runs jobs, the engine's one seam to the pipeline.

    A :class:`~.supervisor.Supervisor` (a registration process of its own), a
    :class:`~.process.ChildSession` (this process), or a test's stand-in.
    """

    def run(self, job: Job, timeout_s: float | None = None) -> Answer:
        """
        Run ``job``; return its answer.

        :param timeout_s: its time limit where one can be kept (a process of its own), else
            ignored; None: the runner's own.
        :raises CgagsError: what the job raised, or why it did not end (its ``code``).
        """

    def supervise(self) -> bool:
        """Replace what died while idle; tell whether something was (call it periodically)."""

    def health(self, prefix: str = 'registration') -> dict[str, Any]:
        """Return its keys of /diagnostics (none in this process)."""

    def close(self) -> None:
        """End it for good (a job in flight in a process of its own ends at once)."""
