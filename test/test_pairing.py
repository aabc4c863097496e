"""cgags_ros.engine.pairing: both modes, waiting sources, bounded queue, drop counters."""

from __future__ import annotations

import collections

from cgags_ros.engine.pairing import is_source_drop, Pairer
from cgags_ros.io.bag import read_messages
import numpy as np
import pytest

S = 1_000_000_000  # ns per second


def drain(pairer):
    return [(p.source.payload, p.target.payload) for p in iter(pairer.pop, None)]


def test_latest_target_pairs_each_source_with_newest_received_target():
    p = Pairer('latest_target', queue_depth=10)
    p.add_target(5 * S, 'map', 'T_old_stamp')
    p.add_source(1 * S, 'lidar', 's1')
    p.add_target(0, 'map', 'T2')  # receipt order counts, not stamps (latched map)
    p.add_source(2 * S, 'lidar', 's2')
    p.add_source(3 * S, 'lidar', 's3')
    assert drain(p) == [('s1', 'T_old_stamp'), ('s2', 'T2'), ('s3', 'T2')]
    assert p.counters()['dropped'] == 0


def test_latest_target_sources_before_any_target_keep_newest_n():
    p = Pairer('latest_target', queue_depth=10, max_waiting_sources=2)
    for k in range(4):
        p.add_source(k * S, 'lidar', f's{k}')
    assert p.waiting_sources == 2 and p.pop() is None
    p.add_target(0, 'map', 'T')
    assert drain(p) == [('s2', 'T'), ('s3', 'T')]
    assert p.drops == {'source_superseded_before_target': 2}


def test_unused_target_replacement_is_counted():
    p = Pairer('latest_target')
    p.add_target(0, 'map', 'T1')
    p.add_target(1, 'map', 'T2')
    p.add_source(2, 'lidar', 's')
    p.add_target(3, 'map', 'T3')  # T2 was used: not a drop
    assert p.drops == {'target_replaced_unused': 1}


def test_bounded_queue_drops_oldest_pairs():
    p = Pairer('latest_target', queue_depth=2)
    p.add_target(0, 'map', 'T')
    for k in range(5):
        p.add_source(k, 'lidar', f's{k}')
    assert p.pending == 2
    assert drain(p) == [('s3', 'T'), ('s4', 'T')]
    c = p.counters()
    assert c['dropped.queue_full'] == 3 and c['paired'] == 5 and c['received_sources'] == 5


def test_synchronized_pairs_nearest_within_slop_one_to_one():
    p = Pairer('synchronized', slop=0.05, queue_depth=10, max_waiting_sources=10)
    p.add_source(int(1.00 * S), 'a', 's1')
    p.add_target(int(0.97 * S), 'm', 't097')
    assert p.pop() is None  # a closer target may still come
    p.add_target(int(1.01 * S), 'm', 't101')  # at/after the source: match is final
    assert drain(p) == [('s1', 't101')]
    p.add_source(int(1.02 * S), 'a', 's2')  # t101 is used; t097 is 0.05 s away
    p.add_target(int(1.2 * S), 'm', 't120')
    assert drain(p) == [('s2', 't097')]


def test_synchronized_drops_are_counted_with_reasons():
    p = Pairer('synchronized', slop=0.05, queue_depth=10, max_waiting_sources=2,
               max_waiting_targets=2)
    p.add_source(1 * S, 'a', 's1')
    p.add_target(2 * S, 'm', 't2')  # newest target far after s1: s1 can never match
    assert p.drops['source_no_target_within_slop'] == 1
    p.add_source(3 * S, 'a', 's3')  # t2 can never match a later source
    assert p.drops['target_no_source_within_slop'] == 1
    for k in range(4, 7):
        p.add_source(k * S, 'a', f's{k}')
    assert p.drops['source_buffer_full'] == 2
    assert p.pop() is None


def test_synchronized_on_lidar_bag_stamps(data_dir):
    """
    Pair the LiDAR bag's sources with their equal-stamp targets under a 50 ms slop.

    The bag's first source (0.1 s) sits between targets 0.0 and 0.2: with a 50 ms slop it is
    dropped, the five others pair with the equal-stamp target.
    """
    p = Pairer('synchronized', slop=0.05, queue_depth=10, max_waiting_sources=3)
    for rec in read_messages(data_dir / 'bags' / 'lidar', ['/source_cloud', '/target_cloud']):
        add = p.add_source if rec.topic == '/source_cloud' else p.add_target
        add(rec.stamp_ns, rec.frame_id, rec.stamp_ns)
    pairs = list(iter(p.pop, None))
    assert len(pairs) == 5 and all(pair.dt_ns == 0 for pair in pairs)
    assert p.drops['source_no_target_within_slop'] == 1


