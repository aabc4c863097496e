"""
The named tuples the front end's compiled functions take, and their numba types.

Arguments that belong together travel as one NamedTuple (numba passes them as tuples): a
neighbour grid (:class:`GridArrays`), the neighbour lists of a block of points
(:class:`NeighbourLists`), a descriptor index (:class:`IndexArrays`) and a query's scratch
arrays (:class:`Scratch`). Their fields, like every other argument, have the types of
:mod:`cgags_ros.compiled_types` (C-contiguous, writable arrays); functions with
``inline='always'`` carry no signature: they are compiled into their callers.
"""

from __future__ import annotations

from typing import NamedTuple

from numba import types
import numpy as np

from ...compiled_types import F32_1D, F32_2D, F64_1D, F64_2D, FLOAT, I32_2D, I64_1D, I64_2D, INT


class GridArrays(NamedTuple):
    """
    Points sorted into grid cells, as the radius search reads them.

    A point's integer cell (ix, iy, iz) >= ``reach`` spans ``lower + (ix - reach) * cell``
    to the next on each axis, with ``cell`` >= radius / reach, so its neighbours lie within
    ``reach`` cells of its own. The linear key of a cell is ``(ix * ny + iy) * nz + iz``
    (ny, nz leave ``reach`` free cells on each side, so neighbouring keys never wrap); a
    column of cells (ix, iy) is numbered ``ix * ny + iy``.
    """

    cells: np.ndarray  # (M, 3) int64: each point's integer cell, in the cloud's row order
    order: np.ndarray  # (M,) int64: the rows sorted by key; position s holds row order[s]
    sorted_points: np.ndarray  # (M, 3) float64, metres: the points in that order
    cell_key: np.ndarray  # (C,) int64: the occupied keys, ascending
    cell_start: np.ndarray  # (C + 1,) int64: where each key's points start in order
    # (columns + 1,) int64: where each column's keys start in cell_key, or (0,): no table,
    # a row of neighbouring cells is then found among all keys
    column_start: np.ndarray
    lower: np.ndarray  # (3,) float64: the grid's lower corner, metres
    ny: int
    nz: int
    cell: float  # cell size, metres
    reach: int  # cells searched on each side of a point's own
    radius: float  # the search radius, metres


class NeighbourLists(NamedTuple):
    """The neighbours of the points at positions offset .. offset + B - 1 (in cell order)."""

    order: np.ndarray  # (M,) int64: the grid's order, position s holds row order[s]
    offset: int  # the first position of the block
    nbr: np.ndarray  # (B, max_nn) int32: row s - offset: position s's neighbours (rows)
    count: np.ndarray  # (B,) int64: the entries set in each row of nbr


class IndexArrays(NamedTuple):
    """
    A descriptor index as its search reads it (:class:`.descriptor_index.DescriptorIndex`).

    Reference rows are stored by cell (cell j holds stored rows starts[j] .. starts[j + 1])
    and within a cell by their distance to its centre (``ring``).
    """

    centres: np.ndarray  # (C, D) float64: the cells' centres
    centresT: np.ndarray  # (D, C) float64: centres.T, C-contiguous
    centre_gap: np.ndarray  # (C, C) float64: distances between centres
    radius: np.ndarray  # (C,) float64: each cell's largest member distance to its centre
    starts: np.ndarray  # (C + 1,) int64: where each cell's stored rows start
    ring: np.ndarray  # (M,) float64: each stored row's distance to its cell's centre
    points: np.ndarray  # (M, D) float64: the stored rows
    basis: np.ndarray  # (P, D) float64: leading principal directions, orthonormal rows
    projectedT: np.ndarray  # (P, M) float32: basis @ points.T
    max_norm: float  # the largest norm of a reference row
    order: np.ndarray  # (M,) int64: the reference row of each stored row
    slot_of: np.ndarray  # (M,) int64: the inverse of order


class Scratch(NamedTuple):
    """One query's working arrays, allocated once per call of a search."""

    dc: np.ndarray  # (C,) float64: squared distances to the centres
    visit: np.ndarray  # (C,) int64: the cells, nearest first
    qp: np.ndarray  # (P,) float32: the query along the principal directions
    acc: np.ndarray  # (M,) float32: screening distances of a cell's members
    cand: np.ndarray  # (M,) int64: the members that pass the screen


GRID_ARRAYS = types.BaseTuple.from_types(
    [I64_2D, I64_1D, F64_2D, I64_1D, I64_1D, I64_1D, F64_1D, INT, INT, FLOAT, INT, FLOAT],
    GridArrays)
NEIGHBOUR_LISTS = types.BaseTuple.from_types([I64_1D, INT, I32_2D, I64_1D], NeighbourLists)
INDEX_ARRAYS = types.BaseTuple.from_types(
    [F64_2D, F64_2D, F64_2D, F64_1D, I64_1D, F64_1D, F64_2D, F64_2D, F32_2D, FLOAT, I64_1D,
     I64_1D], IndexArrays)
SCRATCH = types.BaseTuple.from_types([F64_1D, I64_1D, F32_1D, F32_1D, I64_1D], Scratch)
