"""
Relocalization through register_node over real DDS: map.file, on_demand, guarded initialpose.

The node runs in this process with its own rclpy context and DDS domain. The map is the
redkitchen fragments 0 and 4 merged at full resolution (ground truth from gt_pairs.txt);
scans are fragment 6 and fragment 4 under random rotations and offsets, and a scaled bunny
scan (an unrelated scene). Poses are checked against ground truth.
"""

from __future__ import annotations

import multiprocessing
import threading

from cgags_ros.geometry import apply_transform, make_transform, quaternion_to_matrix
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.clouds import read_cloud, write_cloud
from cgags_ros.io.pointcloud2 import pose_to_transform
from cgags_ros.pipeline.result import PipelineResult
from cgags_ros.refusal import RefusalCode
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

rclpy = pytest.importorskip('rclpy')

from cgags_ros.ros.node import RegisterNode  # noqa: E402, I100
from cgags_ros.ros.outputs import transform_to_pose, xyz_to_pointcloud2  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped  # noqa: E402
from lifecycle_msgs.msg import Transition  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_msgs.msg import Header  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from waiting import (bad_map, EXECUTOR_THREADS, FakeRunner, Lifecycle,  # noqa: E402
                     merged_kitchen_map, ros_overrides, spun_context, wait_for)

pytestmark = pytest.mark.ros
DOMAIN_ID = 65  # distinct from the other DDS test modules
RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
INDOOR = (15.0, 0.3)  # RE (deg), TE (m): the indoor thresholds of the other tests
LIDAR = (5.0, 0.6)


class Wire:
    """The test's side: scans out, ~/relocalize calls, initialpose/candidates/diagnostics in."""

    def __init__(self, context):
        self.node = rclpy.create_node('relocalize_io', context=context)
        self.source_pub = self.node.create_publisher(PointCloud2, 'source_cloud', RELIABLE)
        self.initial: list[PoseWithCovarianceStamped] = []
        self.candidates: list[PoseArray] = []
        self.values: dict[str, str] = {}
        self.level = None
        self.node.create_subscription(PoseWithCovarianceStamped, 'initialpose',
                                      self.initial.append, 10)
        self.node.create_subscription(PoseArray, '/register_node/candidates',
                                      self.candidates.append, 10)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)
        self.client = self.node.create_client(Trigger, '/register_node/relocalize')
        self.lifecycle = Lifecycle(self.node)

    def _on_diag(self, msg):
        for status in msg.status:
            if status.hardware_id == '/register_node':
                self.values = {kv.key: kv.value for kv in status.values}
                self.level = status.level

    def relocalize(self, timeout=120.0):
        assert self.client.wait_for_service(timeout_sec=30.0), 'no ~/relocalize service'
        future = self.client.call_async(Trigger.Request())
        wait_for(future.done, timeout, 'the ~/relocalize answer', lambda: self.values)
        return future.result()

    def send(self, xyz, frame='sensor'):
        wait_for(lambda: self.source_pub.get_subscription_count() > 0, 30.0,
                 'the node subscribing source_cloud')
        self.source_pub.publish(xyz_to_pointcloud2(xyz, Header(frame_id=frame)))


@pytest.fixture(scope='module')
def wire():
    with spun_context(DOMAIN_ID, Wire) as spun:
        yield spun


def start(wire, register=None, **params):
    """Start the node; ``register`` stands in for the registration process (FakeRunner)."""
    if register is not None:  # pairs, not a tracked stream, for a stand-in registration
        params.setdefault('tracking.enabled', False)
    context, executor, io = wire
    io.values, io.level = {}, None
    io.initial.clear()
    io.candidates.clear()
    node = RegisterNode(context=context, runner=FakeRunner(register) if register else None,
                        parameter_overrides=ros_overrides(**params))
    executor.add_node(node)
    return node


def stop(wire, node):
    wire[1].remove_node(node)
    node.destroy_node()


def wait_map(io, timeout=300.0):
    return wait_for(lambda: io.values.get('map.cache') or io.values.get('map.error'), timeout,
                    'the map to load', lambda: io.values)


