"""
The node's stream through the Tracker (cgags_ros/tracking), ROS-free, real scans.

The engine (continuous mode, the real pipeline) is fed real KITTI scans one at a time with
10 Hz stamps, scan-to-map against scan 0 latched as the target; ``pseudo_gt.txt`` holds
each scan's pose in scan 0's frame. What each scan became is read from ~/result's records
(``path``, ``valid``, ``transform``) and /diagnostics' ``tracking.*`` counts.
"""

from __future__ import annotations

import contextlib
import os
import signal
import time

from cgags_ros.config.node import NodeConfig, PairingConfig, RuntimeConfig
from cgags_ros.config.pipeline import PipelineConfig
from cgags_ros.config.tracking import TrackingConfig
from cgags_ros.engine.engine import RegistrationEngine
from cgags_ros.engine.interface import Cloud
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.runtime.jobs import StreamCounts, tracks
import numpy as np
import pytest
from test_engine import Header, Recorder
from waiting import wait_for

pytestmark = pytest.mark.slow
VOXEL = 0.5
PERIOD = 0.1  # seconds between scans: a 10 Hz LiDAR


def start(registration_timeout=0.0, pairing=None, **tracking):
    out = Recorder()
    engine = RegistrationEngine(
        PipelineConfig(voxel_size=VOXEL, tracking=TrackingConfig(**tracking)),
        NodeConfig(runtime=RuntimeConfig(registration_timeout=registration_timeout),
                   pairing=PairingConfig(**(pairing or {}))), out)
    engine.start()
    engine.activate()
    return engine, out


def feed(engine, out, role, cloud, stamp_s):
    """Send one cloud; for a source, wait for its ~/result record and return it."""
    before = len(out.results)
    engine.receive(role, int(round(stamp_s * 1e9)), 'map' if role == 'target' else 'velodyne',
                   Cloud(cloud, Header('map' if role == 'target' else 'velodyne', stamp_s),
                         time.monotonic_ns()))
    if role == 'source':
        wait_for(lambda: len(out.results) > before, 300, 'the scan registered')
        return out.results[-1]
    return None


def stream(engine, out, kitti, indices, start_s=100.0):
    scans, _ = kitti
    return [feed(engine, out, 'source', scans[k], start_s + i * PERIOD)
            for i, k in enumerate(indices)]


def within(record, truth, degrees=1.0, metres=0.2):
    T = np.array(record['transform'])
    return (rotation_error_deg(T, truth) <= degrees
            and translation_error(T, truth) <= metres)


def test_a_jump_falls_back_to_global_and_never_publishes_the_stale_pose(kitti):
    scans, truth = kitti
    engine, out = start()
    try:
        feed(engine, out, 'target', scans[0], 99.0)
        records = stream(engine, out, kitti, [13, 14, 15, 0, 1])  # 15 -> 0: 12 m back
        assert [r['path'] for r in records] == ['global', 'tracked', 'tracked', 'global',
                                                'tracked']
        assert all(r['outcome'] == 'published' and r['valid'] for r in records), records
        for k, r in zip([13, 14, 15, 0, 1], records):
            assert within(r, truth[k]), k
        jump = records[3]
        assert jump['stats']['tracking_failure_code'], jump['stats']  # the prior was tried
        assert not within(jump, truth[15], 5.0, 0.6)  # not the stale pose
        published = [e.transform for e in out.estimates]
        assert len(published) == 5
        assert rotation_error_deg(published[3], truth[0]) <= 1.0
        assert translation_error(published[3], truth[0]) <= 0.2
        stats = engine.statistics()
        assert (stats['tracking.tracked'], stats['tracking.global'],
                stats['tracking.tracking_failures'], stats['tracking.periodic_checks']) == (
                    3, 2, 1, 0), stats
        assert engine.snapshot()['last']['path'] == 'tracked'
        # A ~/relocalize call is answered by a global search, not by the prior.
        engine.relocalize(lambda success, message: None)
        (record,) = stream(engine, out, kitti, [2], start_s=100.5)
        assert record['path'] == 'global' and within(record, truth[2])
        stats = engine.statistics()  # the Tracker did not see it
        assert (stats['tracking.tracked'], stats['tracking.global']) == (3, 2), stats
    finally:
        engine.stop()


def burst(engine, out, kitti, indices, start_s=100.0):
    """
    Send a scan, and the others at once while it is registered; wait for them all.

    The others arrive as a sensor's scans do during a global registration. Return each
    scan's ~/result record, in the order sent.
    """
    scans, _ = kitti
    stamps = [int(round((start_s + i * PERIOD) * 1e9)) for i in range(len(indices))]
    taken = engine.snapshot()['pairing']['taken']
    for i, (stamp, k) in enumerate(zip(stamps, indices)):
        engine.receive('source', stamp, 'velodyne',
                       Cloud(scans[k], Header('velodyne', stamp * 1e-9), time.monotonic_ns()))
        if i == 0:
            wait_for(lambda: engine.snapshot()['pairing']['taken'] > taken, 60, 'taken')
    by_stamp = {}
    wait_for(lambda: by_stamp.update({r['source_stamp_ns']: r for r in out.results})
             or all(s in by_stamp for s in stamps), 300, 'every scan told')
    return [by_stamp[s] for s in stamps]


