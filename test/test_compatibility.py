from cgags_ros.registration.compatibility import (build_compatibility_graph, CompatibilityGraph,
                                                  length_consistency, popcount_rows)
import numpy as np
import pytest
from scipy.spatial.distance import cdist


def _problem(n=300, seed=0):
    rng = np.random.default_rng(seed)
    src = rng.uniform(-1, 1, (n, 3))
    dst = src.copy()
    out = rng.random(n) < 0.7
    dst[out] = rng.uniform(-1, 1, (out.sum(), 3))
    return src, dst, ~out


def test_graph_matches_brute_force_definition():
    src, dst, _ = _problem()
    delta = 0.1
    g = build_compatibility_graph(src, dst, delta)
    expected = np.abs(cdist(src, src) - cdist(dst, dst)) < delta
    np.fill_diagonal(expected, False)
    dense = g.rows(np.arange(g.n))
    # float32 arithmetic may flip pairs lying within 1e-5 of the threshold only
    d = np.abs(cdist(src, src) - cdist(dst, dst))
    differ = dense != expected
    assert np.all(np.abs(d[differ] - delta) < 1e-5)
    assert np.array_equal(dense, dense.T)
    assert not dense.diagonal().any()
    assert np.array_equal(g.degree, dense.sum(axis=1))
    assert g.num_edges == dense.sum() // 2


def test_inliers_form_a_clique():
    src, dst, inl = _problem(seed=3)
    g = build_compatibility_graph(src, dst, 1e-6)
    idx = np.flatnonzero(inl)
    assert g.count_edges_within(idx) == len(idx) * (len(idx) - 1) // 2


def test_min_pair_distance_drops_short_edges():
    src, dst, _ = _problem(seed=4)
    g = build_compatibility_graph(src, dst, 0.1, min_pair_distance=0.5)
    dense = g.rows(np.arange(g.n))
    assert np.all(cdist(src, src)[dense] >= 0.5 - 1e-6)


def test_edge_queries_and_common_neighbourhood():
    src, dst, _ = _problem(n=200, seed=5)
    g = build_compatibility_graph(src, dst, 0.2)
    dense = g.rows(np.arange(g.n))
    rng = np.random.default_rng(0)
    i, j = rng.integers(0, 200, 500), rng.integers(0, 200, 500)
    assert np.array_equal(g.has_edge(i, j), dense[i, j])
    common = np.unpackbits(g.common(i[:10], j[:10]), axis=1, count=200,
                           bitorder='little').astype(bool)
    assert np.array_equal(common, dense[i[:10]] & dense[j[:10]])
    d = length_consistency(src, dst, i, j)
    assert np.allclose(d, np.abs(np.linalg.norm(src[i] - src[j], axis=1)
                                 - np.linalg.norm(dst[i] - dst[j], axis=1)))


def test_memory_is_bit_packed():
    src, dst, _ = _problem(n=1000, seed=6)
    g = build_compatibility_graph(src, dst, 0.1)
    assert g.packed.nbytes == 1000 * 128  # 125 bytes per row, padded to 16 words


def test_member_edges_on_bit_rows_match_the_dense_adjacency():
    # later_neighbour_counts / numbered_edges replace np.triu + np.nonzero of the members'
    # dense adjacency in the stopping rule: same counts, same edges in the same order.
    rng = np.random.default_rng(3)
    for n, density in ((70, 0.5), (200, 0.1), (300, 0.9)):
        dense = np.triu(rng.random((n, n)) < density, 1)
        dense |= dense.T
        g = CompatibilityGraph(np.packbits(dense, axis=1, bitorder='little'), n)
        for size in (0, 1, 2, 40, n):
            members = np.sort(rng.choice(n, size, replace=False))
            a, b = np.nonzero(np.triu(g.adjacency(members)))
            counts = g.later_neighbour_counts(members)
            assert g.count_edges_within(members) == counts.sum() == len(a)
            i, j = g.numbered_edges(members, counts, np.arange(len(a)))
            np.testing.assert_array_equal(i, members[a])
            np.testing.assert_array_equal(j, members[b])
            picks = rng.permutation(len(a))[:7]
            i, j = g.numbered_edges(members, counts, picks)
            np.testing.assert_array_equal(j, members[b[picks]])


@pytest.mark.parametrize('numpy_has_bitwise_count', [True, False])
def test_popcount_rows_counts_set_bits_with_and_without_numpy_2(monkeypatch,
                                                                numpy_has_bitwise_count):
    rows = np.random.default_rng(3).integers(0, 2**63, size=(7, 5), dtype=np.uint64)
    if not numpy_has_bitwise_count:
        monkeypatch.delattr(np, 'bitwise_count', raising=False)
    expected = np.unpackbits(rows.view(np.uint8), axis=1).sum(axis=1)
    assert np.array_equal(popcount_rows(rows.view(np.uint8)), expected)
