"""
cgags_ros.ros.transforms: the node's TF both ways, without DDS.

With tf2_ros absent (hidden here wherever it is installed) the stand-in serves: odometry
interpolated between samples or the nearest within the tolerance, the identity extrinsic
said once, no broadcast. With a fake tf2_ros (a module of this test) the odometry and the
lookups go to tf2's buffers and the broadcasts to tf2's broadcasters.
"""

from __future__ import annotations

import sys
import types

from cgags_ros.geometry import make_transform, rotation_error_deg
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip('rclpy')

from cgags_ros.io.pointcloud2 import stamp_to_ns  # noqa: E402, I100
from cgags_ros.ros.transforms import TOLERANCE_S, Transforms  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

S = 10**9  # nanoseconds a second


def turn(deg, t=(0.0, 0.0, 0.0)):
    return make_transform(Rotation.from_euler('z', deg, degrees=True).as_matrix(), t)


class Node:
    """What Transforms asks of a node: publishers (recorded)."""

    def __init__(self):
        self.publishers, self.destroyed = [], []

    def create_publisher(self, kind, topic, qos):
        self.publishers.append((kind.__name__, topic))
        return types.SimpleNamespace(msg_type=kind, topic=topic)

    def destroy_publisher(self, publisher):
        self.destroyed.append(publisher)


def importable(name):
    try:
        __import__(name)
    except ImportError:
        return False
    return True


def transforms(monkeypatch, tf2, listen=False):
    """Return (Transforms with ``tf2`` as tf2_ros, None hides it; its logs; what it sent)."""
    monkeypatch.setitem(sys.modules, 'tf2_ros', tf2)
    logs, sent = [], []
    tf = Transforms(Node(), lambda *line: logs.append(line),
                    lambda pub, msg: sent.append((pub, msg)), listen=listen)
    return tf, logs, sent


def test_without_tf2_odometry_is_interpolated_between_samples_and_nearest_within_tolerance(
        monkeypatch):
    tf, logs, _ = transforms(monkeypatch, None, listen=True)
    assert tf.odometry('odom', 'base', 5 * S) == (False, None)  # none known: one scan at a time
    tf.add_odometry(6 * S, turn(20, (2.0, 0.0, 0.0)))
    tf.add_odometry(4 * S, turn(-20, (0.0, 0.0, 0.0)))  # out of order: put in place
    tf.add_odometry(int(5.05 * S), turn(10, (1.5, 0.0, 0.0)))
    # Between 4.0 (too far) and 5.05 (within the tolerance): the nearest one stands.
    known, near = tf.odometry('odom', 'base', int(5.025 * S))
    assert known
    np.testing.assert_allclose(near, turn(10, (1.5, 0.0, 0.0)))
    tf.add_odometry(5 * S, turn(0, (1.0, 0.0, 0.0)))
    mid = tf.odometry('odom', 'base', int(5.025 * S))[1]  # halfway between 5.0 and 5.05
    np.testing.assert_allclose(mid[:3, 3], [1.25, 0.0, 0.0], atol=1e-12)
    assert rotation_error_deg(mid, turn(5)) < 1e-6
    np.testing.assert_allclose(tf.odometry('odom', 'base', 5 * S)[1], turn(0, (1.0, 0.0, 0.0)))
    tf.add_odometry(5 * S, turn(0, (1.0, 0.5, 0.0)))  # a repeated stamp replaces
    np.testing.assert_allclose(tf.odometry('odom', 'base', 5 * S)[1], turn(0, (1.0, 0.5, 0.0)))
    assert tf.odometry_samples == 5
    after = tf.odometry('odom', 'base', int((6 + TOLERANCE_S / 2) * S))[1]  # within it
    np.testing.assert_allclose(after, turn(20, (2.0, 0.0, 0.0)))
    assert tf.odometry('odom', 'base', int((6 + 2 * TOLERANCE_S) * S)) == (True, None)
    assert logs == []  # listening without tf2 is silent: nothing was asked of TF yet


def test_without_tf2_the_extrinsic_is_the_identity_and_nothing_is_broadcast(monkeypatch):
    tf, logs, sent = transforms(monkeypatch, None)
    np.testing.assert_array_equal(tf.base_from_sensor('base_link', 'lidar'), np.eye(4))
    assert not tf.available('output.broadcast_tf is set')
    assert tf.lookup('odom', 'base_link', 5 * S) is None
    assert len(logs) == 1 and 'base_from_sensor is not set but tf2_ros is not' in logs[0][1]
    for child in ('child', 'second'):
        tf.broadcast_static(turn(10), Header(frame_id='parent'), child)
    if importable('tf2_msgs.msg'):  # a latched publisher of TFMessage, as tf2's static one is
        assert [(pub.topic, msg.transforms[0].child_frame_id) for pub, msg in sent] == [
            ('/tf_static', 'child'), ('/tf_static', 'second')]
    else:
        assert sent == [] and 'neither tf2_ros nor tf2_msgs' in logs[-1][1] and len(logs) == 2


