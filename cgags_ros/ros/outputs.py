"""
The node's outputs: what the engine's ``EngineOutputs`` asks for, in ROS messages.

:class:`~cgags_ros.engine.interface.EngineOutputs` as ~/pose, ~/pose_with_covariance,
~/aligned_cloud, ~/candidates, initialpose, /tf (:mod:`.transforms`), ~/result and
/diagnostics; in calibrate mode ~/calibration, ~/calibration_report and /tf_static
(latched). Frames and conventions as in :mod:`.node`: a pose maps source-frame points into
the target (map) frame and carries the source's stamp. Pose outputs are lifecycle
publishers: they publish only while the node is active.

The messages are built here from numpy arrays and 4x4 transforms (:func:`transform_to_pose`,
:func:`xyz_to_pointcloud2`, :func:`fields_to_pointcloud2`; :func:`to_rclpy_pointcloud2`
copies a bag's cloud), the reverse of :mod:`cgags_ros.io.pointcloud2`'s decoding, with its
conventions: metres, the header's frame, ``T`` maps source-frame points into the target
frame, quaternions ``(x, y, z, w)``. TF's messages are built in :mod:`.transforms`.
"""

from __future__ import annotations

import array
import collections
from typing import Any

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Pose, PoseArray, PoseStamped, PoseWithCovarianceStamped
import numpy as np
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header, String

from . import diagnostics
from .qos import latched_qos, result_qos
from .transforms import Transforms
from ..engine import statistics
from ..engine.interface import BasePose, Calibration, Estimate, PairResult
from ..errors import InvalidInputError
from ..geometry import finite_transform, matrix_to_quaternion
from ..io.pointcloud2 import data_bytes, POINT_FIELD_TYPES, stamp_to_ns
from ..pipeline.covariance import map_to_odom
from ..refusal import Refusal


class Outputs:
    """
    Publishers, TF and logging of one node: the engine's ``EngineOutputs``.

    ``odometry``: the node takes odometry (``map.file``), TF listens from the start. The
    engine's TF questions are :attr:`tf`'s to answer. Only the engine thread counts (replacing the
    counts whole): :meth:`statistics` needs no lock.
    """

    def __init__(self, node: Any, calibrate: bool = False, odometry: bool = False):
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
        self.counts: collections.Counter[str] = collections.Counter()
        self._odometry = odometry
        self.tf = Transforms(node, self.log, self._send, listen=odometry)
        self.base_from_sensor, self.odometry, self.lookup = (self.tf.base_from_sensor,
                                                             self.tf.odometry, self.tf.lookup)
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
        if estimate.tf_child_frame and self.tf.available('output.broadcast_tf is set'):
            self.tf.broadcast(estimate.transform, header, estimate.tf_child_frame)

    def publish_candidates(self, header: Any, frame_id: str, transforms: list[np.ndarray]) -> None:
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
        if pose.odom_frame and self.tf.available('relocalization.broadcast_map_to_odom is set'):
            T_map_odom = pose.map_from_odom
            if T_map_odom is None:
                T_odom_base = self.tf.lookup(pose.odom_frame, pose.base_frame,
                                             stamp_to_ns(msg.header.stamp))
                if T_odom_base is None:
                    self._count('map_to_odom.no_odom_tf')
                    return
                T_map_odom = map_to_odom(pose.transform, T_odom_base)
            self.tf.broadcast(T_map_odom, msg.header, pose.odom_frame)
            self._count('map_to_odom.broadcast')

    def publish_calibration(self, calibration: Calibration) -> None:
        """Publish ~/calibration, ~/calibration_report and /tf_static (parent <- child)."""
        header = Header(stamp=calibration.header.stamp, frame_id=calibration.parent_frame)
        msg = PoseWithCovarianceStamped(header=header)
        msg.pose.pose = transform_to_pose(calibration.transform)
        msg.pose.covariance = [float(v) for v in calibration.covariance.ravel()]
        self._send(self._calibration_pub, msg)
        self._send(self._report_pub, String(data=calibration.report))
        self.tf.broadcast_static(calibration.transform, header, calibration.child_frame)

    def publish_result(self, result: PairResult) -> None:
        """Publish ~/result (std_msgs/String): the source's result as JSON."""
        self._send(self._result_pub, String(data=result.to_json()))

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
        self.publish_diagnostics({**stats, statistics.CONFIGURE_ERROR: refusal.message,
                                  statistics.CONFIGURE_CODE: refusal.code.value})

    def statistics(self) -> dict[str, int]:
        """Return the ``map_to_odom.*`` counters and ``odometry.samples`` for /diagnostics."""
        stats = {f'initial_pose.{k}': v for k, v in sorted(self.counts.items())}
        if self._odometry:
            stats['odometry.samples'] = self.tf.odometry_samples
        return stats

    def destroy(self) -> None:
        """Destroy the publishers (the node's cleanup)."""
        for pub in self._lifecycle_publishers:
            self._node.destroy_lifecycle_publisher(pub)
        self._node.destroy_publisher(self._diag_pub)
        self._node.destroy_publisher(self._result_pub)
        self.tf.destroy()

    def _count(self, key: str) -> None:
        counts = self.counts.copy()
        counts[key] += 1
        self.counts = counts

    def _send(self, publisher: Any, msg: Any) -> None:
        """
        Publish unless the context has been shut down (Ctrl-C / SIGTERM).

        rclpy's signal handler shuts the context down asynchronously: the executor may
        still dispatch the diagnostics timer, and the engine thread may still be finishing a
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


# ------------------------------------------------------------------ message builders


def transform_to_pose(T: np.ndarray) -> Any:
    """4x4 transform -> geometry_msgs/Pose."""
    T = finite_transform(T)
    qx, qy, qz, qw = matrix_to_quaternion(T[:3, :3])
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in T[:3, 3])
    pose.orientation.x, pose.orientation.y = float(qx), float(qy)
    pose.orientation.z, pose.orientation.w = float(qz), float(qw)
    return pose


def xyz_to_pointcloud2(points: np.ndarray, header: Any = None) -> Any:
    """
    Build a dense, unorganized ``sensor_msgs/PointCloud2`` (float32 x, y, z; 12-byte points).

    ``header`` is a std_msgs/Header (or None for an empty one); points are in its frame.

    :raises InvalidInputError: for anything but an (N, 3) array.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidInputError(f'points must have shape (N, 3), got {pts.shape}')
    xyz = np.dtype([(name, '<f4') for name in 'xyz'])
    return fields_to_pointcloud2(np.ascontiguousarray(pts, dtype='<f4').view(xyz).reshape(-1),
                                 header)


