"""
Twins: the poses a near-symmetric or weakly constrained scene would accept as well as the estimate.

The correspondences' candidates (:mod:`.candidates`) are the other poses the matches
support. A room that looks alike turned round, or a wall along which the overlap can slide,
may give its wrong pose few distinct correspondences but as good a fit on the surfaces. So
before an estimate is called valid, its twins are tried directly: the estimate turned 180
degrees about each principal axis of the overlap (through its centroid); slid both ways
along the translation the overlap constrains least (``SLIDE`` voxels); turned a quarter of
the way both ways about each principal axis of the overlap's normals (a room's walls and
floor face along those axes, and a near-square room turns about its vertical one); and the
other distinct poses the correspondences support (the candidates within the ambiguity ratio
were settled already; the others were not). Each start that already fits reasonably (at
least ``fitted.TWIN_PROMISING`` times the estimate's fitness, on the settling's sample of
the source: a share needs no more to be told apart; most that start worse never settle
anywhere plausible) is settled (:func:`~.settle.settle`, :data:`~.settle.TWIN`: a twin only has to
show where it goes) and measured; :func:`cgags_ros.validity.plausible_twin` judges it, so
that a study judging recorded twins judges them as the pipeline does. A plausible twin
makes the result ambiguous, with the twin as runner-up. The settings were chosen
leave-one-scene-out on real RGB-D pairs (docs/ablation.md); a map target is not checked
here: the relocalizer checks a pose's twins under the map's own symmetries
(:func:`map_symmetries`).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from .candidates import MIN_ROTATION_DEG
from .map import PreparedMap
from .places import REACH_QUANTILE
from .result import Candidate, PipelineResult
from .settle import Pair, settle, SYMMETRY, TWIN
from .. import fitted
from ..config.pipeline import PipelineConfig
from ..frontend.features import CloudFeatures
from ..frontend.matching import Correspondences
from ..frontend.refine import evaluate_alignment
from ..geometry import rotation_error_deg, translation_error
from ..parallel import map_ordered
from ..validity import plausible_twin

SLIDE = 10.0
SYMMETRY_FIT = 0.5  # a turn is a symmetry of a map when it puts half of the map on itself
SYMMETRY_START = 1 / 3  # ...and it is refined only when it starts with a third there
SYMMETRY_POINTS = 2000  # about this many of the map's points judge a turn
AXIS_NORMALS = 4000  # about this many normals find the directions surfaces face...
AXIS_TRIES = 200  # ...each of about this many tried as one
AXIS_TOLERANCE_DEG = 10.0  # a normal faces along a direction within this angle
MAX_SHIFT_BINS = 4096  # the histograms that shift a turn onto the map: at most this many bins


def worth_refining(start_fitness: float, fitness: float,
                   promising: float = fitted.TWIN_PROMISING) -> bool:
    """Tell whether a twin is settled: its start fits ``promising`` times the estimate's."""
    return start_fitness >= promising * fitness


def twin_starts(fs: CloudFeatures, ft: CloudFeatures, T: np.ndarray, distance: float,
                voxel_size: float, candidates: Sequence[np.ndarray] = ()
                ) -> list[tuple[str, np.ndarray]]:
    """
    Return the twins' starting poses of ``T``, each with its name.

    In this order: ``flip0..2``, ``slide1``/``slide-1``, ``turn0..2`` with ``+``/``-``, and
    ``candidate1..`` (``candidates``: the other distinct poses the correspondences support).
    See the module doc.
    """
    align = evaluate_alignment(fs.points, ft.tree, T, distance)
    if len(align.source_index) < 6:
        return []
    rotated = fs.points[align.source_index] @ T[:3, :3].T
    moved = rotated + T[:3, 3]
    centroid = moved.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov(moved.T))
    starts = [(f'flip{i}', _turned(T, axis, np.pi, centroid)) for i, axis in enumerate(axes.T)]
    normals = ft.normals[align.target_index]
    _, directions = np.linalg.eigh(normals.T @ normals)  # least constrained translation first
    for sign in (1, -1):
        M = np.eye(4)
        M[:3, 3] = sign * SLIDE * voxel_size * directions[:, 0]
        starts.append((f'slide{sign}', M @ T))
    # A room's walls and floor face along a few directions, and the eigenvectors of the
    # normals' scatter are those directions: a four-fold symmetric room turns about one.
    for i, axis in enumerate(directions.T):
        for sign, label in ((1, '+'), (-1, '-')):
            starts.append((f'turn{i}{label}', _turned(T, axis, sign * np.pi / 2, centroid)))
    starts.extend((f'candidate{k}', np.asarray(C, dtype=np.float64))
                  for k, C in enumerate(candidates, start=1))
    return starts


