"""
cgags_ros.engine.engine without ROS: pairing, accounting, lifecycle states, guards, requests.

The engine is fed decoded clouds directly and publishes into a recorder; the registration
is a stand-in that returns a known pose (the real pipeline runs in the DDS tests), so these
check the decisions: what is counted where, what is published, what the guards refuse.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

from cgags_ros.config.node import configs_from_parameters
from cgags_ros.config.pipeline import PipelineConfig
from cgags_ros.config.tracking import TrackingConfig
from cgags_ros.engine import startup
from cgags_ros.engine.engine import RegistrationEngine
from cgags_ros.engine.interface import Cloud, StartFailed
from cgags_ros.geometry import make_transform, quaternion_to_matrix
from cgags_ros.io.clouds import write_cloud
from cgags_ros.pipeline.result import PipelineResult
from cgags_ros.refusal import Refusal, RefusalCode
from cgags_ros.runtime.process import ChildSession
from cgags_ros.runtime.procfs import running
from cgags_ros.runtime.supervisor import Supervisor
import numpy as np
import pytest
from waiting import bad_map, FakeRunner, wait_for

T_TRUE = make_transform(quaternion_to_matrix((0.0, 0.0, 0.2588190, 0.9659258)), (1.0, 2.0, 0.5))


class Header:
    """A message header as the engine sees it: a frame (and a stamp it never reads)."""

    def __init__(self, frame_id, stamp=0):
        self.frame_id, self.stamp = frame_id, stamp


class Recorder:
    """The node's side of EngineOutputs: records what the engine publishes and logs."""

    def __init__(self):
        self.estimates, self.candidates, self.initial, self.logs = [], [], [], []
        self.results = []
        self.odom = {}  # odom <- base by stamp (ns), as the node's odometry has it
        self.tf = {}  # (parent, child) -> parent <- child, as the node's TF has it

    def publish_estimate(self, estimate):
        self.estimates.append(estimate)

    def publish_candidates(self, header, frame_id, transforms):
        self.candidates.append((frame_id, transforms))

    def publish_initial_pose(self, pose):
        self.initial.append(pose)

    def publish_result(self, result):
        self.results.append(json.loads(result.to_json()))  # what ~/result carries

    def base_from_sensor(self, base_frame, sensor_frame):
        return np.eye(4)

    def odometry(self, odom_frame, base_frame, stamp_ns):
        return bool(self.odom), self.odom.get(stamp_ns)

    def lookup(self, parent, child, stamp_ns=None):
        return self.tf.get((parent, child))

    def log(self, level, message):
        self.logs.append((level, message))


def fake_register(source, target, *, config):
    """Return a confident estimate: T_TRUE, 40 inliers, no runner-up; invalid for 7 points."""
    valid = len(source) != 7
    return PipelineResult(transform=T_TRUE,
                          refusal=None if valid else Refusal(RefusalCode.FEW_INLIERS, 'fake: 7'),
                          inliers=np.arange(40), num_correspondences=100, fitness=0.8,
                          covariance=np.eye(6) * 1e-4)


def node_config(**keys):
    """Return the NodeConfig of configuration keys (``{'pairing.mode': ...}``)."""
    return configs_from_parameters(keys)[1]


# Pairs, not a tracked stream: these check the plumbing on a stand-in registration.
PIPE = PipelineConfig(tracking=TrackingConfig(enabled=False))


def make(**node):
    out = Recorder()
    engine = RegistrationEngine(PIPE, node_config(**node), out, runner=FakeRunner(fake_register))
    engine.start()
    return engine, out


def ask(engine, timeout=30.0):
    """Request a relocalization; return its answer (success, message)."""
    answers, done = [], threading.Event()
    engine.relocalize(lambda *answer: (answers.append(answer), done.set()))
    assert done.wait(timeout), 'no answer'
    return answers[0]


def send(engine, role, stamp_s, n=50, frame='lidar'):
    xyz = np.random.default_rng(stamp_s).normal(size=(n, 3))
    engine.receive(role, int(stamp_s * 1e9), frame,
                   Cloud(xyz, Header(frame, stamp_s), time.monotonic_ns()))


