"""
Free space: what a pose puts where a cloud's sensor saw nothing.

Each cloud is taken as seen from its frame's origin, its sensor: a depth map of its nearest
point per angular bin says the space in front of that point along the ray was seen to be
empty. :func:`free_space_violation` is the free-space gate's measure (any point of the other
cloud in front of a surface, from either view); :func:`free_space_surface` is the
shared-surface gate's (only pieces of surface, seen from both views): clouds of two places
laid on a shared-looking floor or corner put each room's walls in the other's free space.
"""

from __future__ import annotations

import numpy as np

from ..config.pipeline import PipelineConfig
from ..frontend.features import CloudFeatures
from ..geometry import apply_transform

# The free-space gate's depth margin (voxel sizes) and the angular bin (degrees) of the depth
# maps seen from each cloud's sensor: a point is in front of a surface only when it is nearer
# the sensor by more than the margin, which absorbs the voxel grid's and the sensor's noise.
FREE_SPACE_MARGIN_FACTOR = 2.0
FREE_SPACE_BIN_DEG = 2.0
# The surfaces in free space (:func:`free_space_surface`): depth margin (voxel sizes) and
# angular bin (degrees); a point in front counts when this share of its own cloud's points
# within the radius (voxel sizes) is in front too: a piece of surface the other sensor saw
# through, not a misfit along an occlusion edge, which a right pose leaves in one view.
SURFACE_MARGIN_FACTOR = 1.0
SURFACE_BIN_DEG = 3.0
SURFACE_RADIUS_FACTOR = 3.0
SURFACE_SOLID_SHARE = 0.8


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


def measured_free_space_surface(fs: CloudFeatures, ft: CloudFeatures, transform: np.ndarray,
                                cfg: PipelineConfig, map_target: bool = False) -> float:
    """
    Return :func:`free_space_surface` of ``transform`` when both clouds are sensor views.

    NaN when it does not apply: normals not oriented to the origin, the free-space gate
    disabled (``gates.max_free_space_violation`` 1), a map target (fused from many
    viewpoints) or either cloud's origin not its sensor
    (:attr:`~cgags_ros.frontend.features.CloudFeatures.sensor_at_origin`).
    """
    if (cfg.frontend.normal_orientation != 'origin' or cfg.gates.max_free_space_violation >= 1
            or map_target or not (fs.sensor_at_origin and ft.sensor_at_origin)):
        return float('nan')
    return free_space_surface(fs, ft, transform, cfg.voxel_size)


def free_space_surface(fs: CloudFeatures, ft: CloudFeatures, transform: np.ndarray,
                       voxel_size: float) -> float:
    """
    Return the share of points ``transform`` puts in free space as surfaces both sensors see.

    As :func:`free_space_violation` (each cloud seen from its origin, :func:`depth_status`),
    with the ``SURFACE_*`` margin and bins, but a point in front of the other cloud's surface
    counts only when most of its own cloud's points around it are in front too. Per view,
    the share of such points among those in front or on the surface; returned, the smaller
    of the two views: a right pose leaves at most one view's occlusion edges and fused-in
    surfaces. ``fs``, ``ft``: the clouds' features (points and k-d trees in their own
    frames); ``transform`` source -> target (metres).
    """
    T = np.asarray(transform, dtype=np.float64)
    return min(_surface_share(ft, apply_transform(np.linalg.inv(T), ft.points), fs.points,
                              voxel_size),
               _surface_share(fs, apply_transform(T, fs.points), ft.points, voxel_size))


def _surface_share(own: CloudFeatures, moved: np.ndarray, viewer: np.ndarray,
                   voxel_size: float) -> float:
    front, on = depth_status(moved, viewer, SURFACE_MARGIN_FACTOR * voxel_size,
                             SURFACE_BIN_DEG)
    compared = int(front.sum() + on.sum())
    idx = np.flatnonzero(front)
    if not compared or not len(idx):
        return 0.0
    # a rigid motion keeps neighbourhoods: they are looked up in the cloud's own frame
    near = own.tree.query_ball_point(own.points[idx], r=SURFACE_RADIUS_FACTOR * voxel_size)
    sizes = np.fromiter((len(n) for n in near), dtype=np.int64, count=len(near))
    starts = np.r_[0, np.cumsum(sizes)[:-1]]
    in_front = np.add.reduceat(front[np.concatenate(near)].astype(np.int64), starts)
    return int(np.count_nonzero(in_front >= SURFACE_SOLID_SHARE * sizes)) / compared
