"""
register_node in ``mode: calibrate`` over real DDS: three synchronized frames -> ~/calibration.

The simulated OpenCalib rig: the top LiDAR is the parent (target_cloud), the left LiDAR the
child (source_cloud). The latched ~/calibration pose is checked against the rig's reference
extrinsic within its spread, and nothing is published before the calibration has ended;
with tf2_msgs importable, /tf_static must carry parent <- child.
"""

from __future__ import annotations

import json

from bench.datasets.rigs import OPENCALIB, opencalib_rig, REFERENCE
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.pointcloud2 import pose_to_transform
import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from cgags_ros.ros.node import RegisterNode  # noqa: E402, I100
from cgags_ros.ros.outputs import xyz_to_pointcloud2  # noqa: E402
from cgags_ros.ros.qos import latched_qos  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from std_msgs.msg import Header, String  # noqa: E402
from waiting import CloudWire, ros_overrides, spun_context, wait_for  # noqa: E402

pytestmark = pytest.mark.ros
DOMAIN_ID = 96  # distinct from the other DDS test modules
TOLERANCE = (0.2, 0.03)  # simulated rig: deg, m (the reference spread)
PARAMS = {'mode': 'calibrate', 'voxel_size': 0.3, 'pairing.source_qos': 'reliable',
          'pairing.source_depth': 10, 'pairing.target_durability': 'transient_local',
          'output.diagnostics_period': 0.1}


class Wire(CloudWire):
    """The test's side: clouds out; ~/calibration, its report and /tf_static in."""

    def __init__(self, context):
        super().__init__(context, 'calibrate_io', 10)
        self.calibrations, self.reports, self.static = [], [], []
        node = self.node
        node.create_subscription(PoseWithCovarianceStamped, '/register_node/calibration',
                                 self.calibrations.append, latched_qos())
        node.create_subscription(String, '/register_node/calibration_report',
                                 self.reports.append, latched_qos())
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            self.has_tf = False
        else:
            self.has_tf = True
            node.create_subscription(TFMessage, '/tf_static', self.static.append,
                                     latched_qos())


@pytest.fixture(scope='module')
def rig(data_dir, require_shared):
    require_shared(data_dir / OPENCALIB, 'OpenCalib lidar2lidar rigs', marker=REFERENCE)
    frames, reference, _ = opencalib_rig(data_dir, 'carla_data', 'left')
    return frames[:3], reference


def _cloud(xyz, frame_id, stamp_ns):
    header = Header(frame_id=frame_id)
    header.stamp.sec, header.stamp.nanosec = divmod(stamp_ns, 10**9)
    return xyz_to_pointcloud2(xyz, header)


def test_three_frames_publish_the_reference_extrinsic_latched(rig):
    frames, reference = rig
    with spun_context(DOMAIN_ID, Wire) as (context, executor, io):
        node = RegisterNode(context=context, parameter_overrides=ros_overrides(**PARAMS))
        executor.add_node(node)
        try:
            state = lambda: dict(io.values)  # noqa: E731
            wait_for(lambda: io.values.get('calibration.status') == 'collecting', 60,
                     'the node in calibrate mode', state)
            for k, f in enumerate(frames):
                t = (10 + k) * 10**9
                io.target_pub.publish(_cloud(f.parent, 'top', t))
                # the child 20 ms before: the pair is final once this parent is there
                io.source_pub.publish(_cloud(f.child, 'left', t - 20_000_000))
                wait_for(lambda: io.values.get('calibration.frames_taken') == str(k + 1),
                         300, f'frame {k} taken', state)
                if k < 2:
                    assert not io.calibrations
            wait_for(lambda: io.calibrations, 60, 'the calibration', state)
            msg = io.calibrations[0]
            assert msg.header.frame_id == 'top'
            T = pose_to_transform(msg.pose.pose)
            assert rotation_error_deg(T, reference) <= TOLERANCE[0]
            assert translation_error(T, reference) <= TOLERANCE[1]
            wait_for(lambda: io.reports, 30, 'the report', state)
            report = json.loads(io.reports[0].data)
            assert (report['parent_frame'], report['child_frame']) == ('top', 'left')
            wait_for(lambda: io.values.get('calibration.status') in ('converged', 'max_frames'),
                     30, 'the status', state)
            assert io.values['calibration.frames_agreeing'] == '3'
            if io.has_tf:
                wait_for(lambda: io.static, 30, '/tf_static', state)
                tf = io.static[0].transforms[0]
                assert (tf.header.frame_id, tf.child_frame_id) == ('top', 'left')
                t, q = tf.transform.translation, tf.transform.rotation
                o = msg.pose.pose.orientation
                np.testing.assert_allclose([t.x, t.y, t.z], T[:3, 3], atol=1e-6)
                np.testing.assert_allclose([q.x, q.y, q.z, q.w], [o.x, o.y, o.z, o.w])
        finally:
            executor.remove_node(node)
            node.destroy_node()
