"""
The node's TF: tf2_ros where it imports, else a stand-in; the one place that tells them apart.

tf2_ros (Jazzy's, in ``package.xml``): the ``odom`` topic fills a tf2 ``Buffer`` of its own
(with no message, TF's ``odom_frame`` -> ``base_frame`` serves; a stamp past the newest sample
by at most :data:`TOLERANCE_S` takes the newest); lookups and broadcasts go through tf2. The
stand-in (stacks without it, as the emulated test stack): the odom topic in an
:class:`~cgags_ros.relocalization.sequence.OdometrySamples`, the identity as the extrinsic,
no /tf (said once), /tf_static through a latched tf2_msgs publisher. TF's message is built
here (:func:`transform_to_transform_stamped`).
"""

from __future__ import annotations

from typing import Any, Callable

from geometry_msgs.msg import TransformStamped
import numpy as np
from rclpy.duration import Duration
from rclpy.time import Time
from std_msgs.msg import Header

from .qos import latched_qos
from ..geometry import finite_transform, make_transform, matrix_to_quaternion, quaternion_to_matrix
from ..io.pointcloud2 import stamp_to_ns
from ..relocalization.sequence import KEEP_S, OdometrySamples, TOLERANCE_S

ODOM, BASE = 'odom', 'base'  # the frames of the odom topic's own buffer


class Transforms:
    """TF of one node (see the module doc); ``send(publisher, msg)`` publishes safely."""

    def __init__(self, node: Any, log: Callable[[str, str], None],
                 send: Callable[[Any, Any], None], listen: bool = False):
        self._node, self._log, self._send, self._said = node, log, send, False
        try:
            import tf2_ros as tf2
        except ImportError:
            tf2 = None
        self._tf2: Any = tf2
        self._tf: Any = None  # tf2's (buffer, listener, broadcaster), started once
        self._static: Any = None  # what publishes /tf_static, made once (False: nothing)
        self._topic = False  # the odom topic gives the odometry (once it has sent any)
        self.odometry_samples = 0  # taken: the odom topic's messages, TF's lookups
        self._odom = OdometrySamples() if tf2 is None else tf2.Buffer(Duration(seconds=KEEP_S))
        if listen:  # TF fills while the first scans come
            self.available('')

    def available(self, why: str) -> bool:
        """Start tf2's listener and broadcaster once; False without tf2 (``why`` said once)."""
        if self._tf2 is None:
            if why and not self._said:
                self._said = True
                self._log('warning', f'{why} but tf2_ros is not importable: no TF is broadcast '
                          'or looked up (the sensor pose stands for the base pose unless '
                          'relocalization.base_from_sensor is set)')
            return False
        if self._tf is None:
            buffer = self._tf2.Buffer()
            self._tf = (buffer, self._tf2.TransformListener(buffer, self._node),
                        self._tf2.TransformBroadcaster(self._node))
        return True

    def broadcast(self, T: np.ndarray, header: Any, child: str) -> None:
        """Broadcast ``T`` (``header.frame_id`` <- ``child``) on /tf, once :meth:`available`."""
        self._tf[2].sendTransform(transform_to_transform_stamped(T, header, child))

    def lookup(self, parent: str, child: str, stamp_ns: int | None = None) -> np.ndarray | None:
        """Return ``parent <- child`` from TF at ``stamp_ns`` (None: the latest), or None."""
        return None if self._tf is None else _lookup(self._tf[0], parent, child, stamp_ns)

    def base_from_sensor(self, base_frame: str, sensor_frame: str) -> np.ndarray | None:
        """Return ``T_base_sensor`` from TF; the identity (said once) without tf2_ros."""
        if not self.available('relocalization.base_from_sensor is not set'):
            return np.eye(4)
        return self.lookup(base_frame, sensor_frame)

    def add_odometry(self, stamp_ns: int, odom_from_base: np.ndarray) -> None:
        """Take one sample of the odom topic (a repeated stamp replaces)."""
        if self._tf2 is None:
            self._odom.add(stamp_ns, odom_from_base)
        else:
            self._odom.set_transform(transform_to_transform_stamped(odom_from_base, Header(
                stamp=Time(nanoseconds=stamp_ns).to_msg(), frame_id=ODOM), BASE), 'odom')
        self._topic = True
        self.odometry_samples += 1

    def odometry(self, odom_frame: str, base_frame: str, stamp_ns: int
                 ) -> tuple[bool, np.ndarray | None]:
        """Return (any odometry known, ``odom <- base`` at ``stamp_ns`` or None when none near)."""
        if self._topic:
            if self._tf2 is None:
                return True, self._odom.at(stamp_ns)
            return True, _lookup(self._odom, ODOM, BASE, stamp_ns, TOLERANCE_S)
        if self._tf is None or not self._tf[0].can_transform(odom_frame, base_frame, Time()):
            return False, None
        found = _lookup(self._tf[0], odom_frame, base_frame, stamp_ns, TOLERANCE_S)
        self.odometry_samples += found is not None
        return True, found

    def broadcast_static(self, T: np.ndarray, header: Any, child: str) -> None:
        """Publish ``T`` (``header.frame_id`` <- ``child``) on /tf_static, latched."""
        if self._static is None:
            self._static = self._static_publisher()
        tf = transform_to_transform_stamped(T, header, child)
        if self._static and self._tf2 is not None:
            self._static.sendTransform(tf)
        elif self._static:
            self._send(self._static, self._static.msg_type(transforms=[tf]))

    def _static_publisher(self) -> Any:
        if self._tf2 is not None:
            return self._tf2.StaticTransformBroadcaster(self._node)
        try:  # what tf2's static broadcaster is: a latched publisher of TFMessage
            from tf2_msgs.msg import TFMessage
        except ImportError:
            self._log('warning', 'neither tf2_ros nor tf2_msgs is importable: the calibration '
                      'is not broadcast on /tf_static (use ~/calibration or the '
                      'static_transform_publisher line of ~/calibration_report)')
            return False
        return self._node.create_publisher(TFMessage, '/tf_static', latched_qos())

    def destroy(self) -> None:
        """Destroy the stand-in's /tf_static publisher (the node's cleanup)."""
        if self._static and self._tf2 is None:
            self._node.destroy_publisher(self._static)


def _lookup(buffer: Any, parent: str, child: str, stamp_ns: int | None,
            tolerance_s: float = 0.0) -> np.ndarray | None:
    for time in [Time(nanoseconds=stamp_ns or 0)] + ([Time()] if tolerance_s else []):
        try:
            tf = buffer.lookup_transform(parent, child, time)
        except Exception:  # noqa: BLE001 - tf2's lookup errors have no common base here
            continue
        if stamp_ns is None or abs(stamp_to_ns(tf.header.stamp) - stamp_ns) <= tolerance_s * 1e9:
            r, t = tf.transform.rotation, tf.transform.translation
            return make_transform(quaternion_to_matrix((r.x, r.y, r.z, r.w)), (t.x, t.y, t.z))
    return None


def transform_to_transform_stamped(T: np.ndarray, header: Any, child_frame_id: str) -> Any:
    """4x4 transform -> geometry_msgs/TransformStamped (parent = header.frame_id)."""
    T = finite_transform(T)
    msg = TransformStamped(header=header, child_frame_id=child_frame_id)
    tr, rot = msg.transform.translation, msg.transform.rotation
    tr.x, tr.y, tr.z = (float(v) for v in T[:3, 3])
    rot.x, rot.y, rot.z, rot.w = (float(v) for v in matrix_to_quaternion(T[:3, :3]))
    return msg