def _turned(T: np.ndarray, axis: np.ndarray, angle: float, centre: np.ndarray) -> np.ndarray:
    """Return ``T`` followed by a turn of ``angle`` radians about ``axis`` through ``centre``."""
    M = np.eye(4)
    M[:3, :3] = Rotation.from_rotvec(angle * axis).as_matrix()
    M[:3, 3] = centre - M[:3, :3] @ centre
    return M @ T


def find_twin(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
              result: PipelineResult, cfg: PipelineConfig,
              map_target: bool = False, workers: int = 1) -> Candidate | None:
    """
    Return the first plausible twin of ``result``'s estimate, or None.

    ``result`` has passed the gates (its ``fitness`` is set). 6-DoF pairs of sensor-frame
    clouds only: a 4-DoF estimate cannot turn about a horizontal axis (its yaw flips are
    what the correspondences' own candidates test); without the free-space test (clouds not
    in their sensor frames, or the gate off) a slide along a wall fits as well as the
    estimate whether or not it is right; and a map (``map_target``) was not measured.
    """
    if (cfg.core.motion_model == '4dof' or cfg.refine.method == 'none' or map_target
            or cfg.frontend.normal_orientation != 'origin'
            or cfg.gates.max_free_space_violation >= 1):
        return None
    v, tau = cfg.voxel_size, float(result.inlier_threshold)
    distance = cfg.refine.max_correspondence_distance_factor * v
    T = np.asarray(result.transform, dtype=np.float64)
    pair = Pair(fs, ft, cfg, map_target,
                (fs.points[corr.source_index], ft.points[corr.target_index]), tau)

    def judge(start: np.ndarray) -> Candidate | None:
        """Return the twin settled from ``start`` when it is plausible (see the module doc)."""
        if not worth_refining(
                evaluate_alignment(fs.points[::TWIN.stride], ft.tree, start, distance).fitness,
                result.fitness):
            return None
        s = settle(pair, start, tau, TWIN)
        if not plausible_twin(rotation_error_deg(s.transform, T),
                              translation_error(s.transform, T), s, result.fitness, v,
                              MIN_ROTATION_DEG):
            return None
        return Candidate(s.transform, s.support, s.fitness)

    # The starts are independent: judged side by side, the first plausible one in their
    # order is the twin, as if they were judged one after the other.
    others = [c.transform for c in result.candidates[1:]]
    starts = [start for _, start in twin_starts(fs, ft, T, distance, v, others)]
    twins = map_ordered(judge, starts, workers)
    return next((twin for twin in twins if twin is not None), None)


def add_twin(result: PipelineResult, twin: Candidate) -> None:
    """Make ``twin`` the runner-up of ``result`` (:func:`find_twin` found it plausible)."""
    best = result.candidates[0]
    twin.ratio = twin.num_inliers / best.num_inliers if best.num_inliers else 0.0
    result.candidates.insert(1, twin)
    if twin.num_inliers > 0:
        result.runner_up_ratio = best.num_inliers / twin.num_inliers


def map_symmetries(prepared: PreparedMap, cfg: PipelineConfig) -> list[np.ndarray]:
    """
    Return the turns of a map that put it onto itself (4x4 each, map frame), found once.

    A room, a hall or a box-like store whose floor plan is near-square looks alike turned a
    quarter or half of the way about its vertical: every pose in it has such twins, whatever
    the scans show of the room. Its turns are :func:`symmetries_of` the whole map. Kept on
    ``prepared``; a room inside a larger map has those of :func:`local_symmetries`.
    """
    if prepared.symmetries is None:
        ft = prepared.features
        prepared.symmetries = symmetries_of(ft.points, ft.normals, ft, cfg)
    return prepared.symmetries


def local_symmetries(prepared: PreparedMap, cfg: PipelineConfig,
                     placed: np.ndarray) -> list[np.ndarray]:
    """
    Return the turns of the part of a map that scans placed in it see (4x4 each, map frame).

    A near-square room inside a larger map has no symmetry of the whole map, yet scans in
    the room look alike turned about it. The part is the map within the scans' reach (the
    :data:`~.places.REACH_QUANTILE` percentile of the ``placed`` points' distances from
    their centroid; (N, 3), the map's local frame). Its turns are :func:`symmetries_of` it,
    onto the whole map.
    """
    ft = prepared.features
    centre = placed.mean(axis=0)
    reach = np.percentile(np.linalg.norm(placed - centre, axis=1), REACH_QUANTILE)
    # Turned, the part lands on another side of its room: within twice the reach.
    around = np.sort(np.asarray(ft.tree.query_ball_point(centre, 2 * reach), dtype=np.int64))
    rows = around[np.linalg.norm(ft.points[around] - centre, axis=1) <= reach]
    if len(rows) < SYMMETRY_POINTS:  # too little of the map there to judge a turn
        return []
    return symmetries_of(ft.points[rows], ft.normals[rows], ft, cfg, ft.points[around])