@pytest.fixture(scope='module')
def kitchen(data_dir, tmp_path_factory):
    """Return (merged map file, fragment-6 cloud and GT, fragment-4 cloud and GT)."""
    path, merged, frag6, frag4 = merged_kitchen_map(data_dir, tmp_path_factory.mktemp('map'))
    return path, frag6, frag4, len(merged)


def random_motion(rng):
    return make_transform(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-3, 3, 3))


def errors(pose_msg, T_gt):
    T = pose_to_transform(pose_msg)
    return rotation_error_deg(T, T_gt), translation_error(T, T_gt)


def test_on_demand_relocalization_in_a_merged_kitchen_map(wire, kitchen, data_dir, tmp_path):
    """
    Relocalize fragments 6 and 4 (random any-angle motions) in the 571k-point merged map.

    A ~/relocalize call over DDS answers success with a summary, /initialpose (map frame)
    and ~/candidates (best first) match ground truth; a scaled bunny scan (unrelated scene)
    gets a failed answer, no /initialpose and a counted refusal. A second start with the
    same map and settings reads the feature cache (a hit, from the node's report); a
    changed voxel_size is a miss.
    """
    _, _, io = wire
    path, (frag6, gt6), (frag4, gt4), raw = kitchen
    assert raw >= 500_000
    cache = tmp_path / 'cache'
    params = {'mode': 'on_demand', 'map.file': str(path), 'map.frame': 'map',
              'map.cache_dir': str(cache), 'voxel_size': 0.05, 'pairing.source_qos': 'reliable',
              'frontend.normal_orientation': 'centroid',  # the scans are moved
              'relocalization.publish_initial_pose': True, 'relocalization.cooldown': 0.0,
              'runtime.registration_timeout': 120.0, 'output.diagnostics_period': 0.2,
              'relocalization.max_scan_age': 30.0}
    node = start(wire, **params)
    try:
        assert wait_map(io) == 'miss', io.values.get('map.error')
        assert int(io.values['map.raw_points']) == raw
        rng = np.random.default_rng(13)
        for scan, gt in ((frag6, gt6), (frag4, gt4)):
            A = random_motion(rng)
            n_initial = len(io.initial)
            io.send(apply_transform(A, scan))
            wait_for(lambda: int(io.values.get('pairing.pending', 0)) > 0, 30.0,
                     'the scan to be held', lambda: io.values)
            answer = io.relocalize()
            assert answer.success, answer.message
            assert answer.message.startswith('localized:') and 'inliers' in answer.message
            wait_for(lambda: len(io.initial) > n_initial, 30.0, 'initialpose')
            msg = io.initial[-1]
            assert msg.header.frame_id == 'map'
            T_gt = gt @ np.linalg.inv(A)  # the moved scan's pose in the map
            re, te = errors(msg.pose, T_gt)
            assert re < INDOOR[0] and te < INDOOR[1], f'RE {re:.2f} deg, TE {te:.3f} m'
            wait_for(lambda: io.candidates, 10.0, '~/candidates')
            cands = io.candidates[-1]
            assert cands.header.frame_id == 'map' and len(cands.poses) >= 2
            assert errors(cands.poses[0], T_gt)[0] < INDOOR[0]
        bunny = read_cloud(data_dir / 'objects' / 'stanford_bunny_scans' / 'bun000.ply') * 20
        n_initial = len(io.initial)
        io.send(bunny)
        wait_for(lambda: int(io.values.get('pairing.pending', 0)) > 0, 30.0, 'the bunny scan')
        answer = io.relocalize()
        code = answer.message.split(':', 1)[0]  # the answer starts with the refusal's code
        assert not answer.success and RefusalCode(code) in {
            RefusalCode.CHANCE_LEVEL, RefusalCode.AMBIGUOUS, RefusalCode.NO_ESTIMATE,
            RefusalCode.FEW_INLIERS, RefusalCode.FREE_SPACE, RefusalCode.LOW_FITNESS,
            RefusalCode.LOW_RATIO}, answer.message
        assert answer.message.startswith(f'{code}: not localized: ')
        wait_for(lambda: io.values.get(f'relocalize.failed.{code}') == '1', 10.0,
                 'the failure counted by its code', lambda: io.values)
        assert io.values['relocalize.calls'] == '3'
        assert io.values['relocalize.succeeded'] == '2'
        refused = {k: v for k, v in io.values.items() if k.startswith('initial_pose.refused.')}
        # the guard refused the initial pose with the very refusal the answer gives
        assert refused == {f'initial_pose.refused.{code}': '1'} and len(io.initial) == n_initial
        assert io.values['accounting.ok'] == 'True'
    finally:
        stop(wire, node)
    node = start(wire, **params)
    try:
        assert wait_map(io) == 'hit'
    finally:
        stop(wire, node)
    node = start(wire, **dict(params, voxel_size=0.06))
    try:
        assert wait_map(io) == 'miss'
    finally:
        stop(wire, node)


