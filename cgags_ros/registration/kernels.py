"""
The compiled kernels of the core (numba), and their compilation at start-up.

Which paper step each kernel implements (METHOD.md numbering):

- step 1, compatibility graph: :func:`.kernels_graph.compatibility_words` (4-DoF:
  :func:`.kernels_graph.vertical_compatibility_words`), and its CSR
  neighbour lists :func:`.kernels_graph.neighbour_lists`;
- step 2, minimal compatible subsets (edge and vertex tournaments, collinearity test):
  :func:`.kernels_sampling.draw_triples`, :func:`.kernels_sampling.draw_edges`;
- step 3, hypotheses (3-point fits, pre-screen on common neighbourhoods, residuals):
  :mod:`.kernels_scoring`, whose weighted fit and residuals also serve step 6's re-fits
  (:func:`.rigid.kabsch`, :func:`.rigid.residuals`);
- step 4, preference lists: :func:`.kernels_scoring.merge_preferences`;
- step 5, guided sampling: its kernel (:func:`.kernels_scoring.preference_bits`, rows
  by :func:`.kernels_scoring.kernel_row`) and :func:`.kernels_sampling.draw_guided`;
- step 7, stopping: the edges among the best model's inliers, :mod:`.kernels_subsets`.

Every kernel is compiled with ``cache=True``: numba stores the machine code in
``__pycache__`` next to these modules, or under ``NUMBA_CACHE_DIR`` when set (and falls back
to a user cache directory where the package directory is read-only).
:func:`compile_kernels` runs each kernel once on tiny inputs of the types the search uses;
the first :class:`~.search.Search` calls it, so a process pays compilation (or the cache
load) on its warm-up pair, never on a later one.
"""

from __future__ import annotations

import numpy as np

from . import kernels_graph, kernels_sampling, kernels_scoring, kernels_subsets
from .kernels_sampling import COLLINEAR, EMPTY

__all__ = ['COLLINEAR', 'EMPTY', 'compile_kernels', 'draw_edges', 'draw_triples', 'draw_guided',
           'guided_rows', 'complete_rows', 'all_rows', 'common_support', 'fit_triples',
           'prescreen_scores', 'residual_matrix', 'usable_triangles']

_compiled = False
_VERTEX_PROPOSALS = 64  # uniform members of N(i) proposed per vertex tournament


def _f64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


def _i64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int64)


def draw_edges(rng, graph, lists, src, dst, delta: float, soft: bool, count: int,
               size: int) -> tuple[np.ndarray, np.ndarray]:
    """Edge tournament of ``size`` uniform edges, ``count`` times (step 2): i, j."""
    return kernels_sampling.draw_edges(rng, graph.words, graph.indptr, lists, src, dst,
                                       float(delta), bool(soft), int(count), int(size))


def draw_triples(rng, graph, lists, src, dst, delta: float, soft: bool, count: int,
                 edge_size: int, vertex_size: int, min_area: float):
    """Minimal compatible subsets by edge and vertex tournament (step 2), see the kernel."""
    return kernels_sampling.draw_triples(
        rng, graph.words, graph.indptr, lists, src, dst, float(delta), bool(soft),
        int(count), int(edge_size), int(vertex_size), _VERTEX_PROPOSALS, float(min_area))


def draw_guided(rng, rows: tuple, seed_weights: np.ndarray, count: int, xi: float,
                edges_only: bool = False):
    """Preference-guided subsets on the members of ``rows`` (step 5), see the kernel."""
    return kernels_sampling.draw_guided(
        rng, rows, np.cumsum(seed_weights, dtype=np.float64), int(count), float(xi),
        bool(edges_only))


def guided_rows(bits: np.ndarray, b: int, words: np.ndarray, members: np.ndarray) -> tuple:
    """
    Return the members' kernel and adjacency rows, each computed on first use (step 5).

    ``bits``: the members' preference lists as bit rows
    (:func:`.kernels_scoring.preference_bits`), ``b`` their length; ``words``: the graph's
    bit rows. Unused rows stay unwritten (their pages are never touched).
    """
    m = len(members)
    return (np.empty((m, m), np.float32), np.empty((m, m), np.bool_), np.zeros(m, np.bool_),
            bits, np.float32(b), words, _i64(members))


def complete_rows(kernel: np.ndarray, adjacency: np.ndarray) -> tuple:
    """Return given kernel and adjacency matrices as :func:`guided_rows`, every row done."""
    m = len(kernel)
    return (np.ascontiguousarray(kernel, dtype=np.float32),
            np.ascontiguousarray(adjacency, dtype=np.bool_), np.ones(m, np.bool_),
            np.zeros((m, 1), np.uint64), np.float32(1.0), np.zeros((m, 1), np.uint64),
            np.arange(m, dtype=np.int64))


