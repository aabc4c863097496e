"""What a tracked stream's engine thread skips of its backlog (cgags_ros/engine/pairing.py)."""

from cgags_ros.config.node import NodeConfig, PairingConfig
from cgags_ros.config.pipeline import PipelineConfig
from cgags_ros.config.tracking import TrackingConfig
from cgags_ros.engine.pairing import Backlog, is_source_drop, Pairer, queue_depth, SKIPPED

MS = 10**6


def node(mode='continuous', **pairing):
    return NodeConfig(mode=mode, pairing=PairingConfig(**pairing))


def tracking(enabled=True):
    return PipelineConfig(tracking=TrackingConfig(enabled=enabled))


def test_a_tracked_stream_keeps_the_backlog_other_streams_their_queue():
    assert queue_depth(node(backlog=20, queue_depth=1), tracking()) == 20
    assert queue_depth(node(backlog=20, queue_depth=30), tracking()) == 30
    assert queue_depth(node(backlog=20, queue_depth=1), tracking(enabled=False)) == 1
    assert queue_depth(node(mode='on_demand', backlog=20, queue_depth=1), tracking()) == 1
    assert queue_depth(node(mode='calibrate', backlog=20, queue_depth=2), tracking()) == 2


def test_every_other_scan_is_skipped_while_lagging_after_a_tracked_scan():
    backlog = Backlog()
    lagging = [100 * MS, 200 * MS, 300 * MS, 400 * MS, 500 * MS, 700 * MS]  # 0.6 s behind
    backlog.saw(False, 0)  # a global scan
    assert backlog.to_skip(lagging, 0.5, 0.5, called=False) == 0  # no velocity yet
    backlog.saw(True, 0)  # a tracked, valid scan
    assert backlog.tracked
    assert backlog.to_skip(lagging, 0.5, 0.5, called=False) == 1
    assert backlog.to_skip(lagging[:-1], 0.5, 0.5, called=False) == 0  # 0.4 s: in order
    assert backlog.to_skip(lagging[-1:], 0.5, 0.5, called=False) == 0
    assert backlog.to_skip(lagging, 0.0, 0.5, called=False) == 0  # never skips
    # Never beyond max_age of the last scan, which the Tracker could not predict from.
    assert backlog.to_skip(lagging, 0.5, 0.15, called=False) == 0
    # The oldest already beyond it would go global anyway: the newest is taken.
    assert backlog.to_skip(lagging, 0.5, 0.05, called=False) == 5
    backlog.saw(False, 0)  # a tracked scan refused
    assert backlog.to_skip(lagging, 0.5, 0.5, called=False) == 0


def test_a_relocalize_call_is_answered_from_the_newest_scan():
    backlog = Backlog()
    assert backlog.to_skip([0, 100 * MS, 200 * MS], 0.5, 0.5, called=True) == 2
    assert backlog.to_skip([0], 0.5, 0.5, called=True) == 0


def test_the_pairer_drops_the_oldest_ready_pairs_as_skipped():
    pairer = Pairer('latest_target', queue_depth=10)
    dropped = []
    pairer.on_drop = lambda reason, item: dropped.append((reason, item.stamp_ns))
    pairer.add_target(0, 'map', 'map')
    for stamp in (1, 2, 3):
        pairer.add_source(stamp, 'velodyne', stamp)
    assert pairer.ready_stamps() == [1, 2, 3]
    pairer.drop_oldest(2, SKIPPED)
    assert dropped == [(SKIPPED, 1), (SKIPPED, 2)] and is_source_drop(SKIPPED)
    assert pairer.pop().source.stamp_ns == 3
    counters = pairer.counters()
    assert counters[f'dropped.{SKIPPED}'] == 2 and counters['dropped_sources'] == 2
