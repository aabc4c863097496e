"""
Compiled functions (numba) of descriptor matching: the exact nearest neighbours in FPFH space.

Putative correspondences are the step before Algorithm 1 (docs/method.md, "Input"): each source
descriptor's nearest target descriptor. The index partitions the reference descriptors into
cells by k-means (:func:`kmeans`, :func:`assign`); a query visits the cells nearest first
and skips a cell when a lower bound on the distance to any of its members already exceeds
the k-th best distance found (:func:`search`). The bounds are exact, so the search returns
what brute force would, at a fraction of its distance computations (measurements in
docs/design.md, "Front end"); asked to, it visits only the few nearest cells instead, an
approximate answer at a fraction of that (a map's consensus search, docs/maps.md).

Distances are float64 sums of squared differences in dimension order; they are compared as
squares and ties go to the lower reference row. Every function is ``nogil`` (the caller
splits queries over threads).
"""

from __future__ import annotations

from numba import njit
import numpy as np

from .types import INDEX_ARRAYS, SCRATCH, Scratch
from ...compiled_types import BOOL, BOOL_1D, F64_1D, F64_2D, FLOAT, I64_1D, I64_2D, INT

# Relative and absolute slack subtracted from each lower bound: the bounds are computed in
# float64 from the same rounded distances, so without it a bound could exceed the true
# distance by a few ulps and skip a cell holding the exact nearest row.
_REL = 1e-9
_ABS = 1e-12
# Rounding of a squared distance of up to ~64 terms, relative to it: the plane bound divides
# the difference of two such distances by the centres' gap, which can be small, so their
# rounding is subtracted from it explicitly.
_SQUARED_ROUNDING = 1e-13
# The screening distance is float32 (half the memory traffic, twice the lanes): relative
# slack for its rounding (~2^-24 per operation over a dozen terms), and absolute slack per
# unit of |q| + |p| for rounding the projections to float32 (sqrt(12) * 2 * 2^-24 < 1e-6).
_REL32 = 1e-5
_ABS32 = 1e-6


@njit((F64_2D, F64_1D, F64_1D), cache=True, nogil=True)
def squared_distances_to(rowsT, vector, out):
    """
    Set ``out[j] = |vector - rowsT[:, j]|^2`` for every column j of ``rowsT`` (dim x n).

    Dimension-outer order: the inner loop runs along contiguous memory and vectorizes,
    and every entry is summed in dimension order (the same rounding as a scalar loop).
    """
    out[:] = 0.0
    for t in range(rowsT.shape[0]):
        value = vector[t]
        row = rowsT[t]
        for j in range(rowsT.shape[1]):
            e = value - row[j]
            out[j] += e * e


@njit(cache=True, nogil=True, inline='always')
def _squared(q, rows, r):
    """Return |q - rows[r]|^2 summed in dimension order: every exact distance of the index."""
    s = 0.0
    for t in range(q.shape[0]):
        diff = q[t] - rows[r, t]
        s += diff * diff
    return s


@njit((F64_2D, F64_2D, F64_1D), cache=True, nogil=True)
def squared_pair_distances(a, b, out):
    """Set ``out[i] = |a[i] - b[i]|^2``, summed in dimension order as :func:`search` does."""
    for i in range(a.shape[0]):
        out[i] = _squared(a[i], b, i)


@njit((F64_2D, F64_2D, I64_1D, F64_1D), cache=True, nogil=True)
def assign(points, centresT, labels, dist):
    """Label each row of ``points`` with its nearest centre (exact, lowest index on ties)."""
    d = np.empty(centresT.shape[1])
    for i in range(points.shape[0]):
        squared_distances_to(centresT, points[i], d)
        best = 0
        for j in range(1, len(d)):
            if d[j] < d[best]:
                best = j
        labels[i] = best
        dist[i] = np.sqrt(d[best])