def balanced(engine):
    acc = engine.snapshot()['accounting']
    assert acc['ok'], acc
    return acc


@pytest.mark.subprocess
def test_the_engine_imports_no_ros():
    code = ('import sys, cgags_ros.engine.engine, cgags_ros.engine.map_target, '
            'cgags_ros.engine.startup; '
            "print(sorted(m for m in sys.modules if m.split('.')[0] in "
            "('rclpy', 'rcl_interfaces', 'std_msgs', 'sensor_msgs', 'geometry_msgs')))")
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == '[]'


def test_inactive_sources_are_counted_then_pairs_publish_after_activate():
    engine, out = make()
    try:
        send(engine, 'target', 1, frame='map')
        send(engine, 'source', 2)
        stats = engine.snapshot()
        assert stats['rejected'] == {'inactive': 1} and not out.estimates
        assert balanced(engine)['targets']['pending'] == 1  # the target is still held
        engine.activate()
        send(engine, 'source', 3)
        wait_for(lambda: out.estimates, 10, 'an estimate')
        est = out.estimates[0]
        np.testing.assert_allclose(est.transform, T_TRUE)
        assert est.frame_id == 'map' and est.header.stamp == 3
        np.testing.assert_allclose(est.covariance, np.eye(6) * 1e-4)
        assert est.aligned is None and est.tf_child_frame == ''
        assert out.candidates == [('map', [])]
        acc = wait_for(lambda: engine.snapshot()['counts'].get('published') == 1
                       and balanced(engine), 10, 'published')
        assert acc['sources'] == {'received': 2, 'published': 1, 'rejected': 1, 'dropped': 0,
                                  'pending': 0, 'lost_upstream': 0}
        engine.deactivate()
        send(engine, 'source', 4)
        assert engine.snapshot()['rejected']['inactive'] == 2
        assert len(out.estimates) == 1
        assert engine.statistics()['active'] is False
    finally:
        engine.stop()
    assert not engine.active


def test_invalid_results_are_rejected_unless_publish_invalid():
    engine, out = make(**{'output.publish_aligned_cloud': True, 'output.broadcast_tf': True})
    engine.activate()
    try:
        send(engine, 'target', 1, frame='map')
        send(engine, 'source', 2, n=7)
        wait_for(lambda: engine.snapshot()['rejected'].get('few_inliers'), 10, 'rejection')
        assert not out.estimates
        assert any('invalid registration: fake: 7' in m for _, m in out.logs)
        last = engine.snapshot()['last']  # /diagnostics: the code beside the message
        assert (last['valid'], last['refusal_code'], last['reason']) == (
            False, 'few_inliers', 'fake: 7')
        engine.set_configs(PIPE, node_config(**{
            'output.publish_invalid': True, 'output.publish_aligned_cloud': True,
            'output.broadcast_tf': True}))
        send(engine, 'source', 3, n=7)
        wait_for(lambda: out.estimates, 10, 'the invalid estimate')
        assert out.estimates[0].aligned.shape == (7, 3)
        assert out.estimates[0].tf_child_frame == 'lidar'
        assert engine.snapshot()['counts']['published_invalid'] == 1
        balanced(engine)
    finally:
        engine.stop()


