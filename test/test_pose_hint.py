"""
cgags_ros.engine.pose_hint without ROS: the node's ~/hint checked, carried to a scan, used.

A hint message's numbers are checked (rejections counted by why, never raised), moved into
the map frame by TF, and carried to a scan's sensor by the odometry and the extrinsic. Then
the engine, with the real pipeline on the shared LiDAR pair's map: a hint at the scan's true
place finds it (the initial pose against ground truth); one 200 m away refuses the scan as
``no_shared_surface`` before any registration; a hint ends with the request it made.
"""

from __future__ import annotations

import time

from cgags_ros.config.node import configs_from_parameters
from cgags_ros.config.pipeline import PipelineConfig
from cgags_ros.engine.engine import RegistrationEngine
from cgags_ros.engine.interface import Cloud
from cgags_ros.engine.pose_hint import PoseHint, PoseHints
from cgags_ros.geometry import make_transform, matrix_to_quaternion, quaternion_to_matrix
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.clouds import read_cloud
from cgags_ros.pipeline.hint import Hint, HINT_SIGMAS
from cgags_ros.runtime.jobs import RegisterPair
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_engine import Header, Recorder
from waiting import InProcessRunner, wait_for

S = 10**9  # nanoseconds a second
# RViz's "2D Pose Estimate": 0.5 m in x and y, 15 deg in yaw, no height (a planar pose).
RVIZ = np.diag([0.25, 0.25, 0.0, 0.0, 0.0, 0.0685]).reshape(-1)
# The LiDAR 0.3 m ahead of the base and 0.8 m up, turned 45 deg: p_base = T p_sensor.
BASE_FROM_SENSOR = (0.3, -0.1, 0.8, 0.0, 0.0, 0.3826834, 0.9238795)
LIDAR = (5.0, 0.6)  # RE (deg), TE (m): the LiDAR thresholds of the other tests


def values(T):
    """Return the [x, y, z, qx, qy, qz, qw] of a 4x4 pose, as the node passes a message's."""
    return (*T[:3, 3], *matrix_to_quaternion(T[:3, :3]))


def turn(deg, t=(0.0, 0.0, 0.0)):
    return make_transform(Rotation.from_euler('z', deg, degrees=True).as_matrix(), t)


def receive(hints, pose, cov=RVIZ, frame='map', tf=None, refused=''):
    logs = []
    held = hints.receive(5 * S, frame, pose, cov, 'map', lambda p, c, s: (tf or {}).get((p, c)),
                         lambda *line: logs.append(line), refused)
    return held, logs


@pytest.mark.parametrize('why, pose, cov, frame', [
    ('not_finite', (np.nan, 0, 0, 0, 0, 0, 1), RVIZ, 'map'),
    ('not_finite', (1, 2, 0, 0, 0, 0, 1), np.full(36, np.inf), 'map'),
    ('zero_quaternion', (1, 2, 0, 0, 0, 0, 0), RVIZ, 'map'),
    ('negative_covariance', (1, 2, 0, 0, 0, 0, 1), -RVIZ, 'map'),
    # positive variances, but x and y correlated beyond 1: no covariance at all
    ('negative_covariance', (1, 2, 0, 0, 0, 0, 1),
     (np.diag([1.0, 1.0, 0, 0, 0, 0]) + np.diag([2.0, 0, 0, 0, 0], 1)
      + np.diag([2.0, 0, 0, 0, 0], -1)).reshape(-1), 'map'),
    ('frame', (1, 2, 0, 0, 0, 0, 1), RVIZ, 'odom'),  # no TF map <- odom
    ('frame', (1, 2, 0, 0, 0, 0, 1), RVIZ, ''),
])
def test_a_bad_hint_is_counted_and_logged_by_why_never_raised(why, pose, cov, frame):
    hints = PoseHints()
    held, logs = receive(hints, pose, cov, frame)
    assert held is None
    assert hints.statistics() == {'hint.received': 1, 'hint.used': 0, f'hint.rejected.{why}': 1}
    [(level, message)] = logs
    assert level == 'warning' and message.startswith(f'~/hint rejected ({why}): ')


