"""
A temporal prior for streams: each scan refined from its predicted pose, else searched for.

A robot's scans arrive at 10-20 Hz and move little between two of them. :class:`Tracker`,
held per source/target pair by the stream's caller (the node in continuous mode,
``cgags-replay``), predicts the next pose from the pair's last valid poses (constant
velocity, or the odometry given), refines it (downsampling and refinement only: no FPFH,
no matching, no core) and judges it by the gates a global result passes
(:func:`~cgags_ros.validity.overlap_refusal`), plus two of its own
(:func:`~cgags_ros.validity.tracking_refusal`): the refinement must not have moved the
prediction far, and its fitness must not fall far below the last accepted pose's. When it
fails (a jump, a kidnap, a degenerate view), when the target changed, when the last pose
is too old, the scan goes through :func:`~cgags_ros.pipeline.register.register_clouds`, the
one global path. Periodically a global search checks the tracked pose: in line (the scan
waits for it), or beside the stream (``defer_checks``: the scan is tracked, the caller runs
the check elsewhere and hands its verdict back with :meth:`Tracker.apply_check`; a
disagreement resets the motion either way). ``result.path`` says which path produced the
result; a pose refined from a prediction is never returned as valid unless it passed the
gates, and the usable-covariance bound (``gates.max_position_sigma``) as a global pose does.
Transforms are 4x4 source->target (``p_target = R p_source + t``), metres; stamps in seconds.
"""

from __future__ import annotations

from collections import Counter
import dataclasses
import hashlib

import numpy as np

from .prediction import agree, scaled_motion
from .refined import refine_prediction, target_features
from ..config import fields
from ..config.pipeline import PipelineConfig
from ..frontend.features import CloudFeatures, finite_points
from ..pipeline.map import PreparedMap
from ..pipeline.register import register_clouds
from ..pipeline.result import PipelineResult
from ..registration import single_blas_thread

MAX_AWAITED = 4  # tracked poses kept for checks beside the stream that have not landed
COUNTS = ('tracked', 'global', 'invalid', 'tracking_failures', 'periodic_checks',
          'check_disagreements', 'target_changes')


@dataclasses.dataclass
class _Pose:
    """A valid pose of the pair: when, where, and how well it fitted."""

    stamp: float
    transform: np.ndarray
    fitness: float


@dataclasses.dataclass
class _PairState:
    """What the tracker remembers of one source/target pair."""

    target_key: tuple
    config: PipelineConfig
    features: CloudFeatures | None = None
    origin: np.ndarray | None = None  # the features' local origin in the target's frame
    poses: list[_Pose] = dataclasses.field(default_factory=list)
    tracked_since_global: int = 0
    last_global_stamp: float = float('-inf')
    checked: dict[float, np.ndarray] = dataclasses.field(default_factory=dict)  # awaiting checks


