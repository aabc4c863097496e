"""
Run register_node under faults over real DDS; every cloud must end in a counted bucket.

The faults: a dying registration process, floods of malformed clouds, fuzzed parameters and a bag
replayed in a loop.

The node runs in this process with its own rclpy context and DDS domain; accuracy checks
run the real pipeline and compare ~/pose with the bag's /ground_truth.
"""

from __future__ import annotations

import copy
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from cgags_ros.config import fields
from cgags_ros.config.node import ros_parameter_descriptions, ros_value
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.pointcloud2 import pose_to_transform
from cgags_ros.pipeline.result import PipelineResult
from cgags_ros.runtime.procfs import running
import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from cgags_ros.ros.node import RegisterNode  # noqa: E402, I100
from cgags_ros.ros.outputs import xyz_to_pointcloud2  # noqa: E402
from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_msgs.msg import Header  # noqa: E402
from waiting import CloudWire, FakeRunner, lidar_bag, ros_args, ros_overrides  # noqa: E402
from waiting import spun_context, stop_process, wait_for  # noqa: E402

pytestmark = pytest.mark.ros
DOMAIN_ID = 53  # distinct from the other DDS test modules
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
RELIABLE = QoSProfile(depth=500, reliability=ReliabilityPolicy.RELIABLE)
LIDAR = {'voxel_size': 0.4, 'pairing.source_qos': 'reliable', 'pairing.source_depth': 500,
         'pairing.target_depth': 500, 'pairing.target_durability': 'transient_local',
         'pairing.queue_depth': 50, 'output.diagnostics_period': 0.1}


class Wire(CloudWire):
    """The test's side: publishers, the node's poses and its last /diagnostics."""

    def __init__(self, context):
        super().__init__(context, 'reliability_io', RELIABLE.depth)


@pytest.fixture(scope='module')
def wire():
    with spun_context(DOMAIN_ID, Wire) as spun:
        yield spun


@pytest.fixture(scope='module')
def lidar(data_dir):
    """Return (records in log order as rclpy clouds, ground truth by source stamp)."""
    return lidar_bag(data_dir)


def start(wire, register=None, **params):
    """Start the node; ``register`` stands in for the registration process (FakeRunner)."""
    if register is not None:  # pairs, not a tracked stream, for a stand-in registration
        params.setdefault('tracking.enabled', False)
    context, executor, io = wire
    node = RegisterNode(runner=FakeRunner(register) if register else None, context=context,
                        parameter_overrides=ros_overrides(**params))
    executor.add_node(node)
    try:
        wait_for(lambda: io.source_pub.get_subscription_count()
                 and io.target_pub.get_subscription_count()
                 and io.node.count_publishers('/register_node/pose'), 60, 'discovery')
        wait_for(lambda: io.values.get('sources.received') == '0', 60, 'first diagnostics',
                 lambda: (io.values, node.statistics()))
    except BaseException:
        stop(wire, node)  # its registration process must not outlive the failed test
        raise
    return node


def stop(wire, node):
    io = wire[2]
    wire[1].remove_node(node)
    node.destroy_node()
    io.values, io.level = {}, None
    # A fresh latched publisher: the next test's node must not receive this one's target.
    io.node.destroy_publisher(io.target_pub)
    io.target_pub = io.node.create_publisher(PointCloud2, 'target_cloud', LATCHED)


def check(pose, gt, stamp):
    T = pose_to_transform(pose)
    re, te = rotation_error_deg(T, gt[stamp]), translation_error(T, gt[stamp])
    assert re < 5.0 and te < 0.6, f'RE {re:.2f} deg, TE {te:.3f} m'


def balanced(values):
    """Check the accounting invariant on one /diagnostics message; return its values."""
    v = {k: int(x) for k, x in values.items()
         if k.startswith(('sources.', 'targets.')) and x.lstrip('-').isdigit()}
    assert v['sources.received'] == (v['sources.published'] + v['sources.rejected']
                                     + v['sources.dropped'] + v['sources.pending']), values
    assert v['targets.received'] == (v['targets.used'] + v['targets.rejected']
                                     + v['targets.dropped'] + v['targets.pending']), values
    assert values['accounting.ok'] == 'True'
    return values


