"""
What register_node does, without ROS: pairs in, one job a pair, what to publish out.

ROS-free. :class:`RegistrationEngine` owns the accounting (:mod:`.accounting`: pairing,
upstream losses, the backlog, the counts, under one lock), what runs the jobs (a
:class:`~cgags_ros.runtime.jobs.Runner`: the registration process, or this process), the
lane of a tracked stream's periodic checks (:class:`~cgags_ros.runtime.checks.CheckLane`),
the map of ``map.file`` and what a pose means for localization (:mod:`.relocalization_run`); in
``mode: calibrate`` the pairs are calibration frames (:mod:`.calibration_run`). The node
decodes messages into :class:`Cloud` for :meth:`~RegistrationEngine.receive` and
implements :class:`EngineOutputs`, through which the engine publishes, logs and asks for
TF; it never reaches into the node.

The engine thread takes each pair, chooses its job once (:meth:`~RegistrationEngine._job`: a
scan of a relocalization over several scans, a tracked stream's scan, or a pair), runs it
in the registration process (in this process when ``runtime.registration_timeout`` is 0)
and publishes what its typed answer says. Configuration alone decides the kind (continuous
mode with ``tracking.enabled`` is a stream) and where a stream's periodic checks run (in a
lane of their own when ``runtime.registration_timeout`` > 0). Reception never waits for it:
the accounting's bounded queue drops the oldest pair. While inactive (a lifecycle node's
inactive state) sources are counted as rejected (``inactive``) and nothing is published;
targets are still held, so a latched map survives a deactivation.
"""

from __future__ import annotations

import dataclasses
import threading
import time
import traceback
from typing import Any

import numpy as np

from .accounting import Accounting, LastRegistration, LOG_REPEAT_S, lost_upstream_message
from .calibration_run import CalibrationConfig, CalibrationRun
from .interface import Cloud, EngineOutputs, Estimate, PairResult
from .map_target import MapTarget
from .pairing import Backlog, Pair, queue_depth
from .relocalization_run import RegisteredScan, RelocalizationRun
from .startup import start_registration
from ..config.node import NodeConfig
from ..config.pipeline import PipelineConfig
from ..errors import CgagsError
from ..geometry import apply_transform
from ..pipeline.result import PipelineResult
from ..refusal import Refusal, RefusalCode
from ..relocalization.sequence import StepAnswer
from ..relocalization.service_calls import Answered, stale_scan
from ..runtime.checks import CheckLane
from ..runtime.jobs import (CheckVerdict, Job, RegisterPair, result_of, Runner, SequenceScan,
                            StreamCounts, Tracked, tracks, TrackScan)


@dataclasses.dataclass(frozen=True)
class Outcome:
    """What became of a pair: why it is rejected (None: published), its result."""

    refusal: Refusal | None
    result: PipelineResult | None = None


