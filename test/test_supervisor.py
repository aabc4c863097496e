"""
cgags_ros.runtime.supervisor: typed jobs in a supervised registration process.

No ROS: the real pipeline in a real spawned process, killed, timed out and replaced as the
node's registrations are; each job kind through it, and its typed answer.
"""

from __future__ import annotations

import os
import signal
import threading

from cgags_ros.config import PipelineConfig
from cgags_ros.errors import EmptyCloudError
from cgags_ros.io.clouds import write_cloud
from cgags_ros.pipeline import register_clouds
from cgags_ros.pipeline.map import load_map
from cgags_ros.pipeline.register import terrain_patch
from cgags_ros.relocalization.sequence import StepAnswer
from cgags_ros.runtime.jobs import (CheckScan, CheckVerdict, MapReady, MapRef, PairDone,
                                    PrepareMap, RegisterPair, SequenceScan, Tracked, TrackScan)
from cgags_ros.runtime.procfs import rss_mb, running
from cgags_ros.runtime.supervisor import ProcessCrashed, RegistrationTimeout, Supervisor
import numpy as np
import pytest
from waiting import wait_for

pytestmark = pytest.mark.subprocess
CONFIG = PipelineConfig(voxel_size=0.15)


@pytest.fixture(scope='module')
def pair():
    """Return (source, target): a terrain patch and itself turned by 0.2 rad and moved."""
    target = terrain_patch(np.random.default_rng(3))
    c, s = np.cos(0.2), np.sin(0.2)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return target @ R.T + 0.1, target


@pytest.fixture()
def map_ref(pair, tmp_path):
    """Return a MapRef to a map file of the pair's target."""
    path = tmp_path / 'patch.ply'
    write_cloud(path, pair[1])
    return MapRef(str(path))


def pair_result(supervisor, source, target):
    answer = supervisor.run(RegisterPair(source, target, CONFIG))
    assert isinstance(answer, PairDone)
    return answer.result


def test_the_process_is_sent_an_unchanged_target_once(pair):
    """
    Check that the registration process is sent an unchanged target only once.

    It reports ready once warmed up (not while spawning, nor after a restart until warm).

    The registration process keeps the last target: the same array object is not sent
    again, a new one is, and after a restart (fresh process) it is sent again. Results equal
    the pipeline run in this process.
    """
    source, target = pair
    other = target[::-1].copy()  # same points, another array: must be sent
    iso = Supervisor(60.0)
    try:
        # Spawning, warming up.
        assert not iso.ready and iso.health()['registration.ready'] is False
        first = pair_result(iso, source, target)
        assert iso.ready and iso.health()['registration.ready'] is True
        assert iso.targets_sent == 1
        again = pair_result(iso, source, target)
        assert iso.targets_sent == 1
        changed = pair_result(iso, source, other)
        assert iso.targets_sent == 2
        iso.restart()
        assert not iso.ready  # the fresh child warms up again
        after = pair_result(iso, source, other)
        assert iso.targets_sent == 3 and iso.restarts == 1 and iso.crashes == 0
    finally:
        iso.close()
    assert not iso.ready and iso.pid is None
    local = register_clouds(source, target, config=CONFIG)
    for result in (first, again, changed, after):
        assert result.valid, result.reason
        np.testing.assert_allclose(result.transform, local.transform, atol=1e-6)


def test_a_pair_past_the_time_limit_restarts_the_process_and_the_next_one_runs(pair):
    source, target = pair
    iso = Supervisor(0.01)  # no registration ends this fast
    try:
        iso.wait_ready()  # the warm-up is not counted against the limit
        pid = iso.pid
        with pytest.raises(RegistrationTimeout, match='runtime.registration_timeout = 0.01 s'):
            pair_result(iso, source, target)
        assert iso.restarts == 1 and iso.crashes == 0 and iso.pid != pid
        wait_for(lambda: not running(pid), 10, 'the timed-out process to end')
        iso.timeout_s = 120.0
        result = pair_result(iso, source, target)
        assert result.valid, result.reason
        assert iso.targets_sent == 2  # the fresh process was sent the target again
    finally:
        iso.close()


def test_a_process_killed_busy_fails_its_pair_and_one_killed_idle_costs_nothing(pair):
    source, target = pair
    iso = Supervisor(120.0)
    try:
        iso.wait_ready()
        failed = []
        # Dense noise: seconds of features and matching, killed long before it ends.
        noise = np.random.default_rng(0).uniform(-5.0, 5.0, size=(200_000, 3))

        def register():
            try:
                pair_result(iso, noise, target)
            except ProcessCrashed as exc:
                failed.append(exc)

        caller = threading.Thread(target=register)
        caller.start()
        wait_for(lambda: iso.in_flight, 60, 'the pair to reach the registration process')
        pid = iso.pid
        assert iso.health()['memory.registration_rss_mb'] > 0 and rss_mb(pid) > 0
        os.kill(pid, signal.SIGKILL)
        caller.join(60)
        assert [str(f) for f in failed] == [
            'the registration process died during this pair (killed, out of memory or a '
            'native crash); restarted']
        assert iso.crashes == 1 and iso.restarts == 1 and not iso.in_flight

        iso.wait_ready()
        pid = iso.pid
        os.kill(pid, signal.SIGKILL)  # idle: found dead before the next pair is sent
        wait_for(lambda: not running(pid), 10, 'the idle process to die')
        assert iso.health()['registration.alive'] is False
        result = pair_result(iso, source, target)
        assert result.valid, result.reason
        assert iso.crashes == 2 and iso.pid != pid and iso.health()['registration.alive'] is True
    finally:
        iso.close()
    assert not running(pid)