@pytest.mark.parametrize('utm', [None, (512345.678, 5412345.678, 265.4)],
                         ids=['local', 'utm'])
def test_lidar_initial_pose_is_the_base_pose(wire, data_dir, tmp_path, utm):
    """
    Check the LiDAR pair's initial pose is the base's: ground truth and the extrinsic.

    Continuous mode with relocalization.base_from_sensor; the second scan is refused by
    relocalization.max_auto (counted), while ~/pose keeps the sensor pose. With ``utm`` the
    map file (PLY doubles) is georeferenced: the initial pose is in its UTM frame.
    """
    _, _, io = wire
    folder = data_dir / 'lidar' / 'small_gicp'
    offset = make_transform(np.eye(3), utm or (0.0, 0.0, 0.0))
    gt = offset @ np.loadtxt(folder / 'T_target_source.txt')
    source = read_cloud(folder / 'source.ply')
    map_path = tmp_path / 'map.ply'
    write_cloud(map_path, apply_transform(offset, read_cloud(folder / 'target.ply')))
    rng = np.random.default_rng(5)
    A = random_motion(rng)
    t, q = (0.3, -0.1, 0.8), (0.0, 0.0, 0.3826834, 0.9238795)  # 45 deg yaw, raised
    T_bs = make_transform(quaternion_to_matrix(q), t)
    node = start(wire, **{
        'map.file': str(map_path), 'map.cache_dir': '', 'voxel_size': 0.4,
        'pairing.source_qos': 'reliable', 'relocalization.publish_initial_pose': True,
        'relocalization.cooldown': 0.0, 'relocalization.max_auto': 1,
        'relocalization.base_from_sensor': list(t + q), 'output.diagnostics_period': 0.2})
    try:
        assert wait_map(io) == 'off', io.values.get('map.error')
        for _ in range(2):
            published = int(io.values.get('sources.published', 0))
            io.send(apply_transform(A, source), frame='velodyne')
            wait_for(lambda: int(io.values.get('sources.published', 0)) > published, 120.0,
                     'the scan to be registered', lambda: io.values)
        wait_for(lambda: io.initial, 10.0, 'initialpose')
        wait_for(lambda: io.values.get('initial_pose.refused.max_auto') == '1', 10.0,
                 'the max_auto refusal', lambda: io.values)
        assert len(io.initial) == 1 and io.values['initial_pose.published'] == '1'
        T_map_base = gt @ np.linalg.inv(A) @ np.linalg.inv(T_bs)
        re, te = errors(io.initial[0].pose, T_map_base)
        assert re < LIDAR[0] and te < LIDAR[1], f'RE {re:.2f} deg, TE {te:.3f} m'
        sensor_te = errors(io.initial[0].pose, gt @ np.linalg.inv(A))[1]
        assert sensor_te > 0.5  # the extrinsic really moved it: this is not the sensor pose
    finally:
        stop(wire, node)


