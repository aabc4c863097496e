"""The consensus record: the largest consensus sets kept and the best distinct alternative."""

from cgags_ros.registration.significance import _TOP_MODELS, ConsensusRecord
import numpy as np


def test_top_sets_and_runner_up_equal_a_plain_reference():
    """Against appending every set and one stable sort by size (older first on ties)."""
    rng = np.random.default_rng(3)
    n, tau = 80, 0.5
    record = ConsensusRecord(tau)
    kept: list[tuple[int, np.ndarray]] = []
    for batch in range(40):
        res = rng.random((18, n)) * rng.uniform(0.6, 3.0, (18, 1))  # many equal counts
        record.add(res, 2)
        inside = res <= tau
        floor = kept[-1][0] if len(kept) >= _TOP_MODELS else -1
        kept += [(int(c), m) for c, m in zip(inside.sum(axis=1), inside) if c > floor]
        kept.sort(key=lambda model: -model[0])
        del kept[_TOP_MODELS:]
        assert record.top_counts.tolist() == [c for c, _ in kept]
        assert np.array_equal(record.top_masks, np.array([m for _, m in kept]))
        for inliers in (np.flatnonzero(kept[0][1]), np.flatnonzero(kept[-1][1]),
                        np.arange(n // 3), np.zeros(0, np.int64)):
            distinct = [c for c, m in kept if 2 * np.count_nonzero(m[inliers]) < c]
            assert record.runner_up(inliers) == max(distinct, default=0)
    assert len(kept) == _TOP_MODELS


def test_runner_up_is_zero_before_any_hypothesis():
    assert ConsensusRecord(0.1).runner_up(np.arange(5)) == 0


def test_chance_sample_sets_the_level_and_competes_for_nothing():
    """
    Rows scored only for the chance level count as unselected rows of a batch.

    But they are neither consensus sets (runner-up) nor hypotheses of the Bonferroni
    correction.
    """
    rng = np.random.default_rng(4)
    n, tau = 300, 0.1
    res = rng.random((64, n))  # ~10 % of each row inside tau: ~30 chance inliers
    res[:8, :40] = 0.0  # eight rows of a 40-inlier motion, which must read as chance too
    as_batch, apart = ConsensusRecord(tau, members=2), ConsensusRecord(tau, members=2)
    as_batch.add(res, len(res))
    apart.add_chance(res)
    assert (apart.num_chance, apart.num_zero) == (as_batch.num_chance, as_batch.num_zero)
    assert apart.num_exact == 0 and apart.top_masks is None
    assert apart.runner_up(np.arange(40)) == 0
    scored = rng.random((16, n)) + 0.5 * tau  # sixteen searched hypotheses: ~5 % inside
    apart.add(scored, 0)  # none of them unselected
    assert (apart.num_chance, apart.num_exact) == (len(res), 16)
    assert apart.top_counts.tolist() == sorted((scored <= tau).sum(axis=1), reverse=True)