def test_killed_registration_process_idle_and_busy_is_replaced_and_the_next_pair_is_correct(
        wire, lidar):
    _, _, io = wire
    records, gt = lidar
    targets = [m for t, _, m in records if t == '/target_cloud']
    sources = [(s, m) for t, s, m in records if t == '/source_cloud']
    node = start(wire, **LIDAR)
    iso = node.engine.runner
    try:
        io.target_pub.publish(targets[0])
        stamp, msg = sources[0]
        io.source_pub.publish(msg)
        check(wait_for(lambda: io.pose_at(stamp), 60, 'first pose', node.statistics), gt, stamp)

        # killed while idle: the next pair runs on a fresh process
        pid = iso.pid
        os.kill(pid, signal.SIGKILL)
        wait_for(lambda: not running(pid), 10, 'the registration process to die')
        stamp, msg = sources[1]
        io.source_pub.publish(msg)
        check(wait_for(lambda: io.pose_at(stamp), 60, 'pose after an idle kill',
                       node.statistics), gt, stamp)
        assert iso.pid != pid and iso.crashes == 1

        # killed while registering: that pair is rejected and counted, the next one works
        rng = np.random.default_rng(0)
        noise = xyz_to_pointcloud2(rng.uniform(-40, 40, size=(60000, 3)),
                                   Header(frame_id='velodyne'))
        noise.header.stamp.sec = 1_700_000_001
        io.source_pub.publish(noise)
        wait_for(lambda: iso.in_flight, 30, 'the noise pair to reach the registration process')
        pid = iso.pid
        os.kill(pid, signal.SIGKILL)
        values = wait_for(lambda: io.values.get('rejected.process_crashed') == '1'
                          and io.values, 30, 'the crash in /diagnostics', node.statistics)
        assert io.level == DiagnosticStatus.ERROR
        assert values['registration.failing'] == 'process_crashed'
        assert int(values['registration.crashes']) == 2
        assert int(values['registration.restarts']) == 2
        stamp, msg = sources[2]
        stamp += 2 * 10**9  # after the noise cloud's stamp
        msg = copy.deepcopy(msg)
        msg.header.stamp.sec += 2
        io.source_pub.publish(msg)
        wait_for(lambda: io.pose_at(stamp), 60, 'pose after a busy kill', node.statistics)
        check(io.pose_at(stamp), {stamp: gt[sources[2][0]]}, stamp)
        values = wait_for(lambda: io.values.get('published') == '3' and io.level is not None
                          and io.level < DiagnosticStatus.ERROR and io.values, 10,
                          'the status to recover')
        balanced(values)
        assert float(values['memory.node_rss_mb']) > 0
        assert float(values['memory.registration_rss_mb']) > 0
    finally:
        stop(wire, node)


def malformed(rng, n):
    """Yield ``n`` broken PointCloud2 messages of varied kinds."""
    good = xyz_to_pointcloud2(rng.random((50, 3)), Header(frame_id='f'))
    for k in range(n):
        msg = xyz_to_pointcloud2(rng.random((50, 3)), Header(frame_id='f'))
        kind = k % 6
        if kind == 0:
            msg.row_step += 4  # header disagrees with the data
        elif kind == 1:
            msg.data = good.data[:int(rng.integers(0, len(good.data) - 1))]
        elif kind == 2:
            msg.fields = msg.fields[:2]  # no z
        elif kind == 3:
            msg.fields[0].datatype = 5  # INT32 x
        elif kind == 4:
            msg = xyz_to_pointcloud2(np.full((30, 3), np.nan), Header(frame_id='f'))
        else:
            msg.width = int(rng.integers(10**8, 10**9))  # absurd size claim
        yield msg