def test_a_hint_on_its_topic_places_the_next_scan(wire, data_dir):
    """
    ~/hint over DDS: a relocalization request searched only where the hint says.

    on_demand: the hint alone makes the node register the next scan. A hint 4 m from the
    true base pose (RViz's covariance) finds it (ground truth and the extrinsic); one 200 m
    away refuses the scan as no_shared_surface; a hint in a frame TF cannot move and one
    with a NaN are rejected and counted.
    """
    _, _, io = wire
    folder = data_dir / 'lidar' / 'small_gicp'
    gt, source = np.loadtxt(folder / 'T_target_source.txt'), read_cloud(folder / 'source.ply')
    t, q = (0.3, -0.1, 0.8), (0.0, 0.0, 0.3826834, 0.9238795)
    T_map_base = gt @ np.linalg.inv(make_transform(quaternion_to_matrix(q), t))
    node = start(wire, **{
        'mode': 'on_demand', 'map.file': str(folder / 'target.ply'), 'map.cache_dir': '',
        'voxel_size': 0.4, 'pairing.source_qos': 'reliable', 'relocalization.timeout': 120.0,
        'relocalization.publish_initial_pose': True, 'relocalization.cooldown': 0.0,
        'relocalization.base_from_sensor': list(t + q), 'output.diagnostics_period': 0.2})
    hints = io.node.create_publisher(PoseWithCovarianceStamped, '/register_node/hint', RELIABLE)

    def hint(T, frame='map', calls=None, x=None):
        msg = PoseWithCovarianceStamped(header=Header(frame_id=frame))
        msg.pose.pose = transform_to_pose(T)
        msg.pose.pose.position.x = msg.pose.pose.position.x if x is None else x
        msg.pose.covariance = [0.25, 0, 0, 0, 0, 0, 0, 0.25] + [0.0] * 27 + [0.0685]
        hints.publish(msg)
        if calls:  # the hint's request reached the node: the next scan answers it
            wait_for(lambda: io.values.get('relocalize.calls') == calls, 30.0,
                     'the hint to be taken', lambda: io.values)
            io.send(source, frame='velodyne')

    try:
        assert wait_map(io) == 'off', io.values.get('map.error')
        wait_for(lambda: hints.get_subscription_count() > 0, 30.0, 'the ~/hint subscription')
        offset = make_transform(Rotation.from_euler('z', 20, degrees=True).as_matrix(),
                                (3.0, -2.5, 0.0))
        hint(T_map_base @ offset, calls='1')
        wait_for(lambda: io.initial, 120.0, 'initialpose', lambda: io.values)
        re, te = errors(io.initial[0].pose, T_map_base)
        assert re < LIDAR[0] and te < LIDAR[1], f'RE {re:.2f} deg, TE {te:.3f} m'
        hint(T_map_base @ make_transform(np.eye(3), (200.0, 0.0, 0.0)), calls='2')
        wait_for(lambda: io.values.get('relocalize.failed.no_shared_surface') == '1', 120.0,
                 'the scan refused', lambda: io.values)
        hint(T_map_base, frame='odom')
        hint(T_map_base, x=float('nan'))
        wait_for(lambda: io.values.get('hint.received') == '4', 30.0, 'every hint counted',
                 lambda: io.values)
        values = io.values
        assert values['hint.rejected.frame'] == values['hint.rejected.not_finite'] == '1'
        assert values['hint.used'] == '2' and values['relocalize.calls'] == '2'
        assert len(io.initial) == 1 and values['accounting.ok'] == 'True'
    finally:
        io.node.destroy_publisher(hints)
        stop(wire, node)


