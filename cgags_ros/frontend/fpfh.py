"""
FPFH descriptors of a downsampled cloud with normals (the kernels: :mod:`.kernels_fpfh`).

Radii are multiples of the voxel size (``FrontEndConfig.fpfh_radius_factor``); points in
metres, in the cloud's own frame.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from . import kernels_fpfh, kernels_neighbours
from ..config.frontend import FrontEndConfig
from ..parallel import run_chunks

# Neighbour grid cells are radius / _REACH wide, and a point's neighbours lie within
# _REACH cells of its own: smaller cells than the radius test fewer points that are out of
# it, but more cells cost more lookups; 2 balances the two (docs/design.md).
_REACH = 2
# Neighbour lists of at most this many bytes are kept for both passes; a larger cloud (a
# big map: 100 neighbours of 640k points) is done in blocks whose lists are searched again
# for the second pass, so memory stays bounded.
_NEIGHBOUR_BYTES = 256 << 20
_MAX_KEY = 1 << 62  # linear cell keys must fit in int64
# Columns of cells the lookup table may hold (8 bytes each), beyond which a wide, sparse
# grid (a large map) finds its neighbouring cells among all keys instead.
_MAX_COLUMNS = 1 << 22


def compute_fpfh(points: np.ndarray, normals: np.ndarray, voxel_size: float,
                 config: FrontEndConfig, workers: int = 1) -> np.ndarray:
    """
    Compute the (M, 33) FPFH descriptors with radius ``fpfh_radius_factor * v``.

    Open3D's definition (the ``fpfh_max_nn`` nearest within the radius), computed by the
    kernels of :mod:`.kernels_fpfh` with one neighbour search for both passes, on
    ``workers`` threads; values equal Open3D's to rounding (docs/design.md). A cloud
    spread so far that its neighbour grid's keys would overflow (a stray point millions of
    cells out along every axis) is handed to Open3D's own FPFH, which gives the same values.
    """
    return fpfh_with_spacing(points, normals, voxel_size, config, workers)[0]


def fpfh_with_spacing(points: np.ndarray, normals: np.ndarray, voxel_size: float,
                      config: FrontEndConfig,
                      workers: int = 1) -> tuple[np.ndarray, np.ndarray | None]:
    """
    Return :func:`compute_fpfh` and each point's distance to its nearest other point.

    The distances come from the same neighbour search (metres; inf for a point with no
    other within the FPFH radius), None when Open3D computed the descriptors.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    nrm = np.ascontiguousarray(normals, dtype=np.float64)
    radius = config.fpfh_radius_factor * voxel_size
    grid = NeighbourGrid.build(pts, radius)
    if grid is None:
        return _open3d_fpfh(pts, nrm, radius, config.fpfh_max_nn), None
    max_nn = max(1, min(config.fpfh_max_nn, len(pts)))
    block = max(1, _NEIGHBOUR_BYTES // (4 * max_nn))
    blocks = [(a, min(a + block, len(pts))) for a in range(0, len(pts), block)]
    spf = np.zeros((len(pts), 33))
    out = np.zeros((len(pts), 33))
    spacing = np.empty(len(pts))
    order = grid.order  # blocks and chunks are ranges of the points in cell order
    for a, b in blocks:
        nbr, count = grid.neighbours(a, b, max_nn, spacing, workers)
        run_chunks(lambda lo, hi: kernels_fpfh.spfh(pts, nrm, a + lo, a + hi, a, order, nbr,
                                                    count, spf), b - a, workers)
    kept = (nbr, count) if len(blocks) == 1 else None  # else searched again, block by block
    for a, b in blocks:
        nbr, count = kept or grid.neighbours(a, b, max_nn, spacing, workers)
        run_chunks(lambda lo, hi: kernels_fpfh.fpfh(pts, spf, a + lo, a + hi, a, order, nbr,
                                                    count, out), b - a, workers)
    return out, spacing


def radius_neighbours(points: np.ndarray, radius: float, max_nn: int,
                      workers: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return each point's ``max_nn`` nearest points within ``radius`` (itself included).

    :returns: (M, max_nn) int32 rows (unsorted; only the first ``count`` of a row are set),
        the (M,) counts, and the (M,) distances to the nearest other point (inf where none
        is within ``radius``). Ties at the ``max_nn``-th distance go to the lower row.
    :raises ValueError: when the points are spread too far for a grid of this radius.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    grid = NeighbourGrid.build(pts, radius)
    if grid is None:
        raise ValueError(f'points spread too far for a neighbour grid of radius {radius:g}')
    nearest = np.empty(len(pts))
    nbr, count = grid.neighbours(0, len(pts), max(1, min(int(max_nn), len(pts))), nearest,
                                 workers)
    rows, counts = np.empty_like(nbr), np.empty_like(count)
    rows[grid.order], counts[grid.order] = nbr, count  # from cell order back to row order
    return rows, counts, nearest


class NeighbourGrid:
    """Points sorted into cells of radius / _REACH, for fixed-radius neighbour searches."""

    def __init__(self, points: np.ndarray, radius: float, cell: float, lower: np.ndarray,
                 cells: np.ndarray, shape: tuple[int, int]) -> None:
        """Sort ``points`` by the linear key of their integer ``cells`` (see :meth:`build`)."""
        self.points, self.radius, self.cell, self.lower = points, radius, cell, lower
        self.cells = cells
        self.ny, self.nz = shape
        keys = (cells[:, 0] * self.ny + cells[:, 1]) * self.nz + cells[:, 2]
        self.order = np.argsort(keys, kind='stable')
        self.cell_key, start = np.unique(keys[self.order], return_index=True)
        self.cell_start = np.append(start, len(points))
        # Keys ascend by column (ix * ny + iy), then iz < nz: each column's keys are a range.
        columns = (int(cells[:, 0].max()) + _REACH + 1) * self.ny
        self.column_start = np.zeros(0, np.int64)  # none: rows are found among all keys
        if columns <= max(_MAX_COLUMNS, 8 * len(points)):
            per_column = np.bincount(self.cell_key // self.nz, minlength=columns)
            self.column_start = np.concatenate([[0], np.cumsum(per_column)])
        self.sorted_points = np.ascontiguousarray(points[self.order])

    @classmethod
    def build(cls, points: np.ndarray, radius: float) -> NeighbourGrid | None:
        """Return the grid of ``points`` (finite, float64), or None when its keys overflow."""
        cell = radius * (1.0 + 1e-9) / _REACH
        lower = points.min(axis=0)
        span = (points.max(axis=0) - lower) / cell
        if not np.isfinite(span).all() or span.max() > 2.0 ** 40:
            return None
        dims = [int(d) + 1 + 2 * _REACH for d in span]  # Python ints: no overflow here
        if dims[0] * dims[1] * dims[2] >= _MAX_KEY:
            return None
        cells = np.floor((points - lower) / cell).astype(np.int64) + _REACH
        return cls(points, radius, cell, lower, cells, (dims[1], dims[2]))

    def neighbours(self, first: int, last: int, max_nn: int, nearest: np.ndarray,
                   workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the neighbour rows and counts of the points at positions first .. last.

        Positions are in :attr:`order`; their rows of ``nearest`` (the full (M,) array)
        are set too.
        """
        nbr = np.empty((last - first, max_nn), dtype=np.int32)
        count = np.empty(last - first, dtype=np.int64)
        run_chunks(lambda lo, hi: kernels_neighbours.radius_neighbours(
            self.points, first + lo, first + hi, first, self.cells, self.order,
            self.sorted_points, self.cell_key, self.cell_start, self.column_start, self.ny,
            self.nz, self.lower, self.cell, _REACH, self.radius, max_nn, nbr, count, nearest),
            last - first, workers)
        return nbr, count


def _open3d_fpfh(points: np.ndarray, normals: np.ndarray, radius: float,
                 max_nn: int) -> np.ndarray:
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(points))
    cloud.point.normals = o3d.core.Tensor(normals)
    feature = o3d.t.pipelines.registration.compute_fpfh_feature(cloud, max_nn=max_nn,
                                                                radius=radius)
    return feature.numpy().astype(np.float64, copy=False)
