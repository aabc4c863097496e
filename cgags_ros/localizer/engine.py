"""
What register_node does, without ROS: pairing, the registration process, the accounting.

ROS-free: :class:`RegistrationEngine` owns the pairing of source and target clouds, the
supervised registration process (:mod:`cgags_ros.pipeline.isolated`), the accounting
(:mod:`.health`), the map of ``map.file``, the relocalization requests (:mod:`.relocalize`)
and the initial-pose guards (:mod:`.initial_pose`); in ``mode: calibrate`` the pairs are
calibration frames (:mod:`.calibration_run`); in continuous mode each scan is tracked from
the pair's last pose where registration runs (:mod:`cgags_ros.pipeline.stream`, the counts
``tracking.*``). The node decodes messages into :class:`Cloud`
for :meth:`~RegistrationEngine.receive` and implements :class:`EngineOutputs`, through
which the engine publishes, logs and asks for TF; it never reaches into the node.

Threading: :meth:`~RegistrationEngine.receive` only pairs (any thread); registration runs
on the engine's worker thread (in a child process unless ``worker.registration_timeout`` is 0),
so a slow registration never blocks reception (the pairer's bounded queue drops the
oldest pair). While inactive (:meth:`~RegistrationEngine.deactivate`, a lifecycle node's
inactive state) sources are counted as rejected (``source_inactive``) and nothing is
published; targets are still held, so a latched map survives a deactivation.
"""

from __future__ import annotations

import dataclasses
import threading
import time
import traceback
from typing import Any

import numpy as np

from .calibration_run import CalibrationConfig, CalibrationRun
from .health import LOG_REPEAT_S, lost_upstream_message, NodeHealth
from .initial_pose import extrinsic, ExtrinsicLookup, InitialPoseGuard
from .interface import BasePose, Cloud, EngineOutputs, Estimate, PairResult
from .map_target import MapTarget
from .relocalize import Answered, RelocalizeCalls, stale_scan, summary_line
from .sequence import SequenceRun, Verdict
from .startup import start_registration
from ..config.node import NodeConfig
from ..config.pipeline import PipelineConfig
from ..errors import CgagsError, InvalidInputError
from ..geometry import apply_transform
from ..pipeline import backlog
from ..pipeline.isolated import (IsolatedRegistration, RegisterFn, RegistrationTimeout,
                                 WorkerCrashed)
from ..pipeline.pairing import Pair, Pairer
from ..pipeline.result import PipelineResult
from ..pipeline.stream import StreamCounts, tracks
from ..refusal import Refusal, RefusalCode
from ..validity import quality_refusal


