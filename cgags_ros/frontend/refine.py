"""
Local refinement of a coarse source->target estimate, and alignment quality.

Point-to-plane ICP (Open3D) or GICP (small_gicp) on the downsampled clouds. Transforms are
4x4 source->target (``p_target = R p_source + t``), metres.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from .features import downsample, MIN_POINTS
from ..config.frontend import RefineConfig
from ..geometry import apply_transform, GravityFrame
from ..open3d_import import open3d as o3d

# A first, coarser stage stops once fitness and inlier RMSE change by less than this
# (relative): it only has to bring the estimate within the final distance, whose stage
# keeps Open3D's 1e-6.
COARSE_STAGE_TOLERANCE = 1e-4
MAX_ITERATIONS = 50  # iterations of each refinement stage, at most
# A source of fewer voxels than this is refined once more at half the voxel (refine_finer):
# more voxels constrain the pose at the voxel, and the denser points would only cost time.
FINER_MAX_VOXELS = 5000
FINER_DISTANCE_FACTOR = 0.5  # the finer stage's last correspondence distance, in voxels
FINER_ITERATIONS = 10  # a finer stage's, at most: it starts within the basin it settles in


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
                       transform: np.ndarray, max_distance: float,
                       workers: int = 1) -> Alignment:
    """
    Evaluate ``transform`` (source (N, 3) -> target, metres): fitness and inlier RMSE.

    ``workers``: threads of the nearest-neighbour query (the result does not depend on them).
    """
    tree = target if isinstance(target, cKDTree) else cKDTree(target)
    moved = apply_transform(transform, source)
    dist, nn = tree.query(moved, k=1, distance_upper_bound=max_distance, workers=workers)
    close = np.isfinite(dist)
    rmse = float(np.sqrt(np.mean(dist[close] ** 2))) if close.any() else float('nan')
    fitness = float(close.mean()) if len(source) else 0.0
    return Alignment(np.asarray(transform, dtype=np.float64), fitness, rmse, max_distance,
                     np.flatnonzero(close), nn[close])


def refine_transform(source: np.ndarray, target: np.ndarray, initial: np.ndarray, *,
                     voxel_size: float, config: RefineConfig,
                     target_normals: np.ndarray | None = None,
                     coarse_distance: float | None = None,
                     gravity: np.ndarray | None = None, workers: int = 1,
                     tolerance: float = 1e-6) -> np.ndarray:
    """
    Refine the 4x4 source->target transform ``initial``.

    The final stage matches points within ``max_correspondence_distance_factor * v``. When
    ``coarse_distance`` (metres, typically the core's inlier threshold tau: the coarse
    estimate is only good to about tau) is larger, a first stage runs with it, so that an
    estimate off by more than the final distance still converges; point-to-plane's first
    stage stops at :data:`COARSE_STAGE_TOLERANCE` (GICP runs both stages in full).
    ``config.method == 'none'`` returns ``initial`` unchanged. The final stage stops once
    fitness and inlier RMSE change by less than ``tolerance`` (relative; a tracked scan,
    whose start is already close, needs no more than its gates can tell apart).

    With ``gravity`` (the unit up axis of both clouds, 4-DoF mode) only yaw about it and
    translation are refined, so roll and pitch stay exactly as in ``initial``:
    point-to-plane is a yaw + translation Gauss-Newton (:func:`point_to_plane_4dof`);
    GICP's 6-DoF result is projected onto the nearest yaw-only motion and then polished by
    the same 4-DoF point-to-plane, whose neighbour queries use ``workers`` threads.
    """
    if gravity is not None:
        return _refine_4dof(source, target, initial, voxel_size, config, target_normals,
                            coarse_distance, gravity, workers, tolerance)
    final = config.max_correspondence_distance_factor * voxel_size
    T = np.asarray(initial, dtype=np.float64)
    for distance in stages(coarse_distance, final):
        stop = COARSE_STAGE_TOLERANCE if distance > final else tolerance
        if config.method == 'point_to_plane':
            T = _point_to_plane(source, target, target_normals, T, distance, voxel_size, config,
                                stop)
        elif config.method == 'gicp':
            T = _gicp(source, target, T, distance, voxel_size, config)
    return T


def refine_finer(source: np.ndarray, source_voxels: int, target: np.ndarray,
                 target_normals: np.ndarray, tree: cKDTree, initial: np.ndarray, *,
                 voxel_size: float, config: RefineConfig, workers: int = 1) -> np.ndarray:
    """
    Refine :func:`refine_transform`'s ``initial`` once more with the source's own points.

    ``source``: its points as given (N, 3), not the voxel centroids ``initial`` was refined
    with, which are ``source_voxels``. With few centroids (fewer than
    :data:`FINER_MAX_VOXELS`) point-to-plane can settle degrees from where the source's
    surfaces fit the target, and no more iterations move it; the source downsampled at half
    the voxel settles it (:func:`staged_point_to_plane` against the target's ``tree``,
    :data:`FINER_ITERATIONS` a stage), at the refinement's final distance and then at
    :data:`FINER_DISTANCE_FACTOR` voxels.
    Returns ``initial`` unchanged for more voxels and for a method other than
    point-to-plane (:func:`refines_finer`).
    """
    if not refines_finer(source_voxels, config):
        return np.asarray(initial, dtype=np.float64)
    # At least as many points as the source's voxels, which were MIN_POINTS or more.
    finer = downsample(source, voxel_size / 2, MIN_POINTS, 'source')
    return staged_point_to_plane(finer, target, target_normals, tree, initial,
                                 config.max_correspondence_distance_factor * voxel_size,
                                 FINER_DISTANCE_FACTOR * voxel_size, FINER_ITERATIONS, workers)


def refines_finer(source_voxels: int, config: RefineConfig) -> bool:
    """Tell whether :func:`refine_finer` refines a source of ``source_voxels`` voxels."""
    return config.method == 'point_to_plane' and source_voxels < FINER_MAX_VOXELS


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
                                   max_iteration=MAX_ITERATIONS))
    return np.asarray(result.transformation).copy()


def _gicp(source: np.ndarray, target: np.ndarray, initial: np.ndarray, distance: float,
          voxel_size: float, config: RefineConfig) -> np.ndarray:
    import small_gicp

    # The clouds are already voxelized at v; small_gicp re-voxelizes at the same size, which
    # leaves them (almost) unchanged but is what its one-call API needs for covariances.
    result = small_gicp.align(target, source, initial, registration_type='GICP',
                              downsampling_resolution=voxel_size,
                              max_correspondence_distance=distance,
                              max_iterations=MAX_ITERATIONS, num_threads=1)
    return np.asarray(result.T_target_source).copy()


def _refine_4dof(source, target, initial, voxel_size, config, target_normals, coarse_distance,
                 gravity, workers, final_tolerance) -> np.ndarray:
    if config.method == 'none':
        return np.asarray(initial, dtype=np.float64)
    frame = GravityFrame(tuple(gravity))
    if target_normals is None:
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel_size,
                                                                    max_nn=30))
        target_normals = np.asarray(cloud.normals)
    final = config.max_correspondence_distance_factor * voxel_size
    distances = stages(coarse_distance, final)
    T = frame.to_gravity_transform(np.asarray(initial, dtype=np.float64))
    src, dst = frame.to_gravity(source), frame.to_gravity(target)
    normals = frame.to_gravity(target_normals)
    if config.method == 'gicp':
        T6 = frame.to_gravity_transform(_gicp(source, target, frame.from_gravity(T),
                                              distances[-1], voxel_size, config))
        T = nearest_yaw_motion(T6)
    tree = cKDTree(dst)
    for distance in distances:
        tolerance = COARSE_STAGE_TOLERANCE if distance > final else final_tolerance
        T = point_to_plane_4dof(src, dst, normals, T, distance, MAX_ITERATIONS,
                                tolerance, tree, workers)
    return frame.from_gravity(T)


def nearest_yaw_motion(T: np.ndarray) -> np.ndarray:
    """Return the yaw-only (about z) motion nearest to ``T``, with T's translation."""
    yaw = np.arctan2(T[1, 0] - T[0, 1], T[0, 0] + T[1, 1])
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:3, 3] = T[:3, 3]
    return out


