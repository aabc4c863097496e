"""
cgags_ros.relocalization.sequence without ROS: odometry matched to scans, the node's decisions.

The odometry track and the verdicts are checked on synthetic answers; then the engine, with
the real pipeline in its own process and a map fused from the redkitchen fragments (as in
test_relocalizer.py), relocalizes over consecutive fragments with odometry fed by stamp:
nothing is answered or published before the pose is confirmed, and odometry that
contradicts the scans is refused.
"""

from __future__ import annotations

import time

from cgags_ros.config.node import configs_from_parameters
from cgags_ros.geometry import make_transform, quaternion_to_matrix
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.localizer.engine import RegistrationEngine
from cgags_ros.localizer.interface import Cloud
from cgags_ros.refusal import Refusal, RefusalCode
from cgags_ros.relocalization.odometry import OdometryTrack, TOLERANCE_S
from cgags_ros.relocalization.sequence import SequenceRun, StepAnswer
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_engine import Header, Recorder
import test_relocalizer
from test_relocalizer import EASY, HARD, odometry, right
from waiting import wait_for

scene = test_relocalizer.scene  # the map without the sequence's fragments (a fixture)
S = 10**9  # nanoseconds a second
# The sensor 20 cm ahead of the base, 1 m up, turned 90 deg about z: p_base = T p_sensor.
BASE_FROM_SENSOR = (0.2, 0.0, 1.0, 0.0, 0.0, 0.7071068, 0.7071068)


def turn(deg, t=(0.0, 0.0, 0.0)):
    return make_transform(Rotation.from_euler('z', deg, degrees=True).as_matrix(), t)


def test_odometry_is_interpolated_between_samples_and_nearest_within_the_tolerance():
    track = OdometryTrack()
    assert not track.received and track.at(5 * S) is None
    track.add(6 * S, turn(20, (2.0, 0.0, 0.0)))
    track.add(4 * S, turn(-20, (0.0, 0.0, 0.0)))  # out of order: put in place
    track.add(int(5.05 * S), turn(10, (1.5, 0.0, 0.0)))
    assert track.received
    # Between 4.0 (too far) and 5.05 (within the tolerance): the nearest one stands.
    np.testing.assert_allclose(track.at(int(5.025 * S)), turn(10, (1.5, 0.0, 0.0)))
    track.add(5 * S, turn(0, (1.0, 0.0, 0.0)))
    mid = track.at(int(5.025 * S))  # halfway between 5.0 and 5.05
    np.testing.assert_allclose(mid[:3, 3], [1.25, 0.0, 0.0], atol=1e-12)
    assert rotation_error_deg(mid, turn(5)) < 1e-6
    np.testing.assert_allclose(track.at(5 * S), turn(0, (1.0, 0.0, 0.0)))  # exact stamp
    assert track.samples == 4
    near = track.at(int((6 + TOLERANCE_S / 2) * S))  # after the last sample, within it
    np.testing.assert_allclose(near, turn(20, (2.0, 0.0, 0.0)))
    assert track.at(int((6 + 2 * TOLERANCE_S) * S)) is None


def answer(confirmed, used, refusal=None, done=False):
    code = None if confirmed else (refusal or Refusal(RefusalCode.AMBIGUOUS, 'a rival'))
    T = turn(30, (1.0, 2.0, 0.0))
    return StepAnswer(code, None, confirmed, done or confirmed, T, T @ turn(-5), used, 4)


def test_verdicts_answer_a_confirmed_pose_and_refuse_when_the_scans_run_out():
    run = SequenceRun()
    low = Refusal(RefusalCode.LOW_RATIO, 'best/runner-up 1.2')
    # One scan confirmed by the relocalizer but held back by the initial-pose guards: more.
    v = run.judge(answer(True, 1), low, max_scans=3)
    assert not v.finished and v.refusal.code is RefusalCode.LOW_RATIO and v.scans == 1
    assert run.timed_out(10.0).code is RefusalCode.LOW_RATIO
    assert 'relocalization.timeout = 10 s ran out after 1 scan' in run.timed_out(10.0).message
    # Confirmed over two scans: the relocalizer's checks stand, the single-scan guard not.
    v = run.judge(answer(True, 2), low, max_scans=3)
    assert v.finished and v.refusal is None and v.scans == 2 and v.used == 2
    assert v.line(True, '').startswith('localized: x 1.000 y 2.000 z 0.000 m, yaw 30.0 deg')
    assert run.timed_out(10.0) is None  # reset: nothing in progress
    # A single scan that passes every guard is answered at once, as without odometry.
    assert run.judge(answer(True, 1), None, max_scans=3).finished
    # Never confirmed: another scan until max_scans, then refused with the relocalizer's code.
    verdicts = [run.judge(answer(False, k), None, max_scans=3) for k in (1, 2, 3)]
    assert [v.finished for v in verdicts] == [False, False, True]
    assert all(v.refusal.code is RefusalCode.AMBIGUOUS for v in verdicts)
    assert verdicts[-1].line(False, '').startswith('ambiguous: not localized: a rival')


