"""
The compiled functions (registration/compiled/) against plain numpy on small inputs.

Each function must give what the numpy computation of the same step gives: the same graph,
the same draws from the same random stream, the same inliers and scores, transforms equal
to 1e-9. Draw-by-draw references consume the generator in the compiled functions' order.
"""

from __future__ import annotations

import math

from bench.datasets.synthetic import load_bunny, make_correspondences
from cgags_ros.registration import compatibility, compiled, register_correspondences
from cgags_ros.registration.compatibility import build_compatibility_graph, CompatibilityGraph
from cgags_ros.registration.compiled import (COLLINEAR, compatibility_words, Correspondences,
                                             draw_edges, draw_guided, draw_triples, EMPTY,
                                             fit_triples, intersection_kernel,
                                             merge_preferences, neighbour_lists,
                                             prescreen_scores, residual_matrix)
from cgags_ros.registration.hypotheses import score_values
from cgags_ros.registration.rigid import kabsch_batch
import numpy as np
import pytest

DELTA = 0.15


def _problem(n=150, seed=0, inliers=40):
    """Return a rigid motion of ``inliers`` points plus uniform outliers, metres."""
    rng = np.random.default_rng(seed)
    src = rng.uniform(-1, 1, (n, 3))
    angle = 0.7
    R = np.array([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0],
                  [0, 0, 1.0]])
    dst = rng.uniform(-1, 1, (n, 3))
    dst[:inliers] = src[:inliers] @ R.T + [0.3, -0.2, 0.1] + rng.normal(0, 0.005, (inliers, 3))
    return src, dst


def _numpy_graph(src, dst, delta, min_sq=0.0):
    a = np.linalg.norm(src[:, None] - src[None], axis=2)
    b = np.linalg.norm(dst[:, None] - dst[None], axis=2)
    adj = (np.abs(a - b) < delta) & (a ** 2 >= min_sq)
    np.fill_diagonal(adj, False)
    return adj


def triangle_areas(points, i, j, k):
    """Areas of the triangles (p_i, p_j, p_k): the numpy reference of the collinearity test."""
    return 0.5 * np.linalg.norm(np.cross(points[j] - points[i], points[k] - points[i]), axis=1)


def score_in_common_neighbourhood(graph, src, dst, R, t, triples, tau, mode):
    """Score each hypothesis on {i, j, k} ∪ (N(i) ∩ N(j) ∩ N(k)) only: the numpy pre-screen."""
    i, j, k = triples.T
    cand = np.unpackbits(graph.common(i, j, k), axis=1, count=graph.n, bitorder='little')
    rows = np.arange(len(triples))
    for member in (i, j, k):
        cand[rows, member] = 1
    b, m = np.nonzero(cand)
    moved = np.einsum('bij,bj->bi', R[b], src[m]) + t[b]
    res = np.linalg.norm(moved - dst[m], axis=1)
    return np.bincount(b, weights=score_values(res, tau, mode), minlength=len(triples))


def _unpack(words, n):
    return np.unpackbits(words.view(np.uint8), axis=1, count=n, bitorder='little').view(bool)