def point_to_plane_4dof(source: np.ndarray, target: np.ndarray, normals: np.ndarray,
                        initial: np.ndarray, distance: float, iterations: int,
                        tolerance: float, tree: cKDTree | None = None,
                        workers: int = 1) -> np.ndarray:
    """
    Point-to-plane ICP over yaw about z and translation (gravity frame, metres).

    Gauss-Newton on sum (n_q . (R p + t - q))^2 over the nearest target points within
    ``distance``; the update is a yaw about z composed on the left, so the last row of the
    rotation stays exactly (0, 0, 1) when ``initial``'s does. Stops when fitness and RMSE
    change by less than ``tolerance`` (relative) or after ``iterations``.
    """
    tree = tree if tree is not None else cKDTree(target)
    return _gauss_newton(source, target, normals, initial, distance, iterations, tolerance,
                         tree, workers, _Yaw)


def stages(coarse_distance: float | None, final: float) -> list[float]:
    """Return a refinement's correspondence distances: a coarse stage first when it is larger."""
    if not coarse_distance or coarse_distance <= final:
        return [final]
    return [coarse_distance, final]


def staged_point_to_plane(source: np.ndarray, target: np.ndarray, normals: np.ndarray,
                          tree: cKDTree, initial: np.ndarray, coarse_distance: float,
                          final: float, iterations: int, workers: int = 1) -> np.ndarray:
    """
    Run :func:`point_to_plane_6dof` in a refinement's stages, against a prebuilt ``tree``.

    The ``coarse_distance`` stage first when it is the larger (stopping at
    :data:`COARSE_STAGE_TOLERANCE`), then the ``final`` one (1e-6), ``iterations`` each: for
    the many short refinements against one target (:mod:`cgags_ros.pipeline.settle`).
    """
    T = np.asarray(initial, dtype=np.float64)
    for distance in stages(coarse_distance, final):
        tolerance = COARSE_STAGE_TOLERANCE if distance > final else 1e-6
        T = point_to_plane_6dof(source, target, normals, T, distance, iterations, tolerance,
                                tree, workers)
    return T


