"""
Real KITTI scans at 10 Hz through register_node over DDS, tracked from the last pose.

The node runs as users run it (its own process, registration in its child process, the
shipped Fast DDS profile loaded by itself), scan 0 latched as the map; a short stream of real
scans (~4 MB PointCloud2 each) goes out at 10 Hz with a 7 m jump back in it. Transport: the
test's publisher is reliable on Fast DDS's defaults, and the node's subscription reliable
with its default history (``pairing.source_depth``, 30 scans): a reliable reader still
drops the oldest unread scans beyond its history, and the node's executor may not take one
for over half a second on a loaded machine (docs/transport.md). Its queue is as deep, so
that every scan is registered in order and the count of tracked and global poses does not
depend on the machine's speed.
"""

from __future__ import annotations

from pathlib import Path

import pytest

rclpy = pytest.importorskip('rclpy')

from bench import node_tracking as bench  # noqa: E402, I100
from waiting import ros_args, spun_context, stop_process, wait_for  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]
DOMAIN_ID = 93  # distinct from the other DDS test modules
RATE_HZ = 10.0
ORDER = list(range(10)) + [0, 1]  # scan 9 -> scan 0: a 7 m jump back
NODE_PARAMS = {'voxel_size': 0.5, 'pairing.target_durability': 'transient_local',
               'pairing.source_qos': 'reliable', 'pairing.queue_depth': 30,
               'output.diagnostics_period': 0.2,
               'pairing.backlog_max_lag': 0.0}  # every scan, in order: none skipped


def reliable_client(context):
    return bench.StreamClient(context, reliable=True)


def start_with_map(client, msgs, tmp_path: Path, **params):
    """Start the node (its process warm) and latch scan 0 as its map; return (proc, log)."""
    proc, log = bench.start_node(ros_args(**NODE_PARAMS, **params),
                                 bench.dds_environment(DOMAIN_ID), tmp_path / 'node.log')
    try:
        wait_for(lambda: client.value('registration.ready') == 'True', 300,
                 'the node and its registration process', lambda: client.diagnostics)
        client.target_pub.publish(msgs[0])
        wait_for(lambda: client.value('targets.received') == '1', 60, 'the map')
    except BaseException:
        stop_process(proc, log)
        raise
    return proc, log


def test_a_stream_at_10hz_is_tracked_and_a_jump_searched_again(tmp_path: Path):
    msgs, truth = bench.kitti_messages(), bench.pseudo_ground_truth()
    with spun_context(DOMAIN_ID, reliable_client) as (_, _, client):
        proc, log = start_with_map(client, msgs, tmp_path)
        try:
            stamps = client.play(msgs, ORDER, RATE_HZ)
            client.settle(stamps, quiet_s=60.0, limit_s=300.0)
            cell = bench.summarize(client, stamps, truth)
            wait_for(lambda: client.value('tracking.tracked') == str(cell['tracked']), 10,
                     'the counts on /diagnostics', lambda: client.diagnostics)
            values = dict(client.diagnostics)
        finally:
            out = stop_process(proc, log)
    assert proc.returncode == 0, out
    missing = [i for i, s in enumerate(stamps) if s not in client.results]
    assert not missing, (missing, values.get('sources.lost_upstream'), values, out[-3000:])
    assert cell['results'] == cell['published'] == len(ORDER), (cell, out)
    # The first scan and the jump are global; every other scan is tracked.
    paths = [client.results[s]['path'] for s in stamps]
    assert paths == ['global'] + ['tracked'] * 9 + ['global', 'tracked'], paths
    assert client.results[stamps[10]]['stats']['tracking_failure_code'], 'the jump was tried'
    assert (cell['tracked'], cell['global']) == (10, 2)
    assert cell['within_1deg_20cm'] == len(ORDER) and cell['beyond_5deg_60cm'] == 0, cell
    assert (values['tracking.tracked'], values['tracking.global'],
            values['tracking.tracking_failures'], values['tracking.periodic_checks']) == (
                '10', '2', '1', '0'), values
    assert values['accounting.ok'] == 'True', values


def test_a_periodic_check_runs_beside_the_stream_in_its_own_process(tmp_path: Path):
    """
    A stream through the node while its checks' lane runs: the check's verdict is applied.

    A check is due every fourth tracked scan (``config_file``); the first one starts the
    checks' process, the stream waits for it to warm up, then goes on: the checks run in
    that process, their verdicts (they agree) reach the stream, and every pose stays right.
    """
    msgs, truth = bench.kitti_messages(), bench.pseudo_ground_truth()
    checks = {'tracking.global_check_interval': 4, 'tracking.global_check_period': 0.0}
    with spun_context(DOMAIN_ID, reliable_client) as (_, _, client):
        proc, log = start_with_map(client, msgs, tmp_path, **checks)
        try:
            stamps = client.play(msgs, list(range(6)), RATE_HZ)  # a check due: the lane starts
            client.settle(stamps, quiet_s=60.0, limit_s=300.0)
            wait_for(lambda: client.value('checks.ready') == 'True', 300,
                     'the checks process warm', lambda: client.diagnostics)
            more = client.play(msgs, list(range(6, 16)) + list(range(14, 8, -1)), RATE_HZ)
            client.settle(more, quiet_s=60.0, limit_s=300.0)
            wait_for(lambda: int(client.value('checks.valid') or 0) >= 1, 120,
                     'a check landed', lambda: client.diagnostics)
            last = client.play(msgs, [8, 7, 6, 5], RATE_HZ)  # the next scan takes the verdict
            client.settle(last, quiet_s=60.0, limit_s=300.0)
            stamps += more + last
            wait_for(lambda: int(client.value('tracking.periodic_checks') or 0) >= 1, 30,
                     'the verdict applied', lambda: client.diagnostics)
            values = dict(client.diagnostics)
            cell = bench.summarize(client, stamps, truth)
        finally:
            out = stop_process(proc, log)
    assert proc.returncode == 0, out
    # Reliable, with the subscription's history deep enough (the module's docstring): every
    # scan reaches the node and is published.
    assert cell['results'] == cell['published'] == len(stamps), (cell, out)
    published = cell['published']
    assert cell['within_1deg_20cm'] == published and cell['beyond_5deg_60cm'] == 0, cell
    assert int(values['checks.offered']) >= 1 and int(values['checks.valid']) >= 1, values
    assert 'tracking.check_disagreements' not in values, values  # right poses: they agree
    assert int(values['checks.pid']) > 0 and float(values['memory.checks_rss_mb']) > 0
    assert values['accounting.ok'] == 'True', values