def test_every_accounted_source_has_one_result_saying_what_became_of_it():
    """~/result: one record a source, published, rejected (when and why) or dropped."""
    engine, out = make(**{'pairing.max_waiting_sources': 1})
    try:
        send(engine, 'source', 1)  # inactive: rejected at once
        engine.activate()
        send(engine, 'source', 2)  # no target yet: waits, then is superseded by 3
        send(engine, 'source', 3)
        engine.receive('source', 4 * 10**9, 'lidar', None,
                       Refusal(RefusalCode.BAD_INPUT, 'bad cloud'))
        send(engine, 'target', 5, frame='map')  # pairs 3
        wait_for(lambda: out.estimates, 10, 'the pose of 3')
        send(engine, 'source', 6, n=7)  # registered, invalid
        acc = wait_for(lambda: len(out.results) == 5 and balanced(engine), 10, 'five results')
        assert acc['sources']['pending'] == 0
    finally:
        engine.stop()
    by_stamp = {r['source_stamp_ns'] // 10**9: r for r in out.results}
    assert {k: (r['outcome'], r['cause']) for k, r in by_stamp.items()} == {
        1: ('rejected', 'inactive'), 2: ('dropped', 'source_superseded_before_target'),
        3: ('published', ''), 4: ('rejected', 'bad_input'), 6: ('rejected', 'few_inliers')}
    published, invalid = by_stamp[3], by_stamp[6]
    np.testing.assert_allclose(published['transform'], T_TRUE)  # register_clouds' summary
    assert published['valid'] is True and published['num_inliers'] == 40
    assert published['fitness'] == 0.8 and len(published['covariance']) == 6
    assert (published['frame_id'], published['target_frame']) == ('map', 'map')
    assert published['target_stamp_ns'] == 5 * 10**9 and published['source_frame'] == 'lidar'
    assert invalid['valid'] is False and invalid['reason'] == 'fake: 7'
    assert invalid['message'] == 'invalid registration: fake: 7'
    assert by_stamp[4]['message'] == by_stamp[4]['reason'] == 'bad cloud'
    # the refusal: the registration's own when one ran, else the node's
    assert invalid['refusal'] == {'code': 'few_inliers', 'message': 'fake: 7'}
    assert published['refusal'] is None
    assert {k: by_stamp[k]['refusal']['code'] for k in (1, 2, 4)} == {
        1: 'inactive', 2: 'unpaired', 4: 'bad_input'}
    assert 'transform' not in by_stamp[4] and by_stamp[4]['target_stamp_ns'] is None


def test_initial_pose_guards_extrinsic_and_max_auto():
    t, q = (0.3, -0.1, 0.8), (0.0, 0.0, 0.3826834, 0.9238795)
    engine, out = make(**{'relocalization.publish_initial_pose': True,
                          'relocalization.cooldown': 0.0, 'relocalization.max_auto': 1,
                          'relocalization.base_from_sensor': list(t + q)})
    engine.activate()
    try:
        send(engine, 'target', 1, frame='map')
        for stamp in (2, 3):
            send(engine, 'source', stamp)
            wait_for(lambda: len(out.estimates) == stamp - 1, 10, 'estimate')
        wait_for(lambda: engine.statistics().get('initial_pose.refused.max_auto'), 10,
                 'the max_auto refusal')
        assert len(out.initial) == 1
        base = out.initial[0]
        T_bs = make_transform(quaternion_to_matrix(q), t)
        np.testing.assert_allclose(base.transform, T_TRUE @ np.linalg.inv(T_bs), atol=1e-6)
        assert base.map_frame == 'map' and base.odom_frame == ''
        # the lever arm moves the position's uncertainty: larger than the sensor's
        assert np.trace(base.covariance[:3, :3]) > np.trace(np.eye(3) * 1e-4)
    finally:
        engine.stop()
    strict, out = make(**{'relocalization.publish_initial_pose': True,
                          'relocalization.min_inliers': 41})
    strict.activate()
    try:
        send(strict, 'target', 1, frame='map')
        send(strict, 'source', 2)
        wait_for(lambda: strict.statistics().get('initial_pose.refused.few_inliers'), 10,
                 'the few_inliers refusal')
        assert not out.initial and out.estimates
    finally:
        strict.stop()


def test_one_quality_refusal_a_pair_serves_the_guard_and_the_answer(monkeypatch):
    from cgags_ros.engine import relocalization_run as engine_module

    decide, verdicts = engine_module.quality_refusal, []

    def counted(result, cfg):
        verdicts.append(decide(result, cfg))
        return verdicts[-1]

    monkeypatch.setattr(engine_module, 'quality_refusal', counted)
    engine, out = make(mode='on_demand', **{
        'relocalization.max_scan_age': 30.0, 'relocalization.timeout': 20.0,
        'relocalization.publish_initial_pose': True, 'relocalization.min_inliers': 41})
    engine.activate()
    try:
        send(engine, 'target', 1, frame='map')
        send(engine, 'source', 2)
        wait_for(lambda: engine.snapshot()['pairing']['pending'], 5, 'a held pair')
        success, answer = ask(engine)
        assert not success and answer.startswith('few_inliers: not localized: 40 inliers < '
                                                 'relocalization.min_inliers 41; '), answer
        assert [v.code for v in verdicts] == [RefusalCode.FEW_INLIERS]  # once, for one pair
        stats = engine.statistics()
        assert stats['initial_pose.refused.few_inliers'] == 1
        assert stats['relocalize.failed.few_inliers'] == 1 and not out.initial
    finally:
        engine.stop()


def test_on_demand_registers_only_when_requested_and_answers():
    engine, out = make(mode='on_demand', **{'relocalization.max_scan_age': 30.0,
                                            'relocalization.timeout': 20.0})
    assert ask(engine) == (False, 'inactive: not localized: the node is not active')
    engine.activate()
    try:
        send(engine, 'target', 1, frame='map')
        send(engine, 'source', 2)
        assert wait_for(lambda: engine.snapshot()['pairing']['pending'], 5, 'a held pair')
        assert not out.estimates  # nothing registered before a request
        answers = []
        caller = threading.Thread(target=lambda: answers.append(ask(engine)))
        caller.start()
        caller.join(20)
        assert answers and answers[0][0], answers
        assert answers[0][1].startswith('localized: x 1.000 y 2.000 z 0.500 m, yaw 30.0 deg')
        later = []
        engine.relocalize(lambda *a: later.append(a))
        send(engine, 'source', 3)
        wait_for(lambda: later, 10, 'the answer of a request not waited for')
        assert later[0][0]
        stats = engine.statistics()
        assert stats['relocalize.calls'] == 3 and stats['relocalize.succeeded'] == 2
        assert stats['relocalize.failed.inactive'] == 1
        # a request pending when the node is deactivated fails at once, not at its deadline
        pending = []
        engine.relocalize(lambda *a: pending.append(a))
        engine.deactivate()
        assert pending == [(False, 'inactive: not localized: the node was deactivated')]
        assert engine.statistics()['relocalize.failed.inactive'] == 2
        balanced(engine)
    finally:
        engine.stop()


@pytest.mark.parametrize('mode', ['latest_target', 'synchronized'])
def test_pairing_drops_are_accounted(mode):
    engine, out = make(**{'pairing.mode': mode, 'pairing.sync_slop': 0.01,
                          'pairing.max_waiting_sources': 1})
    engine.activate()
    try:
        send(engine, 'source', 1)
        send(engine, 'source', 2)  # replaces the first, no target yet: dropped
        send(engine, 'target', 2, frame='map')
        # the estimate is published before the pair is accounted: wait for both
        acc = wait_for(lambda: engine.snapshot()['counts'].get('published') == 1
                       and balanced(engine), 10, 'the pair published')
        assert acc['sources']['dropped'] == 1 and acc['sources']['published'] == 1
    finally:
        engine.stop()


def sphere(n=3000):
    """Return a sphere of 2 m seen from inside: (points, unit normals facing outwards)."""
    normals = np.random.default_rng(0).normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return 2.0 * normals, normals


def test_a_map_without_normals_loads_with_a_warning_and_one_with_normals_without(tmp_path):
    """The map's normals face the map origin unless the file signs them: the log says which."""
    from cgags_ros.engine.map_target import MapTarget

    points, normals = sphere()
    write_cloud(tmp_path / 'bare.ply', points)
    write_cloud(tmp_path / 'signed.ply', points, -normals)
    config = PipelineConfig(voxel_size=0.2)
    for name, signed in (('bare.ply', 'origin'), ('signed.ply', 'file normals')):
        cfg = node_config(**{'map.file': str(tmp_path / name)})
        logs = Recorder()
        target = MapTarget(cfg).load(ChildSession(), config, cfg, logs.log)
        assert target is not None
        warned = [m for level, m in logs.logs if level == 'warning']
        assert any(f'normals signed by {signed}' in m for _, m in logs.logs)
        assert bool(warned) == (signed == 'origin')
        assert not warned or 'frontend.normal_orientation' in warned[0]


@pytest.fixture()
def processes(monkeypatch):
    """Record every registration process the engine starts (its pid tells if it still runs)."""
    started = []

    class Recorded(Supervisor):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            started.append(self)

    monkeypatch.setattr(startup, 'Supervisor', Recorded)
    return started


@pytest.mark.subprocess
@pytest.mark.parametrize('with_map', [False, True])
def test_start_returns_once_the_process_is_warm_and_the_map_loaded(
        tmp_path, processes, with_map):
    """start() blocks until a pair can be registered: the real process warm, the map ready."""
    write_cloud(tmp_path / 'map.ply', sphere()[0])
    out = Recorder()
    engine = RegistrationEngine(PipelineConfig(voxel_size=0.2), node_config(**{
        'map.file': str(tmp_path / 'map.ply') if with_map else '', 'map.cache_dir': '',
        'runtime.registration_timeout': 60.0}), out)
    engine.start()
    try:
        (process,) = processes
        assert engine.runner is process and process.ready
        pid = process.pid
        assert running(pid)
        stats = engine.statistics()
        assert stats['registration.ready'] is True
        if with_map:
            assert stats['map.cache'] == 'off' and 0 < stats['map.points'] <= 3000
            assert engine.snapshot()['accounting']['targets']['pending'] == 1  # the map
            assert any(m.startswith('map ready:') for _, m in out.logs)
    finally:
        engine.stop()
    wait_for(lambda: not running(pid), 10, 'the registration process to end')


@pytest.mark.subprocess
@pytest.mark.parametrize('case', ['missing', 'empty', 'unreadable', 'all_nan'])
def test_a_bad_map_fails_start_with_its_reason(tmp_path, case):
    """A missing, empty, unreadable or all-NaN map: StartFailed naming it, no engine thread."""
    path = bad_map(tmp_path, case)
    cfg = node_config(**{'map.file': str(path), 'map.cache_dir': str(tmp_path / 'cache')})
    engine = RegistrationEngine(PipelineConfig(), cfg, Recorder(),
                                runner=FakeRunner(fake_register))
    with pytest.raises(StartFailed, match='map.file cannot be used') as failure:
        engine.start()
    assert path.name in str(failure.value)
    assert engine.statistics()['map.error'] == str(failure.value)
    assert 'engine' not in [t.name for t in threading.enumerate()]
    engine.stop()  # what the node's cleanup does: harmless after a failed start


@pytest.mark.subprocess
def test_a_bad_map_ends_the_registration_process_it_was_loaded_in(tmp_path, processes):
    """The map is loaded in the real process: start fails and that process is ended."""
    engine = RegistrationEngine(PipelineConfig(), node_config(**{
        'map.file': str(bad_map(tmp_path, 'unreadable')), 'runtime.registration_timeout': 60.0}),
        Recorder())
    with pytest.raises(StartFailed, match='map.file cannot be used: .*broken.ply'):
        engine.start()
    (process,) = processes
    assert engine.runner is None and process.pid is None  # closed
    assert not process.ready


@pytest.mark.subprocess
def test_a_process_that_dies_while_warming_up_fails_start(processes):
    """Killed (-9) during its warm-up: StartFailed says so, and nothing is left running."""
    engine = RegistrationEngine(PipelineConfig(),
                                node_config(**{'runtime.registration_timeout': 60.0}), Recorder())
    failures = []

    def start():
        try:
            engine.start()
        except StartFailed as exc:
            failures.append(exc)

    starter = threading.Thread(target=start)
    starter.start()
    pid = wait_for(lambda: processes and processes[0].pid, 30, 'the registration process')
    os.kill(pid, signal.SIGKILL)
    starter.join(60)
    assert not starter.is_alive()
    assert [str(f) for f in failures] == [
        'the registration process failed to start (it died)']
    wait_for(lambda: not running(pid), 10, 'the killed process reaped')
    assert engine.runner is None and processes[0].pid is None
    assert 'engine' not in [t.name for t in threading.enumerate()]
