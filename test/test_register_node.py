"""
cgags_ros.ros.node: the node over real DDS, with the real pipeline on the bags' clouds.

In-process: the node and a test "io" node share one executor on a thread. Out-of-process:
``python -m cgags_ros.register_node --ros-args ...``, stopped with SIGTERM. Only the
plumbing test injects a fake registration; every accuracy check runs the real pipeline and
compares ~/pose with the bag's /ground_truth (same stamp as the source cloud).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
import subprocess
import sys
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

# Imported only after the rclpy skip above: hence E402, and I100 for the first-party block
# placed after numpy and pytest.
from cgags_ros.errors import InvalidConfigError  # noqa: E402, I100
from cgags_ros.geometry import rotation_error_deg, translation_error  # noqa: E402
from cgags_ros.io.bag import read_messages  # noqa: E402
from cgags_ros.io.pointcloud2 import pose_to_transform  # noqa: E402
from cgags_ros.pipeline.result import PipelineResult  # noqa: E402
from cgags_ros.refusal import Refusal, RefusalCode  # noqa: E402
from cgags_ros.ros.node import RegisterNode  # noqa: E402
from cgags_ros.ros.outputs import to_rclpy_pointcloud2, xyz_to_pointcloud2  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_msgs.msg import Header  # noqa: E402
from waiting import FakeRunner, ros_args, ros_overrides, spun_context  # noqa: E402
from waiting import stop_process, wait_for  # noqa: E402

pytestmark = pytest.mark.ros
DOMAIN_ID = 47  # distinct from the other DDS test modules
REPO = Path(__file__).resolve().parents[1]
LIMITS = {'bunny': (5.0, 0.01), 'redkitchen': (15.0, 0.3), 'lidar': (5.0, 0.6),
          'faulty': (5.0, 0.01)}
VOXEL = {'bunny': 0.003, 'redkitchen': 0.05, 'lidar': 0.4, 'faulty': 0.003}
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


class Bag:
    """A test bag: records in log order, rclpy clouds, ground truth by source stamp."""

    def __init__(self, path: Path):
        self.records = []  # (topic, stamp_ns, rclpy msg)
        self.gt = {}
        for rec in read_messages(path):
            if rec.topic == '/ground_truth':
                self.gt[rec.stamp_ns] = pose_to_transform(rec.msg)
            else:
                self.records.append((rec.topic, rec.stamp_ns, to_rclpy_pointcloud2(rec.msg)))

    def clouds(self, topic):
        return [(stamp, msg) for t, stamp, msg in self.records if t == topic]


_BAGS: dict[str, Bag] = {}


def bag(data_dir, name) -> Bag:
    if name not in _BAGS:
        _BAGS[name] = Bag(data_dir / 'bags' / name)
    return _BAGS[name]


def check_pose(pose: PoseStamped, b: Bag, name: str, stamp: int, target_frame: str):
    assert pose.header.frame_id == target_frame
    T = pose_to_transform(pose)
    re, te = rotation_error_deg(T, b.gt[stamp]), translation_error(T, b.gt[stamp])
    max_re, max_te = LIMITS[name]
    assert re < max_re and te < max_te, f'{name}: RE {re:.2f} deg, TE {te:.4f} m'


class IO:
    """The test's side of the wire: publishes clouds, records poses and diagnostics."""

    def __init__(self, context, namespace_node='/register_node'):
        self.node = rclpy.create_node('test_io', context=context)
        self.source_pub = self.node.create_publisher(PointCloud2, 'source_cloud', 10)
        self.target_pub = self.node.create_publisher(PointCloud2, 'target_cloud', LATCHED)
        self.poses: list[PoseStamped] = []
        self.cov: list[PoseWithCovarianceStamped] = []
        self.aligned: list[PointCloud2] = []
        self.diag: dict[str, dict[str, str]] = {}
        self.node.create_subscription(PoseStamped, f'{namespace_node}/pose', self.poses.append, 10)
        self.node.create_subscription(PoseWithCovarianceStamped,
                                      f'{namespace_node}/pose_with_covariance',
                                      self.cov.append, 10)
        self.node.create_subscription(PointCloud2, f'{namespace_node}/aligned_cloud',
                                      self.aligned.append, 10)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)

    def _on_diag(self, msg):
        for status in msg.status:
            self.diag[status.hardware_id] = {kv.key: kv.value for kv in status.values}

    def pose_at(self, stamp_ns):
        for pose in list(self.poses):
            if pose.header.stamp.sec * 10**9 + pose.header.stamp.nanosec == stamp_ns:
                return pose
        return None


