"""
ROS 2 lifecycle node: registers each source cloud onto a target cloud and publishes the pose.

A managed node (``rclpy.lifecycle``): configure reads the parameters, starts the registration
process, waits (bounded) for its warm-up and the map load (:mod:`cgags_ros.engine.startup`)
and creates the topics and services; a failure is logged, reported once on /diagnostics and
leaves the node unconfigured with nothing running. Activate consumes sources and publishes;
deactivate ignores sources (``rejected.source_inactive``) and publishes no pose; cleanup ends
the registration process; shutdown does what cleanup does. With ``autostart`` (default) the
node configures and activates itself, so ``ros2 run cgags_ros register_node`` works alone
(unconfigured, still running, if configure fails); under ``nav2_lifecycle_manager`` set it
false. The bond that manager expects is formed with ``bondpy`` when it is importable;
otherwise set the manager's ``bond_timeout: 0.0`` (docs/lifecycle.md).

Topics (relative names; remap them):
    source_cloud (sensor_msgs/PointCloud2, in): the cloud to align, in its sensor frame.
        Sensor-data QoS by default (``pairing.source_qos``).
    target_cloud (sensor_msgs/PointCloud2, in): the reference (map or previous scan).
        Reliable; durability ``pairing.target_durability``. Not subscribed with ``map.file``.
    odom (nav_msgs/Odometry, in, with ``map.file``; else TF odom -> base): relocalization
        over the next scans (:mod:`cgags_ros.relocalization.sequence`).
    ~/hint (geometry_msgs/PoseWithCovarianceStamped, in, with ``map.file``): where the base
        roughly is, a relocalization request searched there (:mod:`cgags_ros.engine.pose_hint`);
        not ``initialpose``, which the node publishes.
    ~/pose (geometry_msgs/PoseStamped, out): pose of the source frame in the target frame
        (``T``: ``p_target = R p_source + t``, metres), stamped with the source's stamp,
        frame_id = target frame (or ``output.pose_frame_id``).
    ~/pose_with_covariance (geometry_msgs/PoseWithCovarianceStamped, out): the same with
        the pipeline result's covariance.
    ~/aligned_cloud (sensor_msgs/PointCloud2, out, ``output.publish_aligned_cloud``).
    ~/candidates (geometry_msgs/PoseArray, out): ranked candidate poses, best first.
    ~/result (std_msgs/String, out, JSON; reliable): what became of each source (published,
        rejected or dropped, and why) with its registration's result as ``cgags-register
        --json`` prints it (:class:`~cgags_ros.engine.interface.PairResult`), also while
        inactive.
    initialpose (geometry_msgs/PoseWithCovarianceStamped, out,
        ``relocalization.publish_initial_pose``):
        the guarded base pose for Nav2/AMCL (:mod:`cgags_ros.engine.relocalization_run`).
    /diagnostics (diagnostic_msgs/DiagnosticArray, out): status and counters
        (:mod:`.diagnostics`), also while inactive.
    /tf (``output.broadcast_tf``, when tf2_ros is importable): target frame -> source frame.
    ``mode: calibrate`` publishes instead, once, latched: ~/calibration
    (geometry_msgs/PoseWithCovarianceStamped: child = source sensor in parent = target
    frame), ~/calibration_report (std_msgs/String, JSON) and /tf_static parent -> child;
    a FAIL publishes no pose: /diagnostics ERROR (docs/calibration.md).

Services (served by this node, on their own reentrant callback group: a call awaiting its
answer keeps its group until then, and other calls and the topics go on beside it):
    ~/relocalize (std_srvs/Trigger): relocalize with the next registration (in
        ``mode: on_demand`` the only thing that makes the node register); answers success
        and a one-line summary. The callback is a coroutine: while it awaits the engine's
        answer it holds no executor thread.
    reinitialize_global_localization (std_srvs/Empty, relative name, as Nav2 calls it):
        the same request, answered at once; its outcome is logged and, with
        ``relocalization.publish_initial_pose``, published on initialpose.

Parameters: the configuration keys declared ``ros=True`` (:mod:`cgags_ros.config.node`:
voxel_size, mode, pairing.*, map.*, relocalization.*, output.*, frontend.*/core.*; vectors
as arrays), under their own names, with descriptions and ranges from the config dataclasses.
``config_file`` (read first) may set any key; its values become the declared defaults, so a
ROS parameter given to the node (params file, ``-p``) overrides it. Changes at run time are
validated and apply to the next pair; a name that is no ROS parameter is refused.
The node only wires: :class:`~cgags_ros.engine.engine.RegistrationEngine` decides,
:class:`~.outputs.Outputs` publishes.

Transport: :func:`main` points Fast DDS at the package's large-data profile
(:mod:`cgags_ros.engine.transport`) unless the user chose one; the clouds' publisher needs
it too.
"""