class FakeTf2:
    """A tf2_ros whose buffers answer at the stamps they were given, or the latest at 0."""

    def __init__(self):
        self.buffers, self.listeners, self.sent, self.static = [], [], [], []
        self.module = types.ModuleType('tf2_ros')
        fake = self

        class Buffer:
            def __init__(self, cache_time=None):
                self.cache_time, self.frames = cache_time, {}
                fake.buffers.append(self)

            def set_transform(self, msg, authority):
                key = (msg.header.frame_id, msg.child_frame_id)
                self.frames.setdefault(key, {})[stamp_to_ns(msg.header.stamp)] = msg

            def lookup_transform(self, parent, child, time):
                stamps = self.frames.get((parent, child), {})
                ns = time.nanoseconds or max(stamps, default=None)
                if ns not in stamps:
                    raise LookupError(f'no {parent} <- {child} at {ns}')
                return stamps[ns]

            def can_transform(self, parent, child, time):
                return bool(self.frames.get((parent, child)))

        def listener(buffer, node):
            fake.listeners.append(buffer)

        def broadcaster(node, into=self.sent):
            return types.SimpleNamespace(sendTransform=into.append)

        self.module.Buffer, self.module.TransformListener = Buffer, listener
        self.module.TransformBroadcaster = broadcaster
        self.module.StaticTransformBroadcaster = lambda node: broadcaster(node, self.static)


def tf_message(T, parent, child, stamp_ns):
    from cgags_ros.ros.transforms import transform_to_transform_stamped
    from rclpy.time import Time

    return transform_to_transform_stamped(T, Header(
        stamp=Time(nanoseconds=stamp_ns).to_msg(), frame_id=parent), child)


def test_with_tf2_the_odom_topic_fills_a_tf2_buffer_that_serves_the_lookups(monkeypatch):
    tf2 = FakeTf2()
    tf, logs, _ = transforms(monkeypatch, tf2.module, listen=True)
    odom_buffer, tree = tf2.buffers  # the odom topic's own, then the listener's
    assert tf2.listeners == [tree] and odom_buffer.cache_time.nanoseconds == 60 * S
    assert tf.odometry('odom', 'base_link', 5 * S) == (False, None)  # nothing known yet
    tf.add_odometry(5 * S, turn(10, (1.0, 0.0, 0.0)))
    assert list(odom_buffer.frames) == [('odom', 'base')] and tf.odometry_samples == 1
    known, at = tf.odometry('odom', 'base_link', 5 * S)
    assert known
    np.testing.assert_allclose(at, turn(10, (1.0, 0.0, 0.0)), atol=1e-12)
    # Past the newest sample: the newest within the tolerance, none beyond it.
    late = tf.odometry('odom', 'base_link', int((5 + TOLERANCE_S / 2) * S))[1]
    np.testing.assert_allclose(late, turn(10, (1.0, 0.0, 0.0)), atol=1e-12)
    assert tf.odometry('odom', 'base_link', int((5 + 2 * TOLERANCE_S) * S)) == (True, None)
    assert logs == []


def test_with_tf2_and_no_odom_topic_tf_serves_odometry_lookups_and_broadcasts(monkeypatch):
    tf2 = FakeTf2()
    tf, logs, sent = transforms(monkeypatch, tf2.module, listen=True)
    tree = tf2.listeners[0]
    assert tf.base_from_sensor('base_link', 'lidar') is None  # not on TF yet
    tree.set_transform(tf_message(turn(90, (0.2, 0.0, 1.0)), 'base_link', 'lidar', 0), 'tf')
    np.testing.assert_allclose(tf.base_from_sensor('base_link', 'lidar'),
                               turn(90, (0.2, 0.0, 1.0)), atol=1e-12)
    tree.set_transform(tf_message(turn(5, (3.0, 0.0, 0.0)), 'odom', 'base_link', 7 * S), 'tf')
    known, at = tf.odometry('odom', 'base_link', 7 * S)
    assert known and tf.odometry_samples == 1  # a TF lookup taken
    np.testing.assert_allclose(at, turn(5, (3.0, 0.0, 0.0)), atol=1e-12)
    np.testing.assert_allclose(tf.lookup('odom', 'base_link', 7 * S), at)
    assert tf.lookup('odom', 'base_link', 8 * S) is None  # a lookup at a stamp: no tolerance
    tf.add_odometry(7 * S, turn(6, (3.1, 0.0, 0.0)))  # the odom topic, once it sends, serves
    np.testing.assert_allclose(tf.odometry('odom', 'base_link', 7 * S)[1],
                               turn(6, (3.1, 0.0, 0.0)), atol=1e-12)
    assert tf.odometry_samples == 2
    assert tf.available('output.broadcast_tf is set')
    tf.broadcast(turn(30), Header(frame_id='map'), 'lidar')
    tf.broadcast_static(turn(45), Header(frame_id='parent'), 'child')
    assert [m.child_frame_id for m in tf2.sent] == ['lidar']
    assert [m.child_frame_id for m in tf2.static] == ['child'] and sent == [] and logs == []
