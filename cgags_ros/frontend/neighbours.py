"""
Fixed-radius neighbour search on a grid of cells: FPFH's neighbours.

A point's neighbours are the ``max_nn`` nearest within the radius, itself included (Open3D's
hybrid search, which FPFH is defined on); one search serves both of FPFH's passes
(:mod:`.fpfh`). Points in metres, in the cloud's own frame.
"""

from __future__ import annotations

import numpy as np

from . import compiled
from ..geometry import bounds
from ..parallel import run_chunks

# Neighbour grid cells are radius / _REACH wide, and a point's neighbours lie within
# _REACH cells of its own: smaller cells than the radius test fewer points that are out of
# it, but more cells cost more lookups; 2 balances the two (docs/design.md).
_REACH = 2
_MAX_KEY = 1 << 62  # linear cell keys must fit in int64
# Columns of cells the lookup table may hold (8 bytes each), beyond which a wide, sparse
# grid (a large map) finds its neighbouring cells among all keys instead.
_MAX_COLUMNS = 1 << 22


class NeighbourGrid:
    """Points sorted into cells of radius / _REACH, for fixed-radius neighbour searches."""

    def __init__(self, points: np.ndarray, radius: float, cell: float, lower: np.ndarray,
                 cells: np.ndarray, shape: tuple[int, int]) -> None:
        """Sort ``points`` by the linear key of their integer ``cells`` (see :meth:`build`)."""
        ny, nz = shape
        keys = (cells[:, 0] * ny + cells[:, 1]) * nz + cells[:, 2]
        self.order = np.argsort(keys, kind='stable')
        cell_key, start = np.unique(keys[self.order], return_index=True)
        # Keys ascend by column (ix * ny + iy), then iz < nz: each column's keys are a range.
        columns = (int(cells[:, 0].max()) + _REACH + 1) * ny
        self.column_start = np.zeros(0, np.int64)  # none: rows are found among all keys
        if columns <= max(_MAX_COLUMNS, 8 * len(points)):
            per_column = np.bincount(cell_key // nz, minlength=columns)
            self.column_start = np.concatenate([[0], np.cumsum(per_column)])
        self.arrays = compiled.GridArrays(
            cells, self.order, np.ascontiguousarray(points[self.order]), cell_key,
            np.append(start, len(points)), self.column_start, lower, ny, nz, cell, _REACH,
            radius)

    @classmethod
    def build(cls, points: np.ndarray, radius: float) -> NeighbourGrid | None:
        """Return the grid of ``points`` (finite, float64), or None when its keys overflow."""
        cell = radius * (1.0 + 1e-9) / _REACH
        lower, upper = bounds(points)
        span = (upper - lower) / cell
        if not np.isfinite(span).all() or span.max() > 2.0 ** 40:
            return None
        dims = [int(d) + 1 + 2 * _REACH for d in span]  # Python ints: no overflow here
        if dims[0] * dims[1] * dims[2] >= _MAX_KEY:
            return None
        cells = np.floor((points - lower) / cell).astype(np.int64) + _REACH
        return cls(points, radius, cell, lower, cells, (dims[1], dims[2]))

    def neighbours(self, first: int, last: int, max_nn: int, nearest: np.ndarray,
                   workers: int = 1) -> compiled.NeighbourLists:
        """
        Return the neighbour lists of the points at positions first .. last.

        Positions are in :attr:`order` (cell order); each point's list holds its ``max_nn``
        nearest points within the radius (rows, unsorted; ties at the ``max_nn``-th
        distance to the lower row). Their rows of ``nearest`` (the full (M,) array) are set
        to the distance to the nearest other point (metres; inf when none is within the
        radius).
        """
        lists = compiled.NeighbourLists(self.order, first,
                                        np.empty((last - first, max_nn), dtype=np.int32),
                                        np.empty(last - first, dtype=np.int64))
        run_chunks(lambda lo, hi: compiled.radius_neighbours(
            self.arrays, first + lo, first + hi, lists, nearest), last - first, workers)
        return lists