def test_supervise_replaces_a_process_that_died_idle_and_errors_come_back_typed(pair):
    source, target = pair
    iso = Supervisor(120.0)
    try:
        iso.wait_ready()
        assert not iso.supervise()  # alive: nothing to do
        pid = iso.pid
        with open(f'/proc/{pid}/environ', 'rb') as f:  # set before it loaded numpy
            environ = f.read().split(b'\0')
        assert b'OMP_WAIT_POLICY=PASSIVE' in environ or 'OMP_WAIT_POLICY' in os.environ
        os.kill(pid, signal.SIGKILL)
        wait_for(lambda: not running(pid), 10, 'the idle process to die')
        assert iso.supervise() and iso.crashes == 1 and iso.pid != pid
        with pytest.raises(EmptyCloudError):  # raised in the child, re-raised here
            pair_result(iso, np.zeros((0, 3)), target)
        assert iso.crashes == 1 and iso.restarts == 1  # an error is no crash
        assert pair_result(iso, source, target).valid
    finally:
        iso.close()


def test_every_job_kind_gets_its_typed_answer_and_a_killed_process_forgets_its_state(
        pair, map_ref):
    """
    Each job kind runs in the process, which holds what they share until it is killed.

    A map is prepared and kept, a stream's scans are tracked after the first, a sequence's
    scans are judged on the map; after a kill the fresh process holds none of it: the map
    is loaded again, the stream starts global, the sequence starts over.
    """
    source, target = pair
    ref = map_ref
    iso = Supervisor(120.0)
    try:
        ready = iso.run(PrepareMap(ref, CONFIG))
        assert isinstance(ready, MapReady) and ready.info['points'] > 0
        paths = []
        for k in range(3):
            answer = iso.run(TrackScan(source, ref, CONFIG, stamp=0.1 * k))
            assert isinstance(answer, Tracked) and answer.result.valid, answer.result.reason
            paths.append(answer.result.path)
            assert sum(answer.counts.values()) >= 1  # this scan's share of the counts
        assert paths == ['global', 'tracked', 'tracked']
        step = iso.run(SequenceScan(source, ref, CONFIG, np.eye(4), 3, restart=True))
        assert isinstance(step, StepAnswer) and step.scans_used == 1
        step = iso.run(SequenceScan(source, ref, CONFIG, np.eye(4), 3, restart=False))
        assert step.scans_used == 2
        pid = iso.pid
        os.kill(pid, signal.SIGKILL)
        wait_for(lambda: not running(pid), 10, 'the killed process to end')
        answer = iso.run(TrackScan(source, ref, CONFIG, stamp=0.3))
        assert answer.result.path == 'global'  # no prior in the fresh process
        assert answer.result.map_info  # the map loaded again
        step = iso.run(SequenceScan(source, ref, CONFIG, np.eye(4), 3, restart=False))
        assert step.scans_used == 1  # the sequence started over
        assert iso.crashes == 1
    finally:
        iso.close()


def test_a_process_at_low_priority_gets_its_clouds_through_files_and_leaves_none(
        pair, tmp_path):
    """The checks' lane: niceness 15, clouds spilled to files, a check answered by its pose."""
    source, target = pair
    iso = Supervisor(120.0, niceness=15, spill_dir=str(tmp_path))
    try:
        answer = iso.run(CheckScan(source, target, CONFIG, stamp=1.5))
        assert isinstance(answer, CheckVerdict) and answer.stamp == 1.5 and not answer.code
        local = register_clouds(source, target, config=CONFIG)
        np.testing.assert_allclose(answer.transform, local.transform, atol=1e-6)
        assert not list(tmp_path.iterdir())  # the files went with the job
        ours = os.getpriority(os.PRIO_PROCESS, 0)
        assert os.getpriority(os.PRIO_PROCESS, iso.pid) == min(ours + 15, 19)
        refused = iso.run(CheckScan(np.zeros((5, 3)), target, CONFIG, stamp=2.0))
        assert refused.transform is None and refused.code  # too few points: no pose
    finally:
        iso.close()


def test_the_checks_lane_loads_its_map_and_checks_without_ever_waiting(pair, map_ref):
    """Offers return at once: skipped while warming up, then the map first, then the check."""
    from cgags_ros.runtime.checks import CheckLane

    source, target = pair
    ref = map_ref
    lane = CheckLane(120.0)
    try:
        lane.prepare_map(ref, CONFIG, 120.0)
        assert not lane.offer(source, ref, CONFIG, 1.0)
        assert not lane.supervisor.ready  # it returned without waiting for the warm-up
        wait_for(lambda: lane.supervisor.ready, 300, 'the lane warm')
        assert not lane.offer(source, ref, CONFIG, 2.0)  # the map goes first
        wait_for(lambda: lane.landed() is None and not lane.supervisor.in_flight, 300,
                 'the map loaded')
        assert lane.offer(source, ref, CONFIG, 3.0)
        verdict = wait_for(lambda: lane.landed(), 300, 'the check')
        local = register_clouds(source, load_map(ref.path, CONFIG), config=CONFIG)
        assert verdict.stamp == 3.0 and not verdict.code
        np.testing.assert_allclose(verdict.transform, local.transform, atol=1e-6)
        stats = lane.statistics()
        assert (stats['checks.offered'], stats['checks.skipped_busy'], stats['checks.valid']) == (
            1, 2, 1)
    finally:
        lane.close()