def test_malformed_floods_on_both_topics_are_counted_then_a_good_pair_publishes(wire, lidar):
    _, _, io = wire
    records, gt = lidar
    node = start(wire, **LIDAR)
    # Deep enough that the burst of targets is delivered whole (a depth-1 writer would
    # overwrite samples before they are acknowledged); destroyed after the test, so that
    # no later node receives its history.
    burst = io.node.create_publisher(PointCloud2, 'target_cloud', QoSProfile(
        depth=500, reliability=RELIABLE.reliability, durability=LATCHED.durability))
    try:
        wait_for(lambda: burst.get_subscription_count(), 20, 'the burst publisher to match')
        rng = np.random.default_rng(3)
        for src, tgt in zip(malformed(rng, 200), malformed(rng, 200)):
            io.source_pub.publish(src)
            burst.publish(tgt)
        wait_for(lambda: node.statistics().get('received_target') == 200, 60, 'the flood',
                 lambda: (node.statistics() or 'unconfigured', node._state_machine.current_state))
        target = next(m for t, _, m in records if t == '/target_cloud')
        stamp, source = next((s, m) for t, s, m in records if t == '/source_cloud')
        io.target_pub.publish(target)
        wait_for(lambda: node.statistics().get('received_target') == 201, 20, 'the good target',
                 node.statistics)
        io.source_pub.publish(source)
        check(wait_for(lambda: io.pose_at(stamp), 60, 'the good pose', node.statistics),
              gt, stamp)
        values = wait_for(lambda: io.values.get('published') == '1' and io.values, 10,
                          'diagnostics after the pose')
        balanced(values)
        assert values['sources.received'] == values['targets.received'] == '201'
        assert values['sources.rejected'] == values['targets.rejected'] == '200'
        assert int(values['rejected.bad_input']) + int(values['rejected.too_few_points'])\
            == 200
    finally:
        io.node.destroy_publisher(burst)
        stop(wire, node)


FUZZ_VALUES = ['', 'bogus', float('nan'), float('inf'), -1.0, 0.0, 1e9, -5, 0, 3, 10**12,
               True, False, 0.3, 2, 'latest_target', 'gicp', 'none', 'soft']
VECTOR_FUZZ = [[0.0, 0.0, 0.0], [0.0, 1.0], [0.0, -2.0, 0.5], [float('nan')] * 3, [1.0] * 7,
               [0.1, 0.2, 0.3, 0.0, 0.0, 0.0, 2.0], [0.0] * 7, []]


def test_parameter_fuzzing_applies_or_refuses_and_the_next_pair_uses_what_was_accepted(wire):
    _, _, io = wire
    seen = []

    def record(source, target, *, config):
        seen.append(config)
        return PipelineResult(transform=np.eye(4), refusal=None, inliers=np.arange(10),
                              num_correspondences=20, inlier_threshold=0.05)

    node = start(wire, record, **{'output.diagnostics_period': 0.1})
    try:
        rng = np.random.default_rng(7)
        expected = {name: node.get_parameter(name).value
                    for name in ros_parameter_descriptions()}
        tries = [(name, value.item() if hasattr(value, 'item') else value)
                 for name in sorted(expected)
                 for value in rng.permutation(np.array(FUZZ_VALUES, dtype=object))[:8]]
        tries += [(name, value) for name in ('core.gravity', 'relocalization.base_from_sensor')
                  for value in VECTOR_FUZZ]
        for name, value in tries:
            result = node.set_parameters([Parameter(name, value=value)])[0]
            if result.successful:
                expected[name] = value
            else:
                assert result.reason, (name, value)
        # Settings that would refuse or starve the test's own pair, set back to sane values
        for name, value in [('voxel_size', 0.3), ('output.publish_invalid', True)]:
            assert node.set_parameters([Parameter(name, value=value)])[0].successful
            expected[name] = value
        for name, value in expected.items():
            got = node.get_parameter(name).value
            assert got == value or (got != got and value != value), name
        io.target_pub.publish(xyz_to_pointcloud2(np.random.rand(100, 3), Header(frame_id='m')))
        msg = xyz_to_pointcloud2(np.random.rand(100, 3), Header(frame_id='s'))
        msg.header.stamp.sec = 10**6
        io.source_pub.publish(msg)
        wait_for(lambda: seen, 20, 'the pair after fuzzing', node.statistics)
        applied = {k: ros_value(v) for k, v in fields.flatten(seen[-1]).items()}
        expected_keys = {k: v for k, v in expected.items() if k in applied}
        assert {'voxel_size', 'core.gravity', 'core.time_budget'} <= set(expected_keys)
        assert {k: applied[k] for k in expected_keys} == expected_keys
    finally:
        stop(wire, node)


