"""
Relocalization over several scans with odometry through register_node over real DDS.

The node runs in this process with its own rclpy context and DDS domain, the pipeline in its
registration process; the map is the redkitchen scene fused from every fragment but those
of the sequence (as in test_relocalizer.py); the scans are consecutive fragments in their
sensor frame, stamped, and the robot's odometry goes out on ``odom`` (nav_msgs/Odometry,
the base's pose) at the scans' stamps. ~/relocalize calls stay in flight over the scans,
and initialpose goes out only once the pose is confirmed.
"""

from __future__ import annotations

from cgags_ros.geometry import make_transform, quaternion_to_matrix
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.pointcloud2 import pose_to_transform
import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from builtin_interfaces.msg import Time  # noqa: E402, I100
from cgags_ros.ros.node import RegisterNode  # noqa: E402
from cgags_ros.ros.outputs import transform_to_pose, xyz_to_pointcloud2  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_msgs.msg import Header, String  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from test_relocalizer import HARD, right  # noqa: E402
import test_sequence  # noqa: E402
from test_sequence import robot_odometry  # noqa: E402
from waiting import EXECUTOR_THREADS, ros_overrides, spun_context, wait_for  # noqa: E402

pytestmark = pytest.mark.ros
scene = test_sequence.scene  # the map without the sequence's fragments (a fixture)
DOMAIN_ID = 37  # distinct from the other DDS test modules
RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
BASE_FROM_SENSOR = (0.2, 0.0, 1.0, 0.0, 0.0, 0.7071068, 0.7071068)  # x y z qx qy qz qw


class Wire:
    """The test's side: scans and odometry out, calls, initialpose, results, diagnostics in."""

    def __init__(self, context):
        self.node = rclpy.create_node('relocalize_odometry_io', context=context)
        self.source_pub = self.node.create_publisher(PointCloud2, 'source_cloud', RELIABLE)
        self.odom_pub = self.node.create_publisher(Odometry, 'odom', RELIABLE)
        self.initial, self.results, self.values = [], [], {}
        self.node.create_subscription(PoseWithCovarianceStamped, 'initialpose',
                                      self.initial.append, 10)
        self.node.create_subscription(String, '/register_node/result', self.results.append,
                                      RELIABLE)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)
        self.client = self.node.create_client(Trigger, '/register_node/relocalize')

    def _on_diag(self, msg):
        for status in msg.status:
            if status.hardware_id == '/register_node':
                self.values = {kv.key: kv.value for kv in status.values}


def done(values):
    """Return how many scans the node has finished (published or rejected)."""
    return int(values.get('sources.published', 0)) + int(values.get('sources.rejected', 0))


def stamped(seconds, frame):
    return Header(stamp=Time(sec=seconds), frame_id=frame)


def test_calls_in_flight_are_answered_once_the_odometry_confirms_the_pose(scene):
    """
    On-demand calls wait over the scans; initialpose goes out once, when confirmed.

    The first scan alone is ambiguous: nothing is answered or published after it, while the
    calls stay in flight (more than the executor's threads) and the scans and diagnostics
    keep flowing. Once the scans and the odometry confirm a pose, every call answers
    success and initialpose carries the base's pose of that scan in the map.
    """
    _, cfg, poses, fragments, path = scene(HARD)
    odom = robot_odometry(poses, HARD, 2)  # odom <- sensor, with drift
    base = make_transform(quaternion_to_matrix(BASE_FROM_SENSOR[3:]), BASE_FROM_SENSOR[:3])
    with spun_context(DOMAIN_ID, Wire) as (context, executor, io):
        node = RegisterNode(context=context, parameter_overrides=ros_overrides(**{
            'map.file': str(path), 'map.cache_dir': '', 'voxel_size': cfg.voxel_size,
            'mode': 'on_demand', 'pairing.source_qos': 'reliable',
            'relocalization.publish_initial_pose': True, 'relocalization.cooldown': 0.0,
            'relocalization.base_from_sensor': list(BASE_FROM_SENSOR),
            'runtime.registration_timeout': 300.0, 'relocalization.timeout': 900.0,
            'relocalization.max_scan_age': 60.0, 'output.diagnostics_period': 0.2}))
        executor.add_node(node)
        try:
            wait_for(lambda: io.values.get('registration.ready') == 'True', 600.0,
                     'the registration process and the map', lambda: io.values)
            wait_for(lambda: io.source_pub.get_subscription_count() > 0
                     and io.odom_pub.get_subscription_count() > 0, 30.0, 'the subscriptions')
            assert io.client.wait_for_service(timeout_sec=30.0)
            calls = [io.client.call_async(Trigger.Request())
                     for _ in range(EXECUTOR_THREADS + 1)]
            wait_for(lambda: io.values.get('relocalize.calls') == str(len(calls)), 30.0,
                     'every call to reach the node', lambda: io.values)
            confirmed_at = None
            for i, (k, O) in enumerate(zip(HARD, odom)):
                msg = Odometry(header=stamped(100 + i, 'odom'), child_frame_id='base_link')
                msg.pose.pose = transform_to_pose(O @ np.linalg.inv(base))  # odom <- base
                io.odom_pub.publish(msg)
                wait_for(lambda: io.values.get('odometry.samples') == str(i + 1), 30.0,
                         f'odometry {i} to be received', lambda: io.values)
                io.source_pub.publish(xyz_to_pointcloud2(fragments[k],
                                                         stamped(100 + i, 'sensor')))
                wait_for(lambda: len(io.results) > i, 600.0, f'scan {i} to be registered',
                         lambda: io.values)
                # the calls are answered (and counted) before the scan is accounted as done
                wait_for(lambda: done(io.values) > i, 10.0, f'the diagnostics after scan {i}',
                         lambda: io.values)
                if i == 0:  # one scan: ambiguous; the calls wait and nothing is published
                    assert not any(c.done() for c in calls) and io.initial == []
                if any(k.startswith('relocalize.') and k != 'relocalize.calls'
                       for k in io.values):
                    wait_for(lambda: all(c.done() for c in calls), 30.0, 'the answers')
                    confirmed_at = i
                    break
            assert confirmed_at is not None and confirmed_at >= 1, io.values
            answers = [c.result() for c in calls]
            assert all(a.success and ' confirmed over ' in a.message for a in answers), answers
            wait_for(lambda: io.initial, 10.0, 'initialpose')
            assert len(io.initial) == 1 and io.initial[0].header.frame_id == 'map'
            assert io.initial[0].header.stamp.sec == 100 + confirmed_at
            T = pose_to_transform(io.initial[0].pose)
            T_gt = poses[HARD[confirmed_at]] @ np.linalg.inv(base)  # the base in the map
            assert right(T, T_gt), (rotation_error_deg(T, T_gt), translation_error(T, T_gt))
            wait_for(lambda: io.values.get('relocalize.succeeded') == str(len(calls)), 10.0,
                     'the answers counted', lambda: io.values)
            assert io.values['accounting.ok'] == 'True'
        finally:
            executor.remove_node(node)
            node.destroy_node()