@pytest.fixture(scope='module')
def ros():
    """Provide the module's executor (own context and domain), spinning io and any node added."""
    with spun_context(DOMAIN_ID, IO) as (_, executor, io):
        yield executor, io


def start_node(executor, register=None, **params) -> RegisterNode:
    """Start the node; ``register`` stands in for the registration process (FakeRunner)."""
    if register is not None:  # pairs, not a tracked stream, for a stand-in registration
        params.setdefault('tracking.enabled', False)
    node = RegisterNode(runner=FakeRunner(register) if register else None,
                        context=executor.context, parameter_overrides=ros_overrides(**params))
    executor.add_node(node)
    return node


def stop_node(executor, node):
    executor.remove_node(node)
    node.destroy_node()


# ------------------------------------------------------------------------ plumbing (fake)


def fake_register(source, target, *, config):
    """Stand-in for the pipeline: translation = voxel_size along x; invalid above 1 m."""
    T = np.eye(4)
    T[0, 3] = config.voxel_size
    return PipelineResult(transform=T, refusal=None if config.voxel_size <= 1.0 else Refusal(
                              RefusalCode.FEW_INLIERS, 'fake: too coarse'),
                          inliers=np.arange(12), num_correspondences=20,
                          inlier_threshold=0.05)


def test_plumbing_parameters_outputs_and_rejections(ros):
    executor, io = ros
    node = start_node(executor, fake_register, **{'output.diagnostics_period': 0.1,
                                                  'output.publish_aligned_cloud': True})
    try:
        # parameters are generated from the dataclasses, with ranges and read-only flags
        names = {'voxel_size', 'core.gravity', 'pairing.mode', 'output.publish_invalid'}
        assert names <= set(node._parameters)
        d = node.describe_parameter('voxel_size')
        assert d.floating_point_range[0].from_value > 0 and 'metres' in d.description
        assert node.describe_parameter('pairing.mode').read_only
        assert 'synchronized' in node.describe_parameter('pairing.mode').additional_constraints
        assert node.describe_parameter('pairing.queue_depth').integer_range
        assert node.get_parameter('core.gravity').value == [0.0, 0.0, 1.0]

        rng = np.random.default_rng(1)
        pts = rng.random((500, 3))
        io.target_pub.publish(xyz_to_pointcloud2(pts, Header(frame_id='map')))
        wait_for(lambda: node.statistics().get('received_target'), 5, 'target')
        bad = xyz_to_pointcloud2(pts, Header(frame_id='lidar'))
        bad.row_step += 4  # data length no longer matches
        io.source_pub.publish(bad)
        io.source_pub.publish(xyz_to_pointcloud2(np.zeros((0, 3)), Header(frame_id='lidar')))
        good = xyz_to_pointcloud2(pts, Header(frame_id='lidar'))
        good.header.stamp.sec = 7
        io.source_pub.publish(good)
        pose = wait_for(lambda: io.pose_at(7 * 10**9), 5, 'pose of the good source')
        assert pose.header.frame_id == 'map' and pose.pose.position.x == pytest.approx(0.05)
        wait_for(lambda: io.aligned and io.cov, 5, 'aligned cloud and covariance')
        assert io.aligned[-1].header.frame_id == 'map' and io.aligned[-1].width == 500
        cov = np.array(io.cov[-1].pose.covariance).reshape(6, 6)
        assert np.allclose(cov, cov.T) and (np.diag(cov) > 0).all()
        stats = node.statistics()
        assert stats['rejected.bad_input'] == 1 and stats['rejected.too_few_points'] == 1

        # live changes: invalid ones are refused with a reason; valid ones apply next pair
        for name, value, why in [('core.motion_model', 'bogus', 'one of'),
                                 ('voxel_size', -1.0, 'out of range'),
                                 ('pairing.mode', 'synchronized', 'read-only'),
                                 ('pairing_mode', 'synchronized', 'unknown parameter'),
                                 ('core.edge_tournament', 4,
                                  'not a ROS parameter; set it in the YAML of config_file'),
                                 ('core.gravity', [0.0, 0.0, 0.0], 'zero length'),
                                 ('core.gravity', [0.0, 1.0], 'list of 3 finite numbers')]:
            result = node.set_parameters([Parameter(name, value=value)])[0]
            assert not result.successful and why in result.reason, (name, result.reason)
        assert node.set_parameters([Parameter('voxel_size', value=2.0)])[0].successful
        good.header.stamp.sec = 8
        io.source_pub.publish(good)  # fake marks voxel_size > 1 invalid: not published
        wait_for(lambda: node.statistics().get('rejected.few_inliers'), 5, 'invalid result')
        assert io.pose_at(8 * 10**9) is None
        stats = node.statistics()  # the refusal's code beside its message
        assert (stats['last_valid'], stats['last_refusal_code'], stats['last_reason']) == (
            False, 'few_inliers', 'fake: too coarse')
        wait_for(lambda: io.diag.get(node.get_fully_qualified_name(), {})
                 .get('last_refusal_code') == 'few_inliers', 5, 'the code on /diagnostics')
        node.set_parameters([Parameter('output.publish_invalid', value=True)])
        good.header.stamp.sec = 9
        io.source_pub.publish(good)
        wait_for(lambda: io.pose_at(9 * 10**9), 5, 'invalid pose with publish_invalid')
        diag = wait_for(lambda: io.diag.get(node.get_fully_qualified_name(), {})
                        .get('published_invalid'), 5, 'diagnostics')
        assert diag == '1'
    finally:
        stop_node(executor, node)


