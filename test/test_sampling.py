"""
Check that minimal-subset sampling draws the distributions the method asks for.

The compiled edge, tournament and guided draws.
"""

from cgags_ros.registration import compiled
from cgags_ros.registration.compatibility import (CompatibilityGraph, length_consistency,
                                                  popcount_rows)
import numpy as np
import pytest


def _graph(dense: np.ndarray) -> CompatibilityGraph:
    dense = dense | dense.T
    np.fill_diagonal(dense, False)
    return CompatibilityGraph(np.packbits(dense, axis=1, bitorder='little'), len(dense))


def _random_graph(n=60, p=0.2, seed=0):
    rng = np.random.default_rng(seed)
    return _graph(np.triu(rng.random((n, n)) < p, 1))


def _edges(g, rng, count, src, dst, delta, lists, size=1):
    """Draw ``count`` edges as the search does (``size`` = 1: by soft weight over E)."""
    return compiled.draw_edges(rng, g.arrays(g.entry_lists() if lists else None),
                               compiled.Correspondences.of(src, dst), delta, count, size)


@pytest.mark.parametrize('lists', [False, True])
def test_edges_are_edges_and_uniform_over_E(lists):
    g = _random_graph()
    dense = g.rows(np.arange(g.n))
    rng = np.random.default_rng(1)
    pts = np.zeros((g.n, 3))  # every edge weighs 1: uniform over E
    i, j = _edges(g, rng, 200000, pts, pts, 1.0, lists)
    assert dense[i, j].all()
    # undirected edge frequencies: uniform over E within sampling noise
    key = np.minimum(i, j) * g.n + np.maximum(i, j)
    counts = np.bincount(key, minlength=g.n * g.n)[np.flatnonzero(np.triu(dense).ravel())]
    expected = 200000 / g.num_edges
    assert abs(counts.mean() - expected) < 1e-9 + 0.01 * expected
    assert counts.std() < 4 * np.sqrt(expected)  # binomial spread, no systematic bias
    assert counts.min() > 0


@pytest.mark.parametrize('lists', [False, True])
def test_soft_edges_are_drawn_in_proportion_to_their_weight(lists):
    g = _random_graph(n=40, p=0.3, seed=7)
    dense = g.rows(np.arange(g.n))
    rng = np.random.default_rng(8)
    src, dst = rng.random((g.n, 3)), rng.random((g.n, 3))
    a, b = np.nonzero(np.triu(dense))
    delta = 1.01 * length_consistency(src, dst, a, b).max()  # every edge keeps some weight
    draws = 300000
    i, j = _edges(g, rng, draws, src, dst, delta, lists)
    assert len(i) == draws and dense[i, j].all()
    key = np.minimum(i, j) * g.n + np.maximum(i, j)
    counts = np.bincount(key, minlength=g.n * g.n)[a * g.n + b]
    w = 1.0 - (length_consistency(src, dst, a, b) / delta) ** 2
    expected = draws * w / w.sum()
    # chi-square-like check: each edge within 5 binomial sigmas, no systematic tilt
    assert np.all(np.abs(counts - expected) < 5 * np.sqrt(expected) + 5)
    assert np.corrcoef(counts, expected)[0, 1] > 0.98


def test_sparse_graphs_draw_only_their_edges():
    dense = np.zeros((500, 500), dtype=bool)
    dense[0, 1] = dense[1, 2] = dense[0, 2] = True  # one triangle in a large empty graph
    g = _graph(dense)
    rng = np.random.default_rng(2)
    pts = np.zeros((500, 3))
    i, j = _edges(g, rng, 100, pts, pts, 1.0, False)
    assert set(np.unique(np.concatenate([i, j]))) <= {0, 1, 2}
    i, j, k, _, status = compiled.draw_triples(rng, g.arrays(None),
                                               compiled.Correspondences.of(pts, pts), 1.0, 100,
                                               4, 4, compiled.VERTEX_PROPOSALS, 0.0)
    assert (status == 0).all()
    assert np.all((k != i) & (k != j) & np.isin(k, [0, 1, 2]))


def test_tournament_keeps_the_best_supported_candidate():
    g = _random_graph(n=100, p=0.3, seed=5)
    pts = np.zeros((g.n, 3))
    # The candidates: the same random stream drawn as uniform edges, 4 per tournament.
    i, j = _edges(g, np.random.default_rng(6), 40, pts, pts, 1.0, False)
    wi, wj = _edges(g, np.random.default_rng(6), 10, pts, pts, 1.0, False, size=4)
    support = popcount_rows(g.common(i, j)).reshape(10, 4)
    won = popcount_rows(g.common(wi, wj))
    assert np.array_equal(won, support.max(axis=1))


def test_guided_sampling_prefers_high_kernel_partners():
    m = 30
    adjacency = np.ones((m, m), dtype=bool)
    np.fill_diagonal(adjacency, False)
    kernel = np.zeros((m, m), dtype=np.float32)
    group = np.arange(5)
    kernel[np.ix_(group, group)] = 0.8
    np.fill_diagonal(kernel, 0)
    seeds = np.zeros(m)
    seeds[group] = 1
    i, j, k, ok = compiled.draw_guided(np.random.default_rng(8),
                                       compiled.complete_rows(kernel, adjacency), seeds, 5000,
                                       1e-6, False)
    assert ok.all()
    assert np.isin(i, group).all()
    assert np.isin(j, group).mean() > 0.99 and np.isin(k, group).mean() > 0.99
    assert np.all((i != j) & (j != k) & (i != k))
