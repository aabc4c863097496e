"""
Compiled function (numba) of FPFH's neighbour search: the points within a radius, nearest first.

FPFH (:mod:`.fpfh`) is the feature the paper matches to get its putative correspondences
(docs/method.md, "Input"); its neighbours are Open3D's hybrid search: the ``max_nn``
nearest within the radius, the point itself included, ties at the ``max_nn``-th distance
to the lower row. One search serves both of FPFH's passes. The search is ``nogil`` over a
range of points (the caller splits them over threads).
"""

from __future__ import annotations

from numba import njit
import numpy as np

from .types import GRID_ARRAYS, NEIGHBOUR_LISTS
from ...compiled_types import F64_1D, I32_1D, INT


@njit(cache=True, nogil=True, inline='always')
def _gap(x, start, size):
    """Squared distance from x to the interval [start, start + size]."""
    g = max(start - x, x - start - size, 0.0)
    return g * g


@njit(cache=True, nogil=True, inline='always')
def _before(d, j, s, t):
    return d[s] < d[t] or (d[s] == d[t] and j[s] < j[t])


@njit((F64_1D, I32_1D, INT, INT), cache=True, nogil=True)
def _select(d, j, n, m):
    """Move the m smallest (d, j) of the first n entries to the front (quickselect, in place)."""
    lo, hi = 0, n - 1
    while lo < hi:
        mid = (lo + hi) // 2
        # median of three as the pivot, kept at hi
        if _before(d, j, mid, lo):
            d[mid], d[lo] = d[lo], d[mid]
            j[mid], j[lo] = j[lo], j[mid]
        if _before(d, j, hi, lo):
            d[hi], d[lo] = d[lo], d[hi]
            j[hi], j[lo] = j[lo], j[hi]
        if _before(d, j, mid, hi):
            d[mid], d[hi] = d[hi], d[mid]
            j[mid], j[hi] = j[hi], j[mid]
        store = lo
        for s in range(lo, hi):
            if _before(d, j, s, hi):
                d[s], d[store] = d[store], d[s]
                j[s], j[store] = j[store], j[s]
                store += 1
        d[store], d[hi] = d[hi], d[store]
        j[store], j[hi] = j[hi], j[store]
        if store == m - 1 or store == m:
            return
        if store < m:
            lo = store + 1
        else:
            hi = store - 1


@njit((GRID_ARRAYS, INT, INT, NEIGHBOUR_LISTS, F64_1D), cache=True, nogil=True)
def radius_neighbours(grid, first, last, lists, nearest):
    """
    Fill ``lists`` with the neighbours of the points at positions first .. last.

    Positions are in ``grid.order``: the point at position s (row i = order[s]) gets row
    ``s - lists.offset`` of ``lists.nbr``/``lists.count`` and ``nearest[i]``. Points are
    visited in cell order, so the ranges of the neighbouring cells are looked up once per
    cell, not once per point. A point gets the ``max_nn`` (the width of ``nbr``) nearest
    points within ``grid.radius`` (itself included; not sorted) and their count, and
    ``nearest`` the distance to the nearest other point (inf when none is within the
    radius).
    """
    (cells, order, sorted_points, cell_key, cell_start, column_start, lower, ny, nz, cell,
     reach, radius) = grid
    offset, nbr, count = lists.offset, lists.nbr, lists.count
    max_nn = nbr.shape[1]
    r2 = radius * radius
    buf_j = np.empty(len(order), nbr.dtype)
    buf_d = np.empty(len(order))
    side = 2 * reach + 1
    lo_row = np.empty(side * side, np.int64)
    hi_row = np.empty(side * side, np.int64)
    current = -1
    for s0 in range(first, last):
        i = order[s0]
        ix, iy, iz = cells[i, 0], cells[i, 1], cells[i, 2]
        key = (ix * ny + iy) * nz + iz
        if key != current:  # a new cell: where its neighbouring cells' points are
            current = key
            r = 0
            for dx in range(-reach, reach + 1):
                for dy in range(-reach, reach + 1):
                    q = (ix + dx) * ny + (iy + dy)
                    base = q * nz + iz
                    # Searched within the row's column (a few keys) when the table is
                    # there: the same range as among all keys, in a fraction of the steps,
                    # which were much of the search on sparse scans (docs/design.md).
                    a, b = ((column_start[q], column_start[q + 1]) if len(column_start)
                            else (0, len(cell_key)))
                    keys = cell_key[a:b]
                    lo_row[r] = a + np.searchsorted(keys, base - reach)
                    hi_row[r] = a + np.searchsorted(keys, base + reach, side='right')
                    r += 1
        px, py, pz = sorted_points[s0, 0], sorted_points[s0, 1], sorted_points[s0, 2]
        n = 0
        closest = np.inf
        r = -1
        for dx in range(-reach, reach + 1):
            gx = _gap(px, lower[0] + (ix + dx - reach) * cell, cell)
            for dy in range(-reach, reach + 1):
                r += 1
                gxy = gx + _gap(py, lower[1] + (iy + dy - reach) * cell, cell)
                if gxy > r2:
                    continue  # the whole row of cells is out of reach
                base = ((ix + dx) * ny + (iy + dy)) * nz + iz
                for c in range(lo_row[r], hi_row[r]):
                    z = iz + cell_key[c] - base
                    if gxy + _gap(pz, lower[2] + (z - reach) * cell, cell) > r2:
                        continue
                    for s in range(cell_start[c], cell_start[c + 1]):
                        ex = sorted_points[s, 0] - px
                        ey = sorted_points[s, 1] - py
                        ez = sorted_points[s, 2] - pz
                        e = ex * ex + ey * ey + ez * ez
                        # appended without a branch (about half the points tested are out
                        # of the radius: a mispredicted branch each); kept when within
                        buf_j[n] = order[s]
                        buf_d[n] = e
                        n += e <= r2
                        if s != s0:
                            closest = min(closest, e)
        if n > max_nn:
            _select(buf_d, buf_j, n, max_nn)
            n = max_nn
        nbr[s0 - offset, :n] = buf_j[:n]
        count[s0 - offset] = n
        nearest[i] = np.sqrt(closest) if closest <= r2 else np.inf