@contextlib.contextmanager
def behind_a_global_registration(kitti, indices, **pairing):
    """Yield an engine, its outputs and the records of a burst of ``indices`` (scan 0 the map)."""
    scans, _ = kitti
    engine, out = start(pairing=pairing)
    try:
        feed(engine, out, 'target', scans[0], 99.0)
        yield engine, out, burst(engine, out, kitti, indices)
    finally:
        engine.stop()


def test_the_scans_behind_a_global_registration_are_tracked_in_order(kitti):
    _, truth = kitti
    indices = [3, 4, 5, 6, 7, 8, 9, 10]
    # A queue of one pair (the backlog off): the scan after the global one is the newest,
    # older than max_age and metres from the last pose: global again, the rest dropped.
    with behind_a_global_registration(kitti, indices, backlog=1) as (_, _, records):
        assert [r['outcome'] for r in records] == ['published'] + ['dropped'] * 6 + [
            'published'], records
        assert [records[0]['path'], records[-1]['path']] == ['global', 'global']
    # The backlog: every scan kept and tracked from its predecessor, in stamp order.
    with behind_a_global_registration(kitti, indices, backlog_max_lag=0.0) as (
            engine, out, records):
        assert [r['path'] for r in records] == ['global'] + ['tracked'] * 7, records
        assert all(r['outcome'] == 'published' and r['valid'] for r in records), records
        assert all(within(r, truth[k]) for k, r in zip(indices, records))
        assert [r['stats']['prediction'] for r in records[1:3]] == ['last pose',
                                                                    'constant velocity']
        # A jump inside the backlog (12 -> 0: 9 m back) still falls back to global.
        records = burst(engine, out, kitti, [11, 12, 0, 1, 2], start_s=100.8)
        assert [r['path'] for r in records] == ['tracked', 'tracked', 'global', 'tracked',
                                                'tracked'], records
        assert all(within(r, truth[k]) for k, r in zip([11, 12, 0, 1, 2], records))
        assert records[2]['stats']['tracking_failure_code'], records[2]['stats']
        assert not within(records[2], truth[12], 5.0, 0.6)  # not the stale pose
        assert len(out.estimates) == 13


def test_a_backlog_that_lags_skips_every_other_scan_once_tracked(kitti):
    _, truth = kitti
    indices = [3, 4, 5, 6, 7, 8, 9, 10]
    with behind_a_global_registration(kitti, indices, backlog_max_lag=0.45) as (
            engine, _, records):
        # After the global scan (3) none is tracked yet: 4 is taken; then 5..10 wait, 0.5 s
        # apart (more than max_lag): 5 is skipped, 6 tracked; 7..10 are 0.3 s apart: in order.
        outcomes = [r['outcome'] + (f".{r['cause']}" if r['cause'] else '') for r in records]
        assert outcomes == ['published', 'published',
                            'dropped.source_skipped_catching_up'] + ['published'] * 5, outcomes
        published = [(k, r) for k, r in zip(indices, records) if r['outcome'] == 'published']
        assert [r['path'] for _, r in published] == ['global'] + ['tracked'] * 6
        assert all(within(r, truth[k]) for k, r in published)
        assert published[2][1]['stats']['prediction'] == 'constant velocity'  # over 0.2 s
        assert engine.snapshot()['pairing']['dropped.source_skipped_catching_up'] == 1


def test_a_new_target_drops_the_prior(kitti):
    scans, truth = kitti
    engine, out = start()
    try:
        feed(engine, out, 'target', scans[0], 99.0)
        first = stream(engine, out, kitti, [3, 4])
        assert [r['path'] for r in first] == ['global', 'tracked']
        feed(engine, out, 'target', scans[5], 100.15)  # a new map: scan 5's frame
        (record,) = stream(engine, out, kitti, [6], start_s=100.2)
        assert record['path'] == 'global', record['stats']
        expected = np.linalg.inv(truth[5]) @ truth[6]  # scan 6 in scan 5's frame
        assert within(record, expected)
        assert engine.statistics()['tracking.target_changes'] == 1
    finally:
        engine.stop()