def test_a_hint_while_inactive_is_rejected_as_such():
    hints = PoseHints()
    held, logs = receive(hints, (1, 2, 0, 0, 0, 0, 1), refused='inactive')
    assert held is None and hints.statistics()['hint.rejected.inactive'] == 1 and logs


def test_a_hint_in_another_frame_is_moved_into_the_map_frame_by_tf():
    map_utm = turn(90, (10.0, 0.0, 0.0))  # map <- utm
    pose = turn(30, (1.0, 0.0, 0.0))
    cov = np.diag([4.0, 0.01, 0.0, 0.0, 0.0, 0.0]).reshape(-1)  # loose along utm's x
    held, logs = receive(PoseHints(), values(pose), cov, 'utm', {('map', 'utm'): map_utm})
    assert not logs
    np.testing.assert_allclose(held.pose, map_utm @ pose, atol=1e-9)
    # utm's x is the map's y: the loose axis turned with the frame
    np.testing.assert_allclose(np.diag(held.covariance)[:3], [0.01, 4.0, 0.0], atol=1e-9)


def test_a_hint_is_carried_to_the_scan_by_the_odometry_and_to_the_sensor_by_the_extrinsic():
    hints = PoseHints()
    T_map_base = turn(90, (5.0, 2.0, 0.0))
    held, _ = receive(hints, values(T_map_base))
    assert isinstance(held, PoseHint) and held.stamp_ns == 5 * S
    moved = turn(0, (1.0, 0.0, 0.0))  # the base went 1 m ahead since the hint
    base = make_transform(quaternion_to_matrix(BASE_FROM_SENSOR[3:]), BASE_FROM_SENSOR[:3])
    hint = hints.at_scan(held, moved, base)
    # 1 m ahead of a base facing +y is +y; the sensor 0.3 ahead and 0.1 right of it
    np.testing.assert_allclose(hint.position, [5.1, 3.3, 0.8], atol=1e-6)
    assert hint.planar  # RViz's pose has no height: only x and y restrict the places
    # the position's 0.5 m, widened by the yaw's 15 deg over the 0.32 m lever arm
    lever = np.hypot(0.3, 0.1)
    assert hint.radius == pytest.approx(HINT_SIGMAS * np.sqrt(0.25 + 0.0685 * lever**2))
    as_given = hints.at_scan(held, None, None)
    np.testing.assert_allclose(as_given.position, [5.0, 2.0, 0.0])
    assert as_given.radius == pytest.approx(HINT_SIGMAS * 0.5)
    assert hints.statistics() == {'hint.received': 1, 'hint.used': 2}


def test_the_pending_requests_hint_follows_the_robot_to_each_scan():
    """RelocalizationRun: the hint at a scan, moved by the odometry between the two stamps."""
    from cgags_ros.engine.pairing import Pair, Stamped
    from cgags_ros.engine.relocalization_run import RelocalizationRun

    out = Recorder()
    cfg = configs_from_parameters({'map.file': 'map.ply', 'mode': 'on_demand',
                                   'relocalization.base_from_sensor': list(BASE_FROM_SENSOR)})[1]
    run = RelocalizationRun(cfg, out)
    pair = Pair(Stamped(7 * S, 'velodyne', None), Stamped(0, 'map', None))
    assert run.hint(pair, cfg) is None  # no request, no hint
    run.request(60.0, lambda *answer: None)
    assert run.hint(pair, cfg) is None  # a ~/relocalize call carries none
    T_map_base = turn(90, (5.0, 2.0, 0.0))
    run.receive_hint(5 * S, 'map', values(T_map_base), RVIZ, cfg, active=True)
    base = make_transform(quaternion_to_matrix(BASE_FROM_SENSOR[3:]), BASE_FROM_SENSOR[:3])
    as_given = T_map_base @ base
    np.testing.assert_allclose(run.hint(pair, cfg).position, as_given[:3, 3], atol=1e-6)
    out.odom[5 * S] = turn(10, (3.0, 0.0, 0.0))  # the base, then 2 m ahead, at the scan
    out.odom[7 * S] = turn(10, (3.0, 0.0, 0.0)) @ turn(0, (2.0, 0.0, 0.0))
    moved = T_map_base @ turn(0, (2.0, 0.0, 0.0)) @ base
    np.testing.assert_allclose(run.hint(pair, cfg).position, moved[:3, 3], atol=1e-6)
    assert run.statistics()['hint.used'] == 2 and run.statistics()['relocalize.calls'] == 2
    run.calls.answer('localized')  # the requests answered: the hint ends with them
    assert run.hint(pair, cfg) is None


