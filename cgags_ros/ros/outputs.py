"""
The node's outputs: what the engine's ``EngineOutputs`` asks for, in ROS messages.

:class:`~cgags_ros.localizer.interface.EngineOutputs` as ~/pose, ~/pose_with_covariance,
~/aligned_cloud, ~/candidates, initialpose, /tf (when tf2_ros is importable), ~/result and
/diagnostics; in calibrate mode ~/calibration, ~/calibration_report and /tf_static
(latched). Frames and conventions as in :mod:`.node`: a pose maps source-frame points into
the target (map) frame and carries the source's stamp. Pose outputs are lifecycle
publishers: they publish only while the node is active.
"""

from __future__ import annotations

import collections
import threading
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped, PoseWithCovarianceStamped
import numpy as np
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header, String

from . import diagnostics
from .conversions import transform_to_pose, transform_to_transform_stamped, xyz_to_pointcloud2
from .qos import latched_qos, result_qos
from ..geometry import make_transform, quaternion_to_matrix
from ..localizer.interface import BasePose, Calibration, Estimate, PairResult
from ..pipeline.covariance import map_to_odom
from ..refusal import Refusal


class Outputs:
    """Publishers, TF and logging of one node: the engine's ``EngineOutputs``."""

    def __init__(self, node: Any, calibrate: bool = False):
        self._node = node
        lifecycle = node.create_lifecycle_publisher
        self._pose_pub = lifecycle(PoseStamped, '~/pose', 10)
        self._pose_cov_pub = lifecycle(PoseWithCovarianceStamped, '~/pose_with_covariance', 10)
        self._aligned_pub = lifecycle(PointCloud2, '~/aligned_cloud', 1)
        self._candidates_pub = lifecycle(PoseArray, '~/candidates', 10)
        self._initial_pub = lifecycle(PoseWithCovarianceStamped, 'initialpose', 10)
        self._diag_pub = node.create_publisher(DiagnosticArray, '/diagnostics', 10)
        # Not a lifecycle publisher: sources refused while inactive get their result too.
        self._result_pub = node.create_publisher(String, '~/result', result_qos())
        self._lifecycle_publishers = [self._pose_pub, self._pose_cov_pub, self._aligned_pub,
                                      self._candidates_pub, self._initial_pub]
        self._lock = threading.Lock()
        self.counts: collections.Counter[str] = collections.Counter()
        self._tf_buffer: Any = None
        self._tf_listener: Any = None
        self._tf_broadcaster: Any = None
        self._tf_said = False
        self._static_pub: Any = None  # /tf_static: a broadcaster, a publisher, or False
        self._calibration_pub = self._report_pub = None
        if calibrate:
            self._calibration_pub = lifecycle(PoseWithCovarianceStamped, '~/calibration',
                                              latched_qos())
            self._report_pub = lifecycle(String, '~/calibration_report', latched_qos())
            self._lifecycle_publishers += [self._calibration_pub, self._report_pub]

    # ------------------------------------------------------------------ EngineOutputs

    def publish_estimate(self, estimate: Estimate) -> None:
        """Publish ~/pose, ~/pose_with_covariance, and ~/aligned_cloud and /tf as asked."""
        header = Header(stamp=estimate.header.stamp, frame_id=estimate.frame_id)
        pose = transform_to_pose(estimate.transform)
        self._send(self._pose_pub, PoseStamped(header=header, pose=pose))
        cov_msg = PoseWithCovarianceStamped(header=header)
        cov_msg.pose.pose = pose
        cov_msg.pose.covariance = [float(v) for v in estimate.covariance.ravel()]
        self._send(self._pose_cov_pub, cov_msg)
        if estimate.aligned is not None:
            self._send(self._aligned_pub, xyz_to_pointcloud2(estimate.aligned, header))
        if estimate.tf_child_frame and self._tf_ready('output.broadcast_tf is set'):
            self._broadcast(estimate.transform, header, estimate.tf_child_frame)

    def publish_candidates(self, header: Any, frame_id: str,
                           transforms: list[np.ndarray]) -> None:
        """Publish ~/candidates (geometry_msgs/PoseArray, best first)."""
        msg = PoseArray(header=Header(stamp=header.stamp, frame_id=frame_id))
        msg.poses = [transform_to_pose(T) for T in transforms]
        self._send(self._candidates_pub, msg)

    def publish_initial_pose(self, pose: BasePose) -> None:
        """Publish ``initialpose`` and, when asked, Nav2's map -> odom on /tf."""
        msg = PoseWithCovarianceStamped(header=Header(stamp=pose.header.stamp,
                                                      frame_id=pose.map_frame))
        msg.pose.pose = transform_to_pose(pose.transform)
        msg.pose.covariance = [float(v) for v in pose.covariance.ravel()]
        self._send(self._initial_pub, msg)
        if pose.odom_frame and self._tf_ready('relocalization.broadcast_map_to_odom is set'):
            T_odom_base = self._lookup(pose.odom_frame, pose.base_frame, msg.header.stamp)
            if T_odom_base is None:
                self._count('map_to_odom.no_odom_tf')
                return
            self._broadcast(map_to_odom(pose.transform, T_odom_base), msg.header,
                            pose.odom_frame)
            self._count('map_to_odom.broadcast')

    def publish_calibration(self, calibration: Calibration) -> None:
        """Publish ~/calibration, ~/calibration_report and /tf_static (parent <- child)."""
        header = Header(stamp=calibration.header.stamp, frame_id=calibration.parent_frame)
        msg = PoseWithCovarianceStamped(header=header)
        msg.pose.pose = transform_to_pose(calibration.transform)
        msg.pose.covariance = [float(v) for v in calibration.covariance.ravel()]
        self._send(self._calibration_pub, msg)
        self._send(self._report_pub, String(data=calibration.report))
        static = self._static()
        if static:
            tf = transform_to_transform_stamped(calibration.transform, header,
                                                calibration.child_frame)
            if hasattr(static, 'sendTransform'):
                static.sendTransform(tf)
            else:
                from tf2_msgs.msg import TFMessage
                self._send(static, TFMessage(transforms=[tf]))

    def publish_result(self, result: PairResult) -> None:
        """Publish ~/result (std_msgs/String): the source's result as JSON."""
        self._send(self._result_pub, String(data=result.to_json()))

    def base_from_sensor(self, base_frame: str, sensor_frame: str) -> np.ndarray | None:
        """Return ``T_base_sensor`` from TF; the identity (said once) without tf2_ros."""
        if not self._tf_ready('relocalization.base_from_sensor is not set'):
            return np.eye(4)
        return self._lookup(base_frame, sensor_frame)

    def log(self, level: str, message: str) -> None:
        """Log through the node's logger, unless its context has ended."""
        if not self._node.context.ok():
            return
        # One call site a severity: rclpy's logger refuses a site that changes severity.
        logger = self._node.get_logger()
        if level == 'error':
            logger.error(message)
        elif level == 'warning':
            logger.warning(message)
        else:
            logger.info(message)

    # ------------------------------------------------------------------ the node's own

    def publish_diagnostics(self, stats: dict[str, Any]) -> None:
        """Publish /diagnostics from the node's flat statistics."""
        node = self._node
        self._send(self._diag_pub, diagnostics.diagnostic_array(
            stats, f'{node.get_name()}: registration', node.get_fully_qualified_name(),
            node.get_clock().now().to_msg()))

    def publish_configure_failure(self, stats: dict[str, Any], refusal: Refusal) -> None:
        """Publish why configure failed: the last /diagnostics before the node is unconfigured."""
        self.publish_diagnostics({**stats, diagnostics.CONFIGURE_ERROR: refusal.message,
                                  diagnostics.CONFIGURE_CODE: refusal.code.value})

    def statistics(self) -> dict[str, int]:
        """Return the ``map_to_odom.*`` counters for /diagnostics."""
        with self._lock:
            return {f'initial_pose.{k}': v for k, v in sorted(self.counts.items())}

    def destroy(self) -> None:
        """Destroy the publishers (the node's cleanup)."""
        for pub in self._lifecycle_publishers:
            self._node.destroy_lifecycle_publisher(pub)
        self._node.destroy_publisher(self._diag_pub)
        self._node.destroy_publisher(self._result_pub)
        if self._static_pub and not hasattr(self._static_pub, 'sendTransform'):
            self._node.destroy_publisher(self._static_pub)

    def _count(self, key: str) -> None:
        with self._lock:
            self.counts[key] += 1

    def _send(self, publisher: Any, msg: Any) -> None:
        """
        Publish unless the context has been shut down (Ctrl-C / SIGTERM).

        rclpy's signal handler shuts the context down asynchronously: the executor may
        still dispatch the diagnostics timer, and the worker may still be finishing a
        pair. A publish then raises RCLError ("publisher's context is invalid"), which
        from a timer callback would escape rclpy.spin() and end the node with exit 1.
        Errors while the context is still valid are re-raised.
        """
        if not self._node.context.ok():
            return
        try:
            publisher.publish(msg)
        except RuntimeError:  # rclpy's RCLError derives from RuntimeError
            if self._node.context.ok():
                raise

    # ------------------------------------------------------------------ TF

    def _tf_ready(self, why: str) -> bool:
        """Start TF once; False (said once) when tf2_ros is not importable."""
        if self._tf_buffer is not None:
            return True
        try:
            from tf2_ros import Buffer, TransformBroadcaster, TransformListener
        except ImportError:
            if not self._tf_said:
                self._tf_said = True
                self.log('warning', f'{why} but tf2_ros is not importable: no TF is broadcast '
                         'or looked up (the sensor pose stands for the base pose unless '
                         'relocalization.base_from_sensor is set)')
            return False
        self._tf_buffer = Buffer()
        self._tf_listener = TransformListener(self._tf_buffer, self._node)
        self._tf_broadcaster = TransformBroadcaster(self._node)
        return True

    def _static(self) -> Any:
        """
        Return what publishes /tf_static, made once; False (said once) when nothing can.

        tf2_ros's StaticTransformBroadcaster when it imports; else a latched publisher of
        tf2_msgs/TFMessage on /tf_static (what that broadcaster is) when tf2_msgs imports.
        """
        if self._static_pub is None:
            try:
                from tf2_ros import StaticTransformBroadcaster
                self._static_pub = StaticTransformBroadcaster(self._node)
            except ImportError:
                try:
                    from tf2_msgs.msg import TFMessage
                    self._static_pub = self._node.create_publisher(TFMessage, '/tf_static',
                                                                   latched_qos())
                except ImportError:
                    self._static_pub = False
                    self.log('warning', 'neither tf2_ros nor tf2_msgs is importable: the '
                             'calibration is not broadcast on /tf_static (use ~/calibration or '
                             'the static_transform_publisher line of ~/calibration_report)')
        return self._static_pub

    def _broadcast(self, T: np.ndarray, header: Header, child: str) -> None:
        self._tf_broadcaster.sendTransform(transform_to_transform_stamped(T, header, child))

    def _lookup(self, parent: str, child: str, stamp: Any = None) -> np.ndarray | None:
        from rclpy.time import Time

        try:
            tf = self._tf_buffer.lookup_transform(
                parent, child, Time.from_msg(stamp) if stamp is not None else Time())
        except Exception:  # noqa: BLE001 - tf2's lookup errors have no common base here
            return None
        r, t = tf.transform.rotation, tf.transform.translation
        return make_transform(quaternion_to_matrix((r.x, r.y, r.z, r.w)), (t.x, t.y, t.z))
