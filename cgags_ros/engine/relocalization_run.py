"""
The node's relocalization run: what a registered scan answers (requests, sequence, initial pose).

ROS-free. :class:`RelocalizationRun` holds the pending relocalization requests
(:mod:`cgags_ros.relocalization.service_calls`; a pose hint is one, :mod:`.pose_hint`), the
relocalization over several scans in progress (:mod:`cgags_ros.relocalization.sequence`) and
the initial-pose guards (:class:`InitialPoseGuard`). The engine asks it whether a scan is a
step of a sequence (:meth:`~RelocalizationRun.step`) and where the pending requests' hint puts
it (:meth:`~RelocalizationRun.hint`) and, once the scan is registered, hands it the result
(:meth:`~RelocalizationRun.finish`): it publishes the candidates, offers the initial pose,
answers the requests and keeps the last one-line summary for /diagnostics.

The ``initialpose`` for Nav2/AMCL is the robot base's pose, only when all the guards pass.
Quality guards (:func:`cgags_ros.validity.quality_refusal`, decided once per pair): a
valid, unambiguous estimate with at least ``relocalization.min_inliers`` inliers, a
best/runner-up candidate ratio of at least ``relocalization.min_ratio`` and a fitness of at
least ``relocalization.min_fitness``. Then ``relocalization.cooldown`` seconds since the
last publish and, for scans registered without a relocalization request, at most
``relocalization.max_auto`` publishes. Every publish and every refusal is counted,
refusals by code (``initial_pose.refused.<code>``).

The pose is the base's: ``T_map_base = T_map_sensor inv(T_base_sensor)`` with the
extrinsic from ``relocalization.base_from_sensor``, or else from the node's TF lookup
(``relocalization.base_frame`` <- the scan's frame). Its covariance is the sensor pose's
moved along the lever arm (:func:`~cgags_ros.pipeline.covariance.moved_covariance`).
"""

from __future__ import annotations

import collections
import dataclasses
import time
from typing import Any, Callable

import numpy as np

from .interface import BasePose, EngineOutputs
from .pairing import Pair
from .pose_hint import PoseHint, PoseHints
from ..config.node import NodeConfig
from ..geometry import make_transform, quaternion_to_matrix
from ..pipeline.covariance import moved_covariance
from ..pipeline.hint import Hint
from ..pipeline.result import PipelineResult
from ..refusal import Refusal, RefusalCode
from ..relocalization.sequence import SequenceRun, StepAnswer, Verdict
from ..relocalization.service_calls import Answered, ServiceCalls, summary_line
from ..validity import quality_refusal

# (base frame, sensor frame) -> T_base_sensor (4x4, metres), or None when unknown
ExtrinsicLookup = Callable[[str, str], 'np.ndarray | None']


def extrinsic(cfg: NodeConfig) -> np.ndarray | None:
    """Return ``T_base_sensor`` of ``relocalization.base_from_sensor`` (4x4, metres) or None."""
    values = cfg.relocalization.sensor_pose
    if values is None:
        return None
    return make_transform(quaternion_to_matrix(values[3:]), values[:3])


class InitialPoseGuard:
    """
    Decides whether an estimate becomes an initial pose; counts publishes and refusals.

    The engine thread alone offers estimates; :meth:`statistics` may be read from any thread: the
    counts are replaced whole, never changed in place, so no lock is needed.
    """

    def __init__(self) -> None:
        self.counts: collections.Counter[str] = collections.Counter()
        self._last_publish: float | None = None

    def offer(self, refusal: Refusal | None, T: np.ndarray, cov: np.ndarray, sensor_frame: str,
              cfg: NodeConfig, automatic: bool, lookup: ExtrinsicLookup
              ) -> tuple[str, np.ndarray | None, np.ndarray | None]:
        """
        Return the base pose of ``T`` (map <- sensor) if every guard passes.

        :param refusal: the quality guards' verdict on the estimate (None: it passed).
        :param cov: the 6x6 covariance of ``T`` (ROS order).
        :param automatic: the scan was registered without a relocalization request.
        :param lookup: the node's TF lookup of the extrinsic, for an unset
            ``relocalization.base_from_sensor``.
        :returns: (what was published or why not: the refusal as ``code: message``,
            ``T_map_base`` or None, its covariance or None); a publish is counted as done.
        """
        now = time.monotonic()
        if not refusal and self._last_publish is not None \
                and now - self._last_publish < cfg.relocalization.cooldown:
            refusal = Refusal(RefusalCode.COOLDOWN, (
                f'{now - self._last_publish:.1f} s since the last publish < '
                f'relocalization.cooldown {cfg.relocalization.cooldown:g} s'))
        if not refusal and automatic and self.counts['auto'] >= cfg.relocalization.max_auto:
            refusal = Refusal(RefusalCode.MAX_AUTO, (
                f'{self.counts["auto"]} automatic publishes = relocalization.max_auto '
                f'{cfg.relocalization.max_auto}'))
        base = None
        if not refusal:
            base = extrinsic(cfg)
            base = lookup(cfg.relocalization.base_frame, sensor_frame) if base is None else base
        if not refusal and base is None:
            refusal = Refusal(RefusalCode.NO_EXTRINSIC, (
                f'no TF {cfg.relocalization.base_frame} <- {sensor_frame} (set '
                'relocalization.base_from_sensor)'))
        counts = self.counts.copy()
        if refusal:
            counts[f'refused.{refusal.code.value}'] += 1
            self.counts = counts
            return str(refusal), None, None
        counts['published'] += 1
        counts['auto'] += automatic
        self.counts, self._last_publish = counts, now
        sensor_base = np.linalg.inv(base)
        return (f'initial pose published in {cfg.map.frame}', T @ sensor_base,
                moved_covariance(cov, T, sensor_base))

    def may_publish_auto(self, cfg: NodeConfig) -> bool:
        """Tell whether an automatic publish (no relocalization request) is still allowed."""
        return self.counts['auto'] < cfg.relocalization.max_auto

    def statistics(self) -> dict[str, int]:
        """Return ``initial_pose.*`` counters for /diagnostics."""
        return {f'initial_pose.{k}': v for k, v in sorted(self.counts.items())}