class Tracker:
    """
    Register the scans of one source/target stream, tracking when the prior allows it.

    One instance per source/target pair; not thread-safe (a stream is registered in order).
    ``counts()`` tells how many results came from each path, for diagnostics.
    """

    def __init__(self) -> None:
        self._state: _PairState | None = None
        self._counts: Counter[str] = Counter({name: 0 for name in COUNTS})
        self.check_due = False  # the last scan's periodic check is the caller's to run
        self.global_registration = register_clouds  # the global path (tests replace it)

    def counts(self) -> dict[str, int]:
        """
        Return how many results each path produced since construction.

        ``tracked`` and ``global``: results by path; ``invalid``: results not valid (either
        path); ``tracking_failures``: predictions whose refinement failed a gate (the
        scan then went global); ``periodic_checks``: global searches run on a tracked
        stream by ``tracking.global_check_interval``/``global_check_period``;
        ``check_disagreements``: of those, valid results the prediction disagreed with;
        ``target_changes``: a new target (or configuration) that dropped the prior.
        """
        return dict(self._counts)

    def reset(self) -> None:
        """Forget the pair's poses: the next scan is registered globally."""
        self._state = None

    def register(self, source: np.ndarray, target: np.ndarray | PreparedMap, stamp: float, *,
                 config: PipelineConfig | None = None, odometry: np.ndarray | None = None,
                 defer_checks: bool = False) -> PipelineResult:
        """
        Register the stream's next scan ``source`` onto ``target``.

        :param source: (N, 3) points, metres, the sensor's frame.
        :param target: (M, 3) points or a :class:`~.map.PreparedMap`, as for
            :func:`~.register.register_clouds`; a different target (by content) than the
            last call's drops the prior.
        :param stamp: the scan's time, seconds (its header stamp); stamps must increase for
            a prediction to be made.
        :param config: :class:`PipelineConfig` (its ``tracking`` section decides when to
            track); defaults when None. A different config than the last call's drops the
            prior.
        :param odometry: optional 4x4 motion of the sensor since the previous scan (pose of
            this scan's frame in the previous scan's frame, metres): the prediction is then
            the last pose times it instead of a constant velocity.
        :param defer_checks: a periodic check that is due does not run here: the scan is
            tracked, :attr:`check_due` is set, and the caller runs the global search of
            this scan elsewhere and hands its verdict to :meth:`apply_check`.
        :returns: a :class:`PipelineResult` with ``path`` 'tracked' or 'global'; a tracked
            result is always valid (a failed prediction goes global).
        :raises: as :func:`~.register.register_clouds`.
        """
        cfg = fields.update_from_flat(config or PipelineConfig(), {})  # validated copy
        source = finite_points(source, 'source')
        self.check_due = False
        state = self._pair(target, cfg)
        prediction, kind = self._predict(state, stamp, cfg, odometry)
        if prediction is None:
            return self._global(source, target, stamp, cfg, state, kind)
        due = self._check_due(state, stamp, cfg)
        if due and not defer_checks:
            return self._periodic_check(source, target, stamp, cfg, state, prediction, kind)
        with single_blas_thread():
            tracked = self._track(source, target, prediction, cfg, state)
        if tracked.valid:
            if due:  # checked beside the stream: the next check waits its interval again
                state.tracked_since_global, state.last_global_stamp = 0, stamp
                state.checked[stamp] = tracked.transform.copy()
                while len(state.checked) > MAX_AWAITED:  # checks the caller never ran
                    del state.checked[next(iter(state.checked))]
                self.check_due = True
                return self._accept_tracked(tracked, stamp, state, kind, reset=False)
            return self._accept_tracked(tracked, stamp, state, kind)
        self._counts['tracking_failures'] += 1
        state.poses.clear()  # the motion broke off: no velocity across it
        result = self._global(source, target, stamp, cfg, state, 'tracking failed')
        result.stats['tracking_failure'] = tracked.reason
        result.stats['tracking_failure_code'] = tracked.refusal.code.value
        return result

    def _pair(self, target: np.ndarray | PreparedMap, cfg: PipelineConfig) -> _PairState:
        """Return the pair's state, new when the target or the configuration changed."""
        key = target_key(target)
        state = self._state
        if state is None or state.target_key != key or state.config != cfg:
            if state is not None:
                self._counts['target_changes'] += 1
            state = self._state = _PairState(key, cfg)
        return state

    def _predict(self, state: _PairState, stamp: float, cfg: PipelineConfig,
                 odometry: np.ndarray | None) -> tuple[np.ndarray | None, str]:
        """Return the predicted pose and how it was made, or None and why there is none."""
        track = cfg.tracking
        if not track.enabled:
            return None, 'tracking disabled'
        if cfg.refine.method == 'none':
            return None, 'no refinement (refine.method none) to track with'
        if not state.poses:
            return None, 'no recent valid pose of this pair'
        last = state.poses[-1]
        age = stamp - last.stamp
        if not 0.0 < age <= track.max_age:
            return None, (f'the last valid pose is {age:.3g} s from this scan (tracking '
                          f'needs 0 < age <= tracking.max_age {track.max_age:g} s)')
        if odometry is not None:
            return last.transform @ np.asarray(odometry, dtype=np.float64), 'odometry'
        if len(state.poses) < 2:
            return last.transform.copy(), 'last pose'
        previous = state.poses[-2]
        step = last.stamp - previous.stamp
        if not 0.0 < step <= track.max_age:
            return last.transform.copy(), 'last pose'
        motion = np.linalg.inv(previous.transform) @ last.transform
        return last.transform @ scaled_motion(motion, age / step), 'constant velocity'

    def _check_due(self, state: _PairState, stamp: float, cfg: PipelineConfig) -> bool:
        track = cfg.tracking
        by_count = (track.global_check_interval > 0
                    and state.tracked_since_global + 1 >= track.global_check_interval)
        by_time = (track.global_check_period > 0
                   and stamp - state.last_global_stamp >= track.global_check_period)
        return by_count or by_time

    def _track(self, source: np.ndarray, target: np.ndarray | PreparedMap,
               prediction: np.ndarray, cfg: PipelineConfig, state: _PairState,
               last_fitness: float | None = None) -> PipelineResult:
        """Refine ``prediction`` and gate it (:func:`~.refined.refine_prediction`)."""
        timings: dict[str, float] = {}
        if state.features is None:  # the target's features, once per pair
            state.features, state.origin = target_features(target, cfg, timings)
        if last_fitness is None:
            last_fitness = state.poses[-1].fitness if state.poses else 0.0
        result = refine_prediction(source, state.features, prediction, cfg, last_fitness,
                                   isinstance(target, PreparedMap), state.origin)
        result.timings.update(timings)  # the scan that featurised the target says so
        return result

    def apply_check(self, stamp: float, transform: np.ndarray | None) -> None:
        """
        Take the verdict of a periodic check run beside the stream (``defer_checks``).

        :param stamp: the checked scan's stamp (one this Tracker asked to check).
        :param transform: the global result (4x4), or None when the global search refused.
        A valid result that disagrees with the pose tracked for that scan resets the motion:
        the next scan is searched globally. A verdict on a scan of an earlier target or
        configuration is ignored.
        """
        state = self._state
        tracked = None if state is None else state.checked.pop(stamp, None)
        if tracked is None:
            return
        self._counts['periodic_checks'] += 1
        cfg = state.config
        if transform is not None and not agree(tracked, transform, cfg):
            self._counts['check_disagreements'] += 1
            state.poses.clear()

    def _accept_tracked(self, result: PipelineResult, stamp: float, state: _PairState,
                        kind: str, reset: bool = True) -> PipelineResult:
        self._counts['tracked'] += 1
        state.tracked_since_global += reset
        result.stats['prediction'] = kind
        _remember(state, stamp, result)
        return result

    def _global(self, source: np.ndarray, target: np.ndarray | PreparedMap, stamp: float,
                cfg: PipelineConfig, state: _PairState, why: str) -> PipelineResult:
        """Run the global search; a valid result starts the pair's motion afresh."""
        result = self.global_registration(source, target, config=cfg)
        self._count_global(result, stamp, state)
        result.stats['global_because'] = why
        if result.valid:
            state.poses.clear()
            _remember(state, stamp, result)
        return result

    def _count_global(self, result: PipelineResult, stamp: float, state: _PairState) -> None:
        self._counts['global'] += 1
        self._counts['invalid'] += not result.valid
        state.tracked_since_global = 0
        state.last_global_stamp = stamp

    def _periodic_check(self, source: np.ndarray, target: np.ndarray | PreparedMap,
                        stamp: float, cfg: PipelineConfig, state: _PairState,
                        prediction: np.ndarray, kind: str) -> PipelineResult:
        """
        Run the global search on a tracked stream; it wins when it is valid.

        A valid global result that disagrees with the prediction resets the motion (the
        tracked poses may have slid into a wrong minimum); one that agrees keeps it. When
        the global search refuses (an ambiguous or degenerate view), the prediction is
        refined and gated as on any other scan.
        """
        self._counts['periodic_checks'] += 1
        result = self.global_registration(source, target, config=cfg)
        if not result.valid:
            # checked: the next check waits its interval again, even though this one refused
            state.tracked_since_global, state.last_global_stamp = 0, stamp
            with single_blas_thread():
                tracked = self._track(source, target, prediction, cfg, state)
            if tracked.valid:
                tracked.stats['global_check'] = result.reason
                return self._accept_tracked(tracked, stamp, state, kind)
            self._counts['tracking_failures'] += 1
            self._count_global(result, stamp, state)
            result.stats.update(global_because='periodic check',
                                tracking_failure=tracked.reason,
                                tracking_failure_code=tracked.refusal.code.value)
            return result
        self._count_global(result, stamp, state)
        result.stats['global_because'] = 'periodic check'
        if not agree(prediction, result.transform, cfg):
            self._counts['check_disagreements'] += 1
            result.stats['check_disagreement'] = True
            state.poses.clear()
        _remember(state, stamp, result)
        return result


def _remember(state: _PairState, stamp: float, result: PipelineResult) -> None:
    """Keep the last two valid poses of the pair (what a constant velocity needs)."""
    state.poses = state.poses[-1:] + [_Pose(stamp, result.transform.copy(), result.fitness)]


def target_key(target: np.ndarray | PreparedMap) -> tuple:
    """Identify a target by content (a latched map re-sent unchanged is the same target)."""
    if isinstance(target, PreparedMap):
        return ('map', target.path, target.digest)
    points = np.ascontiguousarray(target)
    return ('cloud', hashlib.sha256(points).digest(), points.shape, str(points.dtype))
