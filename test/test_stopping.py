import math

from cgags_ros.registration.compatibility import CompatibilityGraph
from cgags_ros.registration.stopping import (
    compatible_sample_inlier_probability,
    empirical_inlier_probability,
    futility_draws,
    poisson_isf,
    ransac_bound,
)
import numpy as np


def test_ransac_bound():
    assert math.isclose(ransac_bound(0.99, 0.5), math.log(0.01) / math.log(0.5))
    assert ransac_bound(0.99, 0.0) == math.inf
    assert ransac_bound(0.99, 1.0) == 1.0
    assert ransac_bound(0.99, 1e-4) > ransac_bound(0.99, 1e-3) > ransac_bound(0.9, 1e-3)


def test_futility_draws_bound_edges_only():
    n = 100
    adj = np.zeros((n, n), dtype=bool)
    adj[np.arange(n - 1), np.arange(1, n)] = True  # a path: 99 edges
    graph = CompatibilityGraph(np.packbits(adj | adj.T, axis=1, bitorder='little'), n)
    # 6 inliers: C(6, 2) = 15 of the 99 edges per uniform draw.
    assert math.isclose(futility_draws(graph, 6, 0.99, 2), ransac_bound(0.99, 15 / 99))
    assert futility_draws(graph, 6, 0.99, 3) == math.inf  # triangles: no conservative bound
    assert futility_draws(graph, 20, 0.99, 2) == 1.0  # more inlier pairs than edges


def test_inlier_probability_of_compatible_sampling_on_a_known_graph():
    # 6 inliers forming a clique, plus 6 outliers forming a second clique: |E| = 30,
    # inlier edges 15; every inlier edge's common neighbourhood is the other 4 inliers.
    n = 12
    dense = np.zeros((n, n), dtype=bool)
    dense[:6, :6] = True
    dense[6:, 6:] = True
    np.fill_diagonal(dense, False)
    g = CompatibilityGraph(np.packbits(dense, axis=1, bitorder='little'), n)
    w = compatible_sample_inlier_probability(g, np.arange(6), np.random.default_rng(0))
    assert math.isclose(w, 15 / 30 * 1.0)
    assert compatible_sample_inlier_probability(g, np.arange(2), np.random.default_rng(0)) == 0.0


def test_empirical_inlier_probability():
    mask = np.zeros(10, dtype=bool)
    mask[:4] = True
    samples = [np.array([[0, 1, 2], [0, 1, 5]]), np.array([[1, 2, 3], [7, 8, 9]])]
    assert empirical_inlier_probability(samples, mask) == 0.5
    assert empirical_inlier_probability([], mask) == 0.0


def test_poisson_isf_matches_scipy():
    from scipy.stats import poisson

    for lam in (1e-4, 0.05, 0.4, 1.0, 3.7, 12.0, 40.0):
        for alpha in (0.5, 1e-2, 1e-4, 1e-7, 1e-12):
            assert poisson_isf(alpha, lam) == int(poisson.isf(alpha, lam)), (alpha, lam)