def point_to_plane_6dof(source: np.ndarray, target: np.ndarray, normals: np.ndarray,
                        initial: np.ndarray, distance: float, iterations: int,
                        tolerance: float, tree: cKDTree, workers: int = 1) -> np.ndarray:
    """
    Point-to-plane ICP over rotation and translation (source -> target, metres).

    Gauss-Newton on sum (n_q . (R p + t - q))^2 over the nearest target points within
    ``distance``, found in ``tree`` (the target's, built once by its caller, so that many
    short refinements against one target pay for it once); the update is a rotation vector
    and a translation composed on the left. It runs no OpenMP loop: on a loaded machine
    many short refinements are not held up by idle threads. Stops when fitness and RMSE
    change by less than ``tolerance`` (relative) or after ``iterations``.
    """
    return _gauss_newton(source, target, normals, initial, distance, iterations, tolerance,
                         tree, workers, _Rigid)


class _Yaw:
    """Yaw about z and translation: 4 parameters (radians, metres)."""

    size = 4

    @staticmethod
    def jacobian(p: np.ndarray, n: np.ndarray) -> np.ndarray:
        return np.column_stack([n[:, 1] * p[:, 0] - n[:, 0] * p[:, 1], n])

    @staticmethod
    def step(dx: np.ndarray) -> np.ndarray:
        c, s = np.cos(dx[0]), np.sin(dx[0])
        step = np.eye(4)
        step[:2, :2] = [[c, -s], [s, c]]
        step[:3, 3] = dx[1:]
        return step

    @staticmethod
    def negligible(dx: np.ndarray, p: np.ndarray, distance: float) -> bool:
        # A step far below the correspondence distance changes no pairing: converged.
        return abs(dx[0]) * np.sqrt(np.mean(np.sum(p[:, :2] ** 2, axis=1))) + np.linalg.norm(
            dx[1:]) < 1e-5 * distance


class _Rigid:
    """Rotation vector and translation: 6 parameters (radians, metres)."""

    size = 6

    @staticmethod
    def jacobian(p: np.ndarray, n: np.ndarray) -> np.ndarray:
        return np.column_stack([np.cross(p, n), n])

    @staticmethod
    def step(dx: np.ndarray) -> np.ndarray:
        step = np.eye(4)
        step[:3, :3] = _rotation_from_vector(dx[:3])
        step[:3, 3] = dx[3:]
        return step

    @staticmethod
    def negligible(dx: np.ndarray, p: np.ndarray, distance: float) -> bool:
        return False


def _gauss_newton(source: np.ndarray, target: np.ndarray, normals: np.ndarray,
                  initial: np.ndarray, distance: float, iterations: int, tolerance: float,
                  tree: cKDTree, workers: int, motion: type) -> np.ndarray:
    """Run the point-to-plane Gauss-Newton of the functions above over ``motion``."""
    T = np.asarray(initial, dtype=np.float64).copy()
    previous = None
    for _ in range(iterations):
        moved = apply_transform(T, source)
        dist, nn = tree.query(moved, k=1, distance_upper_bound=distance, workers=workers)
        close = np.isfinite(dist)
        if close.sum() < motion.size:
            break
        p, q, n = moved[close], target[nn[close]], normals[nn[close]]
        r = np.einsum('ij,ij->i', n, p - q)
        J = motion.jacobian(p, n)
        H = J.T @ J
        H += 1e-12 * np.trace(H) * np.eye(motion.size)
        dx = np.linalg.solve(H, -J.T @ r)
        T = motion.step(dx) @ T
        state = (close.mean(), np.sqrt(np.mean(dist[close] ** 2)))
        if previous is not None and all(abs(a - b) <= tolerance * max(abs(b), 1e-12)
                                        for a, b in zip(state, previous)):
            break
        if motion.negligible(dx, p, distance):
            break
        previous = state
    return T


def _rotation_from_vector(w: np.ndarray) -> np.ndarray:
    """Return the rotation matrix of the rotation vector ``w`` (radians), by Rodrigues."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-15:
        return np.eye(3)
    k = w / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)
