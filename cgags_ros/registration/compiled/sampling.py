"""
Compiled functions (numba) of the samplers: steps 2 and 5 of Algorithm 1.

Step 2, minimal compatible subsets: graph edge sampling (:func:`draw_edges`) and graph
vertex sampling (:func:`draw_triples`), each by tournament, and the collinearity test
(:func:`usable_triangles`). Step 5, guided sampling (:func:`draw_guided`) on the rows of the
intersection kernel K that step 6 refreshes (:class:`.GuidedRows`, :func:`guided_rows`).

A whole batch of minimal subsets is drawn in one call: per subset, the edge tournament,
the vertex tournament and the collinearity test are a few dozen bit-row operations, which
as numpy calls would each pay the per-call overhead (docs/design.md). The
functions draw from the search's own ``numpy.random.Generator`` (numba shares its bit
generator state), so a search stays deterministic for its seed.

Edges are drawn uniformly from E as entry e of the directed adjacency (row i by the
cumulative degrees ``indptr``, then the (e - indptr[i])-th neighbour of i): the expanded
CSR lists (row and column of each entry) make that O(1) once built; before, the same entry
is found by bisection and on the bit row, so both give the same draws.
"""

from __future__ import annotations

import math

from numba import njit
import numpy as np

from .bits import popcount
from .graph import adjacency_row, has_edge, nth_set_bit
from .preferences import kernel_row
from .types import CORRESPONDENCES, GRAPH_ARRAYS, GUIDED_ROWS, GuidedRows
from ...compiled_types import BOOL, c_array, F64_1D, FLOAT, I64_2D, INT, RNG

EMPTY = 1  # status of a draw: N(i) ∩ N(j) empty (no triangle on the edge)
COLLINEAR = 2  # status of a draw: triangle area below the minimum in either cloud
VERTEX_PROPOSALS = 64  # uniform members of N(i) proposed per vertex tournament


@njit(cache=True, nogil=True, inline='always')
def _entry(graph, e):
    """
    Return (i, j) of entry e of the directed adjacency (rows in order, columns ascending).

    From the graph's entry lists (CSR with the rows expanded) when built, else i by
    bisection of ``indptr``, j on the bit row.
    """
    words, indptr, lists = graph
    if len(lists):
        return np.int64(lists[e, 0]), np.int64(lists[e, 1])
    lo, hi = 0, len(indptr) - 1
    while hi - lo > 1:  # the last row whose start is <= e
        mid = (lo + hi) >> 1
        if indptr[mid] <= e:
            lo = mid
        else:
            hi = mid
    return lo, nth_set_bit(words[lo], e - indptr[lo])


@njit(cache=True, nogil=True, inline='always')
def _neighbour(graph, i, r):
    """Return the r-th neighbour of i (from the entry lists when built, else the bit row)."""
    words, indptr, lists = graph
    if len(lists):
        return np.int64(lists[indptr[i] + r, 1])
    return nth_set_bit(words[i], r)


@njit(cache=True, nogil=True, inline='always')
def _soft_weight(corr, i, j, delta):
    """Soft compatibility weight 1 - (d_ij / delta)^2 of edge (i, j)."""
    src, dst = corr
    a = math.sqrt((src[i, 0] - src[j, 0]) ** 2 + (src[i, 1] - src[j, 1]) ** 2
                  + (src[i, 2] - src[j, 2]) ** 2)
    b = math.sqrt((dst[i, 0] - dst[j, 0]) ** 2 + (dst[i, 1] - dst[j, 1]) ** 2
                  + (dst[i, 2] - dst[j, 2]) ** 2)
    return 1.0 - ((a - b) / delta) ** 2


@njit(cache=True, nogil=True, inline='always')
def _pair_support(words, i, j):
    s = 0
    for k in range(words.shape[1]):
        s += popcount(words[i, k] & words[j, k])
    return s