def fields_to_pointcloud2(table: np.ndarray, header: Any = None) -> Any:
    """
    Build a dense, unorganized ``sensor_msgs/PointCloud2`` carrying every field of ``table``.

    ``table`` is a structured array, one record per point, of numeric scalar fields (e.g.
    :func:`cgags_ros.io.pcd.read_fields`: x, y, z in metres, intensity, normals...);
    the layout is the array's, little-endian. ``header`` as in :func:`xyz_to_pointcloud2`.

    :raises InvalidInputError: for a field that is not a numeric scalar of a PointField type.
    """
    table = np.ascontiguousarray(table)
    names = table.dtype.names or ()
    datatypes = {np.dtype(name.lower()): code for code, (name, _) in POINT_FIELD_TYPES.items()}
    fields = []
    for name in names:
        kind, offset = table.dtype.fields[name][:2]
        if kind.shape or kind.newbyteorder('<') not in datatypes:
            raise InvalidInputError(f'field {name!r} of type {kind} has no PointField type')
        if kind.byteorder == '>':
            raise InvalidInputError(f'field {name!r} is big-endian')
        fields.append(PointField(name=name, offset=int(offset),
                                 datatype=datatypes[kind.newbyteorder('<')], count=1))
    msg = PointCloud2()
    if header is not None:
        msg.header = header
    msg.height, msg.width = 1, int(table.shape[0])
    msg.fields = fields
    msg.is_bigendian = False
    msg.point_step = table.dtype.itemsize
    msg.row_step = msg.point_step * msg.width
    msg.is_dense = all(np.isfinite(table[c]).all() for c in 'xyz' if c in names)
    # array.array('B') takes rclpy's fast path; a bytes/list value is checked byte by byte.
    buf = array.array('B')
    buf.frombytes(table.tobytes())
    msg.data = buf
    return msg


def to_rclpy_pointcloud2(msg: Any) -> Any:
    """
    Copy any PointCloud2-like message (e.g. from rosbags) into an rclpy PointCloud2.

    The copy is byte for byte: layout, header and even malformed sizes are kept, so a bag
    can be republished exactly as recorded.
    """
    out = PointCloud2()
    out.header = Header(stamp=Time(sec=int(msg.header.stamp.sec),
                                   nanosec=int(msg.header.stamp.nanosec)),
                        frame_id=str(msg.header.frame_id))
    out.height, out.width = int(msg.height), int(msg.width)
    out.fields = [PointField(name=str(f.name), offset=int(f.offset), datatype=int(f.datatype),
                             count=int(f.count)) for f in msg.fields]
    out.is_bigendian, out.is_dense = bool(msg.is_bigendian), bool(msg.is_dense)
    out.point_step, out.row_step = int(msg.point_step), int(msg.row_step)
    buf = array.array('B')
    buf.frombytes(data_bytes(msg.data).tobytes())
    out.data = buf
    return out