def test_reset_counts_discarded_and_keeps_latched_target():
    p = Pairer('latest_target', queue_depth=5)
    p.add_target(0, 'm', 'T')
    p.add_source(1, 'a', 's')
    p.reset()
    assert p.drops['source_reset'] == 1 and p.has_target


def test_invalid_arguments():
    with pytest.raises(ValueError, match='pairing mode'):
        Pairer('nearest')
    with pytest.raises(ValueError):
        Pairer(queue_depth=0)


def balanced(p):
    """Check the accounting invariant of both sides; return the counters."""
    c = p.counters()
    assert c['received_sources'] == (c['dropped_sources'] + c['waiting_sources']
                                     + c['pending'] + c['taken']), c
    assert c['received_targets'] == (c['dropped_targets'] + c['targets_held']
                                     + c['targets_used']), c
    return c


@pytest.mark.parametrize('mode', ['latest_target', 'synchronized'])
def test_every_cloud_is_accounted_for(mode):
    rng = np.random.default_rng(4)
    p = Pairer(mode, slop=0.03, queue_depth=2, max_waiting_sources=2, max_waiting_targets=3)
    dropped, taken = [], []
    p.on_drop = lambda reason, item: dropped.append((reason, item.payload))
    stamp = 0
    for k in range(400):
        stamp += int(rng.integers(0, 40_000_000))
        if rng.random() < 0.05:
            stamp -= 2_000_000_000  # a clock reset now and then
        role = 'source' if rng.random() < 0.6 else 'target'
        (p.add_source if role == 'source' else p.add_target)(stamp, 'f', (role, k))
        if rng.random() < 0.3 and (pair := p.pop()) is not None:
            taken.append(pair.source.payload)
        balanced(p)
    c = balanced(p)
    assert c['taken'] > 20 and c['dropped'] > 0 and sum(p.clock_resets.values()) > 5
    # on_drop sees every drop, once, with the item dropped: a source for a source reason
    assert collections.Counter(reason for reason, _ in dropped) == p.drops
    assert all((item[0] == 'source') == is_source_drop(reason) for reason, item in dropped)
    assert len({item for _, item in dropped}) == len(dropped)
    assert not {item for _, item in dropped} & set(taken)


def test_bag_loop_resets_waiting_but_keeps_the_latched_map_and_ready_pairs():
    p = Pairer('latest_target', queue_depth=5)
    p.add_target(0, 'map', 'M')
    for t in (10, 20, 30):
        p.add_source(t, 's', t)
    p.add_source(10, 's', 'loop')  # the bag starts again
    assert p.clock_resets['source_stamp_backwards'] == 1
    assert [p.pop().source.payload for _ in range(4)] == [10, 20, 30, 'loop']
    assert p.has_target and balanced(p)['dropped'] == 0


def test_stale_target_from_before_a_clock_reset_is_not_used():
    p = Pairer('latest_target', queue_depth=5)
    p.add_target(100, 'odom', 'T100')
    p.add_source(100, 's', 'a')
    p.add_source(5, 's', 'b')  # the clock restarted: the target is from the old clock
    assert p.pop().target.payload == 'T100' and p.pop() is None
    assert not p.has_target and p.waiting_sources == 1
    p.add_target(6, 'odom', 'T6')
    assert p.pop().target.payload == 'T6'
    c = balanced(p)
    assert c['targets_used'] == 1 and c['clock_resets.source_stamp_backwards'] == 1


def test_synchronized_target_clock_reset_drops_unmatched_targets():
    p = Pairer('synchronized', slop=0.01, queue_depth=5, max_waiting_targets=5)
    p.add_target(50_000_000, 't', 'x')
    p.add_target(10_000_000, 't', 'y')  # backwards: 'x' is from before the jump
    assert p.drops['target_reset'] == 1
    p.add_source(10_000_000, 's', 's')
    assert p.pop().target.payload == 'y'
    balanced(p)