def test_invalid_startup_parameter_raises(ros):
    executor, _ = ros
    with pytest.raises(InvalidConfigError, match="pairing.mode = 'nearest' is not one of"):
        RegisterNode(runner=FakeRunner(fake_register), context=executor.context,
                     parameter_overrides=[Parameter('pairing.mode', value='nearest')])
    # a name that is no ROS parameter: refused, saying where it belongs
    with pytest.raises(InvalidConfigError, match='pairing_mode: unknown parameter'):
        RegisterNode(runner=FakeRunner(fake_register), context=executor.context,
                     parameter_overrides=[Parameter('pairing_mode', value='synchronized')])
    with pytest.raises(InvalidConfigError, match='core.p1: not a ROS parameter; set it in'):
        RegisterNode(runner=FakeRunner(fake_register), context=executor.context,
                     parameter_overrides=[Parameter('core.p1', value=0.9)])


def test_config_file_sits_between_the_defaults_and_the_ros_parameters(tmp_path):
    """
    Check a value's precedence in the node: default < config_file < params file < -p.

    Through rclpy's own argument handling (``--ros-args --params-file ... -p ...``), as
    ``ros2 run`` passes them. ``config_file`` may hold any key, ROS parameters included.
    """
    from rclpy.context import Context

    config = tmp_path / 'config_file.yaml'  # nested and flat keys, wrapped as a params file
    config.write_text('register_node:\n  ros__parameters:\n    voxel_size: 0.7\n'
                      '    pairing:\n      sync_slop: 0.2\n      max_waiting_sources: 3\n'
                      '    core.gravity: [0.0, 1.0, 0.0]\n    core.p1: 0.9\n'
                      '    output.publish_invalid: true\n')
    params = tmp_path / 'params.yaml'  # the same format: overrides config_file
    params.write_text('/**:\n  ros__parameters:\n    pairing.sync_slop: 0.3\n'
                      f'    config_file: {config}\n    output.publish_invalid: false\n')
    context = Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID, args=[
        '--ros-args', '--params-file', str(params), '-p', 'pairing.sync_slop:=0.4',
        '-p', 'autostart:=false'])
    node = RegisterNode(runner=FakeRunner(fake_register), context=context)
    try:
        value = {name: node.get_parameter(name).value for name in (
            'voxel_size', 'pairing.sync_slop', 'core.gravity', 'output.publish_invalid',
            'output.diagnostics_period')}
        assert value == {'voxel_size': 0.7,  # config_file over the default
                         'pairing.sync_slop': 0.4,  # -p over the params file over the file
                         'core.gravity': [0.0, 1.0, 0.0],  # an array, from config_file
                         'output.publish_invalid': False,  # the params file over config_file
                         'output.diagnostics_period': 1.0}  # the default
        pipe, cfg = node._configs()
        assert (pipe.voxel_size, pipe.core.p1, pipe.core.gravity) == (0.7, 0.9, (0.0, 1.0, 0.0))
        assert (cfg.pairing.sync_slop, cfg.pairing.max_waiting_sources) == (0.4, 3)
        assert not cfg.output.publish_invalid and cfg.config_file == str(config)
        # a run-time change keeps config_file's other keys
        assert node.set_parameters([Parameter('voxel_size', value=0.5)])[0].successful
        pipe, cfg = node._configs()
        assert (pipe.voxel_size, pipe.core.p1, cfg.pairing.max_waiting_sources) == (0.5, 0.9, 3)
    finally:
        node.destroy_node()
        rclpy.shutdown(context=context)