@njit((RNG, GRAPH_ARRAYS, CORRESPONDENCES, FLOAT, INT, INT), cache=True, nogil=True)
def draw_edges(rng, graph, corr, delta, count, size):
    """
    Draw ``count`` compatible edges by edge tournament (step 2, graph edge sampling).

    Of ``size`` edges, each drawn in proportion to its soft compatibility weight
    1 - (d_ij / delta)^2, the one with the most common neighbours |N(i) ∩ N(j)| wins (the
    first on ties); ``size`` = 1 draws by weight alone.

    :returns: i, j (int64).
    """
    ii = np.empty(count, np.int64)
    jj = np.empty(count, np.int64)
    indptr = graph.indptr
    total = indptr[len(indptr) - 1]
    for m in range(count):
        best = -1
        for _ in range(size):
            # A uniform edge of E, accepted with its soft weight (rejection: accepted
            # edges are drawn in proportion to it).
            while True:
                e = min(np.int64(rng.random() * total), total - 1)
                i, j = _entry(graph, e)
                if rng.random() < _soft_weight(corr, i, j, delta):
                    break
            s = _pair_support(graph.words, i, j) if size > 1 else 0
            if s > best:
                best, ii[m], jj[m] = s, i, j
    return ii, jj


@njit(cache=True, nogil=True, inline='always')
def _area(p, i, j, k):
    ax, ay, az = p[j, 0] - p[i, 0], p[j, 1] - p[i, 1], p[j, 2] - p[i, 2]
    bx, by, bz = p[k, 0] - p[i, 0], p[k, 1] - p[i, 1], p[k, 2] - p[i, 2]
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    return 0.5 * math.sqrt(cx * cx + cy * cy + cz * cz)


@njit((RNG, GRAPH_ARRAYS, CORRESPONDENCES, FLOAT, INT, INT, INT, INT, FLOAT), cache=True,
      nogil=True)
def draw_triples(rng, graph, corr, delta, count, edge_size, vertex_size, proposals,
                 min_area):
    """
    Draw ``count`` minimal compatible subsets (step 2: an edge, then a common vertex).

    The edge by :func:`draw_edges`; then k in N(i) ∩ N(j) by vertex tournament: of
    ``proposals`` uniform members of N(i), the first ``vertex_size`` that are also in N(j)
    compete, and the one with the largest |N(i) ∩ N(j) ∩ N(k)| wins (the first on ties).
    If no proposal hits, k is drawn uniformly from N(i) ∩ N(j) exactly. Triangles whose
    area is below ``min_area`` in either cloud are marked COLLINEAR.

    :returns: i, j, k (int64), support |N(i) ∩ N(j) ∩ N(k)| (int64), status (int8:
        0 usable, EMPTY, COLLINEAR).
    """
    words, indptr, _ = graph
    src, dst = corr
    w = words.shape[1]
    ii, jj = draw_edges(rng, graph, corr, delta, count, edge_size)
    kk = np.zeros(count, np.int64)
    support = np.zeros(count, np.int64)
    status = np.zeros(count, np.int8)
    common = np.empty(w, np.uint64)
    for m in range(count):
        i, j = ii[m], jj[m]
        for c in range(w):
            common[c] = words[i, c] & words[j, c]
        deg = indptr[i + 1] - indptr[i]
        best, hits = -1, 0
        for _ in range(proposals):
            k = _neighbour(graph, i, min(np.int64(rng.random() * deg), deg - 1))
            if has_edge(words, j, k):
                s = 0
                for c in range(w):
                    s += popcount(common[c] & words[k, c])
                if s > best:
                    best, kk[m] = s, k
                hits += 1
                if hits == vertex_size:
                    break
        if hits == 0:
            size = 0
            for c in range(w):
                size += popcount(common[c])
            if size == 0:
                status[m] = EMPTY
                continue
            k = nth_set_bit(common, min(np.int64(rng.random() * size), size - 1))
            best, kk[m] = 0, k
            for c in range(w):
                best += popcount(common[c] & words[k, c])
        support[m] = best
        k = kk[m]
        if min_area > 0 and (_area(src, i, j, k) < min_area or _area(dst, i, j, k) < min_area):
            status[m] = COLLINEAR
    return ii, jj, kk, support, status


@njit(cache=True, nogil=True, inline='always')
def _weighted_pick(u, weights, m):
    """Return the first index whose cumulative weight exceeds u * total (-1: all zero)."""
    total = 0.0
    for c in range(m):
        total += weights[c]
    if total <= 0.0:
        return -1
    target, acc = u * total, 0.0
    last = -1
    for c in range(m):
        if weights[c] > 0.0:
            acc += weights[c]
            last = c
            if acc > target:
                return c
    return last


