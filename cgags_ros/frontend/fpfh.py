"""
FPFH descriptors of a downsampled cloud with normals (compiled in :mod:`.compiled.fpfh`).

Radii are multiples of the voxel size (``FrontEndConfig.fpfh_radius_factor``); points in
metres, in the cloud's own frame.
"""

from __future__ import annotations

import numpy as np

from . import compiled
from .neighbours import NeighbourGrid
from ..compiled_types import c_array
from ..config.frontend import FrontEndConfig
from ..open3d_import import open3d as o3d
from ..parallel import run_chunks

# Neighbour lists of at most this many bytes are kept for both passes; a larger cloud (a
# big map: 100 neighbours of 640k points) is done in blocks whose lists are searched again
# for the second pass, so memory stays bounded.
_NEIGHBOUR_BYTES = 256 << 20
# A point's FPFH is made of at most this many nearest neighbours within the radius.
FPFH_MAX_NN = 100


def fpfh_with_spacing(points: np.ndarray, normals: np.ndarray, voxel_size: float,
                      config: FrontEndConfig,
                      workers: int = 1, max_nn: int = FPFH_MAX_NN
                      ) -> tuple[np.ndarray, np.ndarray | None]:
    """
    Return the (M, 33) FPFH descriptors and each point's distance to its nearest other point.

    FPFH with radius ``fpfh_radius_factor * v``, Open3D's definition (the ``max_nn``
    nearest within the radius), computed by :mod:`.compiled.fpfh` with one neighbour search
    (:class:`.NeighbourGrid`) for both passes, on ``workers`` threads; values equal
    Open3D's to rounding (docs/design.md). A cloud spread so far that its neighbour grid's
    keys would overflow (a stray point millions of cells out along every axis) is handed to
    Open3D's own FPFH, which gives the same values.

    The distances come from the same neighbour search (metres; inf for a point with no
    other within the FPFH radius), None when Open3D computed the descriptors.
    """
    pts = c_array(points, np.float64)
    nrm = c_array(normals, np.float64)
    radius = config.fpfh_radius_factor * voxel_size
    grid = NeighbourGrid.build(pts, radius)
    if grid is None:
        return _open3d_fpfh(pts, nrm, radius, max_nn), None
    max_nn = max(1, min(max_nn, len(pts)))
    block = max(1, _NEIGHBOUR_BYTES // (4 * max_nn))
    blocks = [(a, min(a + block, len(pts))) for a in range(0, len(pts), block)]
    spf = np.zeros((len(pts), 33))
    out = np.zeros((len(pts), 33))
    spacing = np.empty(len(pts))
    # blocks and chunks are ranges of the points in cell order (grid.order)
    for a, b in blocks:
        lists = grid.neighbours(a, b, max_nn, spacing, workers)
        run_chunks(lambda lo, hi: compiled.spfh_pass(pts, nrm, lists, a + lo, a + hi, spf), b - a,
                   workers)
    kept = lists if len(blocks) == 1 else None  # else searched again, block by block
    for a, b in blocks:
        lists = kept if kept is not None else grid.neighbours(a, b, max_nn, spacing, workers)
        run_chunks(lambda lo, hi: compiled.fpfh_pass(pts, spf, lists, a + lo, a + hi, out), b - a,
                   workers)
    return out, spacing


def _open3d_fpfh(points: np.ndarray, normals: np.ndarray, radius: float,
                 max_nn: int) -> np.ndarray:
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(points))
    cloud.point.normals = o3d.core.Tensor(normals)
    feature = o3d.t.pipelines.registration.compute_fpfh_feature(cloud, max_nn=max_nn,
                                                                radius=radius)
    return feature.numpy().astype(np.float64, copy=False)