@njit((F64_2D, F64_2D, INT), cache=True, nogil=True)
def kmeans(sample, centres, iterations):
    """
    Run Lloyd's iterations on ``sample`` from the initial ``centres`` (updated in place).

    A centre left without members keeps its position. Only the partition's quality depends
    on this (how many cells a query visits), never the search's answer.
    """
    k, dim = centres.shape
    labels = np.empty(sample.shape[0], np.int64)
    dist = np.empty(sample.shape[0])
    sums = np.empty((k, dim))
    counts = np.empty(k, np.int64)
    for _ in range(iterations):
        assign(sample, np.ascontiguousarray(centres.T), labels, dist)
        sums[:] = 0.0
        counts[:] = 0
        for i in range(sample.shape[0]):
            counts[labels[i]] += 1
            for t in range(dim):
                sums[labels[i], t] += sample[i, t]
        for j in range(k):
            if counts[j] > 0:
                for t in range(dim):
                    centres[j, t] = sums[j, t] / counts[j]


@njit(cache=True, nogil=True, inline='always')
def _better(s, o, d, i):
    return s < d or (s == d and o < i)


@njit(cache=True, nogil=True, inline='always')
def _screen_limit(b2, slack):
    """Return the largest float32 screening value (squared) of a row within sqrt(b2)."""
    r = np.sqrt(b2) * (1.0 + _REL32) + slack
    return r * r


@njit((INDEX_ARRAYS, SCRATCH, F64_1D, INT, FLOAT, INT, FLOAT, INT, BOOL, INT), cache=True,
      nogil=True)
def _nearest(index, scratch, q, k, d1, i1, d2, i2, stop_when_beaten, cells):
    """
    Return ``(d1, i1, d2, i2)``: the squared distances and rows of the ``k`` nearest to ``q``.

    The search starts from the given best (``d1``, ``i1``) and second (``d2``, ``i2``) and
    only looks for rows that beat them; with ``stop_when_beaten`` it returns as soon as one
    row beats the first. ``cells`` > 0 visits no more cells, nearest centre first, once
    ``k`` rows are found: the rows found are then the nearest among those cells' members,
    not necessarily the nearest of all.
    """
    (centres, centresT, centre_gap, radius, starts, ring, points, basis, projectedT, max_norm,
     order, _) = index
    dc, visit, qp, acc, cand = scratch
    ncell = centres.shape[0]
    squared_distances_to(centresT, q, dc)
    norm = 0.0
    for r in range(basis.shape[0]):
        acc_r = 0.0
        for t in range(q.shape[0]):
            acc_r += basis[r, t] * q[t]
        qp[r] = acc_r
    for t in range(q.shape[0]):
        norm += q[t] * q[t]
    slack = _ABS32 * (np.sqrt(norm) + max_norm)
    # Cells nearest first (insertion sort, stable: a handful of cells, no allocation).
    for v in range(ncell):
        x = dc[v]
        w = v
        while w > 0 and dc[visit[w - 1]] > x:
            visit[w] = visit[w - 1]
            w -= 1
        visit[w] = v
    c0 = visit[0]
    start = i1
    for v in range(ncell):
        if 0 < cells <= v and (i2 if k == 2 else i1) >= 0:
            break
        j = visit[v]
        b2 = d1 if k == 1 else d2  # squared k-th best so far
        b = np.sqrt(b2)
        dj = np.sqrt(dc[j])
        low = dj - radius[j]
        if j != c0:
            plane = ((dc[j] - dc[c0] - _SQUARED_ROUNDING * (dc[j] + dc[c0]))
                     / (2.0 * centre_gap[j, c0]))
            low = max(low, plane)
        if low * (1.0 - _REL) - _ABS > b:
            continue
        a = starts[j]
        e = starts[j + 1]
        if b2 < np.inf:
            a += np.searchsorted(ring[a:e], (dj - b) * (1.0 - _REL) - _ABS)
            e = a + np.searchsorted(ring[a:e], (dj + b) * (1.0 + _REL) + _ABS, side='right')
        if e <= a:
            continue
        n = e - a
        acc[:n] = 0.0
        for r in range(basis.shape[0]):
            value = qp[r]
            row = projectedT[r, a:e]
            for p in range(n):
                diff = value - row[p]
                acc[p] += diff * diff
        # Members whose lower bound (the distance along the principal directions) does not
        # already exceed b, collected without a branch (most are screened out, and a
        # mispredicted branch per member cost more than the screening itself).
        limit = _screen_limit(b2, slack)
        m = 0
        for p in range(n):
            cand[m] = p
            m += acc[p] <= limit
        for u in range(m):
            p = cand[u]
            if acc[p] > limit:
                continue  # b has shrunk since
            s = _squared(q, points, a + p)
            if s > b2:
                continue
            o = order[a + p]
            if _better(s, o, d1, i1):
                d2, i2 = d1, i1
                d1, i1 = s, o
                if stop_when_beaten and i1 != start:
                    return d1, i1, d2, i2
            elif k == 2 and _better(s, o, d2, i2):
                d2, i2 = s, o
            b2 = d1 if k == 1 else d2
            limit = _screen_limit(b2, slack)
    return d1, i1, d2, i2