from __future__ import annotations

import contextlib
import functools
import os
import time
from typing import Any

from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
import rclpy
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.qos import qos_profile_sensor_data
from rclpy.task import Future
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Empty, Trigger

from .bond import start_bond
from .outputs import Outputs
from .parameters import descriptor, not_a_parameter
from .qos import source_qos, target_qos
from ..config import fields
from ..config.node import (calibration_config, configs_from_file, configs_from_parameters,
                           NodeConfig, ros_parameter_descriptions,
                           ros_value)
from ..config.pipeline import PipelineConfig
from ..engine import statistics
from ..engine.engine import RegistrationEngine
from ..engine.interface import Cloud
from ..engine.transport import PROFILE_VARIABLE, use_large_data_profile
from ..errors import CgagsError, InvalidConfigError, InvalidInputError
from ..io.pointcloud2 import pointcloud2_to_xyz, pose_to_transform, stamp_to_ns
from ..refusal import Refusal
from ..runtime.jobs import Runner
from ..runtime.procfs import rss_mb

SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE
# How the node destroys what configure created (so that it leaves the node's lists too).
_DESTROY = {'Subscription': LifecycleNode.destroy_subscription,
            'Timer': LifecycleNode.destroy_timer, 'Service': LifecycleNode.destroy_service}