class RegistrationEngine:
    """
    Registers paired clouds and decides what is published (see the module doc).

    ``register_fn`` replaces the pipeline; it exists for tests of the plumbing only. The
    engine is built stopped and inactive: :meth:`start` starts the registration process,
    waits for it and the map, and starts the worker; :meth:`activate` lets sources in and
    outputs out; :meth:`stop` ends the process and the worker for good.
    """

    def __init__(self, pipeline_cfg: PipelineConfig, node_cfg: NodeConfig,
                 outputs: EngineOutputs, register_fn: RegisterFn | None = None,
                 calibration: CalibrationConfig | None = None):
        self._lock = threading.Lock()  # guards the configs and the active flag
        self._pipeline_cfg, self._node_cfg = pipeline_cfg, node_cfg
        self._outputs = outputs
        self._register_fn = register_fn
        self._register: RegisterFn | None = None
        self.registration: IsolatedRegistration | None = None  # the supervised process
        cfg = node_cfg
        # A map file is one latched target; on demand only the latest pair is kept.
        pairing = ('latest_target' if cfg.map.file else
                   'synchronized' if cfg.mode == 'calibrate' else cfg.pairing.mode)
        self._calibration = CalibrationRun.for_mode(cfg.mode, pipeline_cfg, calibration,
                                                    outputs)
        self._health = NodeHealth(Pairer.from_config(dataclasses.replace(
            cfg.pairing, mode=pairing,
            queue_depth=1 if cfg.mode == 'on_demand' else backlog.queue_depth(cfg, pipeline_cfg))))
        self._backlog = backlog.Backlog()  # a tracked stream's scans waiting (continuous)
        self.on_demand = cfg.mode == 'on_demand'
        self._map = MapTarget(cfg) if cfg.map.file else None
        self._calls = RelocalizeCalls()
        # With odometry, a relocalization goes on over the next scans (see .sequence).
        self._sequence = SequenceRun() if cfg.map.file else None
        self._initial_pose = InitialPoseGuard()
        self._candidates: list[Any] = []
        self._last_summary = ''
        self._active = False
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self._registered: PipelineResult | None = None  # the worker's pair, once registered
        self._tracking = StreamCounts()

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """
        Start registering; return once a pair can be registered (see :mod:`.startup`).

        Blocks while the registration process warms up and the map of ``map.file`` loads.

        :raises StartFailed: why it cannot register; nothing it started is left running.
        """
        self._register, self.registration, target = start_registration(
            self.pipeline_config, self.node_config, self._calibration is not None,
            self._register_fn, self._map, self._outputs.log)
        if target is not None:
            self._health.receive('target', 0, target.header.frame_id, target)
        self._worker = threading.Thread(target=self._work, name='register_worker', daemon=True)
        self._worker.start()

    def activate(self) -> None:
        """Consume sources and publish outputs."""
        with self._lock:
            self._active = True

    def deactivate(self) -> None:
        """Ignore sources (counted as rejected), publish nothing, fail pending requests."""
        with self._lock:
            self._active = False
        self._calls.wake()  # no scan is registered for a pending request until activated
        self._calls.fail(Refusal(RefusalCode.INACTIVE, 'the node was deactivated'))

    @property
    def active(self) -> bool:
        """Tell whether sources are consumed and outputs published."""
        with self._lock:
            return self._active

    def stop(self) -> None:
        """End the worker and the registration process; answer pending requests."""
        self._calls.fail(Refusal(RefusalCode.SHUTDOWN, 'the node is shutting down'))
        self.deactivate()
        self._stop.set()
        self._health.wake()
        if self.registration is not None:
            self.registration.close()  # ends a registration in flight at once
        if self._worker is not None:
            self._worker.join(timeout=5.0)

    # ------------------------------------------------------------------ configuration

    @property
    def pipeline_config(self) -> PipelineConfig:
        """Return the pipeline configuration the next pair uses."""
        with self._lock:
            return self._pipeline_cfg

    @property
    def node_config(self) -> NodeConfig:
        """Return the node configuration the next pair uses."""
        with self._lock:
            return self._node_cfg

    def set_configs(self, pipeline_cfg: PipelineConfig, node_cfg: NodeConfig) -> None:
        """Use new (validated) configurations from the next pair on."""
        with self._lock:
            self._pipeline_cfg, self._node_cfg = pipeline_cfg, node_cfg
        self._health.set_slop(node_cfg.pairing.sync_slop)
        if not self.on_demand:  # tracking switched on or off: the backlog follows
            self._health.set_queue_depth(backlog.queue_depth(node_cfg, pipeline_cfg))

    # ------------------------------------------------------------------ input

    def receive(self, role: str, stamp_ns: int, frame_id: str, cloud: Cloud | None,
                rejection: str = '', message: str = '') -> None:
        """
        Count and pair a received ``role`` ('source' or 'target') cloud.

        ``rejection`` (with a log ``message``) counts a cloud the node could not decode;
        ``stamp_ns`` is 0 when even its header could not be read.
        """
        if not rejection and role == 'source' and not self.active:
            rejection = 'source_inactive'
            message = 'source cloud ignored: the node is inactive (lifecycle)'
        lost = self._health.receive(role, stamp_ns, frame_id, cloud, rejection=rejection)
        if rejection:
            self._log_rejection(rejection, message)
            if role == 'source':
                code = (RefusalCode.INACTIVE if rejection == 'source_inactive'
                        else RefusalCode.TOO_FEW_POINTS if rejection.endswith('_empty')
                        else RefusalCode.BAD_INPUT)
                self._outputs.publish_result(PairResult(
                    stamp_ns, frame_id, 'rejected', rejection, message,
                    refusal=Refusal(code, message)))
        self._tell_dropped()
        if lost:
            self._log_lost_upstream()

    def _tell_dropped(self) -> None:
        """Publish what pairing dropped since the last call (a ~/result each)."""
        for reason, source in self._health.dropped_sources():
            why = f'dropped by pairing: {reason} (docs/pairing.md)'
            self._outputs.publish_result(PairResult(
                source.stamp_ns, source.frame_id, 'dropped', reason, why,
                refusal=Refusal(RefusalCode.UNPAIRED, why)))

    def relocalize(self, wait: bool = True, on_answer: Answered | None = None
                   ) -> tuple[bool, str]:
        """
        Request a relocalization: the next registration answers it (see :mod:`.relocalize`).

        :param wait: block until answered and return (success, message); else return
            (True, 'requested') at once and report the answer to ``on_answer``.
        """
        if not self.active:
            answer = self._calls.refuse(Refusal(RefusalCode.INACTIVE, 'the node is not active'))
            if on_answer is not None:
                on_answer(*answer)
            return answer
        timeout = self.node_config.relocalization.timeout
        req = self._calls.add(timeout, on_answer)
        if not wait:
            return True, 'requested'
        # The worker answers, or expire() does at the deadline; the margin covers a
        # registration that started just before the deadline.
        req.done.wait(timeout + 3600.0)
        return req.answer

    def odometry(self, stamp_ns: int, odom_from_base: np.ndarray) -> None:
        """Take the robot's odometry: ``odom <- base`` (4x4, metres) at ``stamp_ns``."""
        if self._sequence is not None:
            self._sequence.track.add(stamp_ns, odom_from_base)

    # ------------------------------------------------------------------ worker

    def _work(self) -> None:
        while not self._stop.is_set():
            pair = self._health.take(timeout=0.2, skip=self._skip) if self._ready() else None
            if pair is None:
                continue
            self._tell_dropped()  # the scans a backlog skipped
            cause, refusal = 'internal_error', Refusal(RefusalCode.INTERNAL_ERROR, 'pair failed')
            self._registered = None
            try:
                cause, refusal = self._process(pair)
            except Exception as exc:  # noqa: BLE001 - the worker must outlive any bad pair
                refusal = Refusal(refusal.code, f'pair failed: {exc!r}\n{traceback.format_exc()}')
            finally:
                latency = (time.monotonic_ns() - pair.source.payload.receipt_ns) * 1e-9
                self._publish_result(pair, cause, refusal)
                self._health.finish(cause, latency)
                self._settle(cause, refusal)
            if cause and refusal and not self._stop.is_set():
                self._log_rejection(cause, refusal.message)

    def _skip(self, pending_ns: list[int]) -> int:
        """Return how many of the oldest waiting pairs a tracked stream skips (the backlog)."""
        cfg, pipe_cfg = self.node_config, self.pipeline_config
        if not tracks(cfg.mode, pipe_cfg):
            return 0
        return self._backlog.to_skip(pending_ns, cfg.pairing.backlog_max_lag,
                                     pipe_cfg.tracking.max_age,
                                     self._calls.waiting() is not None)

    def _ready(self) -> bool:
        """Tell whether the worker may take a pair now; else wait a little."""
        seq = self._sequence
        late = seq.timed_out(self.node_config.relocalization.timeout) if seq else None
        if self._calls.expire(late) and seq is not None and self._calls.waiting() is None:
            seq.reset()
        if not self.active:
            self._stop.wait(0.2)
            return False
        if self.on_demand and self._calls.waiting() is None:
            self._calls.wait(0.2)
            return False
        return True

    def _process(self, pair: Pair) -> tuple[str, Refusal | None]:
        """Register and publish a pair; return ('', None) or its rejection (cause, refusal)."""
        if self._calibration is not None:
            return self._calibration.take(pair)
        source, target = pair.source.payload, pair.target.payload
        pipe_cfg, cfg = self.pipeline_config, self.node_config
        stale = stale_scan(self._calls.waiting() if self.on_demand else None,
                           source.receipt_ns, cfg.relocalization.max_scan_age)
        if stale:
            return 'on_demand_stale_scan', stale
        step = self._step(pair, cfg)
        # Continuous mode is a stream: tracked from the last pose (a ~/relocalize call, a
        # relocalization over scans and the other modes search globally); a test's
        # register_fn replaces both paths.
        stream = (step is None and tracks(cfg.mode, pipe_cfg) and self._register_fn is None
                  and self._calls.waiting() is None)
        try:
            result = self._register(source.xyz, step or target.as_target(), config=pipe_cfg,
                                    **({'stamp': pair.source.stamp_ns * 1e-9} if stream else {}))
            answer, result = (result, result.result) if step else (None, result)
        except InvalidInputError as exc:
            return 'pipeline_input', Refusal(exc.code, f'pair rejected by the pipeline: {exc}')
        except RegistrationTimeout as exc:
            return 'timeout', exc.refusal
        except WorkerCrashed as exc:
            self._health.failed('worker_crashed')
            return 'worker_crashed', exc.refusal
        except CgagsError as exc:
            return 'pipeline_error', Refusal(exc.code, f'registration failed: {exc}')
        self._registered = result
        self._tracking.add(result)
        self._backlog.saw(result, pair.source.stamp_ns)
        T = np.asarray(result.transform, dtype=np.float64)
        refusal = result.refusal or (None if np.isfinite(T).all() else Refusal(
            RefusalCode.INTERNAL_ERROR, 'the estimated transform is not finite'))
        if self._map is not None:
            self._map.update(result)
        frame = cfg.output.pose_frame_id or str(target.header.frame_id)
        self._health.registered({
            'valid': refusal is None, 'reason': refusal.message if refusal else '',
            'refusal_code': refusal.code.value if refusal else '', 'inliers': result.num_inliers,
            'fitness': float(result.fitness), 'voxel_size': pipe_cfg.voxel_size,
            'path': result.path,
            'timings': dict(result.timings), 'source_stamp_ns': pair.source.stamp_ns})
        if not self.active:
            return 'inactive', Refusal(RefusalCode.INACTIVE, 'deactivated during registration')
        cov = np.asarray(result.covariance, dtype=np.float64)
        if refusal is not None:
            if not cfg.output.publish_invalid or not np.isfinite(T).all():
                self._finish(pair, result, T, cov, cfg, frame, answer)
                return 'invalid_result', Refusal(refusal.code,
                                                 f'invalid registration: {refusal.message}')
            self._health.count('published_invalid')
        self._outputs.publish_estimate(Estimate(
            T, cov, source.header, frame,
            apply_transform(T, source.xyz) if cfg.output.publish_aligned_cloud else None,
            (cfg.output.tf_child_frame or str(source.header.frame_id))
            if cfg.output.broadcast_tf else ''))
        self._finish(pair, result, T, cov, cfg, frame, answer)
        return '', None

    # ------------------------------------------------------------------ map and requests

    def _step(self, pair: Pair, cfg: NodeConfig) -> Any:
        """Return the scan's step of a relocalization over several scans, or None."""
        seq, called = self._sequence, self._calls.waiting() is not None
        reloc = cfg.relocalization
        if seq is None or not (called or (reloc.publish_initial_pose and not self.on_demand
                                          and self._initial_pose.may_publish_auto(cfg))):
            return None
        frame = str(pair.source.payload.header.frame_id)
        base = extrinsic(cfg)
        base = self._outputs.base_from_sensor(reloc.base_frame, frame) if base is None else base
        return seq.step(pair.target.payload.as_target(), pair.source.stamp_ns, base,
                        reloc.max_scans)

    def _finish(self, pair: Pair, result: PipelineResult, T: np.ndarray, cov: np.ndarray,
                cfg: NodeConfig, frame_id: str, answer: Any = None) -> None:
        """Publish the candidates, offer the initial pose, answer pending requests."""
        header = pair.source.payload.header
        candidates = list(result.candidates)
        self._outputs.publish_candidates(header, frame_id, [
            c.transform for c in candidates if np.isfinite(c.transform).all()])
        called = self._calls.waiting() is not None
        published, why = False, 'relocalization.publish_initial_pose is off'
        refusal = quality_refusal(result, cfg)  # once: the guard and the answer share it
        reloc = cfg.relocalization
        verdict: Verdict | None = None
        if answer is not None:  # a scan of a relocalization over several scans
            verdict = self._sequence.judge(answer, refusal, reloc.max_scans)
            refusal, T = verdict.refusal, verdict.transform
        if verdict is not None and not verdict.finished:
            why = 'not confirmed yet'
        elif reloc.publish_initial_pose and (called or not self.on_demand):
            lookup: ExtrinsicLookup = self._outputs.base_from_sensor
            why, T_map_base, cov_base = self._initial_pose.offer(
                refusal, T, cov, str(header.frame_id), cfg, not called, lookup)
            if T_map_base is not None:
                published = True
                self._outputs.publish_initial_pose(BasePose(
                    T_map_base, cov_base, header, cfg.map.frame,
                    reloc.odom_frame if reloc.broadcast_map_to_odom else '', reloc.base_frame,
                    verdict.map_from_odom if verdict else None))
        line = (verdict.line(published, why) if verdict
                else summary_line(result, T, refusal, published, why))
        with self._lock:
            self._candidates, self._last_summary = candidates, line
        if called and (verdict is None or verdict.finished):
            self._calls.answer(line, refusal)

    def _publish_result(self, pair: Pair, cause: str, refusal: Refusal | None) -> None:
        """Publish what became of the worker's pair (before it is counted as done)."""
        result, source, target = self._registered, pair.source, pair.target
        valid = (result is not None and bool(result.valid)
                 and bool(np.isfinite(result.transform).all()))
        self._outputs.publish_result(PairResult(
            source.stamp_ns, source.frame_id, 'rejected' if cause else 'published', cause,
            refusal.message if refusal and cause else '', target.stamp_ns, target.frame_id,
            self.node_config.output.pose_frame_id or target.frame_id, valid, result,
            refusal if cause else None))

    def _settle(self, cause: str, refusal: Refusal | None) -> None:
        """Answer requests still pending after a pair that failed before :meth:`_finish`."""
        if (refusal and refusal.code is not RefusalCode.STALE and cause != 'invalid_result'
                and self._calls.waiting() is not None):
            self._calls.fail(refusal)
            if self._sequence is not None:
                self._sequence.reset()

    # ------------------------------------------------------------------ health

    def supervise(self) -> None:
        """Replace a registration process that died while idle (call it periodically)."""
        if self.registration is not None and self.registration.supervise():
            self._health.failed('worker_crashed')
            self._outputs.log('warning', 'the registration process had died while idle; a '
                              'fresh one was started')

    def _log_rejection(self, cause: str, message: str) -> None:
        """Log a counted rejection, once per cause and then at most every 30 s."""
        n, due = self._health.reject_count(cause)
        if due and not self._stop.is_set():
            suffix = (f' ({n} so far; repeats are logged every {LOG_REPEAT_S:.0f} s)'
                      if n > 1 else '')
            self._outputs.log('warning', message + suffix)

    def _log_lost_upstream(self) -> None:
        """Warn that source scans went missing before the node, at most every 30 s."""
        n, due = self._health.lost_upstream()
        if due:
            self._outputs.log('warning', lost_upstream_message(n))

    def snapshot(self) -> dict[str, Any]:
        """Return the counters of the accounting (see NodeHealth.snapshot)."""
        return self._health.snapshot()

    def statistics(self) -> dict[str, Any]:
        """Return the engine's keys of /diagnostics beside the accounting snapshot's."""
        with self._lock:
            candidates, line, active = list(self._candidates), self._last_summary, self._active
        stats: dict[str, Any] = {'mode': self.node_config.mode, 'active': active,
                                 **self._tracking.statistics()}
        if self._map is not None:
            stats.update(self._map.statistics())
            stats['odometry.samples'] = self._sequence.track.samples
        stats['candidates.count'] = len(candidates)
        for i, c in enumerate(candidates):
            stats[f'candidates.{i}.inliers'] = c.num_inliers
            stats[f'candidates.{i}.fitness'] = round(c.fitness, 4)
            stats[f'candidates.{i}.ratio'] = round(c.ratio, 4)
        if line:
            stats['last_summary'] = line
        stats.update(self._calibration.statistics() if self._calibration else {})
        stats.update(self._initial_pose.statistics())
        stats.update(self._calls.statistics())
        if self.registration is not None:
            stats.update(self.registration.health())
        return stats