@dataclasses.dataclass(frozen=True)
class RegisteredScan:
    """
    A scan the engine registered, what :meth:`RelocalizationRun.finish` reads of it.

    :ivar result: its registration (``transform``: map <- sensor, metres).
    :ivar header: the scan's message header (its stamp is the outputs').
    :ivar sensor_frame: the scan's frame. :ivar frame_id: the frame of its pose.
    :ivar config: the node's configuration it was registered with.
    :ivar step: the relocalizer's answer when the scan was a step of a sequence, else None.
    """

    result: PipelineResult
    header: Any
    sensor_frame: str
    frame_id: str
    config: NodeConfig
    step: StepAnswer | None = None


class RelocalizationRun:
    """
    Requests, the sequence in progress and the initial pose of one node.

    The engine thread registers and finishes scans; any thread requests (:meth:`request`, the
    requests hold their own lock) and reads :meth:`statistics`. What that reads the engine thread
    alone writes, replacing it whole: no lock here.
    """

    def __init__(self, cfg: NodeConfig, outputs: EngineOutputs):
        self._outputs = outputs
        self._on_demand = cfg.mode == 'on_demand'
        self.calls = ServiceCalls()
        # With a map and odometry, a relocalization goes on over the next scans.
        self.sequence = SequenceRun() if cfg.map.file else None
        self._initial_pose = InitialPoseGuard()
        self.hints = PoseHints() if cfg.map.file else None  # hints place scans in a map
        self._shown: tuple[list[Any], str] = ([], '')  # the last candidates and summary

    def request(self, timeout_s: float, on_answer: Answered) -> None:
        """Queue a request; ``on_answer(success, message)`` once a scan answers it."""
        self.calls.add(timeout_s, on_answer)

    def receive_hint(self, stamp_ns: int, frame_id: str, pose: Any, covariance: Any,
                     cfg: NodeConfig, active: bool) -> None:
        """Make a hint's request (:meth:`.engine.RegistrationEngine.hint`), or reject it."""
        if self.hints is None:  # no map to place it in; the node subscribes only with one
            return
        held = self.hints.receive(stamp_ns, frame_id, pose, covariance, cfg.map.frame,
                                  self._outputs.lookup, self._outputs.log,
                                  '' if active else 'inactive')
        if held is not None:
            self.calls.add(cfg.relocalization.timeout, self._hint_answered, held)

    def _hint_answered(self, success: bool, message: str) -> None:
        self._outputs.log('info' if success else 'warning', f'~/hint: {message}')

    def tick(self, timeout_s: float) -> None:
        """Fail the requests past their deadline (why: the sequence in progress, if any)."""
        seq = self.sequence
        late = seq.timed_out(timeout_s) if seq else None
        if self.calls.expire(late) and seq is not None and self.calls.waiting() is None:
            seq.reset()

    def step(self, pair: Pair, cfg: NodeConfig) -> tuple[np.ndarray | None, bool] | None:
        """
        Return (odom <- sensor, restart) when the scan is a step of a sequence, else None.

        A scan is one while a request waits, or in continuous mode while an automatic
        initial pose may still go out, with a map and any odometry known (the node's).
        """
        seq, called = self.sequence, self.calls.waiting() is not None
        reloc = cfg.relocalization
        if seq is None or not (called or (reloc.publish_initial_pose and not self._on_demand
                                          and self._initial_pose.may_publish_auto(cfg))):
            return None
        known, odom_base = self._outputs.odometry(reloc.odom_frame, reloc.base_frame,
                                                  pair.source.stamp_ns)
        if not known:
            return None
        return seq.step(odom_base, self._base_from_sensor(pair, cfg))

    def hint(self, pair: Pair, cfg: NodeConfig) -> Hint | None:
        """
        Return where the pending requests' hint puts the scan's sensor (None: no hint).

        The hint is carried to the scan's stamp by the odometry, when known at both stamps,
        and to the sensor by the extrinsic (:meth:`.pose_hint.PoseHints.at_scan`).
        """
        held = self.calls.hint()
        if not isinstance(held, PoseHint) or self.hints is None:
            return None
        reloc, moved = cfg.relocalization, None
        then = self._outputs.odometry(reloc.odom_frame, reloc.base_frame, held.stamp_ns)[1]
        if then is not None and held.stamp_ns:
            now = self._outputs.odometry(reloc.odom_frame, reloc.base_frame,
                                         pair.source.stamp_ns)[1]
            moved = None if now is None else np.linalg.inv(then) @ now
        return self.hints.at_scan(held, moved, self._base_from_sensor(pair, cfg))

    def _base_from_sensor(self, pair: Pair, cfg: NodeConfig) -> np.ndarray | None:
        """Return ``T_base_sensor`` of the pair's scan (the parameter's, else TF's), or None."""
        base = extrinsic(cfg)
        if base is None:
            base = self._outputs.base_from_sensor(cfg.relocalization.base_frame,
                                                  pair.source.frame_id)
        return base

    def finish(self, scan: RegisteredScan) -> None:
        """Publish the candidates, offer the initial pose, answer pending requests."""
        result, cfg, header, answer = scan.result, scan.config, scan.header, scan.step
        T = np.asarray(result.transform, dtype=np.float64)
        candidates = list(result.candidates)
        self._outputs.publish_candidates(header, scan.frame_id, [
            c.transform for c in candidates if np.isfinite(c.transform).all()])
        called = self.calls.waiting() is not None
        published, why = False, 'relocalization.publish_initial_pose is off'
        refusal = quality_refusal(result, cfg)  # once: the guard and the answer share it
        reloc = cfg.relocalization
        verdict: Verdict | None = None
        if answer is not None:  # a scan of a relocalization over several scans
            verdict = self.sequence.judge(answer, refusal, reloc.max_scans)
            refusal, T = verdict.refusal, verdict.transform
        if verdict is not None and not verdict.finished:
            why = 'not confirmed yet'
        elif reloc.publish_initial_pose and (called or not self._on_demand):
            why, T_map_base, cov_base = self._initial_pose.offer(
                refusal, T, np.asarray(result.covariance, dtype=np.float64), scan.sensor_frame,
                cfg, not called, self._outputs.base_from_sensor)
            if T_map_base is not None:
                published = True
                self._outputs.publish_initial_pose(BasePose(
                    T_map_base, cov_base, header, cfg.map.frame,
                    reloc.odom_frame if reloc.broadcast_map_to_odom else '', reloc.base_frame,
                    verdict.map_from_odom if verdict else None))
        line = (verdict.line(published, why) if verdict
                else summary_line(result, T, refusal, published, why))
        self._shown = (candidates, line)
        if called and (verdict is None or verdict.finished):
            self.calls.answer(line, refusal)

    def settle(self, refusal: Refusal | None, registered: bool) -> None:
        """Answer requests still pending after a pair that failed before a result."""
        if (refusal and refusal.code is not RefusalCode.STALE and not registered
                and self.calls.waiting() is not None):
            self.calls.fail(refusal)
            if self.sequence is not None:
                self.sequence.reset()

    def statistics(self) -> dict[str, Any]:
        """Return the candidates, the last summary, the guards' and the requests' keys."""
        candidates, line = self._shown
        stats: dict[str, Any] = {'candidates.count': len(candidates)}
        for i, c in enumerate(candidates):
            stats[f'candidates.{i}.inliers'] = c.num_inliers
            stats[f'candidates.{i}.fitness'] = round(c.fitness, 4)
            stats[f'candidates.{i}.ratio'] = round(c.ratio, 4)
        if line:
            stats['last_summary'] = line
        stats.update(self._initial_pose.statistics())
        stats.update(self.calls.statistics())
        stats.update(self.hints.statistics() if self.hints is not None else {})
        return stats