def test_relocalize_calls_in_flight_hold_no_executor_thread(wire):
    """
    More ~/relocalize calls than executor threads wait at once, and the topics go on.

    The registration is held (a stand-in that waits on a gate), so every call stays
    unanswered; meanwhile scans are received and accounted and /diagnostics keeps coming,
    which a call that held an executor thread each would stop. Once the gate opens, that
    registration answers every call.
    """
    _, _, io = wire
    gate, registering = threading.Event(), threading.Event()

    def held(source, target, *, config):
        registering.set()
        assert gate.wait(60.0), 'the gate never opened'
        return PipelineResult(transform=np.eye(4), refusal=None, inliers=np.arange(40),
                              num_correspondences=100, fitness=0.8)

    node = start(wire, held, **{'pairing.source_qos': 'reliable', 'relocalization.timeout': 120.0,
                                'output.diagnostics_period': 0.1})
    target = io.node.create_publisher(PointCloud2, 'target_cloud', RELIABLE)
    calls = []
    try:
        wait_for(lambda: target.get_subscription_count() > 0, 30.0, 'the target subscription')
        target.publish(xyz_to_pointcloud2(np.random.rand(50, 3), Header(frame_id='map')))
        wait_for(lambda: io.values.get('received_target') == '1', 30.0, 'the target',
                 lambda: io.values)
        io.send(np.random.rand(50, 3))
        assert registering.wait(30.0), 'the first scan was not registered'
        assert io.client.wait_for_service(timeout_sec=30.0)
        calls = [io.client.call_async(Trigger.Request())
                 for _ in range(2 * EXECUTOR_THREADS)]
        wait_for(lambda: io.values.get('relocalize.calls') == str(len(calls)), 30.0,
                 'every call to reach the node', lambda: io.values)
        for k in range(5):  # the topics go on while every call waits
            io.send(np.random.rand(50, 3))
            wait_for(lambda: io.values.get('sources.received') == str(2 + k), 30.0,
                     f'scan {2 + k} to be accounted', lambda: io.values)
        values = io.values
        assert values['accounting.ok'] == 'True' and not any(c.done() for c in calls)
        # the scan being registered and the five since: pending (queued) or dropped (queue full)
        assert int(values['sources.pending']) + int(values['sources.dropped']) == 6
        gate.set()
        wait_for(lambda: all(c.done() for c in calls), 30.0, 'the answers', lambda: io.values)
        answers = [c.result() for c in calls]
        assert all(a.success and a.message.startswith('localized: x 0.000') for a in answers)
        wait_for(lambda: io.values.get('relocalize.succeeded') == str(len(calls)), 10.0,
                 'the answers counted', lambda: io.values)
    finally:
        gate.set()
        io.node.destroy_publisher(target)
        stop(wire, node)


@pytest.mark.parametrize('case, autostart', [('missing', False), ('empty', True),
                                             ('unreadable', False), ('all_nan', True)])
def test_a_bad_map_file_fails_configure_and_leaves_nothing_running(
        wire, tmp_path, data_dir, capfd, case, autostart):
    """
    A missing, empty, unreadable or all-NaN map: configure fails, as a lifecycle manager sees it.

    change_state answers failure (or autostart's configure fails, the process running on);
    the node is unconfigured with no registration process left; the reason is logged (at
    ERROR, on the console) and is the node's last /diagnostics (ERROR). Configured again once
    the map file is usable, it succeeds.
    """
    _, _, io = wire
    path = bad_map(tmp_path, case)
    node = start(wire, **{'map.file': str(path), 'map.cache_dir': str(tmp_path / 'c'),
                          'runtime.registration_timeout': 30.0, 'voxel_size': 0.4,
                          'output.diagnostics_period': 0.2, 'autostart': autostart})
    try:
        if not autostart:
            assert io.lifecycle.state() == 'unconfigured'
            assert io.lifecycle.change(Transition.TRANSITION_CONFIGURE) == (False, 'unconfigured')
        assert io.lifecycle.state() == 'unconfigured' and node.engine is None
        assert multiprocessing.active_children() == []  # the registration process ended
        console = capfd.readouterr()
        logged = [line for line in (console.err + console.out).splitlines()
                  if 'register_node' in line and 'cannot configure: ' in line]
        assert len(logged) == 1 and 'ERROR' in logged[0], logged
        assert 'map.file cannot be used: ' in logged[0] and path.name in logged[0]
        wait_for(lambda: io.values.get('configure.error'), 10, 'the reason on /diagnostics')
        assert io.level == DiagnosticStatus.ERROR and path.name in io.values['configure.error']
        assert io.values['configure.refusal_code'] == 'start_failed'  # beside its message
        assert node.context.ok()
        if case == 'missing':  # the file appears: a configure now succeeds
            write_cloud(path, read_cloud(data_dir / 'lidar' / 'small_gicp' / 'target.ply'))
            assert io.lifecycle.change(Transition.TRANSITION_CONFIGURE) == (True, 'inactive')
            assert node.engine.runner.ready
            assert node.engine.statistics()['map.cache'] == 'miss'
    finally:
        stop(wire, node)