@njit((INDEX_ARRAYS,), cache=True, nogil=True)
def _scratch(index):
    """Return a query's working arrays, sized for ``index``."""
    ncell, npro, nrow = index.centres.shape[0], index.basis.shape[0], index.points.shape[0]
    return Scratch(np.empty(ncell), np.empty(ncell, np.int64), np.empty(npro, np.float32),
                   np.empty(nrow, np.float32), np.empty(nrow, np.int64))


@njit((INDEX_ARRAYS, F64_2D, INT, INT, I64_2D, F64_2D), cache=True, nogil=True)
def search(index, queries, k, cells, out_index, out_dist):
    """
    Find the ``k`` (1 or 2) nearest reference rows of each query (see module doc).

    Reference rows are stored by cell (``index.starts``: cell j holds rows starts[j] ..
    starts[j+1] of ``index.points``, M x dim) and within a cell by ``ring``, their distance
    to the centre; ``order`` maps a stored row back to its reference row. A query q with
    nearest centre c0 and current k-th best distance b skips cell j when
    ``max(|q - c_j| - radius_j, (|q - c_j|^2 - |q - c0|^2) / (2 |c_j - c0|)) > b`` (triangle
    inequality; distance to the bisecting plane, since every member of j is nearer c_j than
    c0), and in a visited cell considers only members with ``|ring - |q - c_j|| <= b``.
    Those are screened by their distance in the few leading principal directions
    (``basis``, orthonormal rows; ``projectedT`` = basis @ points.T in float32), which
    never exceeds the full distance up to the float32 rounding the screen allows for
    (``max_norm``: the largest reference row norm); only the members that pass get their
    exact distance. The answer is exact with ``cells`` 0; ``cells`` > 0 visits that many
    cells (nearest centre first, more only until ``k`` rows are found): an approximate
    search, the nearest among those cells' members.
    """
    scratch = _scratch(index)
    for i in range(queries.shape[0]):
        d1, i1, d2, i2 = _nearest(index, scratch, queries[i], k, np.inf, -1, np.inf, -1, False,
                                  cells)
        out_index[i, 0] = i1
        out_dist[i, 0] = np.sqrt(d1)
        if k == 2:
            out_index[i, 1] = i2
            out_dist[i, 1] = np.sqrt(d2)


@njit((INDEX_ARRAYS, F64_2D, I64_1D, BOOL_1D), cache=True, nogil=True)
def nearest_is(index, queries, rows, out):
    """
    Set ``out[i]`` to whether reference row ``rows[i]`` is the nearest to ``queries[i]``.

    Nearest as :func:`search` ranks (ties to the lower row). The search starts with that
    row as its best and ends at the first row that beats it: the mutual check of matching
    asks only this, and most candidates are beaten early.
    """
    scratch = _scratch(index)
    for i in range(queries.shape[0]):
        q = queries[i]
        row = rows[i]
        # its stored copy, as search would compute
        s = _squared(q, index.points, index.slot_of[row])
        _, i1, _, _ = _nearest(index, scratch, q, 1, s, row, np.inf, -1, True, 0)
        out[i] = i1 == row
