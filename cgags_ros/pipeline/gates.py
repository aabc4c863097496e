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

from .result import PipelineResult
from ..config.pipeline import PipelineConfig
from ..frontend.features import CloudFeatures
from ..frontend.matching import Correspondences
from ..frontend.refine import Alignment, evaluate_alignment
from ..geometry import apply_transform, GravityFrame
from ..registration import poisson_isf

# The free-space gate's depth margin (voxel sizes) and the angular bin (degrees) of the depth
# maps seen from each cloud's sensor: a point is in front of a surface only when it is nearer
# the sensor by more than the margin, which absorbs the voxel grid's and the sensor's noise.
FREE_SPACE_MARGIN_FACTOR = 2.0
FREE_SPACE_BIN_DEG = 2.0


def measure(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
            result: PipelineResult, cfg: PipelineConfig, map_target: bool = False
            ) -> Alignment:
    """
    Set the measurements the gates judge on ``result`` (its ``transform`` is the estimate).

    The chance-level inliers of the correspondences and their bound, then
    :func:`measure_overlap`, whose overlap is returned, and the descriptors' agreement
    over it (:func:`descriptor_ratio`). ``map_target``: the target is a map
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
                           cfg: PipelineConfig) -> None:
    """Set ``result.shared_area``, ``descriptor_ratio`` (and ``observability``) alone."""
    distance = cfg.refine.max_correspondence_distance_factor * cfg.voxel_size
    T = result.transform
    align = evaluate_alignment(fs.points, ft.tree, T, distance)
    result.shared_area = shared_area(
        align, evaluate_alignment(ft.points, fs.tree, np.linalg.inv(T), distance),
        cfg.voxel_size)
    result.descriptor_ratio = descriptor_ratio(fs.descriptors, ft.descriptors, align)
    result.observability = observability(fs.points, ft.normals, align)


def measured_free_space(fs: CloudFeatures, ft: CloudFeatures, transform: np.ndarray,
                        cfg: PipelineConfig, map_target: bool = False) -> float:
    """
    Return :func:`free_space_violation` of ``transform`` as the config asks for it.

    NaN when the gate does not apply: clouds not in their sensor frames (normals not
    oriented to the origin, or neither cloud's origin its sensor:
    :attr:`~cgags_ros.frontend.features.CloudFeatures.sensor_at_origin`) or the gate
    disabled (``gates.max_free_space_violation`` 1).
    """
    return free_space_of(fs.points, ft.points, transform, cfg, fs.sensor_at_origin,
                         not map_target and ft.sensor_at_origin)


def free_space_of(source: np.ndarray, target: np.ndarray, transform: np.ndarray,
                  cfg: PipelineConfig, source_view: bool = True,
                  target_view: bool = True) -> float:
    """Return :func:`measured_free_space` of the downsampled clouds' points (metres)."""
    if (cfg.frontend.normal_orientation != 'origin' or cfg.gates.max_free_space_violation >= 1
            or not (source_view or target_view)):
        return float('nan')
    return free_space_violation(source, target, transform,
                                FREE_SPACE_MARGIN_FACTOR * cfg.voxel_size,
                                FREE_SPACE_BIN_DEG, target_view, source_view)