# --- the engine, on the LiDAR pair's map ------------------------------------------------------


@pytest.fixture(scope='module')
def lidar(data_dir):
    """Return the map file, the source scan (its sensor frame) and its true pose in the map."""
    folder = data_dir / 'lidar' / 'small_gicp'
    return (folder / 'target.ply', read_cloud(folder / 'source.ply'),
            np.loadtxt(folder / 'T_target_source.txt'))


def test_the_engine_looks_for_a_scan_only_where_its_hint_says(lidar):
    path, scan, T_map_sensor = lidar
    base = make_transform(quaternion_to_matrix(BASE_FROM_SENSOR[3:]), BASE_FROM_SENSOR[:3])
    T_map_base = T_map_sensor @ np.linalg.inv(base)
    out, runner = Recorder(), InProcessRunner()
    cfg = configs_from_parameters({
        'map.file': str(path), 'map.cache_dir': '', 'voxel_size': 0.4, 'mode': 'on_demand',
        'relocalization.publish_initial_pose': True, 'relocalization.cooldown': 0.0,
        'relocalization.base_from_sensor': list(BASE_FROM_SENSOR),
        'relocalization.timeout': 120.0})[1]
    engine = RegistrationEngine(PipelineConfig(voxel_size=0.4), cfg, out, runner=runner)
    engine.start()
    answers = []

    def scan_for(hint_pose, stamp_s):
        """Send a hint, then a scan; return the scan's ~/result."""
        n = len(out.results)
        engine.hint(stamp_s * S, 'map', values(hint_pose), RVIZ)
        engine.receive('source', (stamp_s + 1) * S, 'velodyne', Cloud(
            scan, Header('velodyne', stamp_s + 1), time.monotonic_ns()))
        wait_for(lambda: len(out.results) > n, 300, 'the scan to be registered')
        return out.results[-1]

    try:
        engine.hint(S, 'map', values(T_map_base), RVIZ)  # inactive: rejected, no request
        assert engine.statistics()['hint.rejected.inactive'] == 1
        assert 'relocalize.calls' not in engine.statistics()  # no request was made
        engine.activate()
        # Right here, 4 m off: the 1.5 m of RViz's covariance and the scan's reach cover it.
        right = scan_for(T_map_base @ turn(20, (3.0, -2.5, 0.0)), 10)
        assert right['outcome'] == 'published', right['message']
        [pose] = out.initial
        assert rotation_error_deg(pose.transform, T_map_base) < LIDAR[0]
        assert translation_error(pose.transform, T_map_base) < LIDAR[1]
        job = runner.jobs[-1]
        assert isinstance(job, RegisterPair) and isinstance(job.hint, Hint) and job.hint.planar
        # 200 m away, nowhere near the map: refused at once, no place registered
        wrong = scan_for(T_map_base @ turn(0, (200.0, 0.0, 0.0)), 20)
        assert wrong['refusal']['code'] == 'no_shared_surface', wrong
        assert 'covers no place' in wrong['message'] and wrong['num_target_points'] == 0
        assert len(out.initial) == 1
        stats = engine.statistics()
        assert stats['hint.received'] == 3 and stats['hint.used'] == 2
        assert stats['relocalize.succeeded'] == 1
        assert stats['relocalize.failed.no_shared_surface'] == 1
        logged = [m for level, m in out.logs if m.startswith('~/hint: ')]
        assert logged[0].startswith('~/hint: localized: ') and len(logged) == 2
        assert logged[1].startswith('~/hint: no_shared_surface: not localized: ')
        # The hint ended with its request: a ~/relocalize call searches the whole map.
        engine.relocalize(lambda *a: answers.append(a))
        engine.receive('source', 30 * S, 'velodyne',
                       Cloud(scan, Header('velodyne', 30), time.monotonic_ns()))
        wait_for(lambda: answers, 300, 'the answer of the call')
        assert answers[0][0], answers
        assert runner.jobs[-1].hint is None and engine.statistics()['hint.used'] == 2
    finally:
        engine.stop()
