"""
4-DoF mode through register_node over real DDS: ``core.motion_model:=4dof``.

The node runs in-process with the parameter override; the levelled LiDAR pair (see
test_motion_4dof_pipeline.py) under a random yaw and offset is published, and ~/pose is
checked against the yaw-only truth, with roll and pitch zero.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

rclpy = pytest.importorskip('rclpy')

# Imported only after the rclpy skip above: hence E402, and I100 for the first-party block
# placed after the third-party ones.
from cgags_ros.geometry import apply_transform, rotation_error_deg  # noqa: E402, I100
from cgags_ros.geometry import translation_error  # noqa: E402
from cgags_ros.io.clouds import read_cloud  # noqa: E402
from cgags_ros.io.pointcloud2 import pose_to_transform  # noqa: E402
from cgags_ros.ros.node import RegisterNode  # noqa: E402
from cgags_ros.ros.outputs import to_rclpy_pointcloud2, xyz_to_pointcloud2  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_msgs.msg import Header  # noqa: E402
from waiting import spun_context, wait_for  # noqa: E402

pytestmark = pytest.mark.ros
DOMAIN_ID = 71  # distinct from the other DDS test modules
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def yaw_matrix(angle: float) -> np.ndarray:
    return Rotation.from_euler('z', angle).as_matrix()


def levelled_problem(data_dir, rng):
    """Return the levelled LiDAR source under a random yaw + offset, target and truth."""
    folder = data_dir / 'lidar' / 'small_gicp'
    src, tgt = read_cloud(folder / 'source.ply'), read_cloud(folder / 'target.ply')
    T = np.loadtxt(folder / 'T_target_source.txt')
    yaw = np.arctan2(T[1, 0] - T[0, 1], T[0, 0] + T[1, 1])
    src = src @ (yaw_matrix(yaw).T @ T[:3, :3]).T  # levelled: the truth is yaw-only
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = yaw_matrix(yaw), T[:3, 3]
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = yaw_matrix(rng.uniform(-np.pi, np.pi)), rng.uniform(-5, 5, 3)
    return apply_transform(M, src), tgt, truth @ np.linalg.inv(M)


def cloud_msg(points, frame, stamp_ns):
    header = Header(frame_id=frame)
    header.stamp.sec, header.stamp.nanosec = divmod(stamp_ns, 10**9)
    return to_rclpy_pointcloud2(xyz_to_pointcloud2(points.astype(np.float32), header))


class Wire:
    """The test's node, in the module's own context."""

    def __init__(self, context):
        self.node = rclpy.create_node('test_io_4dof', context=context)


@pytest.fixture
def ros():
    with spun_context(DOMAIN_ID, Wire) as (context, executor, wire):
        yield context, executor, wire.node


def test_node_4dof_parameter_registers_levelled_lidar(ros, data_dir):
    context, executor, io = ros
    src, tgt, truth = levelled_problem(data_dir, np.random.default_rng(21))
    poses: list[PoseStamped] = []
    io.create_subscription(PoseStamped, '/register_node/pose', poses.append, 10)
    source_pub = io.create_publisher(PointCloud2, 'source_cloud', 10)
    target_pub = io.create_publisher(PointCloud2, 'target_cloud', LATCHED)
    overrides = [Parameter('core.motion_model', value='4dof'),
                 Parameter('voxel_size', value=0.3)]
    node = RegisterNode(context=context, parameter_overrides=overrides)
    executor.add_node(node)
    try:
        assert node.get_parameter('core.motion_model').value == '4dof'
        wait_for(lambda: (source_pub.get_subscription_count()
                          and target_pub.get_subscription_count()
                          and io.count_publishers('/register_node/pose')), 20, 'DDS matching')
        target_pub.publish(cloud_msg(tgt, 'map', 1 * 10**9))
        wait_for(lambda: node.statistics().get('received_target'), 20, 'target')
        source_pub.publish(cloud_msg(src, 'lidar', 2 * 10**9))
        pose = wait_for(lambda: poses and poses[-1], 120, 'the pose')
        T = pose_to_transform(pose)
        assert pose.header.frame_id == 'map'
        assert rotation_error_deg(T, truth) < 0.5 and translation_error(T, truth) < 0.1
        # Roll and pitch zero: the quaternion is a rotation about z alone (float64 on the wire).
        assert abs(pose.pose.orientation.x) < 1e-12 and abs(pose.pose.orientation.y) < 1e-12
    finally:
        executor.remove_node(node)
        node.destroy_node()
