"""cgags_ros.engine.accounting.UpstreamLoss: scans lost before the node, from stamp gaps."""

from __future__ import annotations

from cgags_ros.engine.accounting import UpstreamLoss
import numpy as np
import pytest

MS = 1_000_000  # ns per millisecond
PERIOD = 100 * MS  # a 10-Hz LiDAR


def feed(stamps, **kwargs):
    loss = UpstreamLoss(**kwargs)
    increments = [loss.add(int(s)) for s in stamps]
    assert sum(increments) == loss.lost  # add() reports exactly what it adds
    return loss


def test_a_regular_stream_loses_nothing_and_learns_its_period():
    loss = feed(np.arange(100) * PERIOD + 7)
    assert loss.lost == 0 and loss.period_ns == PERIOD


def test_every_third_scan_missing_is_counted_exactly():
    kept = [k for k in range(300) if k % 3 != 2]
    loss = feed(np.array(kept) * PERIOD)
    assert loss.lost == sum(1 for k in range(kept[0], kept[-1]) if k % 3 == 2)


@pytest.mark.parametrize('kept_fraction', [0.8, 0.3, 0.1])
def test_heavy_random_loss_is_counted_between_first_and_last_scan(kept_fraction):
    rng = np.random.default_rng(3)
    sent = np.arange(2000)
    kept = sent[rng.random(sent.size) < kept_fraction]
    jitter = rng.integers(-2 * MS, 2 * MS, kept.size)
    loss = feed(kept * PERIOD + jitter, window=64)
    assert loss.lost == kept[-1] - kept[0] + 1 - kept.size
    assert abs(loss.period_ns - PERIOD) < 3 * MS


def test_heavy_loss_without_two_scans_back_to_back_still_finds_the_period():
    rng = np.random.default_rng(5)
    steps = rng.choice([2, 3, 4, 5, 7], 40)  # no interval of one period
    kept = np.concatenate([[0], np.cumsum(steps)])
    loss = feed(kept * PERIOD + rng.integers(-2 * MS, 2 * MS, kept.size))
    assert loss.lost == kept[-1] + 1 - kept.size
    assert abs(loss.period_ns - PERIOD) < 1 * MS


def test_a_sensor_slower_than_its_gaps_suggest_is_not_divided():
    # a regular 2.5-Hz stream with a few scans missing: its period stays 400 ms
    kept = np.delete(np.arange(60), [10, 20, 21, 40])
    loss = feed(kept * 4 * PERIOD)
    assert loss.period_ns == 4 * PERIOD and loss.lost == 4


def test_jitter_alone_is_not_a_loss_but_one_missing_scan_is():
    rng = np.random.default_rng(0)
    stamps = np.arange(200) * PERIOD + rng.integers(-5 * MS, 5 * MS, 200)
    assert feed(stamps).lost == 0
    assert feed(np.delete(stamps, 100)).lost == 1


def test_one_odd_short_interval_does_not_set_the_period():
    # a duplicated scan 1 ms after its original, then a regular stream with gaps of 2
    stamps = [0, 1 * MS] + [k * 2 * PERIOD + 1 * MS for k in range(1, 30)]
    loss = feed(stamps)
    assert loss.lost == 0 and loss.period_ns == 2 * PERIOD


def test_the_count_waits_for_the_period_then_counts_earlier_gaps():
    stamps = np.array([0, 3, 6, 9, 10, 11]) * PERIOD  # single periods only at the end
    loss = UpstreamLoss()
    assert [loss.add(int(s)) for s in stamps] == [0, 0, 0, 0, 0, 6]
    assert loss.period_ns == PERIOD


def test_stamps_going_backwards_start_a_new_stream_without_a_false_loss():
    loop = np.arange(20) * PERIOD
    loss = feed(np.concatenate([loop, loop, np.delete(loop, 5)]))
    assert loss.lost == 1


def test_a_pause_longer_than_pause_s_is_not_a_loss():
    stamps = np.concatenate([np.arange(20) * PERIOD, 60_000 * MS + np.arange(20) * PERIOD])
    assert feed(stamps, pause_s=10.0).lost == 0
    assert feed(stamps, pause_s=100.0).lost == 599 - 19


def test_bad_settings_raise():
    with pytest.raises(ValueError):
        UpstreamLoss(window=1)
    with pytest.raises(ValueError):
        UpstreamLoss(pause_s=0)