class RegistrationEngine:
    """
    Registers paired clouds and decides what is published (see the module doc).

    The engine is built stopped and inactive: :meth:`start` starts the registration process,
    waits for it and the map, and starts the engine thread; :meth:`activate` lets sources in and
    outputs out; :meth:`stop` ends the processes and the engine thread for good. ``runner`` runs
    the jobs instead of what :meth:`start` would start (a test's stand-in, for the plumbing:
    the job kinds are chosen as without it); it stays the caller's, never closed here.

    Two threads: the node's executor calls every method but the engine thread's loop, which runs
    on the engine thread. The executor alone writes the configurations (replaced whole, one
    pair) and the active flag, which the engine thread reads: no lock. The one event between them
    stops the engine thread; the accounting, the requests and the registration process, which
    both threads write, hold a lock each.
    """

    def __init__(self, pipeline_cfg: PipelineConfig, node_cfg: NodeConfig,
                 outputs: EngineOutputs, calibration: CalibrationConfig | None = None,
                 runner: Runner | None = None):
        self._configs = (pipeline_cfg, node_cfg)
        self._outputs = outputs
        self._given = runner
        self.runner: Runner | None = None  # runs the stream's jobs, once started
        self.checks: CheckLane | None = None  # the periodic checks' lane, while tracked
        self._verdict: CheckVerdict | None = None  # a check landed, for the next scan
        cfg = node_cfg
        # A map file is one latched target; on demand only the latest pair is kept.
        pairing = ('latest_target' if cfg.map.file else
                   'synchronized' if cfg.mode == 'calibrate' else cfg.pairing.mode)
        self._calibration = CalibrationRun.for_mode(cfg.mode, pipeline_cfg, calibration,
                                                    outputs)
        self._accounting = Accounting(
            dataclasses.replace(cfg.pairing, mode=pairing),
            1 if cfg.mode == 'on_demand' else queue_depth(cfg, pipeline_cfg))
        self.on_demand = cfg.mode == 'on_demand'
        self._map = MapTarget(cfg) if cfg.map.file else None
        self._relocalization = RelocalizationRun(cfg, outputs)
        self._active = False
        # Set by the lifecycle's thread, waited on by the engine thread.
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._work, name='engine', daemon=True)
        self._tracking = StreamCounts()

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """
        Start registering; return once a pair can be registered (see :mod:`.startup`).

        Blocks while the registration process warms up and the map of ``map.file`` loads.

        :raises StartFailed: why it cannot register; nothing it started is left running.
        """
        self.runner, target = start_registration(
            self.pipeline_config, self.node_config, self._calibration is not None, self._map,
            self._outputs.log, self._given)
        if target is not None:
            self._accounting.receive('target', 0, target.frame_id, target)
        self._thread.start()

    def activate(self) -> None:
        """Consume sources and publish outputs."""
        self._active = True

    def deactivate(self) -> None:
        """Ignore sources (counted as rejected), publish nothing, fail pending requests."""
        self._active = False
        calls = self._relocalization.calls
        calls.wake()  # no scan is registered for a pending request until activated
        calls.fail(Refusal(RefusalCode.INACTIVE, 'the node was deactivated'))

    @property
    def active(self) -> bool:
        """Tell whether sources are consumed and outputs published."""
        return self._active

    def stop(self) -> None:
        """End the engine thread and the registration processes; answer pending requests."""
        self._relocalization.calls.fail(Refusal(RefusalCode.SHUTDOWN, 'the node is shutting down'))
        self.deactivate()
        self._stop.set()
        self._accounting.wake()
        if self.runner is not None and self._given is None:
            self.runner.close()  # ends a job in flight in a process of its own at once
        if self._thread.ident is not None:  # started
            self._thread.join(timeout=5.0)
        if self.checks is not None:  # after the engine thread, which may have just started it
            self.checks.close()

    # ------------------------------------------------------------------ configuration

    @property
    def pipeline_config(self) -> PipelineConfig:
        """Return the pipeline configuration the next pair uses."""
        return self._configs[0]

    @property
    def node_config(self) -> NodeConfig:
        """Return the node configuration the next pair uses."""
        return self._configs[1]

    def set_configs(self, pipeline_cfg: PipelineConfig, node_cfg: NodeConfig) -> None:
        """Use new (validated) configurations from the next pair on."""
        self._configs = (pipeline_cfg, node_cfg)
        self._accounting.set_slop(node_cfg.pairing.sync_slop)
        if not self.on_demand:  # tracking switched on or off: the backlog follows
            self._accounting.set_queue_depth(queue_depth(node_cfg, pipeline_cfg))

    # ------------------------------------------------------------------ input

    def receive(self, role: str, stamp_ns: int, frame_id: str, cloud: Cloud | None,
                rejection: Refusal | None = None) -> None:
        """
        Count and pair a received ``role`` ('source' or 'target') cloud.

        ``rejection`` counts a cloud the node could not decode (its code and why);
        ``stamp_ns`` is 0 when even its header could not be read.
        """
        if rejection is None and role == 'source' and not self.active:
            rejection = Refusal(RefusalCode.INACTIVE,
                                'source cloud ignored: the node is inactive (lifecycle)')
        lost = self._accounting.receive(role, stamp_ns, frame_id, cloud, rejection)
        if rejection is not None:
            self._log_rejection(rejection, role)
            if role == 'source':
                self._outputs.publish_result(PairResult(stamp_ns, frame_id, 'rejected',
                                                        refusal=rejection))
        self._tell_dropped()
        if lost:
            n, due = self._accounting.lost_upstream()
            if due:
                self._outputs.log('warning', lost_upstream_message(n))

    def _tell_dropped(self) -> None:
        """Publish what pairing dropped since the last call (a ~/result each)."""
        for reason, source in self._accounting.dropped_sources():
            why = f'dropped by pairing: {reason} (docs/pairing.md)'
            self._outputs.publish_result(PairResult(
                source.stamp_ns, source.frame_id, 'dropped', reason,
                refusal=Refusal(RefusalCode.UNPAIRED, why)))

    def relocalize(self, on_answer: Answered) -> None:
        """
        Request a relocalization: the next registration answers it.

        The answer goes to ``on_answer(success, message)``, from the engine thread, or at
        once when inactive (:mod:`cgags_ros.relocalization.service_calls`).
        """
        if not self.active:
            on_answer(*self._relocalization.calls.refuse(
                Refusal(RefusalCode.INACTIVE, 'the node is not active')))
            return
        self._relocalization.request(self.node_config.relocalization.timeout, on_answer)

    def hint(self, stamp_ns: int, frame_id: str, pose: Any, covariance: Any) -> None:
        """
        Take a pose hint, a relocalization request searched where it says (:mod:`.pose_hint`).

        ``pose``: [x y z qx qy qz qw], the base in ``frame_id`` (m); ``covariance``: 36 values.
        """
        self._relocalization.receive_hint(stamp_ns, frame_id, pose, covariance,
                                          self.node_config, self.active)

    # ------------------------------------------------------------- engine thread

    def _work(self) -> None:
        while not self._stop.is_set():
            self._collect_check()
            pair = self._accounting.take(0.1, self._skip) if self._ready() else None
            if pair is None:
                continue
            self._tell_dropped()  # the scans a backlog skipped
            outcome = Outcome(Refusal(RefusalCode.INTERNAL_ERROR, 'pair failed'))
            try:
                outcome = self._process(pair)
            except Exception as exc:  # noqa: BLE001 - the engine thread must outlive any bad pair
                outcome = Outcome(Refusal(RefusalCode.INTERNAL_ERROR,
                                          f'pair failed: {exc!r}\n{traceback.format_exc()}'))
            finally:
                latency = (time.monotonic_ns() - pair.source.payload.receipt_ns) * 1e-9
                self._publish_result(pair, outcome, latency)
                self._accounting.finish(outcome.refusal, latency)
                self._relocalization.settle(outcome.refusal, outcome.result is not None)
            if outcome.refusal is not None and not self._stop.is_set():
                self._log_rejection(outcome.refusal, 'source')

    def _skip(self, pending_ns: list[int], log: Backlog) -> int:
        """Return how many of the oldest waiting pairs a tracked stream skips (the backlog)."""
        pipe_cfg, cfg = self._configs
        if not tracks(cfg.mode, pipe_cfg):
            return 0
        return log.to_skip(pending_ns, cfg.pairing.backlog_max_lag, pipe_cfg.tracking.max_age,
                           self._relocalization.calls.waiting() is not None)

    def _ready(self) -> bool:
        """Tell whether the engine thread may take a pair now; else wait a little."""
        self._relocalization.tick(self.node_config.relocalization.timeout)
        if not self.active:
            self._stop.wait(0.1)
            return False
        if self.on_demand and self._relocalization.calls.waiting() is None:
            self._relocalization.calls.wait(0.1)
            return False
        return True

    def _job(self, pair: Pair, cfg: NodeConfig, pipe_cfg: PipelineConfig) -> Job:
        """Choose the pair's job, once: a sequence's scan, a tracked stream's scan, or a pair."""
        source, target = pair.source.payload.xyz, pair.target.payload.as_target()
        step = self._relocalization.step(pair, cfg)
        hint = self._relocalization.hint(pair, cfg)  # a hint is a request: never tracked
        if step is not None:
            return SequenceScan(source, target, pipe_cfg, step[0],
                                cfg.relocalization.max_scans, step[1], hint)
        # A ~/relocalize call is answered from a global search, as the other modes are.
        if tracks(cfg.mode, pipe_cfg) and self._relocalization.calls.waiting() is None:
            verdict, self._verdict = self._verdict, None
            return TrackScan(source, target, pipe_cfg, pair.source.stamp_ns * 1e-9,
                             checks_beside=cfg.runtime.registration_timeout > 0, verdict=verdict)
        return RegisterPair(source, target, pipe_cfg, hint)

    def _process(self, pair: Pair) -> Outcome:
        """Register and publish a pair; return what became of it."""
        if self._calibration is not None:
            return Outcome(self._calibration.take(pair))
        source = pair.source.payload
        pipe_cfg, cfg = self._configs  # one pair of configurations for the whole pair
        stale = stale_scan(self._relocalization.calls.waiting() if self.on_demand else None,
                           source.receipt_ns, cfg.relocalization.max_scan_age)
        if stale:
            return Outcome(stale)
        job, runner = self._job(pair, cfg, pipe_cfg), self.runner
        assert runner is not None  # the engine thread runs once started
        try:
            answer = runner.run(job)
        except CgagsError as exc:
            if exc.code is RefusalCode.PROCESS_CRASHED:
                self._accounting.failed(exc.code.value)
            return Outcome(Refusal(exc.code, f'registration failed: {exc}'))
        result = result_of(answer)
        if isinstance(answer, Tracked):
            self._tracking.add(answer.counts)
            if answer.check_due and isinstance(job, TrackScan):
                self._offer_check(job)
        T = np.asarray(result.transform, dtype=np.float64)
        refusal = result.refusal or (None if np.isfinite(T).all() else Refusal(
            RefusalCode.INTERNAL_ERROR, 'the estimated transform is not finite'))
        if self._map is not None:
            self._map.update(result)
        frame = cfg.output.pose_frame_id or pair.target.frame_id
        self._accounting.registered(LastRegistration.of(result, refusal, pipe_cfg.voxel_size,
                                                        pair.source.stamp_ns))
        if not self.active:
            return Outcome(Refusal(RefusalCode.INACTIVE, 'deactivated during registration'),
                           result)
        scan = RegisteredScan(result, source.header, pair.source.frame_id, frame, cfg,
                              answer if isinstance(answer, StepAnswer) else None)
        if refusal is not None:
            if not cfg.output.publish_invalid or not np.isfinite(T).all():
                self._relocalization.finish(scan)
                return Outcome(Refusal(refusal.code, f'invalid registration: {refusal.message}'),
                               result)
            self._accounting.count('published_invalid')
        out = cfg.output
        self._outputs.publish_estimate(Estimate(
            T, np.asarray(result.covariance, dtype=np.float64), source.header, frame,
            apply_transform(T, source.xyz) if out.publish_aligned_cloud else None,
            (out.tf_child_frame or pair.source.frame_id) if out.broadcast_tf else ''))
        self._relocalization.finish(scan)
        return Outcome(None, result)

    # ------------------------------------------------------------------ the second lane

    def _offer_check(self, job: TrackScan) -> None:
        """Run the periodic check of a tracked scan in the checks' lane (started once)."""
        if self._stop.is_set():
            return
        if self.checks is None:
            self.checks = CheckLane(self.node_config.runtime.registration_timeout)
            if self._map is not None:  # loaded there once the lane is warm, before a check
                self.checks.prepare_map(self._map.ref, job.config,
                                        self.node_config.map.load_timeout)
        self.checks.offer(job.source, job.target, job.config, job.stamp)

    def _collect_check(self) -> None:
        """Keep a check that landed for the stream's next scan."""
        if self.checks is not None:
            verdict = self.checks.landed()
            if verdict is not None:
                self._verdict = verdict

    # ------------------------------------------------------------------ results and health

    def _publish_result(self, pair: Pair, outcome: Outcome, latency_s: float) -> None:
        """Publish what became of the engine thread's pair (before it is counted as done)."""
        source, target, result = pair.source, pair.target, outcome.result
        valid = (result is not None and bool(result.valid)
                 and bool(np.isfinite(result.transform).all()))
        self._outputs.publish_result(PairResult(
            source.stamp_ns, source.frame_id, 'rejected' if outcome.refusal else 'published',
            '', target.stamp_ns, target.frame_id,
            self.node_config.output.pose_frame_id or target.frame_id, valid, result,
            outcome.refusal, round(latency_s, 4)))

    def supervise(self) -> None:
        """Replace a registration process that died while idle (call it periodically)."""
        if self.runner is not None and self.runner.supervise():
            self._accounting.failed(RefusalCode.PROCESS_CRASHED.value)
            self._outputs.log('warning', 'the registration process had died while idle; a '
                              'fresh one was started')
        if self.checks is not None:
            self.checks.supervisor.supervise()

    def _log_rejection(self, refusal: Refusal, role: str) -> None:
        """Log a counted rejection, once per role and code, then at most every 30 s."""
        n, due = self._accounting.log_due(role, refusal.code.value)
        if due and not self._stop.is_set():
            suffix = (f' ({n} so far; repeats are logged every {LOG_REPEAT_S:.0f} s)'
                      if n > 1 else '')
            self._outputs.log('warning', refusal.message + suffix)

    def snapshot(self) -> dict[str, Any]:
        """Return the counters of the accounting (see Accounting.snapshot)."""
        return self._accounting.snapshot()

    def statistics(self) -> dict[str, Any]:
        """Return the engine's keys of /diagnostics beside the accounting snapshot's."""
        stats: dict[str, Any] = {'mode': self.node_config.mode, 'active': self.active,
                                 **self._tracking.statistics()}
        if self._map is not None:
            stats.update(self._map.statistics())
        stats.update(self._relocalization.statistics())
        stats.update(self._calibration.statistics() if self._calibration else {})
        if self.runner is not None:
            stats.update(self.runner.health())
        if self.checks is not None:
            stats.update(self.checks.statistics())
        return stats