def test_a_bag_replayed_twice_gives_the_same_poses(wire, lidar):
    _, _, io = wire
    records, gt = lidar
    sources = [s for t, s, _ in records if t == '/source_cloud']
    node = start(wire, **LIDAR)
    try:
        loops = []
        for loop in range(2):
            io.poses.clear()
            for topic, _, msg in records:
                (io.target_pub if topic == '/target_cloud' else io.source_pub).publish(msg)
                time.sleep(0.05)
            wait_for(lambda: all(io.pose_at(s) for s in sources), 90, f'loop {loop} poses',
                     node.statistics)
            loops.append({s: pose_to_transform(io.pose_at(s)) for s in sources})
        for stamp in sources:
            check(io.pose_at(stamp), gt, stamp)
            np.testing.assert_allclose(loops[0][stamp], loops[1][stamp], atol=1e-9)
        values = wait_for(lambda: io.values.get('published') == str(2 * len(sources))
                          and io.values, 10, 'diagnostics after both loops')
        balanced(values)
        assert values['pairing.clock_resets.source_stamp_backwards'] == '1'
    finally:
        stop(wire, node)


def test_separate_process_node_survives_a_registration_process_kill_quietly(wire, lidar,
                                                                            tmp_path):
    """The node as users run it: a killed registration process is replaced, no traceback."""
    _, _, io = wire
    records, gt = lidar
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID), PYTHONUNBUFFERED='1',
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    log = open(tmp_path / 'node.log', 'w+')  # a file, not a pipe: a full pipe would block
    proc = subprocess.Popen(
        [sys.executable, '-m', 'cgags_ros.register_node', '--ros-args'] + ros_args(**LIDAR),
        cwd=Path(__file__).resolve().parents[1], env=env, stdout=log,
        stderr=subprocess.STDOUT, text=True)
    try:
        wait_for(lambda: io.source_pub.get_subscription_count()
                 and io.target_pub.get_subscription_count()
                 and io.values.get('sources.received') == '0'
                 and int(io.values.get('registration.pid', 0)), 60,
                 'the node and its registration process')
        pid = int(io.values['registration.pid'])
        os.kill(pid, signal.SIGKILL)
        values = wait_for(lambda: io.values.get('registration.crashes') == '1' and io.values, 20,
                          'the idle crash in /diagnostics')
        assert io.level == DiagnosticStatus.ERROR and int(values['registration.pid']) != pid
        io.poses.clear()  # an earlier test's pose at this stamp is no answer of this node
        io.target_pub.publish(next(m for t, _, m in records if t == '/target_cloud'))
        stamp, source = next((s, m) for t, s, m in records if t == '/source_cloud')
        io.source_pub.publish(source)
        check(wait_for(lambda: io.pose_at(stamp), 60, 'the pose after the kill'), gt, stamp)
        balanced(wait_for(lambda: io.values.get('published') == '1' and io.values, 10,
                          'diagnostics after the pose', lambda: io.values))
    finally:
        out = stop_process(proc, log)
        io.values, io.level = {}, None
    assert proc.returncode == 0, out
    assert 'Traceback' not in out and 'KeyError' not in out, out