def symmetries_of(points: np.ndarray, normals: np.ndarray, ft: CloudFeatures,
                  cfg: PipelineConfig, around: np.ndarray | None = None) -> list[np.ndarray]:
    """
    Return the turns that put ``points`` (with their ``normals``) onto the map ``ft``.

    The points are turned by 90, -90 and 180 degrees about each of their
    :func:`facing_axes`, through their centroid, and shifted along those axes onto
    ``around`` (the map near them; default themselves: :func:`_onto`, since the centroid
    of the part of a room a scan sees is not the room's centre); a turn that puts
    at least ``SYMMETRY_START`` of about ``SYMMETRY_POINTS`` evenly spread points on the
    map is settled onto it (:data:`~.settle.SYMMETRY`), and one that then puts at least
    ``SYMMETRY_FIT`` of them there is a symmetry, and so is its inverse.
    """
    final = cfg.refine.max_correspondence_distance_factor * cfg.voxel_size
    sample = points[::max(1, len(points) // SYMMETRY_POINTS)]
    found, pair = [], Pair(sample, ft, cfg)
    if len(sample) < 6:
        return found
    centre, axes = points.mean(axis=0), facing_axes(normals)
    around = points if around is None else around
    spread = around[::max(1, len(around) // (4 * SYMMETRY_POINTS))]
    for axis in axes:
        for angle in (np.pi / 2, -np.pi / 2, np.pi):
            start = _onto(_turned(np.eye(4), axis, angle, centre), sample, spread, axes,
                          cfg.voxel_size)
            if evaluate_alignment(sample, ft.tree, start, final).fitness < SYMMETRY_START:
                continue
            S = settle(pair, start, SLIDE * cfg.voxel_size, SYMMETRY)
            if S.fitness >= SYMMETRY_FIT:
                found.append(S.transform)
    # A turn that puts a room onto itself does so turned back too, though that start may
    # have missed (a quarter turn one way found, the other screened out).
    for S in list(found):
        back = np.linalg.inv(S)
        if all(rotation_error_deg(back, F) > MIN_ROTATION_DEG for F in found):
            found.append(back)
    return found


def facing_axes(normals: np.ndarray) -> np.ndarray:
    """
    Return three orthonormal directions (rows) most surfaces of ``normals`` face along.

    A room's floor and walls face along three directions. The principal axes of the normals'
    scatter find them only when the three are faced by different amounts of surface; two
    walls seen alike make two axes equal and their eigenvectors any mix of the two. So the
    first direction is the one most normals face (either way, within ``AXIS_TOLERANCE_DEG``),
    the second the one most of the normals across it face, the third across both.
    """
    n = normals[::max(1, len(normals) // AXIS_NORMALS)]
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    across = np.sin(np.radians(AXIS_TOLERANCE_DEG))
    first = _most_faced(n)
    others = n[np.abs(n @ first) < across]
    if len(others) == 0:  # one plane: any direction across it will do
        others = np.cross(first, np.eye(3)[np.argmin(np.abs(first))])[None]
    second = _most_faced(others)
    second = second - (second @ first) * first
    second /= np.linalg.norm(second)
    return np.stack([first, second, np.cross(first, second)])


def _most_faced(n: np.ndarray) -> np.ndarray:
    """Return the unit direction most unit normals ``n`` face (either way): their mean there."""
    near = np.cos(np.radians(AXIS_TOLERANCE_DEG))
    tries = n[::max(1, len(n) // AXIS_TRIES)]
    best = tries[np.argmax((np.abs(tries @ n.T) > near).sum(axis=1))]
    along = n @ best
    mean = (np.sign(along[np.abs(along) > near])[:, None] * n[np.abs(along) > near]).sum(axis=0)
    return mean / np.linalg.norm(mean)


def _onto(start: np.ndarray, sample: np.ndarray, points: np.ndarray, axes: np.ndarray,
          bin_size: float) -> np.ndarray:
    """
    Return ``start`` shifted along each of ``axes`` to put ``sample`` most on ``points``.

    Along each axis, the shift that best lines up the histograms of the moved sample's and
    the points' coordinates (``bin_size`` metres a bin): a room's walls and floor are its
    histograms' peaks, and a turn about the wrong centre only shifts them.
    """
    moved = sample @ start[:3, :3].T + start[:3, 3]
    shift = np.zeros(3)
    for axis in axes:
        a, b = moved @ axis, points @ axis
        low, high = min(a.min(), b.min()), max(a.max(), b.max())
        # A map kilometres long gets coarser bins: the settling finds the rest.
        bin_size = max(bin_size, (high - low) / MAX_SHIFT_BINS)
        bins = int((high - low) / bin_size) + 1
        ha = np.bincount(((a - low) / bin_size).astype(np.int64), minlength=bins)
        hb = np.bincount(((b - low) / bin_size).astype(np.int64), minlength=bins)
        best = int(np.argmax(np.correlate(hb / len(b), ha / len(a), 'full'))) - (bins - 1)
        shift += best * bin_size * axis
    T = np.array(start, dtype=np.float64)
    T[:3, 3] += shift
    return T
