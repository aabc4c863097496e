"""
ROS 2 node: registers each source cloud onto a target cloud and publishes the pose.

Topics (relative names; remap them):
    source_cloud (sensor_msgs/PointCloud2, in): the cloud to align, in its sensor frame.
        Sensor-data QoS by default (``source_qos``).
    target_cloud (sensor_msgs/PointCloud2, in): the reference (map or previous scan).
        Reliable; durability ``target_durability`` ('transient_local' receives a latched
        map published before the node started, but then only matches transient-local
        publishers; 'volatile', the default, matches every publisher).
    ~/pose (geometry_msgs/PoseStamped, out): pose of the source frame in the target frame
        (``T``: ``p_target = R p_source + t``, metres), stamped with the source's stamp,
        frame_id = target frame (or ``pose_frame_id``).
    ~/pose_with_covariance (geometry_msgs/PoseWithCovarianceStamped, out): the same with
        the covariance of :func:`cgags_ros.pipeline.covariance.pose_covariance`.
    ~/aligned_cloud (sensor_msgs/PointCloud2, out, ``publish_aligned_cloud``): the source
        transformed into the target frame, for RViz.
    /diagnostics (diagnostic_msgs/DiagnosticArray, out): status, counts of received,
        published, rejected and dropped (per reason) clouds, sources lost before the node
        (``sources.lost_upstream``), last inliers, timings and latency.
    /tf (``broadcast_tf``, when tf2_ros is importable): target frame -> source frame.

Parameters: every key of PipelineConfig (``voxel_size``, ``core.*``, ``frontend.*``, ``refine.*``,
``seed``) and of NodeConfig (``pairing_mode``, ``sync_slop``...), declared with descriptions and
ranges generated from the dataclasses. Changes at run time are validated and apply to the next
pair. Note ROS parameters are typed: write ``1.0``, not ``1``, for a float.

Threading: subscription callbacks only decode the cloud (vectorized numpy) and hand it to
the :class:`~cgags_ros.pipeline.pairing.Pairer`; registration runs on one worker thread
(in a child process, :mod:`.worker`), so a slow registration never blocks reception (the
pairer's bounded queue drops the oldest pair).

Transport: :func:`main` points Fast DDS at the package's large-data profile
(:mod:`.transport`) unless the user chose one; the clouds' publisher needs it too.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import time
import traceback
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
from rcl_interfaces.msg import SetParametersResult
import rclpy
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from . import diagnostics
from .health import LOG_REPEAT_S, NodeHealth
from .localization import Localization
from .outputs import Outputs
from .parameters import descriptor
from .qos import source_qos, target_qos
from .transport import PROFILE_VARIABLE, use_large_data_profile
from .worker import (IsolatedRegistration, load_pipeline, RegisterFn, RegistrationTimeout,
                     rss_mb, WorkerCrashed)
from ..config.node import configs_from_parameters, NodeConfig, parameter_descriptions
from ..config.pipeline import PipelineConfig
from ..errors import CgagsError, EmptyCloudError, InvalidConfigError, InvalidInputError
from ..io.pointcloud2 import pointcloud2_to_xyz, stamp_to_ns
from ..pipeline.pairing import Pair, Pairer


class _Cloud:
    """A decoded cloud: points (N, 3) metres in ``header.frame_id``, receipt time."""

    __slots__ = ('xyz', 'header', 'receipt_ns')

    def __init__(self, xyz: np.ndarray, header: Any, receipt_ns: int):
        self.xyz, self.header, self.receipt_ns = xyz, header, receipt_ns


class RegisterNode(Node):
    """
    Wires topics, parameters and diagnostics around ``cgags_ros.pipeline.register_clouds``.

    ``register_fn`` replaces the pipeline; it exists for unit tests of the plumbing only.
    """

    def __init__(self, node_name: str = 'register_node', *,
                 register_fn: RegisterFn | None = None, **kwargs: Any):
        super().__init__(node_name, **kwargs)
        self._declare_parameters()
        values = {name: self.get_parameter(name).value for name in self._descriptions}
        # Invalid startup values (e.g. a choice typo) raise InvalidConfigError here.
        self._pipeline_cfg, self._node_cfg = configs_from_parameters(values)
        self._isolated: IsolatedRegistration | None = None
        if register_fn is not None:  # unit tests of the plumbing only
            self._register = register_fn
        elif self._node_cfg.registration_timeout > 0:
            self._isolated = IsolatedRegistration(self._node_cfg.registration_timeout)
            self._register = self._isolated
        else:  # import the pipeline (and Open3D) now, so the first pair is not slowed by it
            self._register = load_pipeline()
        self._lock = threading.Lock()  # guards the configs
        cfg = self._node_cfg
        # A map file is one latched target; on demand only the latest pair is kept.
        self._pairer = Pairer.from_config(dataclasses.replace(
            cfg, pairing_mode='latest_target' if cfg.map_file else cfg.pairing_mode,
            queue_depth=1 if cfg.mode == 'on_demand' else cfg.queue_depth))
        self._health = NodeHealth(self._pairer)
        self._loc = Localization(self, cfg)
        self._transport_profile = os.environ.get(PROFILE_VARIABLE, '')

        self.create_subscription(PointCloud2, 'source_cloud', self._on_source, source_qos(cfg))
        if not cfg.map_file:
            self.create_subscription(PointCloud2, 'target_cloud', self._on_target,
                                     target_qos(cfg))
        self._outputs = Outputs(self)
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._stop = threading.Event()
        self.create_timer(cfg.diagnostics_period, self._publish_diagnostics)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._worker = threading.Thread(target=self._work, name='register_worker', daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"registering source_cloud onto {cfg.map_file or 'target_cloud'} ({cfg.mode}, "
            f'{cfg.pairing_mode}, voxel_size {self._pipeline_cfg.voxel_size} m; '
            f"Fast DDS profile: {self._transport_profile or 'none'})")

    # ------------------------------------------------------------------ parameters

    def _declare_parameters(self) -> None:
        self._descriptions = parameter_descriptions()
        for name, meta in self._descriptions.items():
            self.declare_parameter(name, meta['default'], descriptor(name, meta))

    def _on_set_parameters(self, params: list[rclpy.parameter.Parameter]) -> SetParametersResult:
        changes = {p.name: p.value for p in params if p.name in self._descriptions}
        if not changes:
            return SetParametersResult(successful=True)
        with self._lock:
            try:
                pipe, node = configs_from_parameters(
                    changes, base=(self._pipeline_cfg, self._node_cfg))
            except InvalidConfigError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
            self._pipeline_cfg, self._node_cfg = pipe, node
            self._pairer.set_slop(node.sync_slop)
        self.get_logger().info(f'parameters changed (next pair): {changes}')
        return SetParametersResult(successful=True)

    @property
    def pipeline_config(self) -> PipelineConfig:
        with self._lock:
            return self._pipeline_cfg

    @property
    def node_config(self) -> NodeConfig:
        with self._lock:
            return self._node_cfg

    # ------------------------------------------------------------------ input

    def _receive(self, msg: PointCloud2, role: str) -> None:
        receipt = time.monotonic_ns()
        with self._lock:
            max_points = self._node_cfg.max_cloud_points
        stamp = 0
        try:
            stamp = stamp_to_ns(msg.header.stamp)
            cloud = _Cloud(pointcloud2_to_xyz(msg, max_points=max_points), msg.header, receipt)
        except InvalidInputError as exc:
            cause = f"{role}_{'empty' if isinstance(exc, EmptyCloudError) else 'malformed'}"
            lost = self._health.receive(role, stamp, '', None, rejection=cause)
            self._log_rejection(cause, f'{role} cloud rejected: {exc}')
        else:
            lost = self._health.receive(role, stamp, str(msg.header.frame_id), cloud)
        if lost:
            self._log_lost_upstream()

    def _on_source(self, msg: PointCloud2) -> None:
        self._receive(msg, 'source')

    def _on_target(self, msg: PointCloud2) -> None:
        self._receive(msg, 'target')

    # ------------------------------------------------------------------ worker

    def _work(self) -> None:
        if self._loc.map_ref is not None and self._loc.load_map(
                self._register, self.pipeline_config, self.node_config):
            header = Header(frame_id=self.node_config.map_frame)
            self._health.receive('target', 0, header.frame_id,
                                 _Cloud(self._loc.map_ref, header, time.monotonic_ns()))
        while not self._stop.is_set():
            pair = self._health.take(timeout=0.2) if self._loc.ready() else None
            if pair is None:
                continue
            cause, message = 'internal_error', ''
            try:
                cause, message = self._process(pair)
            except Exception as exc:  # noqa: BLE001 - the worker must outlive any bad pair
                message = f'pair failed: {exc!r}\n{traceback.format_exc()}'
            finally:
                latency = (time.monotonic_ns() - pair.source.payload.receipt_ns) * 1e-9
                self._health.finish(cause, latency)
                self._loc.settle(cause, message)
            if cause and not self._stop.is_set() and self.context.ok():
                self._log_rejection(cause, message)

    def _process(self, pair: Pair) -> tuple[str, str]:
        """Register and publish a pair; return ('', '') or its rejection (cause, message)."""
        source, target = pair.source.payload, pair.target.payload
        with self._lock:
            pipe_cfg, cfg = self._pipeline_cfg, self._node_cfg
        stale = self._loc.stale(pair, cfg)
        if stale:
            return 'on_demand_stale_scan', stale
        try:
            result = self._register(source.xyz, target.xyz, config=pipe_cfg)
        except InvalidInputError as exc:
            return 'pipeline_input', f'pair rejected by the pipeline: {exc}'
        except RegistrationTimeout as exc:
            return 'timeout', str(exc)
        except WorkerCrashed as exc:
            self._health.failing = 'worker_crashed'
            return 'worker_crashed', str(exc)
        except CgagsError as exc:
            return 'pipeline_error', f'registration failed: {exc}'
        T = np.asarray(result.transform, dtype=np.float64)
        valid = bool(result.valid) and np.isfinite(T).all()
        self._loc.update_map_info(result)
        frame = cfg.pose_frame_id or target.header.frame_id
        with self._health.lock:
            self._health.failing = ''
            self._health.last = {
                'valid': valid, 'reason': str(result.reason),
                'inliers': int(result.num_inliers), 'fitness': float(result.fitness),
                'voxel_size': pipe_cfg.voxel_size, 'timings': dict(result.timings),
                'source_stamp_ns': pair.source.stamp_ns}
        if not valid:
            if not cfg.publish_invalid or not np.isfinite(T).all():
                self._loc.finish(pair, result, T, None, cfg, frame)
                return 'invalid_result', f'invalid registration: {result.reason}'
            with self._health.lock:
                self._health.counts['published_invalid'] += 1
        cov = self._publish(pair, T, result, pipe_cfg, cfg, frame)
        self._loc.finish(pair, result, T, cov, cfg, frame)
        return '', ''

    def _publish(self, pair: Pair, T: np.ndarray, result: Any, pipe_cfg: PipelineConfig,
                 cfg: NodeConfig, frame: str | None = None) -> np.ndarray:
        frame = frame or cfg.pose_frame_id or pair.target.payload.header.frame_id
        return self._outputs.publish(pair, T, result, pipe_cfg, cfg, frame)

    # ------------------------------------------------------------------ health

    def _log_rejection(self, cause: str, message: str) -> None:
        """Log a counted rejection, once per cause and then at most every 30 s."""
        n, due = self._health.reject_count(cause)
        if due:
            suffix = (f' ({n} so far; repeats are logged every {LOG_REPEAT_S:.0f} s)'
                      if n > 1 else '')
            self.get_logger().warning(message + suffix)

    def _log_lost_upstream(self) -> None:
        """Warn that source scans went missing before the node, at most every 30 s."""
        n, due = self._health.lost_upstream()
        if due:
            self.get_logger().warning(diagnostics.lost_upstream_message(n))

    def statistics(self) -> dict[str, Any]:
        """Return a flat snapshot of the node's counters (what /diagnostics carries)."""
        with self._lock:
            voxel = self._pipeline_cfg.voxel_size
        extra = {'memory.node_rss_mb': round(rss_mb() or 0.0, 1),
                 'transport.profile': self._transport_profile,
                 **self._loc.statistics(self.node_config.mode)}
        if self._isolated is not None:
            extra.update(self._isolated.health())
        return diagnostics.build_statistics(self._health.snapshot(), voxel, extra)

    def _publish_diagnostics(self) -> None:
        if self._stop.is_set():
            # destroy_node has begun: an executor spinning on another thread may still
            # dispatch this timer, and the node's handle is about to go (InvalidHandle).
            return
        if self._isolated is not None and self._isolated.supervise():
            self._health.failing = 'worker_crashed'
            self.get_logger().warning('the registration process had died while idle; '
                                      'a fresh one was started')
        msg = diagnostics.diagnostic_array(
            self.statistics(), f'{self.get_name()}: registration',
            self.get_fully_qualified_name(), self.get_clock().now().to_msg())
        self._send(self._diag_pub, msg)

    def _send(self, publisher: Any, msg: Any) -> None:
        """
        Publish unless the context has been shut down (Ctrl-C / SIGTERM).

        rclpy's signal handler shuts the context down asynchronously: the executor may
        still dispatch the diagnostics timer, and the worker may still be finishing a
        pair. A publish then raises RCLError ("publisher's context is invalid"), which
        from a timer callback would escape rclpy.spin() and end the node with exit 1.
        Errors while the context is still valid are re-raised.
        """
        if not self.context.ok():
            return
        try:
            publisher.publish(msg)
        except RuntimeError:  # rclpy's RCLError derives from RuntimeError
            if self.context.ok():
                raise

    # ------------------------------------------------------------------ shutdown

    def destroy_node(self) -> None:
        self._stop.set()
        self._pairer.wake()
        if self._isolated is not None:
            self._isolated.close()  # ends a registration in flight at once
        self._worker.join(timeout=5.0)
        self._loc.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    """
    Spin the node until Ctrl-C or SIGTERM, then shut down cleanly.

    The ``register_node`` entry point (``ros2 run``, ``python -m cgags_ros.register_node``).
    """
    from rclpy.executors import ExternalShutdownException
    use_large_data_profile()
    rclpy.init(args=args)
    node = None
    try:
        node = RegisterNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except InvalidConfigError as exc:  # e.g. a pairing_mode typo in the YAML
        rclpy.logging.get_logger('register_node').fatal(str(exc))
        raise SystemExit(2) from None
    except RuntimeError:  # an rclpy call racing the signal handler's shutdown
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