def all_rows(rows: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Compute every row of :func:`guided_rows`; return the kernel and the adjacency."""
    kernels_sampling.fill_rows(rows)
    return rows[0], rows[1]


def usable_triangles(src, dst, triples: np.ndarray, min_area: float) -> np.ndarray:
    """Mask of the triples whose triangles span >= ``min_area`` in both clouds (step 2)."""
    return kernels_sampling.usable_triangles(src, dst, _i64(triples), float(min_area))


def common_support(graph, triples: np.ndarray) -> np.ndarray:
    """Return |N(i) ∩ N(j) ∩ N(k)| per row (i, j, k) of ``triples``."""
    return kernels_graph.common_support(graph.words, _i64(triples))


def fit_triples(src: np.ndarray, dst: np.ndarray, triples: np.ndarray):
    """Closed-form rigid fits (R (B, 3, 3), t (B, 3)) of the rows of ``triples`` (step 3)."""
    return kernels_scoring.fit_triples(src, dst, _i64(triples))


def prescreen_scores(graph, src, dst, R, t, triples, tau: float, score: str,
                     dense: bool) -> np.ndarray:
    """Scores on the triples' common neighbourhoods (all N with ``dense``), step 3."""
    return kernels_scoring.prescreen_scores(graph.words, src, dst, _f64(R), _f64(t),
                                            _i64(triples), float(tau), score == 'truncated',
                                            bool(dense))


def residual_matrix(src, dst, R, t) -> np.ndarray:
    """Residuals of all N correspondences under E hypotheses: (E, N) float32 (step 3)."""
    return kernels_scoring.residual_matrix(src, dst, _f64(R), _f64(t))


def compile_kernels() -> None:
    """Compile (or load from the on-disk cache) every kernel of the core, once per process."""
    global _compiled
    if _compiled:
        return
    rng = np.random.default_rng(0)
    # A 70-point rigid problem: enough for a graph with edges and triangles.
    src = rng.random((70, 3))
    dst = src[:, ::-1].copy()
    words = kernels_graph.compatibility_words(src, dst, 0.05, 0.0)
    split = np.zeros_like(words)  # the graph's passes as threads run them (large N)
    kernels_graph.length_rows(kernels_graph.columns(src, dst, 2), split, 0, 70, 0.0025, 0.0)
    kernels_graph.or_transpose_blocks(split, 0, 2)
    u = np.sort(rng.random(70))
    kernels_graph.vertical_compatibility_words(src, dst, u, np.searchsorted(u, u + 0.05),
                                               0.05, 0.0)
    degree = kernels_graph.row_degrees(words)
    indptr = np.concatenate([[0], np.cumsum(degree)])
    pairs = kernels_graph.neighbour_lists(words, indptr)
    kernels_graph.common_support(words, np.zeros((2, 3), np.int64))
    kernels_graph.common_within(words, np.zeros(2, np.int64), np.ones(2, np.int64), words[0])
    for lists in (pairs, pairs[:0]):
        for soft in (True, False):
            kernels_sampling.draw_edges(rng, words, indptr, lists, src, dst, 0.05, soft, 2, 2)
            i, j, k, _, _ = kernels_sampling.draw_triples(
                rng, words, indptr, lists, src, dst, 0.05, soft, 2, 2, 2, 4, 1e-9)
    triples = np.stack([i, j, k], axis=1)
    kernels_sampling.usable_triangles(src, dst, triples, 1e-9)
    R, t = kernels_scoring.fit_triples(src, dst, triples)
    T = kernels_scoring.fit_weighted(src, dst, np.ones(70))
    kernels_scoring.point_residuals(T, src, dst)
    for truncated in (True, False):
        for dense in (True, False):
            kernels_scoring.prescreen_scores(words, src, dst, R, t, triples, 0.05, truncated,
                                             dense)
    res = kernels_scoring.residual_matrix(src, dst, R, t)
    ids = np.full((70, 3), -1, np.int64)
    kernels_scoring.merge_preferences(np.full((70, 3), np.inf, np.float32), ids, res, 0)
    kernels_scoring.intersection_kernel(ids, np.arange(5, dtype=np.int64), len(res), 3)
    bits = kernels_scoring.preference_bits(ids, np.arange(5, dtype=np.int64), len(res), 3)
    kernels_graph.sub_adjacency(words, np.arange(5, dtype=np.int64))
    members = np.arange(5, dtype=np.int64)
    mask = kernels_subsets.member_mask(members, words.shape[1])
    counts = kernels_subsets.later_member_counts(words, members, mask)
    kernels_subsets.later_member_pairs(words, members, mask, np.cumsum(counts) - counts,
                                       np.zeros(1, np.int64))
    rows = guided_rows(bits, 3, words, np.arange(5))
    kernels_sampling.fill_rows(rows)
    for edges_only in (True, False):
        kernels_sampling.draw_guided(rng, rows, np.arange(1.0, 6.0), 2, 1e-6, edges_only)
    _compiled = True
