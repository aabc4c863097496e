"""
cgags_ros.relocalization.sequence without ROS: odometry matched to scans, the node's decisions.

The steps and the verdicts are checked on synthetic answers; then the engine, with the real
pipeline and a map fused from the redkitchen fragments (as in test_relocalizer.py),
relocalizes over consecutive fragments with the odometry its outputs give by stamp:
nothing is answered or published before the pose is confirmed, and odometry that
contradicts the scans is refused.
"""

from __future__ import annotations

import time

from cgags_ros.config.node import configs_from_parameters
from cgags_ros.engine.engine import RegistrationEngine
from cgags_ros.engine.interface import Cloud
from cgags_ros.geometry import make_transform, quaternion_to_matrix
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.refusal import Refusal, RefusalCode
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
    base = make_transform(quaternion_to_matrix(BASE_FROM_SENSOR[3:]), BASE_FROM_SENSOR[:3])
    odom, restart = run.step(turn(10, (1.0, 0.0, 0.0)), base)
    assert restart
    np.testing.assert_allclose(odom, turn(10, (1.0, 0.0, 0.0)) @ base)
    odom, restart = run.step(None, base)  # no odometry near this scan's stamp
    assert odom is None and not restart
    run.judge(answer(False, 1), None, 3)
    assert run.judge(answer(True, 1), None, 3).map_from_odom is None  # no odometry: no map->odom
    assert run.step(turn(10, (1.0, 0.0, 0.0)), base)[1]  # the scan after the gap starts over
    assert run.step(turn(10, (1.0, 0.0, 0.0)), None)[0] is None  # unknown extrinsic


def test_a_scan_is_a_step_of_a_sequence_only_with_odometry_known():
    from cgags_ros.engine.relocalization_run import RelocalizationRun
    from cgags_ros.engine.pairing import Pair, Stamped

    out = Recorder()
    cfg = configs_from_parameters({'map.file': 'map.ply', 'mode': 'on_demand',
                                   'relocalization.base_from_sensor': list(BASE_FROM_SENSOR)})[1]
    localization = RelocalizationRun(cfg, out)
    pair = Pair(Stamped(5 * S, 'sensor', None), Stamped(0, 'map', None))
    out.odom[5 * S] = turn(10, (1.0, 0.0, 0.0))
    assert localization.step(pair, cfg) is None  # no request waits: one scan at a time
    localization.request(60.0, lambda *answer: None)
    out.odom.clear()
    assert localization.step(pair, cfg) is None  # no odometry known: one scan at a time
    out.odom[6 * S] = turn(10, (1.0, 0.0, 0.0))
    assert localization.step(pair, cfg) == (None, True)  # none near its stamp: judged alone
    out.odom[5 * S] = turn(10, (1.0, 0.0, 0.0))
    base = make_transform(quaternion_to_matrix(BASE_FROM_SENSOR[3:]), BASE_FROM_SENSOR[:3])
    odom, restart = localization.step(pair, cfg)
    assert restart  # the scan after one without odometry starts over
    np.testing.assert_allclose(odom, turn(10, (1.0, 0.0, 0.0)) @ base)
    assert localization.step(pair, cfg)[1] is False  # the next one continues


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

    The odometry (``odom <- base`` from ``odom_sensor`` and the extrinsic) is known at each
    scan's stamp, and half a second before it (not the scan's).
    """
    _, cfg, poses, fragments, path = scene_data
    base = make_transform(quaternion_to_matrix(BASE_FROM_SENSOR[3:]), BASE_FROM_SENSOR[:3])
    out = Recorder()
    engine = RegistrationEngine(cfg, configs_from_parameters({
        'map.file': str(path), 'map.cache_dir': '', 'runtime.registration_timeout': 0.0,
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
            out.odom[stamp - S // 2] = O_base @ turn(45, (1.0, 0.0, 0.0))
            out.odom[stamp] = O_base
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
