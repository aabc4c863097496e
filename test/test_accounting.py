"""
cgags_ros.engine.accounting and .statistics: scans lost upstream, beside the balanced buckets.

No DDS: the node's accounting object fed directly, its /diagnostics message built (with the
ROS message packages; the rest without).
"""

from __future__ import annotations

import threading

from cgags_ros.config.node import PairingConfig
from cgags_ros.engine import statistics
from cgags_ros.engine.accounting import Accounting
from cgags_ros.engine.transport import PROFILE_VARIABLE
from cgags_ros.refusal import Refusal, RefusalCode
import pytest

PERIOD = 100_000_000  # ns, a 10-Hz LiDAR


def message(health):
    """Return the node's statistics of ``health`` and the /diagnostics status built of them."""
    pytest.importorskip('rclpy')
    from cgags_ros.ros import diagnostics

    stats = statistics.build_statistics(health.snapshot(), 0.5, {})
    status = diagnostics.diagnostic_array(stats, 'n', '/n', None).status[0]
    return stats, status


def test_gaps_in_source_stamps_are_counted_outside_the_balance_with_a_warning():
    health = Accounting(PairingConfig(), queue_depth=100)
    assert health.receive('target', 1, 'map', 'T') == 0
    kept = [k for k in range(60) if k % 4 != 3]  # every fourth scan lost upstream
    new = [health.receive('source', 10 * PERIOD + k * PERIOD, 'lidar', k) for k in kept]
    health.receive('source', 0, '', None, Refusal(RefusalCode.BAD_INPUT, 'x'))  # no stamp: no gap
    stats, status = message(health)
    assert stats['sources.lost_upstream'] == sum(new) == 14
    assert stats['sources.period_s'] == pytest.approx(0.1)
    assert stats['sources.received'] == len(kept) + 1
    assert stats['sources.received'] == (stats['sources.published'] + stats['sources.rejected']
                                         + stats['sources.dropped'] + stats['sources.pending'])
    assert stats['accounting.ok'] is True
    assert status.level == type(status).WARN
    assert '14 source scans lost' in status.message and PROFILE_VARIABLE in status.message
    assert health.lost_upstream() == (14, True)
    assert health.lost_upstream() == (14, False)  # logged again only after 30 s


def test_no_source_yet_names_the_transport_fix():
    health = Accounting(PairingConfig(), queue_depth=2)
    health.receive('target', 1, 'map', 'T')
    stats, status = message(health)
    assert status.level == type(status).STALE and PROFILE_VARIABLE in status.message
    assert stats['sources.lost_upstream'] == 0 and 'sources.period_s' not in stats


def test_take_wakes_on_a_pair_and_on_wake():
    """The engine thread's wait for a pair ends when a source completes one, or when woken."""
    health = Accounting(PairingConfig(), queue_depth=2)
    health.receive('target', 1, 'map', 'T')
    threading.Timer(0.05, health.receive, args=('source', 2, 'lidar', 's')).start()
    pair = health.take(timeout=5.0)
    assert pair is not None and pair.source.payload == 's'
    threading.Timer(0.05, health.wake).start()
    assert health.take(timeout=5.0) is None
    health.finish()
    assert health.snapshot()['accounting']['ok']
