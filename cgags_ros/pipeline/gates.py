"""
What the validity gates judge a refined estimate on: the measurements, set on its result.

:func:`measure` sets the fitness and overlap, the chance-level inliers and their bound, the
observability of the overlap geometry (planes, lines, spheres leave a motion free), the
free-space violation (clouds in their sensor frames) and, in 4-DoF mode, the tilt between
the clouds' gravity axes; :func:`cgags_ros.validity.gate_refusal` decides on them.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .free_space import free_space_of, measured_free_space_surface
from .result import PipelineResult
from ..config.pipeline import PipelineConfig
from ..frontend.features import CloudFeatures
from ..frontend.matching import Correspondences
from ..frontend.refine import Alignment, evaluate_alignment
from ..geometry import apply_transform, GravityFrame
from ..registration import poisson_isf


def measure(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
            result: PipelineResult, cfg: PipelineConfig, map_target: bool = False
            ) -> Alignment:
    """
    Set the measurements the gates judge on ``result`` (its ``transform`` is the estimate).

    The chance-level inliers of the correspondences and their bound, then
    :func:`measure_overlap`, whose overlap is returned, the descriptors' agreement
    over it (:func:`descriptor_ratio`) and the surfaces it puts in free space as both
    sensors see it (:func:`~.free_space.free_space_surface`). ``map_target``: the target is a map
    fused from many viewpoints, so it has no sensor at its origin (the free-space violation
    is then measured against the scan's view only).
    """
    result.chance_inliers = chance_inliers(fs.points[corr.source_index],
                                           ft.points[corr.target_index], result.coarse_transform,
                                           result.inlier_threshold)
    members = 2 if cfg.core.motion_model == '4dof' else 3
    result.chance_bound = float('nan')  # the gate is off
    if cfg.gates.significance > 0:
        result.chance_bound = chance_bound(result.chance_inliers, result.num_hypotheses,
                                           cfg.gates.significance, members)
    align = measure_overlap(fs.points, fs.tree, ft, result, cfg, map_target,
                            fs.sensor_at_origin)
    result.descriptor_ratio = descriptor_ratio(fs.descriptors, ft.descriptors, align)
    result.free_space_surface = measured_free_space_surface(fs, ft, result.transform, cfg,
                                                            map_target)
    return align


def measure_overlap(source: np.ndarray, source_tree: cKDTree | None, ft: CloudFeatures,
                    result: PipelineResult, cfg: PipelineConfig,
                    map_target: bool = False, source_view: bool = True) -> Alignment:
    """
    Set the measurements of ``result.transform``'s overlap alone; return the overlap.

    The measurements that need no correspondences, so that an estimate refined from a
    prediction (:mod:`.tracking`) is judged as a global one is
    (:func:`cgags_ros.validity.overlap_refusal`): fitness, observability, free space, and in
    4-DoF mode the tilt. ``source`` is the downsampled source (metres, its own frame) and
    ``source_tree`` a k-d tree over it, for the target side of ``overlap``; None leaves
    ``overlap`` NaN (no gate reads it: only the candidates' settling after a global search
    does). ``source_view``: the source's origin may be its sensor (else free space is judged
    from the target's view alone). Sets ``fitness``, ``inlier_rmse``, ``overlap``,
    ``observability``, ``shared_area``, ``free_space_violation`` (and ``tilt_deg``) on
    ``result``. The
    :class:`~cgags_ros.frontend.refine.Alignment` returned pairs the overlapping source
    points with their nearest target points.
    """
    distance = cfg.refine.max_correspondence_distance_factor * cfg.voxel_size
    align = evaluate_alignment(source, ft.tree, result.transform, distance)
    result.fitness, result.inlier_rmse = align.fitness, align.inlier_rmse
    result.overlap = result.shared_area = float('nan')
    if source_tree is not None:
        back = evaluate_alignment(ft.points, source_tree, np.linalg.inv(result.transform),
                                  distance)
        result.overlap = min(align.fitness, back.fitness)
        result.shared_area = shared_area(align, back, cfg.voxel_size)
    if cfg.core.motion_model == '4dof':  # yaw + translation only: no roll/pitch motion
        frame = GravityFrame(cfg.core.gravity_axis)
        result.observability = observability(source, ft.normals, align, frame)
        result.tilt_deg = residual_tilt(source, ft.points, ft.normals, align, frame)
    else:
        result.observability = observability(source, ft.normals, align)
    result.free_space_violation = free_space_of(
        source, ft.points, result.transform, cfg, source_view,
        not map_target and ft.sensor_at_origin)
    return align


def shared_area(align: Alignment, back: Alignment, voxel_size: float) -> float:
    """
    Return the surface (square metres) two clouds share under an alignment.

    ``align`` pairs the source's downsampled points with the target, ``back`` the target's
    with the source: the smaller count of points that found a neighbour, each a surface
    cell of ``voxel_size`` squared. Clouds that share no surface still meet somewhere under
    any pose (a floor on a floor, a wall corner); what they share is then small.
    """
    return min(len(align.source_index), len(back.source_index)) * voxel_size ** 2


def descriptor_ratio(source_descriptors: np.ndarray, target_descriptors: np.ndarray,
                     align: Alignment) -> float:
    """
    Return how much more alike the descriptors of an overlap's point pairs are than chance.

    The median L2 distance between the unit-normalised descriptors (FPFH) of ``align``'s
    pairs (each overlapping source point and its nearest target point), over the median of
    the same points paired at random (seeded): well below 1 where the shared surface is one
    surface seen twice, near 1 where different surfaces only meet. NaN under 10 pairs.
    """
    if len(align.source_index) < 10:
        return float('nan')
    ds = _unit_rows(source_descriptors[align.source_index])
    dt = _unit_rows(target_descriptors[align.target_index])
    paired = np.median(np.linalg.norm(ds - dt, axis=1))
    shuffled = dt[np.random.default_rng(0).permutation(len(dt))]
    chance = np.median(np.linalg.norm(ds - shuffled, axis=1))
    return float(paired / chance) if chance > 0 else float('nan')


def _unit_rows(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


def measure_shared_surface(fs: CloudFeatures, ft: CloudFeatures, result: PipelineResult,
                           cfg: PipelineConfig, map_target: bool = False) -> None:
    """
    Set what the shared-surface gate reads of ``result.transform`` alone.

    ``shared_area``, ``descriptor_ratio``, ``free_space_surface``, ``overlap`` and
    ``observability``: for an estimate the core refused, whose overlap was not measured.
    """
    distance = cfg.refine.max_correspondence_distance_factor * cfg.voxel_size
    T = result.transform
    align = evaluate_alignment(fs.points, ft.tree, T, distance)
    back = evaluate_alignment(ft.points, fs.tree, np.linalg.inv(T), distance)
    result.overlap = min(align.fitness, back.fitness)
    result.shared_area = shared_area(align, back, cfg.voxel_size)
    result.descriptor_ratio = descriptor_ratio(fs.descriptors, ft.descriptors, align)
    result.free_space_surface = measured_free_space_surface(fs, ft, T, cfg, map_target)
    result.observability = observability(fs.points, ft.normals, align)


def chance_inliers(src: np.ndarray, dst: np.ndarray, transform: np.ndarray, tau: float) -> float:
    """
    Return the expected inliers of ``transform`` if correspondences were paired at random.

    Averages, over all (i, j), whether ``dst[j]`` lies within ``tau`` of ``T src[i]``: the
    exact expectation under a random permutation of the target rows. It is high where
    keypoints are dense or the threshold loose, i.e. where a count means little.
    """
    moved = apply_transform(transform, src)
    counts = cKDTree(dst).query_ball_point(moved, r=tau, return_length=True)
    return float(np.sum(counts) / max(len(src), 1))


def observability(source: np.ndarray, target_normals: np.ndarray, align: Alignment,
                  frame: GravityFrame | None = None) -> float:
    """
    Return the smallest / largest eigenvalue of the 6x6 point-to-plane information matrix.

    With ``frame`` (4-DoF mode) the 4x4 one of yaw about its gravity axis and translation:
    roll and pitch are not estimated, so they cannot be unconstrained.

    Rows are ``[(p - c) x n / L, n]`` over the overlapping points (p: moved source point,
    n: normal of its nearest target point, c, L: centroid and RMS radius of the overlap,
    which makes rotation and translation columns commensurate). A plane leaves in-plane
    motion unconstrained, a line its axis, a sphere all rotations: the ratio is then ~0.
    """
    if len(align.source_index) < 6:
        return 0.0
    T = align.transform
    p = apply_transform(T, source[align.source_index])
    n = target_normals[align.target_index]
    centred = p - p.mean(axis=0)
    radius = np.sqrt(np.mean(np.sum(centred ** 2, axis=1)))
    if radius <= 0:
        return 0.0
    J = np.hstack([np.cross(centred / radius, n), n])
    if frame is not None:
        J = np.column_stack([J[:, :3] @ frame.A[2], J[:, 3:]])
    eig = np.linalg.eigvalsh(J.T @ J / len(J))
    return float(max(eig[0], 0.0) / eig[-1]) if eig[-1] > 0 else 0.0


def residual_tilt(source: np.ndarray, target: np.ndarray, target_normals: np.ndarray,
                  align: Alignment, frame: GravityFrame) -> float:
    """
    Return the tilt (degrees) one 6-DoF point-to-plane step adds to a 4-DoF estimate.

    The Gauss-Newton step over the overlap (``align``'s pairs) of all six degrees of
    freedom; its rotation about the horizontal axes (across gravity) is the tilt the
    levelled estimate cannot represent. NaN with fewer than 6 overlapping points.
    """
    if len(align.source_index) < 6:
        return float('nan')
    p = apply_transform(align.transform, source[align.source_index])
    q, n = target[align.target_index], target_normals[align.target_index]
    c = p.mean(axis=0)
    J = np.hstack([np.cross(p - c, n), n])
    r = np.einsum('ij,ij->i', n, p - q)
    H = J.T @ J
    H += 1e-12 * np.trace(H) * np.eye(6)
    omega = np.linalg.solve(H, -J.T @ r)[:3]
    horizontal = omega - (omega @ frame.A[2]) * frame.A[2]
    return float(np.degrees(np.linalg.norm(horizontal)))


def chance_bound(chance: float, hypotheses: int, significance: float,
                 members: int = 3) -> float:
    """
    Return the inlier count the best of ``hypotheses`` chance-level estimates may reach.

    If all correspondences were outliers, the inliers of a fixed transform are
    ~Poisson(``chance``) (:func:`chance_inliers`), plus the ``members`` (3; 2 for a 4-DoF
    edge) that define a hypothesis; the best of H hypotheses then exceeds the Poisson
    1 - significance/H quantile with probability ~significance (union bound).
    """
    return members + poisson_isf(significance / max(hypotheses, 1), chance)
