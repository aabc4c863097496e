"""
Local refinement of a coarse source->target estimate, and alignment quality.

Point-to-plane ICP (Open3D) or GICP (small_gicp) on the downsampled clouds. Transforms are
4x4 source->target (``p_target = R p_source + t``), metres.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from ..config.frontend import RefineConfig
from ..geometry import apply_transform


@dataclasses.dataclass
class Alignment:
    """
    How well ``transform`` puts the source onto the target.

    :ivar transform: 4x4 source->target, metres.
    :ivar fitness: share of source points with a target point within ``max_distance``.
    :ivar inlier_rmse: RMS distance (metres) of those source points to their nearest target
        point; NaN when there are none.
    :ivar max_distance: the distance (metres) that defines an overlapping point.
    :ivar source_index: the overlapping source points (indices into the source given).
    :ivar target_index: their nearest target points (indices into the target given).
    """

    transform: np.ndarray
    fitness: float
    inlier_rmse: float
    max_distance: float
    source_index: np.ndarray
    target_index: np.ndarray


def evaluate_alignment(source: np.ndarray, target: np.ndarray | cKDTree,
                       transform: np.ndarray, max_distance: float) -> Alignment:
    """Evaluate ``transform`` (source (N, 3) -> target, metres): fitness and inlier RMSE."""
    tree = target if isinstance(target, cKDTree) else cKDTree(target)
    moved = apply_transform(transform, source)
    dist, nn = tree.query(moved, k=1, distance_upper_bound=max_distance)
    close = np.isfinite(dist)
    rmse = float(np.sqrt(np.mean(dist[close] ** 2))) if close.any() else float('nan')
    fitness = float(close.mean()) if len(source) else 0.0
    return Alignment(np.asarray(transform, dtype=np.float64), fitness, rmse, max_distance,
                     np.flatnonzero(close), nn[close])


def refine_transform(source: np.ndarray, target: np.ndarray, initial: np.ndarray, *,
                     voxel_size: float, config: RefineConfig,
                     target_normals: np.ndarray | None = None,
                     coarse_distance: float | None = None) -> np.ndarray:
    """
    Refine the 4x4 source->target transform ``initial``.

    The final stage matches points within ``max_correspondence_distance_factor * v``. When
    ``coarse_distance`` (metres, typically the core's inlier threshold tau: the coarse
    estimate is only good to about tau) is larger, a first stage runs with it, so that an
    estimate off by more than the final distance still converges; point-to-plane's first
    stage stops at ``config.coarse_stage_tolerance`` (GICP runs both stages in full).
    ``config.method == 'none'`` returns ``initial`` unchanged.
    """
    final = config.max_correspondence_distance_factor * voxel_size
    stages = ([final] if not coarse_distance or coarse_distance <= final
              else [coarse_distance, final])
    T = np.asarray(initial, dtype=np.float64)
    for distance in stages:
        tolerance = config.coarse_stage_tolerance if distance > final else 1e-6
        if config.method == 'point_to_plane':
            T = _point_to_plane(source, target, target_normals, T, distance, voxel_size, config,
                                tolerance)
        elif config.method == 'gicp':
            T = _gicp(source, target, T, distance, voxel_size, config)
    return T


def _point_to_plane(source: np.ndarray, target: np.ndarray, target_normals: np.ndarray | None,
                    initial: np.ndarray, distance: float, voxel_size: float,
                    config: RefineConfig, tolerance: float = 1e-6) -> np.ndarray:
    reg = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    if target_normals is None:
        dst.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel_size,
                                                                  max_nn=30))
    else:
        dst.normals = o3d.utility.Vector3dVector(target_normals)
    result = reg.registration_icp(
        src, dst, distance, initial, reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(relative_fitness=tolerance, relative_rmse=tolerance,
                                   max_iteration=config.max_iterations))
    return np.asarray(result.transformation).copy()


def _gicp(source: np.ndarray, target: np.ndarray, initial: np.ndarray, distance: float,
          voxel_size: float, config: RefineConfig) -> np.ndarray:
    import small_gicp

    # The clouds are already voxelized at v; small_gicp re-voxelizes at the same size, which
    # leaves them (almost) unchanged but is what its one-call API needs for covariances.
    result = small_gicp.align(target, source, initial, registration_type='GICP',
                              downsampling_resolution=voxel_size,
                              max_correspondence_distance=distance,
                              max_iterations=config.max_iterations, num_threads=1)
    return np.asarray(result.T_target_source).copy()