class RegisterNode(LifecycleNode):
    """
    Wires topics, services, parameters and diagnostics around a :class:`RegistrationEngine`.

    ``runner`` runs the jobs instead of a registration process (a test's stand-in, for the
    plumbing). Invalid parameters at construction raise :class:`InvalidConfigError`.
    """

    def __init__(self, node_name: str = 'register_node', *, runner: Runner | None = None,
                 **kwargs: Any):
        # Undeclared names reach _on_set_parameters, which refuses them with a reason.
        kwargs.setdefault('allow_undeclared_parameters', True)
        super().__init__(node_name, **kwargs)
        self._descriptions = ros_parameter_descriptions()
        self._declare_parameters()
        _, cfg = self._configs()  # invalid startup values (a choice typo) raise here
        self._runner = runner
        self._engine: RegistrationEngine | None = None
        self.outputs: Outputs | None = None
        self._entities: list[Any] = []
        self._service_group = ReentrantCallbackGroup()
        self._bond: Any = None
        self._transport_profile = os.environ.get(PROFILE_VARIABLE, '')
        self.add_on_set_parameters_callback(self._on_set_parameters)
        if cfg.autostart and self.trigger_configure() == SUCCESS:
            self.trigger_activate()

    @property
    def engine(self) -> RegistrationEngine | None:
        """Return the registration object (None while unconfigured)."""
        return self._engine

    # ------------------------------------------------------------------ lifecycle

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Read the parameters, start registering (waits for it), create topics and services."""
        try:
            pipe, cfg = self._configs()
            calibration = (calibration_config(pipe, cfg.config_file)
                           if cfg.mode == 'calibrate' else None)
            self.outputs = Outputs(self, calibrate=calibration is not None,
                                   odometry=bool(cfg.map.file))
            self._engine = RegistrationEngine(pipe, cfg, self.outputs, calibration,
                                              self._runner)
            self._engine.start()  # returns once the process is warm and the map loaded
        except CgagsError as exc:  # a parameter, the registration process or the map
            self.get_logger().error(f'cannot configure: {exc}; the node stays unconfigured')
            if self.outputs is not None:
                self.outputs.publish_configure_failure(self.statistics(), exc.refusal)
            self._teardown()
            return FAILURE
        self._entities = [
            self.create_subscription(PointCloud2, 'source_cloud', functools.partial(
                self._receive, role='source'), source_qos(cfg)),
            self.create_timer(cfg.output.diagnostics_period, self._publish_diagnostics),
            self.create_service(Trigger, '~/relocalize', self._on_relocalize,
                                callback_group=self._service_group),
            self.create_service(Empty, 'reinitialize_global_localization',
                                self._on_reinitialize, callback_group=self._service_group)]
        if not cfg.map.file:
            self._entities.append(self.create_subscription(
                PointCloud2, 'target_cloud', functools.partial(self._receive, role='target'),
                target_qos(cfg)))
        else:  # a map: odometry carries a relocalization over scans; a hint says where
            self._entities += [self.create_subscription(
                Odometry, 'odom', self._on_odometry, qos_profile_sensor_data),
                self.create_subscription(PoseWithCovarianceStamped, '~/hint', self._on_hint, 10)]
        self.get_logger().info(
            f"registering source_cloud onto {cfg.map.file or 'target_cloud'} ({cfg.mode}, "
            f'{cfg.pairing.mode}, voxel_size {pipe.voxel_size} m; '
            f"Fast DDS profile: {self._transport_profile or 'none'})")
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Consume sources and publish."""
        self._engine.activate()
        self._bond = start_bond(self)
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Ignore sources (counted) and publish no pose."""
        self._engine.deactivate()
        if self._bond is not None:
            self._bond.shutdown()
            self._bond = None
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """End the registration process; destroy the topics and services."""
        self._teardown()
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Do what cleanup does, from any state."""
        self._teardown()
        return super().on_shutdown(state)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Recover to unconfigured: end everything configure started."""
        self._teardown()
        return SUCCESS

    def _teardown(self) -> None:
        if self._bond is not None:
            self._bond.shutdown()
            self._bond = None
        engine, self._engine = self._engine, None
        if engine is not None:
            engine.stop()
        for entity in self._entities:
            _DESTROY[type(entity).__name__](self, entity)
        self._entities = []
        if self.outputs is not None:
            self.outputs.destroy()
            self.outputs = None

    def destroy_node(self) -> None:
        """End the registration process, then destroy the node."""
        self._teardown()
        super().destroy_node()

    # ------------------------------------------------------------------ parameters

    def _declare_parameters(self) -> None:
        """
        Declare the ROS parameters, their defaults taken from ``config_file``.

        ``config_file`` is declared (and read) first; every other parameter is declared with
        the file's value as its default, so the parameters given to the node (params file,
        ``-p``) override the file and the file overrides the dataclass defaults.
        """
        meta = self._descriptions['config_file']
        path = self.declare_parameter('config_file', meta['default'],
                                      descriptor('config_file', meta)).value
        self._file_configs = configs_from_file(path)
        defaults = {**fields.flatten(self._file_configs[0]),
                    **fields.flatten(self._file_configs[1])}
        for name, meta in self._descriptions.items():
            if name != 'config_file':
                self.declare_parameter(name, ros_value(defaults[name]), descriptor(name, meta))
        unknown = sorted(n for n in self._parameter_overrides
                         if not self.has_parameter(n) and not n.startswith('qos_overrides.'))
        if unknown:  # a typo or a key that is no ROS parameter, in a params file or -p
            raise InvalidConfigError('; '.join(not_a_parameter(n) for n in unknown))

    def _configs(self) -> tuple[PipelineConfig, NodeConfig]:
        """Return the validated configurations: config_file's, then the ROS parameters."""
        return configs_from_parameters(
            {name: self.get_parameter(name).value for name in self._descriptions},
            base=self._file_configs)

    def _on_set_parameters(self, params: list[rclpy.parameter.Parameter]) -> SetParametersResult:
        for p in params:
            if not self.has_parameter(p.name):
                return SetParametersResult(successful=False, reason=not_a_parameter(p.name))
        changes = {p.name: p.value for p in params if p.name in self._descriptions}
        if not changes:
            return SetParametersResult(successful=True)
        engine = self._engine
        try:
            base = ((engine.pipeline_config, engine.node_config) if engine is not None
                    else self._configs())
            pipe, node = configs_from_parameters(changes, base=base)
        except InvalidConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        if engine is not None:
            engine.set_configs(pipe, node)
        self.get_logger().info(f'parameters changed (next pair): {changes}')
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ input

    def _receive(self, msg: PointCloud2, role: str) -> None:
        engine = self._engine
        if engine is None:
            return
        receipt = time.monotonic_ns()
        stamp = 0
        try:
            stamp = stamp_to_ns(msg.header.stamp)
            xyz = pointcloud2_to_xyz(msg, max_points=engine.node_config.pairing.max_cloud_points)
        except InvalidInputError as exc:
            engine.receive(role, stamp, '', None,
                           Refusal(exc.code, f'{role} cloud rejected: {exc}'))
        else:
            engine.receive(role, stamp, str(msg.header.frame_id),
                           Cloud(xyz, msg.header, receipt))

    def _on_odometry(self, msg: Odometry) -> None:
        with contextlib.suppress(InvalidInputError):  # a zero quaternion: no pose
            if self.outputs is not None:
                self.outputs.tf.add_odometry(stamp_to_ns(msg.header.stamp), pose_to_transform(msg))

    def _on_hint(self, msg: PoseWithCovarianceStamped) -> None:
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        if self._engine is not None:
            self._engine.hint(stamp_to_ns(msg.header.stamp), msg.header.frame_id,
                              (p.x, p.y, p.z, q.x, q.y, q.z, q.w), msg.pose.covariance)

    # ------------------------------------------------------------------ services

    async def _on_relocalize(self, request: Any, response: Any) -> Any:
        engine, executor = self._engine, self.executor
        if engine is None:
            response.success = False
            response.message = 'unconfigured: not localized: the node is not configured'
            return response
        answer = Future()

        def on_answer(success: bool, message: str) -> None:  # the engine thread, or at once
            answer.set_result((success, message))
            if executor is not None:
                executor.wake()  # the executor resumes an awaiting callback when it wakes

        engine.relocalize(on_answer)
        response.success, response.message = await answer
        return response

    def _on_reinitialize(self, request: Any, response: Any) -> Any:
        engine = self._engine
        if engine is not None:
            engine.relocalize(self._log_reinitialized)
        return response

    def _log_reinitialized(self, success: bool, message: str) -> None:
        if self.outputs is not None:
            self.outputs.log('info' if success else 'warning',
                             f'reinitialize_global_localization: {message}')

    # ------------------------------------------------------------------ health

    def statistics(self) -> dict[str, Any]:
        """Return a flat snapshot of the node's counters (what /diagnostics carries)."""
        engine, outputs = self._engine, self.outputs
        if engine is None or outputs is None:
            return {}
        extra = {'memory.node_rss_mb': round(rss_mb() or 0.0, 1),
                 'transport.profile': self._transport_profile,
                 **engine.statistics(), **outputs.statistics()}
        return statistics.build_statistics(engine.snapshot(),
                                           engine.pipeline_config.voxel_size, extra)

    def _publish_diagnostics(self) -> None:
        engine, outputs = self._engine, self.outputs
        if engine is None or outputs is None:
            return  # cleaned up while the executor held this timer's callback
        engine.supervise()
        outputs.publish_diagnostics(self.statistics())


def main(args: list[str] | None = None) -> None:
    """
    Spin the node until Ctrl-C or SIGTERM, then shut down cleanly.

    The ``register_node`` entry point (``ros2 run``, ``python -m cgags_ros.register_node``).
    A single-threaded executor: every callback is short (a cloud decoded and counted, a
    parameter checked, the diagnostics), the registration runs in the engine thread
    thread and its process, and ``~/relocalize`` awaits its answer without holding the
    executor. rclpy's multi-threaded executor took received scans to their callback
    later, its own loop busy while they waited (docs/tracking.md, item 11).
    """
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    use_large_data_profile()
    rclpy.init(args=args)
    node = None
    executor = SingleThreadedExecutor()
    try:
        node = RegisterNode()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except InvalidConfigError as exc:  # e.g. a pairing.mode typo in the YAML
        rclpy.logging.get_logger('register_node').fatal(str(exc))
        raise SystemExit(2) from None
    except RuntimeError:  # an rclpy call racing the signal handler's shutdown
        if rclpy.ok():
            raise
    finally:
        executor.shutdown(timeout_sec=2.0)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
