"""
Compiled kernels (numba) of the samplers: steps 2 and 5 of Algorithm 1 (METHOD.md).

A whole batch of minimal subsets is drawn in one call: per subset, the edge tournament,
the vertex tournament and the collinearity test are a few dozen bit-row operations, which
as numpy calls would each pay the per-call overhead (docs/implementation.md, "Compiled
kernels"). The kernels draw from the search's own ``numpy.random.Generator`` (numba shares
its bit generator state), so a search stays deterministic for its seed.

Edges are drawn uniformly from E as entry e of the directed adjacency (row i by the
cumulative degrees ``indptr``, then the (e - indptr[i])-th neighbour of i): the expanded
CSR lists (row and column of each entry) make that O(1) once built; before, the same entry
is found by bisection and on the bit row, so both give the same draws.
"""

from __future__ import annotations

import math

from numba import njit
import numpy as np

from .kernels_graph import adjacency_row, has_edge, nth_set_bit, popcount
from .kernels_scoring import kernel_row

EMPTY = 1  # status of a draw: N(i) ∩ N(j) empty (no triangle on the edge)
COLLINEAR = 2  # status of a draw: triangle area below the minimum in either cloud


@njit(cache=True, nogil=True, inline='always')
def _entry(words, indptr, lists, e):
    """
    Return (i, j) of entry e of the directed adjacency (rows in order, columns ascending).

    ``lists`` is (2|E|, 2) int32: the row and the column of every entry (CSR with the
    rows expanded), or empty: then i by bisection of ``indptr``, j on the bit row.
    """
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
def _neighbour(words, indptr, lists, i, r):
    """Return the r-th neighbour of i (from ``lists`` when given, else the bit row)."""
    if len(lists):
        return np.int64(lists[indptr[i] + r, 1])
    return nth_set_bit(words[i], r)


@njit(cache=True, nogil=True, inline='always')
def _soft_weight(src, dst, i, j, delta):
    """Soft compatibility weight 1 - (d_ij / delta)^2 of edge (i, j)."""
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


@njit(cache=True, nogil=True)
def draw_edges(rng, words, indptr, lists, src, dst, delta, soft, count, size):
    """
    Draw ``count`` compatible edges by edge tournament (step 2, graph edge sampling).

    Of ``size`` uniform edges (soft: in proportion to 1 - (d_ij / delta)^2) the one with
    the most common neighbours |N(i) ∩ N(j)| wins (the first on ties); ``size`` = 1 is
    uniform sampling.

    :returns: i, j (int64).
    """
    ii = np.empty(count, np.int64)
    jj = np.empty(count, np.int64)
    total = indptr[len(indptr) - 1]
    for m in range(count):
        best = -1
        for _ in range(size):
            # A uniform edge of E; with soft compatibility accepted with its soft weight
            # (rejection: accepted edges are drawn in proportion to it).
            while True:
                e = min(np.int64(rng.random() * total), total - 1)
                i, j = _entry(words, indptr, lists, e)
                if not soft or rng.random() < _soft_weight(src, dst, i, j, delta):
                    break
            s = _pair_support(words, i, j) if size > 1 else 0
            if s > best:
                best, ii[m], jj[m] = s, i, j
    return ii, jj


@njit(cache=True, nogil=True, inline='always')
def _area(p, i, j, k):
    ax, ay, az = p[j, 0] - p[i, 0], p[j, 1] - p[i, 1], p[j, 2] - p[i, 2]
    bx, by, bz = p[k, 0] - p[i, 0], p[k, 1] - p[i, 1], p[k, 2] - p[i, 2]
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    return 0.5 * math.sqrt(cx * cx + cy * cy + cz * cz)


@njit(cache=True, nogil=True)
def draw_triples(rng, words, indptr, lists, src, dst, delta, soft, count, edge_size,
                 vertex_size, proposals, min_area):
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
    w = words.shape[1]
    ii, jj = draw_edges(rng, words, indptr, lists, src, dst, delta, soft, count, edge_size)
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
            k = _neighbour(words, indptr, lists, i, min(np.int64(rng.random() * deg), deg - 1))
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


@njit(cache=True, nogil=True, inline='always')
def _row(rows, a):
    """
    Return rows a of the kernel K and of the adjacency, computing them on first use.

    ``rows`` is :func:`.kernels.guided_rows`' tuple (K, A, done, bits, scale, words,
    members): a batch draws from a few dozen members' rows, so the M x M matrices are
    never filled whole (M reaches the thousands with many inliers).
    """
    K, A, done, bits, scale, words, members = rows
    if not done[a]:
        kernel_row(bits, a, scale, K[a])
        adjacency_row(words, members, a, A[a])
        done[a] = True
    return K[a], A[a]


@njit(cache=True, nogil=True)
def fill_rows(rows):
    """Compute every row of ``rows`` (for seed weights over the whole kernel)."""
    for a in range(rows[2].shape[0]):
        _row(rows, a)


@njit(cache=True, nogil=True)
def draw_guided(rng, rows, seed_cdf, count, xi, edges_only):
    """
    Draw ``count`` preference-guided subsets on M members (step 5; local indices).

    Seed i by the cumulative seed weights ``seed_cdf``; j in N(i) with probability
    proportional to K(i, j) + xi; then (unless ``edges_only``, the 4-DoF edge) k in
    N(i) ∩ N(j) proportional to K(i, k) K(j, k) + xi. ``rows``: the members' kernel and
    adjacency rows (:func:`_row`).

    :returns: i, j, k (k = j with ``edges_only``) and an ok mask (a partner was found).
    """
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


@njit(cache=True, nogil=True)
def usable_triangles(src, dst, triples, min_area):
    """Return, per row (i, j, k), whether its triangle's area is >= ``min_area`` in both clouds."""
    ok = np.empty(len(triples), np.bool_)
    for m in range(len(triples)):
        i, j, k = triples[m, 0], triples[m, 1], triples[m, 2]
        ok[m] = _area(src, i, j, k) >= min_area and _area(dst, i, j, k) >= min_area
    return ok