def test_a_scan_without_odometry_near_its_stamp_is_judged_alone_and_starts_over():
    run = SequenceRun()
    assert run.step(5 * S, np.eye(4)) is None  # no odometry at all: one scan at a time
    run.track.add(5 * S, turn(10, (1.0, 0.0, 0.0)))
    base = make_transform(quaternion_to_matrix(BASE_FROM_SENSOR[3:]), BASE_FROM_SENSOR[:3])
    odom, restart = run.step(5 * S, base)
    assert restart
    np.testing.assert_allclose(odom, turn(10, (1.0, 0.0, 0.0)) @ base)
    odom, restart = run.step(7 * S, base)  # two seconds from any odometry
    assert odom is None and not restart
    run.judge(answer(False, 1), None, 3)
    assert run.judge(answer(True, 1), None, 3).map_from_odom is None  # no odometry: no map->odom
    run.track.add(8 * S, turn(10, (1.0, 0.0, 0.0)))
    assert run.step(8 * S, base)[1]  # the scan after the gap starts over
    assert run.step(8 * S, None)[0] is None  # unknown extrinsic


# --- the engine on real fragments -------------------------------------------------------------

def robot_odometry(poses, ids, seed):
    """
    Return odom <- sensor of ``ids`` (test_relocalizer's drifting odometry), rotations exact.

    The fragments' poses are rotations to about 1e-5 only; an odometry message carries a
    quaternion, an exact rotation, so the poses the node gets are these.
    """
    out = odometry(poses, ids, np.random.default_rng(seed))
    for T in out:
        T[:3, :3] = Rotation.from_matrix(T[:3, :3]).as_matrix()
    return out


def relocalize(scene_data, ids, odom_sensor, **node):
    """
    Run one on-demand request over the scans ``ids`` through the engine; return what it did.

    The odometry (``odom <- base`` from ``odom_sensor`` and the extrinsic) is fed at each
    scan's stamp, and half a second before it (too far to count).
    """
    _, cfg, poses, fragments, path = scene_data
    base = make_transform(quaternion_to_matrix(BASE_FROM_SENSOR[3:]), BASE_FROM_SENSOR[:3])
    out = Recorder()
    engine = RegistrationEngine(cfg, configs_from_parameters({
        'map.file': str(path), 'map.cache_dir': '', 'worker.registration_timeout': 0.0,
        'mode': 'on_demand', 'relocalization.publish_initial_pose': True,
        'relocalization.cooldown': 0.0, 'relocalization.timeout': 600.0,
        'relocalization.base_from_sensor': list(BASE_FROM_SENSOR), **node})[1], out)
    engine.start()
    engine.activate()
    answers, steps = [], []
    try:
        engine.relocalize(lambda *a: answers.append(a))
        for i, (k, O) in enumerate(zip(ids, odom_sensor)):
            stamp = (100 + i) * S
            O_base = O @ np.linalg.inv(base)
            engine.odometry(stamp - S // 2, O_base @ turn(45, (1.0, 0.0, 0.0)))
            engine.odometry(stamp, O_base)
            engine.receive('source', stamp, 'sensor',
                           Cloud(fragments[k], Header('sensor', stamp), time.monotonic_ns()))
            wait_for(lambda: len(out.results) > i, 600, f'scan {i} to be registered')
            steps.append((len(answers), len(out.initial)))
            if answers:
                break
    finally:
        engine.stop()
    return answers, steps, out, base


@pytest.mark.slow
def test_the_engine_answers_once_the_scans_confirm_what_one_cannot(scene):
    data = scene(HARD)
    poses = data[2]
    odom = robot_odometry(poses, HARD, 2)
    answers, steps, out, base = relocalize(data, HARD, odom)
    assert steps[0] == (0, 0)  # one scan: ambiguous, neither answered nor published
    assert len(answers) == 1 and answers[0][0], answers
    assert steps[-1] == (1, 1) and len(out.initial) == 1  # published once, when confirmed
    assert ' confirmed over ' in answers[0][1] and len(steps) >= 2
    k = HARD[len(steps) - 1]
    pose = out.initial[0]
    T_map_base = poses[k] @ np.linalg.inv(base)  # the confirming scan's base in the map
    errors = rotation_error_deg(pose.transform, T_map_base), translation_error(
        pose.transform, T_map_base)
    assert right(pose.transform, T_map_base), errors
    # map <- odom carries the odometry's base pose of that scan to the same place
    assert right(pose.map_from_odom @ odom[len(steps) - 1] @ np.linalg.inv(base), T_map_base)


@pytest.mark.slow
def test_the_engine_refuses_odometry_that_contradicts_the_scans(scene):
    data = scene(EASY)
    odom = robot_odometry(data[2], EASY, 1)
    odom[1] = odom[1] @ turn(30, (1.0, 0.0, 0.0))  # the second scan's odometry is off
    # Single scans held back by the guards (each alone is valid): only the sequence decides.
    answers, steps, out, _ = relocalize(data, EASY, odom, **{'relocalization.min_ratio': 1e6})
    assert [s[0] for s in steps] == [0, 0, 1]  # answered after the third scan, not before
    (success, message), = answers
    assert not success and message.startswith('unexplained: not localized: '), message
    assert 'odometry contradicts the scans' in message and out.initial == []