def guided_rows(bits: np.ndarray, b: int, words: np.ndarray,
                members: np.ndarray) -> GuidedRows:
    """
    Return the members' rows of K and of the adjacency, each computed on first use (step 5).

    ``bits``: the members' preference lists as bit rows (:func:`.preferences.preference_bits`),
    ``b`` their length; ``words``: the graph's bit rows. Built anew at each refresh of the
    kernel (step 6); unused rows stay unwritten (their pages are never touched).
    """
    m = len(members)
    return GuidedRows(np.empty((m, m), np.float32), np.empty((m, m), np.bool_),
                      np.zeros(m, np.bool_), c_array(bits, np.uint64), np.float32(b),
                      c_array(words, np.uint64), c_array(members, np.int64))


def complete_rows(kernel: np.ndarray, adjacency: np.ndarray) -> GuidedRows:
    """Return given K and adjacency matrices as :func:`guided_rows`, every row done."""
    m = len(kernel)
    return GuidedRows(c_array(kernel, np.float32), c_array(adjacency, np.bool_),
                      np.ones(m, np.bool_), np.zeros((m, 1), np.uint64), np.float32(1.0),
                      np.zeros((m, 1), np.uint64), np.arange(m, dtype=np.int64))


@njit(cache=True, nogil=True, inline='always')
def _row(rows, a):
    """
    Return rows a of K and of the adjacency, computing them on first use.

    A batch draws from a few dozen members' rows, so the M x M matrices are never filled
    whole (M reaches the thousands with many inliers).
    """
    if not rows.done[a]:
        kernel_row(rows.bits, a, rows.scale, rows.kernel[a])
        adjacency_row(rows.words, rows.members, a, rows.adjacency[a])
        rows.done[a] = True
    return rows.kernel[a], rows.adjacency[a]


@njit((RNG, GUIDED_ROWS, F64_1D, INT, FLOAT, BOOL), cache=True, nogil=True)
def draw_guided(rng, rows, seed_weights, count, xi, edges_only):
    """
    Draw ``count`` preference-guided subsets on M members (step 5; local indices).

    Seed i in proportion to ``seed_weights``; j in N(i) with probability proportional to
    K(i, j) + xi; then (unless ``edges_only``, the 4-DoF edge) k in N(i) ∩ N(j)
    proportional to K(i, k) K(j, k) + xi. ``rows``: the members' rows of K and of the
    adjacency (:func:`guided_rows`).

    :returns: i, j, k (k = j with ``edges_only``) and an ok mask (a partner was found).
    """
    seed_cdf = np.cumsum(seed_weights)
    m = len(seed_cdf)
    ii = np.zeros(count, np.int64)
    jj = np.zeros(count, np.int64)
    kk = np.zeros(count, np.int64)
    ok = np.zeros(count, np.bool_)
    weights = np.empty(m)
    for b in range(count):
        i = min(np.searchsorted(seed_cdf, rng.random() * seed_cdf[m - 1], side='right'), m - 1)
        kernel_i, adjacency_i = _row(rows, i)
        for c in range(m):
            weights[c] = (np.float64(kernel_i[c]) + xi) if adjacency_i[c] else 0.0
        j = _weighted_pick(rng.random(), weights, m)
        ii[b] = i
        if j < 0:
            continue
        jj[b] = j
        if edges_only:
            kk[b], ok[b] = j, True
            continue
        kernel_j, adjacency_j = _row(rows, j)
        for c in range(m):
            both = adjacency_i[c] and adjacency_j[c]
            weights[c] = (np.float64(kernel_i[c]) * kernel_j[c] + xi) if both else 0.0
        k = _weighted_pick(rng.random(), weights, m)
        if k >= 0:
            kk[b], ok[b] = k, True
    return ii, jj, kk, ok


@njit((CORRESPONDENCES, I64_2D, FLOAT), cache=True, nogil=True)
def usable_triangles(corr, triangles, min_area):
    """Return, per row (i, j, k), whether its triangle's area is >= ``min_area`` in both clouds."""
    if triangles.shape[1] != 3:
        raise ValueError('usable_triangles tests triangles: rows (i, j, k)')
    src, dst = corr
    ok = np.empty(len(triangles), np.bool_)
    for m in range(len(triangles)):
        i, j, k = triangles[m, 0], triangles[m, 1], triangles[m, 2]
        ok[m] = _area(src, i, j, k) >= min_area and _area(dst, i, j, k) >= min_area
    return ok