def test_periodic_global_checks_and_tracking_off(kitti):
    scans, truth = kitti
    engine, out = start(global_check_interval=3, global_check_period=0.0)
    try:
        feed(engine, out, 'target', scans[0], 99.0)
        indices = [1, 2, 3, 4, 5, 6, 7]
        records = stream(engine, out, kitti, indices)
        assert [r['path'] for r in records] == ['global', 'tracked', 'tracked'] * 2 + ['global']
        assert records[3]['stats']['global_because'] == 'periodic check'
        assert all(within(r, truth[k]) for k, r in zip(indices, records))
        assert engine.statistics()['tracking.periodic_checks'] == 2
        pipe = engine.pipeline_config
        engine.set_configs(PipelineConfig(voxel_size=VOXEL,
                                          tracking=TrackingConfig(enabled=False)),
                           engine.node_config)
        records = stream(engine, out, kitti, [8, 9], start_s=100.7)
        assert [r['path'] for r in records] == ['global', 'global']
        assert engine.statistics()['tracking.global'] == 3  # the Tracker saw none of them
        assert not tracks('continuous', engine.pipeline_config) and tracks('continuous', pipe)
        assert not tracks('on_demand', pipe)
    finally:
        engine.stop()


@pytest.mark.subprocess
def test_the_registration_process_holds_the_tracker_and_a_restart_forgets_it(kitti):
    scans, truth = kitti
    engine, out = start(registration_timeout=120.0)
    try:
        feed(engine, out, 'target', scans[0], 99.0)
        records = stream(engine, out, kitti, [7, 8, 9])
        assert [r['path'] for r in records] == ['global', 'tracked', 'tracked']
        assert all(within(r, truth[k]) for k, r in zip([7, 8, 9], records))
        engine.runner.restart()  # a fresh process: no prior, the target sent again
        records = stream(engine, out, kitti, [10, 11], start_s=100.3)
        assert [r['path'] for r in records] == ['global', 'tracked']
        assert all(within(r, truth[k]) for k, r in zip([10, 11], records))
        stats = engine.statistics()
        assert (stats['tracking.tracked'], stats['tracking.global']) == (3, 2), stats
    finally:
        engine.stop()


def test_stream_counts_add_up_the_scans_shares():
    counts = StreamCounts()
    assert counts.statistics() == {'tracking.global': 0, 'tracking.periodic_checks': 0,
                                   'tracking.tracked': 0, 'tracking.tracking_failures': 0}
    for share in ({'tracked': 1}, {'global': 1, 'tracking_failures': 1}, {'tracked': 1}):
        counts.add(share)
    counts.add({})  # registered without the Tracker: counts nothing
    stats = counts.statistics()
    assert (stats['tracking.tracked'], stats['tracking.global'],
            stats['tracking.tracking_failures']) == (2, 1, 1)


@pytest.mark.subprocess
def test_a_periodic_check_runs_beside_the_stream_which_never_waits_for_it(kitti):
    """
    With a registration process, the check of a tracked scan runs in the second lane.

    The scan is tracked, and the stream goes on while the check's process is stopped (a check
    made slow on purpose: SIGSTOP); once it lands, its verdict (it agrees) is applied to the
    next scan and the motion is kept.
    """
    scans, truth = kitti
    engine, out = start(registration_timeout=120.0, global_check_interval=3,
                        global_check_period=0.0)
    try:
        feed(engine, out, 'target', scans[0], 99.0)
        records = stream(engine, out, kitti, [1, 2, 3, 4])  # 4: its check is due
        assert [r['path'] for r in records] == ['global'] + ['tracked'] * 3, records
        lane = engine.checks  # started by the first check due, which it skips (warming up)
        assert lane is not None and engine.statistics()['checks.skipped_busy'] == 1
        wait_for(lambda: lane.supervisor.ready, 300, 'the checks process warmed up')
        records = stream(engine, out, kitti, [5, 6, 7], start_s=100.4)  # 7: due, offered
        assert lane.supervisor.in_flight
        os.kill(lane.supervisor.pid, signal.SIGSTOP)  # the check cannot end now
        try:
            later = stream(engine, out, kitti, [8, 9], start_s=100.7)
            assert [r['path'] for r in records + later] == ['tracked'] * 5, records + later
            assert lane.supervisor.in_flight  # the stream never waited for it
        finally:
            os.kill(lane.supervisor.pid, signal.SIGCONT)
        wait_for(lambda: not lane.supervisor.in_flight, 300, 'the check landed')
        records = stream(engine, out, kitti, [10, 11], start_s=100.9)
        assert [r['path'] for r in records] == ['tracked', 'tracked'], records
        stats = engine.statistics()
        assert stats['tracking.periodic_checks'] == 1, stats  # its verdict applied
        assert stats.get('tracking.check_disagreements', 0) == 0  # it agreed
        assert stats['checks.valid'] == 1 and stats['checks.pid'] > 0
        assert all(within(r, truth[k]) for k, r in zip([10, 11], records))
    finally:
        engine.stop()