def test_callbacks_after_context_shutdown_do_not_raise():
    """
    Check that callbacks running after the context has shut down end quietly.

    SIGTERM shuts the context down while the executor may still dispatch the
    diagnostics timer or the engine thread may still publish a pose; that must end quietly, not
    as an RCLError that makes rclpy.spin() raise and the node exit 1 (seen once in CI).
    """
    from cgags_ros.engine.interface import Estimate
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    node = RegisterNode(runner=FakeRunner(fake_register), context=ctx)
    xyz = np.random.default_rng(0).normal(size=(30, 3))
    result = fake_register(xyz, xyz, config=node.engine.pipeline_config)
    estimate = Estimate(result.transform, result.covariance, Header(frame_id='lidar'), 'map',
                        xyz, 'lidar')
    probe = node.create_publisher(DiagnosticArray, '~/probe', 1)
    ctx.try_shutdown()
    try:
        with pytest.raises(RuntimeError, match='context is invalid'):  # what would escape
            probe.publish(DiagnosticArray())
        node._publish_diagnostics()  # noqa: SLF001 - the timer's callback
        node.outputs.publish_estimate(estimate)  # the engine thread's publish
        node.outputs.publish_diagnostics(node.statistics())
    finally:
        node.destroy_node()


# ------------------------------------------------------------------------ real pipeline


def test_latched_target_then_live_voxel_changes_across_bags(ros, data_dir):
    """
    Register with a latched target, then with voxel_size changed live, across three bags.

    The bunny bag runs with a map latched before the node starts, then redkitchen and lidar
    after changing voxel_size live on the same node.
    """
    executor, io = ros
    bunny = bag(data_dir, 'bunny')
    stamp0, target0 = bunny.clouds('/target_cloud')[0]
    io.target_pub.publish(target0)  # latched before the node exists
    node = start_node(executor, voxel_size=VOXEL['bunny'], **{
        'pairing.target_durability': 'transient_local', 'output.diagnostics_period': 0.2})
    try:
        wait_for(lambda: node.statistics().get('received_target') == 1, 10, 'latched target')
        for name in ('bunny', 'redkitchen', 'lidar'):
            b = bag(data_dir, name)
            if name != 'bunny':
                result = node.set_parameters([Parameter('voxel_size', value=VOXEL[name])])[0]
                assert result.successful
                before = node.statistics()['received_target']
                io.target_pub.publish(b.clouds('/target_cloud')[0][1])
                wait_for(lambda: node.statistics()['received_target'] > before, 10, 'target')
            stamp, source = b.clouds('/source_cloud')[0]
            io.poses.clear()
            io.source_pub.publish(source)
            pose = wait_for(lambda: io.pose_at(stamp), 30, f'{name} pose', node.statistics)
            target_frame = b.clouds('/target_cloud')[0][1].header.frame_id
            check_pose(pose, b, name, stamp, target_frame)
            assert node.statistics()['last_voxel_size'] == VOXEL[name]
        key = node.get_fully_qualified_name()
        diag = wait_for(lambda: io.diag.get(key, {}).get('published') == '3' and io.diag[key],
                        5, 'diagnostics with 3 published')
        assert diag['voxel_size'] == str(VOXEL['lidar']) and int(diag['last_inliers']) > 6
    finally:
        stop_node(executor, node)


def test_faulty_bag_rejections_counted_and_good_pair_published(ros, data_dir):
    executor, io = ros
    b = bag(data_dir, 'faulty')
    # One faulty cloud (2000 collinear points) must end as a counted rejection, and the
    # good pair after it still be published; registration_timeout (the node's watchdog)
    # bounds it should the core ever stall on it.
    node = start_node(executor, voxel_size=VOXEL['faulty'], **{
        'output.diagnostics_period': 0.2, 'pairing.queue_depth': 10,
        'runtime.registration_timeout': 20.0})
    try:
        # Configure returns once the registration process is warm; the subscriptions exist
        # from then, so wait until both sides of both topics have matched.
        wait_for(lambda: io.source_pub.get_subscription_count() and
                 io.target_pub.get_subscription_count() and
                 node.count_publishers('/source_cloud') and
                 node.count_publishers('/target_cloud'), 30, 'node discovery')
        io.poses.clear()
        for topic, _, msg in b.records:
            (io.target_pub if topic == '/target_cloud' else io.source_pub).publish(msg)
            time.sleep(0.05)
        good_stamp = max(b.gt)
        pose = wait_for(lambda: io.pose_at(good_stamp), 60, 'pose of the good source',
                        node.statistics)
        check_pose(pose, b, 'faulty', good_stamp, 'turntable')
        key = node.get_fully_qualified_name()
        # Diagnostics are a snapshot every 0.2 s: wait for one taken after the last pair.
        # The good pair need not be the bag's last source: wait for one taken after all 8.
        diag = wait_for(lambda: io.diag.get(key, {}).get('received_source') == '8'
                        and io.diag[key], 10, 'diagnostics after all 8 sources',
                        lambda: io.diag.get(key))
        assert diag['rejected.bad_input'] == '2'  # no z field / bad layout
        # no points / all NaN (2), and any pair the pipeline refuses for the same reason
        assert int(diag['rejected.too_few_points']) >= 2
        assert int(diag['rejected']) >= 5
    finally:
        stop_node(executor, node)