@pytest.mark.parametrize('n', [3, 63, 64, 65, 150, 300])
@pytest.mark.parametrize('min_sq', [0.0, 0.2])
def test_graph_equals_numpy(n, min_sq):
    src, dst = _problem(n, inliers=min(n, 40))
    words = compatibility_words(Correspondences.of(src, dst), DELTA, min_sq)
    assert words.shape == (n, (n + 63) // 64)
    assert np.array_equal(_unpack(words, n), _numpy_graph(src, dst, DELTA, min_sq))
    # Bits past column N stay zero (popcounts over whole words count no padding).
    full = np.unpackbits(words.view(np.uint8), axis=1, bitorder='little')
    assert not full[:, n:].any()


@pytest.mark.parametrize('n', [130, 700, 1100])
@pytest.mark.parametrize('workers', [2, 3])
def test_graph_split_over_threads_equals_numpy(n, workers, monkeypatch):
    """The two passes split into ranges of equal work, on threads, give the same bits."""
    monkeypatch.setattr(compatibility, '_SPLIT_MIN', 0)  # split whatever N
    src, dst = _problem(n, inliers=60)
    min_distance = 0.3 if n == 700 else 0.0
    graph = build_compatibility_graph(src, dst, DELTA, min_distance, workers)
    assert np.array_equal(graph.rows(np.arange(n)),
                          _numpy_graph(src, dst, DELTA, min_distance ** 2))
    single = build_compatibility_graph(src, dst, DELTA, min_distance, 1)
    assert np.array_equal(graph.packed, single.packed)


def test_graph_object_and_lists():
    src, dst = _problem(200)
    graph = build_compatibility_graph(src, dst, DELTA)
    adj = _numpy_graph(src, dst, DELTA)
    assert np.array_equal(graph.rows(np.arange(200)), adj)
    assert np.array_equal(graph.degree, adj.sum(axis=1))
    pairs = neighbour_lists(graph.words, graph.indptr)
    rows, cols = np.nonzero(adj)
    assert np.array_equal(pairs[:, 0], rows) and np.array_equal(pairs[:, 1], cols)
    triples = np.random.default_rng(1).integers(0, 200, (50, 3))
    expected = graph.popcount(graph.common(*triples.T))
    assert np.array_equal(compiled.common_support(graph.words, triples), expected)
    edges = np.ascontiguousarray(triples[:, :2])  # 4-DoF minimal subsets: |N(i) ∩ N(j)|
    expected = graph.popcount(graph.common(*edges.T))
    assert np.array_equal(compiled.common_support(graph.words, edges), expected)
    with pytest.raises(ValueError):
        compiled.common_support(graph.words, np.zeros((2, 4), np.int64))
    members = np.random.default_rng(2).choice(200, 37, replace=False)
    assert np.array_equal(graph.adjacency(members), adj[np.ix_(members, members)])
    assert graph.count_edges_within(members) == adj[np.ix_(members, members)].sum() // 2


def _reference_edges(rng, graph, src, dst, delta, count, size):
    """Edge tournament as the compiled function draws it, in plain numpy/Python."""
    indptr = graph.indptr
    cols = np.nonzero(graph.rows(np.arange(graph.n)))[1]
    total = indptr[-1]
    out = []
    for _ in range(count):
        best, pick = -1, None
        for _ in range(size):
            while True:
                e = min(int(rng.random() * total), total - 1)
                i = int(np.searchsorted(indptr, e, side='right') - 1)
                j = int(cols[e])
                d = abs(np.linalg.norm(src[i] - src[j]) - np.linalg.norm(dst[i] - dst[j]))
                if rng.random() < 1.0 - (d / delta) ** 2:
                    break
            s = int(graph.popcount(graph.common(np.array([i]), np.array([j])))[0])
            if size == 1 or s > best:
                best, pick = s, (i, j)
        out.append(pick)
    return np.array(out).reshape(-1, 2)


@pytest.mark.parametrize('size', [1, 4])
@pytest.mark.parametrize('with_lists', [False, True])
def test_edges_equal_numpy_draws(size, with_lists):
    src, dst = _problem(150)
    graph = build_compatibility_graph(src, dst, DELTA)
    lists = graph.entry_lists() if with_lists else None
    i, j = draw_edges(np.random.default_rng(5), graph.arrays(lists), Correspondences.of(src, dst),
                      DELTA, 40, size)
    ref = _reference_edges(np.random.default_rng(5), graph, src, dst, DELTA, 40, size)
    assert np.array_equal(np.stack([i, j], 1), ref)


def _reference_triples(rng, graph, src, dst, count, edge_size, vertex_size, proposals,
                       min_area):
    edges = _reference_edges(rng, graph, src, dst, DELTA, count, edge_size)
    rows = graph.rows(np.arange(graph.n))
    out = []
    for i, j in edges:
        nbrs = np.flatnonzero(rows[i])
        common = rows[i] & rows[j]
        best, k, hits = -1, 0, 0
        for _ in range(proposals):
            c = nbrs[min(int(rng.random() * len(nbrs)), len(nbrs) - 1)]
            if rows[j, c]:
                s = int((common & rows[c]).sum())
                if s > best:
                    best, k = s, c
                hits += 1
                if hits == vertex_size:
                    break
        status = 0
        if hits == 0:
            members = np.flatnonzero(common)
            if len(members) == 0:
                out.append((i, j, 0, 0, EMPTY))
                continue
            k = members[min(int(rng.random() * len(members)), len(members) - 1)]
            best = int((common & rows[k]).sum())
        ijk = (np.array([i]), np.array([j]), np.array([k]))
        if min(triangle_areas(src, *ijk)[0], triangle_areas(dst, *ijk)[0]) < min_area:
            status = COLLINEAR
        out.append((i, j, k, best, status))
    return np.array(out)


@pytest.mark.parametrize('with_lists', [False, True])
def test_triples_equal_numpy_draws(with_lists):
    src, dst = _problem(150)
    graph = build_compatibility_graph(src, dst, DELTA)
    lists = graph.entry_lists() if with_lists else None
    got = draw_triples(np.random.default_rng(3), graph.arrays(lists), Correspondences.of(src, dst),
                       DELTA, 60, 4, 3, 16, 0.05)
    ref = _reference_triples(np.random.default_rng(3), graph, src, dst, 60, 4, 3, 16, 0.05)
    got = np.stack([np.asarray(a, dtype=np.int64) for a in got], axis=1)
    usable = ref[:, 4] != EMPTY
    assert np.array_equal(got[:, 4], ref[:, 4])
    assert np.array_equal(got[usable], ref[usable])
    assert (got[:, 4] == 0).sum() > 10  # the check saw usable triangles


def test_fits_equal_kabsch():
    src, dst = _problem(100)
    triples = np.random.default_rng(2).integers(0, 100, (80, 3))
    triples = triples[(triples[:, 0] != triples[:, 1]) & (triples[:, 1] != triples[:, 2])
                      & (triples[:, 0] != triples[:, 2])]
    R, t = fit_triples(Correspondences.of(src, dst), triples)
    R_ref, t_ref = kabsch_batch(src[triples], dst[triples])
    np.testing.assert_allclose(R, R_ref, atol=1e-9)
    np.testing.assert_allclose(t, t_ref, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


@pytest.mark.parametrize('score', ['inlier_count', 'truncated'])
def test_prescreen_and_residuals_equal_numpy(score):
    src, dst = _problem(150)
    graph = build_compatibility_graph(src, dst, DELTA)
    rng = np.random.default_rng(4)
    triples = np.concatenate([rng.permutation(40)[:30].reshape(10, 3),
                              rng.integers(0, 150, (20, 3))])
    triples[-3:, 2] = triples[-3:, 1]  # as the 4-DoF edges (i, j), their reference below
    R, t = (np.ascontiguousarray(a) for a in kabsch_batch(src[triples], dst[triples]))
    tau = 0.05
    truncated = score == 'truncated'
    corr = Correspondences.of(src, dst)
    pre = prescreen_scores(graph.words, corr, R, t, triples, tau, truncated, False)
    ref = score_in_common_neighbourhood(graph, src, dst, R, t, triples, tau, score)
    np.testing.assert_allclose(pre, ref, atol=1e-9)
    # Edges (i, j): on {i, j} ∪ (N(i) ∩ N(j)), the same terms in the same order as (i, j, j).
    edges = np.ascontiguousarray(triples[-3:, :2])
    got = prescreen_scores(graph.words, corr, R[-3:], t[-3:], edges, tau, truncated, False)
    assert np.array_equal(got, pre[-3:])
    res = residual_matrix(corr, R, t)
    res_ref = np.linalg.norm(np.einsum('bij,nj->bni', R, src) + t[:, None] - dst[None], axis=2)
    np.testing.assert_allclose(res, res_ref, rtol=1e-6, atol=1e-7)
    dense = prescreen_scores(graph.words, corr, R, t, triples, tau, truncated, True)
    np.testing.assert_allclose(dense, score_values(res_ref, tau, score).sum(axis=1), atol=1e-9)
    assert dense[:10].max() >= 30  # the inlier triples found their inliers


def test_preference_merge_equals_numpy():
    """Each list: the b smallest residuals so far, ascending, equal ones in hypothesis order."""
    rng = np.random.default_rng(6)
    n, b = 50, 5
    res = np.full((n, b), np.inf, np.float32)
    ids = np.full((n, b), -1, np.int64)
    ref_res, ref_ids, first = res.copy(), ids.copy(), 0
    for e in (3, 4, 7, 1, 12, 30):
        new = (np.round(rng.random((e, n)) * 8) / 8).astype(np.float32)  # many ties
        new[0, :5] = np.inf  # never listed
        merge_preferences(res, ids, new, first)
        both = np.concatenate([ref_res, new.T], axis=1)
        both_ids = np.concatenate([ref_ids, np.broadcast_to(np.arange(first, first + e),
                                                            (n, e))], axis=1)
        keep = np.argsort(both, axis=1, kind='stable')[:, :b]
        ref_res = np.take_along_axis(both, keep, axis=1)
        ref_ids = np.where(np.isinf(ref_res), -1, np.take_along_axis(both_ids, keep, axis=1))
        first += e
        assert np.array_equal(ids, ref_ids)
        assert np.array_equal(res, ref_res)


def test_usable_triangles_equal_numpy_areas():
    src, dst = _problem(60)
    triples = np.random.default_rng(9).integers(0, 60, (300, 3))
    triples[:20, 2] = triples[:20, 1]  # degenerate: zero area
    min_area = 0.05
    i, j, k = triples.T
    ref = ((triangle_areas(src, i, j, k) >= min_area) & (triangle_areas(dst, i, j, k) >= min_area))
    got = compiled.usable_triangles(Correspondences.of(src, dst), triples, min_area)
    assert np.array_equal(got, ref) and 0 < ref.sum() < len(ref)


def test_common_within_equals_numpy():
    """|N(i) ∩ N(j)| and its part inside a subset (the stage-one w1), against numpy sets."""
    src, dst = _problem(150)
    graph = build_compatibility_graph(src, dst, DELTA)
    adj = _numpy_graph(src, dst, DELTA)
    rng = np.random.default_rng(8)
    i, j = rng.integers(0, 150, 40), rng.integers(0, 150, 40)
    members = np.concatenate([np.arange(40), rng.choice(150, 20)])  # duplicates too
    total, inside = graph.common_within(i, j, members)
    subset = np.zeros(150, bool)
    subset[members] = True
    assert np.array_equal(total, (adj[i] & adj[j]).sum(axis=1))
    assert np.array_equal(inside, (adj[i] & adj[j] & subset).sum(axis=1))
    assert inside.max() > 0


@pytest.mark.parametrize('b', [1, 5, 20])
def test_intersection_kernel_equals_numpy(b):
    """K(a, c) = |T_a ∩ T_c| / b: the bit-row kernel against the dense 0/1 product."""
    rng = np.random.default_rng(b)
    n, hypotheses = 120, 150  # > 64 hypotheses in use: several words per bit row
    ids = np.stack([rng.choice(hypotheses, b, replace=False) for _ in range(n)])
    ids[rng.random((n, b)) < 0.1] = -1  # empty slots
    ids[:10] = ids[0]  # identical lists
    members = rng.choice(n, 70, replace=False)
    members[:5] = np.arange(5)
    K = intersection_kernel(ids, members, hypotheses, b)
    S = np.zeros((len(members), hypotheses), np.float32)
    rows, slots = np.nonzero(ids[members] >= 0)
    S[rows, ids[members][rows, slots]] = 1.0
    ref = (S @ S.T) / np.float32(b)
    np.fill_diagonal(ref, 0.0)
    assert K.dtype == np.float32 and np.array_equal(K, ref)
    assert K[0, 1] == np.float32(np.count_nonzero(ids[0] >= 0)) / np.float32(b)  # all shared


@pytest.mark.parametrize('edges_only', [False, True])
def test_guided_rows_on_first_use_equal_the_full_matrices(edges_only):
    """Rows of K and of the adjacency computed when a draw reads them: the same draws."""
    rng = np.random.default_rng(5)
    n, b, hypotheses = 200, 20, 300
    ids = np.stack([rng.choice(hypotheses, b, replace=False) for _ in range(n)])
    ids[rng.random((n, b)) < 0.1] = -1
    dense = np.triu(rng.random((n, n)) < 0.3, 1)
    graph = CompatibilityGraph(np.packbits(dense | dense.T, axis=1, bitorder='little'), n)
    members = np.sort(rng.choice(n, 90, replace=False))
    bits = compiled.preference_bits(ids, members, hypotheses, b)
    lazy = compiled.guided_rows(bits, b, graph.words, members)
    full = compiled.complete_rows(intersection_kernel(ids, members, hypotheses, b),
                                  graph.adjacency(members))
    seeds = rng.random(len(members))
    a = draw_guided(np.random.default_rng(2), lazy, seeds, 300, 1e-6, edges_only)
    c = draw_guided(np.random.default_rng(2), full, seeds, 300, 1e-6, edges_only)
    for x, y in zip(a, c):
        np.testing.assert_array_equal(x, y)
    done = lazy.done
    assert 0 < done.sum() < len(members)  # only the rows drawn from were computed
    np.testing.assert_array_equal(lazy.kernel[done], full.kernel[done])
    np.testing.assert_array_equal(lazy.adjacency[done], full.adjacency[done])


@pytest.mark.parametrize('edges_only', [False, True])
def test_guided_equals_numpy_draws(edges_only):
    rng = np.random.default_rng(7)
    m, xi = 12, 1e-6
    kernel = rng.random((m, m)).astype(np.float32)
    adjacency = rng.random((m, m)) < 0.5
    np.fill_diagonal(adjacency, False)
    adjacency[3] = False  # a seed without partners
    seed_w = rng.random(m)
    i, j, k, ok = draw_guided(np.random.default_rng(8), compiled.complete_rows(kernel, adjacency),
                              seed_w, 50, xi, edges_only)
    r = np.random.default_rng(8)
    cdf = np.cumsum(seed_w)

    def pick(weights):
        u = r.random()  # drawn whether or not a partner exists, as the compiled draw does
        if weights.sum() <= 0:
            return -1
        return int(np.argmax(np.cumsum(weights) > u * weights.sum()))

    for b in range(50):
        si = min(int(np.searchsorted(cdf, r.random() * cdf[-1], side='right')), m - 1)
        assert i[b] == si
        sj = pick((kernel[si].astype(np.float64) + xi) * adjacency[si])
        if sj < 0:
            assert not ok[b]
            continue
        assert j[b] == sj
        if edges_only:
            assert ok[b] and k[b] == sj
            continue
        wk = (kernel[si].astype(np.float64) * kernel[sj] + xi) * (adjacency[si] & adjacency[sj])
        sk = pick(wk)
        assert ok[b] == (sk >= 0) and (sk < 0 or k[b] == sk)


def test_core_deterministic_for_a_seed(data_dir):
    model = load_bunny(data_dir)
    p = make_correspondences(model, 600, 0.97, noise_sigma=0.01, rng=11)
    a = register_correspondences(p.src, p.dst, inlier_threshold=0.05, seed=3)
    b = register_correspondences(p.src, p.dst, inlier_threshold=0.05, seed=3)
    assert a.valid and np.array_equal(a.transform, b.transform)
    assert np.array_equal(a.inliers, b.inliers) and a.num_hypotheses == b.num_hypotheses


def _compiled_functions():
    """Every compiled function of the core with a declared signature (not the inlined helpers)."""
    from cgags_ros.registration.compiled import (graph, inlier_edges, preferences, sampling,
                                                 scoring)

    modules = (graph, inlier_edges, preferences, sampling, scoring)
    return [getattr(m, name) for m in modules for name in dir(m)
            if hasattr(getattr(m, name), 'signatures')
            and getattr(m, name).targetoptions.get('inline') != 'always']


def test_compiled_at_import_from_the_declared_signatures():
    functions = _compiled_functions()
    assert compatibility_words in functions and draw_guided in functions
    for fn in functions:
        assert len(fn.signatures) == 1, fn  # compiled (or loaded from the cache) at import
    src, dst = _problem(20, inliers=10)
    R, t = (np.ascontiguousarray(a) for a in kabsch_batch(src[None, :3], dst[None, :3]))
    residual_matrix(Correspondences.of(src, dst), R, t)
    for other in (Correspondences(src.astype(np.float32), dst),  # another dtype
                  Correspondences(src, np.asfortranarray(dst))):  # another layout
        with pytest.raises(TypeError):
            residual_matrix(other, R, t)
    assert all(len(fn.signatures) == 1 for fn in functions)


def test_searches_use_only_the_compiled_signatures(monkeypatch, data_dir):
    """A search calls the compiled functions only with their declared argument types."""
    from cgags_ros.registration import CoreConfig

    functions = _compiled_functions()
    before = {fn: list(fn.signatures) for fn in functions}
    model = load_bunny(data_dir)
    monkeypatch.setattr(compatibility, '_SPLIT_MIN', 0)  # the graph split over threads too
    p = make_correspondences(model, 800, 0.98, noise_sigma=0.01, rng=2)
    dst = p.dst.copy()
    dst.flags.writeable = False
    for motion in ('6dof', '4dof'):
        src = np.asfortranarray(p.src)  # any layout, read-only too: the core copies as needed
        register_correspondences(src, dst, inlier_threshold=0.05, seed=1,
                                 config=CoreConfig(motion_model=motion), workers=2)
    assert {fn: list(fn.signatures) for fn in functions} == before
