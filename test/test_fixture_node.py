"""
register_node over real DDS on the committed LiDAR fixture: the end-to-end test of a bare clone.

test/fixtures/small_gicp/ holds two consecutive LiDAR scans (koide3/small_gicp, MIT),
voxelized, with their ground truth; no ../shared is needed. The source is moved by a random
rotation of 90-180 degrees (and a few metres), so the node must register without an initial
guess. The node runs as users run it (``python -m cgags_ros.register_node``, its own
process); its ~/pose is checked against the ground truth composed with that motion.
"""

from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys

from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.clouds import read_cloud
from cgags_ros.io.pointcloud2 import pose_to_transform
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

rclpy = pytest.importorskip('rclpy')

from cgags_ros.ros.outputs import xyz_to_pointcloud2  # noqa: E402, I100
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_msgs.msg import Header  # noqa: E402
from waiting import ros_args, spun_context, stop_process, wait_for  # noqa: E402

pytestmark = pytest.mark.ros
REPO = Path(__file__).resolve().parents[1]
FIXTURE = REPO / 'test' / 'fixtures' / 'small_gicp'
DOMAIN_ID = 77  # distinct from the other DDS test modules
VOXEL_M = 0.4
# The real scans register to ~0.2 degrees / 3 cm here; a wrong solution is off by metres.
MAX_RE_DEG, MAX_TE_M = 2.0, 0.2
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
NODE = '/register_node'
# A fresh clone compiles the numba code first (no numba cache yet): minutes on a slow machine.
WARM_UP_S = 600


class Wire:
    """The test's side: publishers, the node's poses and its last /diagnostics values."""

    def __init__(self, context):
        self.node = rclpy.create_node('fixture_io', context=context)
        self.source_pub = self.node.create_publisher(PointCloud2, 'source_cloud', RELIABLE)
        self.target_pub = self.node.create_publisher(PointCloud2, 'target_cloud', LATCHED)
        self.poses: list[PoseStamped] = []
        self.values: dict[str, str] = {}
        self.node.create_subscription(PoseStamped, f'{NODE}/pose', self.poses.append, RELIABLE)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)

    def _on_diag(self, msg):
        for status in msg.status:
            if status.hardware_id == NODE:
                self.values = {kv.key: kv.value for kv in status.values}

    def pose_at(self, stamp_ns):
        return next((p for p in list(self.poses)
                     if p.header.stamp.sec * 10**9 + p.header.stamp.nanosec == stamp_ns), None)


def large_motion(rng):
    """Return a 4x4 rigid motion: a random axis, 90-180 degrees, up to 5 m along each axis."""
    axis = rng.normal(size=3)
    angle = np.radians(rng.uniform(90.0, 180.0))
    X = np.eye(4)
    X[:3, :3] = Rotation.from_rotvec(angle * axis / np.linalg.norm(axis)).as_matrix()
    X[:3, 3] = rng.uniform(-5.0, 5.0, 3)
    return X


def test_fixture_pair_over_dds_meets_ground_truth(tmp_path):
    source = read_cloud(FIXTURE / 'source.npy')
    target = read_cloud(FIXTURE / 'target.npy')
    T_target_source = np.loadtxt(FIXTURE / 'T_target_source.txt')
    X = large_motion(np.random.default_rng(24))
    assert np.degrees(Rotation.from_matrix(X[:3, :3]).magnitude()) >= 90.0
    moved = source @ X[:3, :3].T + X[:3, 3]
    truth = T_target_source @ np.linalg.inv(X)  # p_target = truth p_moved

    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID), PYTHONUNBUFFERED='1',
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    params = {'voxel_size': VOXEL_M, 'pairing.target_durability': 'transient_local',
              # Reliable so the test is deterministic on a loaded machine; sensor-data
              # (best-effort) transport is the DDS tests' subject, not this one's.
              'pairing.source_qos': 'reliable', 'output.diagnostics_period': 0.2}
    with spun_context(DOMAIN_ID, Wire) as (_, _, io):
        log = open(tmp_path / 'node.log', 'w+')  # a file, not a pipe: a full pipe would block
        proc = subprocess.Popen(
            [sys.executable, '-m', 'cgags_ros.register_node', '--ros-args']
            + ros_args(**params),
            cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, text=True)
        try:
            wait_for(lambda: io.source_pub.get_subscription_count()
                     and io.target_pub.get_subscription_count()
                     and io.node.count_publishers(f'{NODE}/pose'), 60, 'node discovery')
            # The publisher can see the match before the subscriber does, and a pair sent
            # while the registration process still compiles waits on it: wait for both.
            wait_for(lambda: io.values.get('registration.ready') == 'True', WARM_UP_S,
                     'the registration process to be ready', lambda: io.values)
            io.target_pub.publish(xyz_to_pointcloud2(target, Header(frame_id='map')))
            wait_for(lambda: io.values.get('received_target') == '1', 30, 'the target',
                     lambda: io.values)
            header = Header(frame_id='lidar')
            header.stamp.sec = 5
            io.source_pub.publish(xyz_to_pointcloud2(moved, header))
            pose = wait_for(lambda: io.pose_at(5 * 10**9), 120, 'the pose', lambda: io.values)
            values = wait_for(lambda: io.values.get('published') == '1' and io.values, 10,
                              'diagnostics after the pose')
        finally:
            out = stop_process(proc, log)
    assert proc.returncode == 0 and 'Traceback' not in out, out
    assert pose.header.frame_id == 'map'
    T = pose_to_transform(pose)
    re, te = rotation_error_deg(T, truth), translation_error(T, truth)
    assert re < MAX_RE_DEG and te < MAX_TE_M, f'RE {re:.3f} deg, TE {te:.3f} m'
    assert values['accounting.ok'] == 'True' and values['sources.received'] == '1'