def test_synchronized_targets_keep_a_history_like_the_sources():
    from cgags_ros.config.node import NodeConfig
    from cgags_ros.ros.qos import target_qos

    cfg = NodeConfig()
    assert target_qos(cfg).depth == cfg.pairing.target_depth == 1  # a map: the newest
    synced = dataclasses.replace(cfg, pairing=dataclasses.replace(
        cfg.pairing, mode='synchronized', source_depth=7))
    assert target_qos(synced).depth == 7
    deeper = dataclasses.replace(synced, pairing=dataclasses.replace(
        synced.pairing, target_depth=20))
    assert target_qos(deeper).depth == 20


def test_separate_process_synchronized_lidar_then_sigterm(ros, data_dir, tmp_path):
    executor, io = ros
    b = bag(data_dir, 'lidar')
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID), PYTHONUNBUFFERED='1',
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    log = open(tmp_path / 'node.log', 'w+')  # a file, not a pipe: a full pipe would block
    proc = subprocess.Popen(
        [sys.executable, '-m', 'cgags_ros.register_node', '--ros-args',
         '--params-file', str(REPO / 'config' / 'register_node.yaml')] + ros_args(
            **{'pairing.mode': 'synchronized', 'pairing.sync_slop': 0.02,
               'voxel_size': VOXEL['lidar'], 'pairing.queue_depth': 10,
               'pairing.max_waiting_sources': 10, 'output.diagnostics_period': 0.2},
            # Reliable here so the test is deterministic: best-effort 1 MB clouds across
            # processes on a loaded machine lose samples (sensor_data is used in-process).
            **{'pairing.source_qos': 'reliable'}),
        cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, text=True)
    # Every target is paired here, so none may be overwritten before delivery: the latched
    # publisher keeps only its last sample, and a 1-MB cloud still unacknowledged when the
    # next is published (a loaded machine) would be lost from its history. This one keeps
    # ten; the node's synchronized subscription keeps pairing.source_depth.
    targets = io.node.create_publisher(
        PointCloud2, 'target_cloud', QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    try:
        wait_for(lambda: io.source_pub.get_subscription_count() and
                 targets.get_subscription_count() and
                 io.node.count_publishers('/register_node/pose'), 30, 'node discovery')
        # The publisher can see the match before the subscriber does; a sample sent in
        # between is lost even when reliable, so wait until the node reports itself.
        wait_for(lambda: '/register_node' in io.diag, 30, "the node's first diagnostics")
        # a live parameter change over the parameter service: invalid refused, valid taken
        client = io.node.create_client(SetParameters, '/register_node/set_parameters')
        assert client.wait_for_service(timeout_sec=10)
        for name, value, ok in [('core.motion_model', 'bogus', False),
                                ('core.edge_tournament', 4, False),  # config_file's
                                ('core.time_budget', 30.0, True)]:
            req = SetParameters.Request(parameters=[
                Parameter(name, value=value).to_parameter_msg()])
            future = client.call_async(req)
            wait_for(future.done, 10, 'set_parameters reply')
            assert future.result().results[0].successful is ok
        io.poses.clear()
        for topic, _, msg in b.records:
            (targets if topic == '/target_cloud' else io.source_pub).publish(msg)
            time.sleep(0.1)
        sources = [stamp for stamp, _ in b.clouds('/source_cloud')]
        # the first source (0.1 s) has no target within 20 ms; the five others pair exactly
        wait_for(lambda: all(io.pose_at(s) for s in sources[1:]), 60, 'five lidar poses',
                 lambda: io.diag.get('/register_node'))
        for stamp in sources[1:]:
            check_pose(io.pose_at(stamp), b, 'lidar', stamp, 'map')
        assert io.pose_at(sources[0]) is None
        diag = wait_for(lambda: io.diag.get('/register_node', {})
                        .get('pairing.dropped.source_no_target_within_slop'), 10, 'diagnostics')
        assert diag == '1'
    finally:
        io.node.destroy_publisher(targets)
        out = stop_process(proc, log)
    assert proc.returncode == 0, out
    assert 'Traceback' not in out, out
