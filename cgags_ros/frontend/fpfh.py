"""
FPFH descriptors of a downsampled cloud with normals (the kernels: :mod:`.kernels_fpfh`).

Radii are multiples of the voxel size (``FrontEndConfig.fpfh_radius_factor``); points in
metres, in the cloud's own frame.
"""

from __future__ import annotations

import numpy as np

from . import kernels_fpfh
from .parallel import run_chunks
from ..config.frontend import FrontEndConfig

# Neighbour grid cells are radius / _REACH wide, and a point's neighbours lie within
# _REACH cells of its own: smaller cells than the radius test fewer points that are out of
# it (on the redkitchen 1.8 cm features 1.5x faster than _REACH = 1; 3 is slower again).
_REACH = 2


def compute_fpfh(points: np.ndarray, normals: np.ndarray, voxel_size: float,
                 config: FrontEndConfig, workers: int = 1) -> np.ndarray:
    """
    Compute the (M, 33) FPFH descriptors with radius ``fpfh_radius_factor * v``.

    Open3D's definition (the ``fpfh_max_nn`` nearest within the radius), computed by the
    kernels of :mod:`.kernels_fpfh` with one neighbour search for both passes, on
    ``workers`` threads; values equal Open3D's to rounding (docs/implementation.md).
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    nrm = np.ascontiguousarray(normals, dtype=np.float64)
    nbr, count = radius_neighbours(pts, config.fpfh_radius_factor * voxel_size,
                                   config.fpfh_max_nn, workers)
    spf = np.zeros((len(pts), 33))
    run_chunks(lambda a, b: kernels_fpfh.spfh(pts, nrm, a, b, nbr, count, spf), len(pts),
               workers)
    out = np.zeros((len(pts), 33))
    run_chunks(lambda a, b: kernels_fpfh.fpfh(pts, spf, a, b, nbr, count, out), len(pts),
               workers)
    return out


def radius_neighbours(points: np.ndarray, radius: float, max_nn: int,
                      workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """
    Return each point's ``max_nn`` nearest points within ``radius`` (itself included).

    :returns: (M, max_nn) int32 rows (unsorted; only the first ``count`` of a row are set)
        and the (M,) counts. Ties at the ``max_nn``-th distance go to the lower row.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    max_nn = max(1, min(int(max_nn), len(pts)))
    cell = radius * (1.0 + 1e-9) / _REACH
    lower = pts.min(axis=0)
    cells = np.floor((pts - lower) / cell).astype(np.int64) + _REACH
    ny, nz = cells[:, 1].max() + 1 + _REACH, cells[:, 2].max() + 1 + _REACH
    keys = (cells[:, 0] * ny + cells[:, 1]) * nz + cells[:, 2]
    order = np.argsort(keys, kind='stable')
    cell_key, cell_start = np.unique(keys[order], return_index=True)
    cell_start = np.append(cell_start, len(pts))
    sorted_points = np.ascontiguousarray(pts[order])
    nbr = np.empty((len(pts), max_nn), dtype=np.int32)
    count = np.empty(len(pts), dtype=np.int64)
    run_chunks(lambda a, b: kernels_fpfh.radius_neighbours(
        pts, a, b, cells, order, sorted_points, cell_key, cell_start, ny, nz, lower, cell,
        _REACH, radius, max_nn, nbr, count), len(pts), workers)
    return nbr, count