def free_space_violation(source: np.ndarray, target: np.ndarray, transform: np.ndarray,
                         margin: float, bin_deg: float, target_view: bool = True,
                         source_view: bool = True) -> float:
    """
    Return the share of points an alignment puts where the other cloud's sensor saw nothing.

    Each cloud is taken as seen from its own origin (its sensor): a depth map of its
    nearest point per angular bin (``bin_deg`` degrees) says the space in front of that
    point along the ray was seen to be empty. Under ``transform`` (source -> target,
    metres), a point of the other cloud landing in an observed bin is *in front* (closer to
    the sensor by more than ``margin`` metres: a surface where the sensor saw through),
    *on* the surface (within ``margin``) or behind it (occluded: says nothing). Returns,
    for the source seen from the target's sensor (when ``target_view``) and the target
    seen from the source's (when ``source_view``), the larger share in front / (in front +
    on); 0 with nothing to compare. A right pose leaves only the misfits at occlusion edges
    and from the fusion of several views; a wrong one stacks surfaces in front of each other.
    """
    T = np.asarray(transform, dtype=np.float64)
    inverse = np.linalg.inv(T)
    worst = 0.0
    if source_view:
        seen = _in_reach(target, T[:3, 3], source, margin)
        worst = _in_front_share(apply_transform(inverse, seen), source, margin, bin_deg)
    if target_view:
        seen = _in_reach(source, inverse[:3, 3], target, margin)
        worst = max(worst, _in_front_share(apply_transform(T, seen), target, margin, bin_deg))
    return worst


def _in_reach(points: np.ndarray, sensor: np.ndarray, viewer: np.ndarray,
              margin: float) -> np.ndarray:
    """
    Return the ``points`` the ``viewer`` cloud's sensor (at ``sensor``, their frame) can judge.

    A point farther from it than the viewer's farthest point by more than the margin lies
    behind every surface it saw and changes no share; against a map, most points do.
    """
    if len(points) == 0 or len(viewer) == 0:
        return points
    reach = np.sqrt(np.einsum('ij,ij->i', viewer, viewer).max()) + 2.0 * margin
    offset = points - sensor
    return points[np.einsum('ij,ij->i', offset, offset) <= reach * reach]


def _view_bins(points: np.ndarray, bin_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Return the angular bin key of each point seen from the origin, and its range."""
    r = np.linalg.norm(points, axis=1)
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    elevation = np.arcsin(np.clip(points[:, 2] / np.maximum(r, 1e-12), -1.0, 1.0))
    ia = np.floor((azimuth + np.pi) / bin_rad).astype(np.int64)
    ie = np.floor((elevation + np.pi / 2) / bin_rad).astype(np.int64)
    return ia * (int(np.pi / bin_rad) + 2) + ie, r


def depth_status(moved: np.ndarray, viewer: np.ndarray, margin: float,
                 bin_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """
    Return which ``moved`` points lie in front of ``viewer``'s surface, and which on it.

    ``viewer`` seen from its origin, its sensor, as :func:`free_space_violation` sees it: a
    depth map of its nearest point per angular bin of ``bin_deg`` degrees; a point of
    ``moved`` (in the same frame) in an observed bin is in front when nearer the origin by
    more than ``margin`` (metres), on the surface within it; both False in a bin the viewer
    did not observe, or behind its surface.
    """
    front = np.zeros(len(moved), dtype=bool)
    if len(moved) == 0 or len(viewer) == 0:
        return front, front.copy()
    bin_rad = np.radians(bin_deg)
    keys, ranges = _view_bins(viewer, bin_rad)
    order = np.lexsort((ranges, keys))
    keys, ranges = keys[order], ranges[order]
    first = np.r_[True, keys[1:] != keys[:-1]]
    keys, nearest = keys[first], ranges[first]  # the depth map: nearest range per bin
    k, r = _view_bins(moved, bin_rad)
    i = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
    seen = np.flatnonzero(keys[i] == k)
    depth = nearest[i[seen]] - r[seen]  # > 0: in front of the observed surface
    on = front.copy()
    front[seen], on[seen] = depth > margin, np.abs(depth) <= margin
    return front, on


def _in_front_share(moved: np.ndarray, viewer: np.ndarray, margin: float,
                    bin_deg: float) -> float:
    """Share of ``moved`` points in front of ``viewer``'s surface, among those in front or on."""
    front, on = depth_status(moved, viewer, margin, bin_deg)
    in_front, compared = int(front.sum()), int(front.sum() + on.sum())
    return in_front / compared if compared else 0.0


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
