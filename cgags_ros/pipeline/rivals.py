"""
Structured rivals: the poses a near-symmetric or weakly constrained scene would also accept.

The candidate search (:mod:`.candidates`) finds rivals the correspondences support. A room
that looks alike turned round, or a wall along which the overlap can slide, may give its
wrong pose few distinct correspondences but as good a fit on the surfaces. So before an
estimate is called valid, the poses such a scene would confuse it with are tried directly:
the estimate turned 180 degrees about each principal axis of the overlap (through its
centroid); slid both ways along the translation the overlap constrains least (``SLIDE``
voxels); turned a quarter of the way both ways about each principal axis of the overlap's
normals (a room's walls and floor face along those axes, and a near-square room turns
about its vertical one); and the other distinct poses the correspondences support (the
candidates within the ambiguity ratio were refined already; the others were not). Built but
off (``VOTED_PEAKS`` 0; docs/ablation.md has the measurements): the turns about the room's
own centre, wherever it is. The estimate's rotation is turned a quarter and a half of the
way about each dominant direction of the overlap's normals (the walls' and the floor's,
found as the densest bundles of normals), each with the translations the correspondences
vote for most under that rotation. A turn about any centre is that rotation with some
translation, so the correspondences that are right under the twin pose cluster on its
translation however far the centre is. Each
start that already fits reasonably (at least ``PROMISING`` times the estimate's fitness,
on every ``STRIDE``-th source point: a share needs no more to be told apart; most that
start worse never settle anywhere plausible) is refined in the estimate's stages
(``ITERATIONS`` a stage of point-to-plane against the target's k-d tree, built once with
its features: a rival only has to show where it settles) and judged like the estimate. A
rival is plausible when it settles away from the estimate (more than
``candidate_min_rotation_deg`` or ``APART`` voxels), does not stack surfaces where a sensor
saw free space (violation at most ``MAX_VIOLATION``) and fits at least ``1 /
OVERLAP_RATIO`` as well as the estimate (fitness, the share of source points on the
target: a large target's share would say nothing): the result is then ambiguous, with the
rival as runner-up. Each test of that verdict is a function of its own (:func:`worth_refining`,
:func:`settled_apart`, :func:`fits_as_well`, :func:`clear_of_free_space`), so that a study
judging recorded rivals judges them as the pipeline does. The settings were chosen
leave-one-scene-out on real RGB-D pairs (docs/ablation.md); a map target is not checked.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from .candidates import support
from .gates import measured_free_space
from .map import PreparedMap
from .result import Candidate, PipelineResult
from ..config.pipeline import PipelineConfig
from ..frontend.features import CloudFeatures
from ..frontend.matching import Correspondences
from ..frontend.refine import evaluate_alignment, staged_point_to_plane
from ..geometry import rotation_error_deg, translation_error
from ..parallel import map_ordered

SLIDE = 10.0
# Voted turns, off: on real low-overlap pairs their twins fit nearly as well and refused
# right poses, for none of the wrong ones (docs/ablation.md).
VOTED_PEAKS = 0  # translations tried a voted turn (0: no voted turns; 3 was measured)
VOTED_SHARE = 0.25  # ...each voted for by at least this share of the estimate's inliers
VOTED_ANGLES = {'+': np.pi / 2, '-': -np.pi / 2, 'h': np.pi}  # the turns voted on, by label
AXIS_BUNDLE_DEG = 10.0  # normals this close (either sign) make one direction's bundle
SECOND_AXIS_DEG = 20.0  # a second direction is at least 90 less this from the first
AXIS_NORMALS = 400  # about this many of the overlap's normals find the directions
SYMMETRY_FIT = 0.5  # a turn is a symmetry of a map when it puts half of the map on itself
SYMMETRY_START = 1 / 3  # ...and it is refined only when it starts with a third there
SYMMETRY_POINTS = 2000  # about this many of the map's points judge a turn
ITERATIONS = 5
STRIDE = 2
# The verdict's limits (:func:`worth_refining`, :func:`settled_apart`, :func:`fits_as_well`,
# :func:`clear_of_free_space`), chosen on real RGB-D pairs (docs/ablation.md);
# ``python -m bench.studies.fit`` regenerates them from the study's records.
PROMISING = 0.45
APART = 4.0
MAX_VIOLATION = 0.1
OVERLAP_RATIO = 1.25


def worth_refining(start_fitness: float, fitness: float, promising: float = PROMISING) -> bool:
    """Tell whether a rival is refined: its start fits ``promising`` times the estimate's."""
    return start_fitness >= promising * fitness


def settled_apart(rotation_deg: float, translation_m: float, voxel_size: float,
                  min_rotation_deg: float, apart: float = APART) -> bool:
    """Tell whether a rival settled this far from the estimate is another pose, not it."""
    return rotation_deg > min_rotation_deg or translation_m > apart * voxel_size


def fits_as_well(fitness: float, estimate_fitness: float, ratio: float = OVERLAP_RATIO) -> bool:
    """Tell whether a rival's fitness is at least ``1 / ratio`` of the estimate's."""
    return fitness * ratio >= estimate_fitness


def clear_of_free_space(violation: float, limit: float = MAX_VIOLATION) -> bool:
    """Tell whether a rival stacks few enough surfaces in free space (NaN: not measured)."""
    return not violation > limit


def rival_starts(fs: CloudFeatures, ft: CloudFeatures, T: np.ndarray, distance: float,
                 voxel_size: float, candidates: Sequence[np.ndarray] = (),
                 matches: tuple[np.ndarray, np.ndarray] | None = None, tau: float = 0.0,
                 min_votes: int = 3) -> list[tuple[str, np.ndarray]]:
    """
    Return the structured rivals' starting poses of ``T``, each with its name.

    In this order: ``flip0..2``, ``slide1``/``slide-1``, ``turn0..2`` with ``+``/``-``,
    ``candidate1..`` (``candidates``: the other distinct poses the correspondences support),
    and with ``matches`` (the correspondences' source and target points) the voted turns
    ``voted<axis><+|-|h><peak>`` (votes within ``tau`` of each other agree; at least
    ``min_votes`` of them). See the module doc.
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
    if matches is not None and VOTED_PEAKS > 0 and tau > 0:
        starts.extend(voted_turns(T, dominant_axes(normals), *matches, tau, min_votes))
    return starts


def dominant_axes(normals: np.ndarray) -> np.ndarray:
    """
    Return three orthonormal directions (columns) along which most normals face.

    The first is the densest bundle of normals (within ``AXIS_BUNDLE_DEG``, either sign),
    the second the densest of those across it (within ``SECOND_AXIS_DEG`` of a right angle
    to the first), the third their cross product: a room's floor and two walls. The
    eigenvectors of the normals' scatter are those directions only when one surface
    dominates; a corner that shows floor and two walls alike scatters its normals evenly.
    """
    n = normals[::max(1, len(normals) // AXIS_NORMALS)]
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    near = np.abs(n @ n.T) > np.cos(np.deg2rad(AXIS_BUNDLE_DEG))
    first = _bundle_axis(n, near, np.arange(len(n)))
    across = np.flatnonzero(np.abs(n @ first) < np.sin(np.deg2rad(SECOND_AXIS_DEG)))
    if len(across) < 3:
        across = np.flatnonzero(np.abs(n @ first) < 0.9)  # no second surface: any across
    if len(across) == 0:  # one plane: its normal, and any two directions across it
        return np.linalg.svd(first[None, :])[2].T
    second = _bundle_axis(n, near, across)
    second = second - (second @ first) * first
    second /= np.linalg.norm(second)
    return np.stack([first, second, np.cross(first, second)], axis=1)


def _bundle_axis(n: np.ndarray, near: np.ndarray, among: np.ndarray) -> np.ndarray:
    """Return the mean direction of the densest bundle of ``n[among]`` (signs aligned)."""
    centre = among[int(np.argmax(near[among][:, among].sum(axis=1)))]
    members = n[near[centre]]
    signs = np.where(members @ n[centre] < 0, -1.0, 1.0)
    axis = (members * signs[:, None]).mean(axis=0)
    return axis / np.linalg.norm(axis)


def voted_turns(T: np.ndarray, axes: np.ndarray, source: np.ndarray, target: np.ndarray,
                tau: float, min_votes: int = 3) -> list[tuple[str, np.ndarray]]:
    """
    Return ``T``'s rotation turned about each of ``axes``, with the translations voted for.

    Each correspondence (``source[i]``, ``target[i]``) votes ``target - R source`` for the
    turned rotation ``R``. The votes are counted in cubes of side ``tau``; the
    ``VOTED_PEAKS`` fullest cubes, each at least ``2 tau`` from those before it, give the
    translations: the mean of the votes within ``tau`` of their cube's mean, when at least
    ``min_votes`` votes are that close (a twin pose that few correspondences support is
    left to the other starts: refining every weak peak costs more than it finds).
    """
    starts = []
    for i, axis in enumerate(axes.T):
        for label, angle in VOTED_ANGLES.items():
            R = Rotation.from_rotvec(angle * axis).as_matrix() @ T[:3, :3]
            votes = target - source @ R.T
            _, cube, counts = np.unique(_cube_keys(votes, tau), return_inverse=True,
                                        return_counts=True)
            chosen: list[np.ndarray] = []
            for c in np.argsort(-counts, kind='stable')[:4 * VOTED_PEAKS]:
                if 2 * counts[c] < min_votes or len(chosen) == VOTED_PEAKS:
                    break  # a bound on the work: a peak spread thinner than this is missed
                centre = votes[cube == c].mean(axis=0)
                if any(np.linalg.norm(centre - t) < 2 * tau for t in chosen):
                    continue
                near = np.linalg.norm(votes - centre, axis=1) <= tau
                if np.count_nonzero(near) < min_votes:
                    continue
                chosen.append(votes[near].mean(axis=0))
                start = np.eye(4)
                start[:3, :3], start[:3, 3] = R, chosen[-1]
                starts.append((f'voted{i}{label}{len(chosen) - 1}', start))
    return starts


def _cube_keys(points: np.ndarray, side: float) -> np.ndarray:
    """Return one integer a cube of ``side`` for each point (equal keys: the same cube)."""
    cells = np.floor(points / side).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    return (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]


def _turned(T: np.ndarray, axis: np.ndarray, angle: float, centre: np.ndarray) -> np.ndarray:
    """Return ``T`` followed by a turn of ``angle`` radians about ``axis`` through ``centre``."""
    M = np.eye(4)
    M[:3, :3] = Rotation.from_rotvec(angle * axis).as_matrix()
    M[:3, 3] = centre - M[:3, :3] @ centre
    return M @ T


def settle(fs: CloudFeatures, ft: CloudFeatures, start: np.ndarray, coarse_distance: float,
           cfg: PipelineConfig) -> np.ndarray:
    """
    Return where a rival starting at ``start`` settles (4x4 source -> target, metres).

    The estimate's stages (the core's inlier threshold ``coarse_distance`` first when it is
    the larger, then the final correspondence distance), ``ITERATIONS`` each, point-to-plane
    on the target's normals whatever the estimate's refinement method, from every
    ``STRIDE``-th source point: a rival only has to show where it goes, not how precisely
    (its fitness is then judged on every point), and the target's k-d tree serves every
    rival.
    """
    final = cfg.refine.max_correspondence_distance_factor * cfg.voxel_size
    return staged_point_to_plane(fs.points[::STRIDE], ft.points, ft.normals, ft.tree, start,
                                 coarse_distance, final, ITERATIONS,
                                 cfg.refine.coarse_stage_tolerance)


def structured_rival(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
                     result: PipelineResult, cfg: PipelineConfig,
                     map_target: bool = False, workers: int = 1) -> Candidate | None:
    """
    Return the first plausible structured rival of ``result``'s estimate, or None.

    ``result`` has passed the gates (its ``fitness`` is set). 6-DoF pairs of sensor-frame
    clouds only: a 4-DoF estimate cannot turn about a horizontal axis (its yaw flips are
    what the correspondences' own rivals test); without the free-space test (clouds not in
    their sensor frames, or the gate off) a slide along a wall fits as well as the estimate
    whether or not it is right; and a map (``map_target``) was not measured.
    """
    if (cfg.core.motion_model == '4dof' or cfg.refine.method == 'none' or map_target
            or cfg.frontend.normal_orientation != 'origin'
            or cfg.gates.max_free_space_violation >= 1):
        return None
    v = cfg.voxel_size
    distance = cfg.refine.max_correspondence_distance_factor * v
    T = np.asarray(result.transform, dtype=np.float64)

    def judge(start: np.ndarray) -> Candidate | None:
        """Return the rival settled from ``start`` when it is plausible (see the module doc)."""
        if not worth_refining(
                evaluate_alignment(fs.points[::STRIDE], ft.tree, start, distance).fitness,
                result.fitness):
            return None
        R = settle(fs, ft, start, float(result.inlier_threshold), cfg)
        if not settled_apart(rotation_error_deg(R, T), translation_error(R, T), v,
                             cfg.candidate_min_rotation_deg):
            return None  # settled back onto the estimate: it is constrained there
        fitness = evaluate_alignment(fs.points, ft.tree, R, distance).fitness
        if not fits_as_well(fitness, result.fitness):
            return None
        if not clear_of_free_space(measured_free_space(fs, ft, R, cfg, map_target)):
            return None
        inliers = support(fs.points[corr.source_index], ft.points[corr.target_index], R,
                          float(result.inlier_threshold))
        return Candidate(R, int(np.count_nonzero(inliers)), fitness)

    # The starts are independent: judged side by side, the first plausible one in their
    # order is the rival, as if they were judged one after the other.
    others = [c.transform for c in result.candidates[1:]]
    matches = ((fs.points[corr.source_index], ft.points[corr.target_index]) if VOTED_PEAKS
               else None)  # only the voted turns read them
    min_votes = max(3, int(np.ceil(VOTED_SHARE * result.num_inliers)))
    starts = [start for _, start in rival_starts(fs, ft, T, distance, v, others, matches,
                                                 float(result.inlier_threshold), min_votes)]
    rivals = map_ordered(judge, starts, workers)
    return next((rival for rival in rivals if rival is not None), None)


def mark_ambiguous(result: PipelineResult, rival: Candidate) -> None:
    """Make ``rival`` the runner-up of ``result`` and flag the result ambiguous."""
    best = result.candidates[0]
    rival.ratio = rival.num_inliers / best.num_inliers if best.num_inliers else 0.0
    result.candidates.insert(1, rival)
    result.ambiguous = True
    if rival.num_inliers > 0:
        result.runner_up_ratio = best.num_inliers / rival.num_inliers


def map_symmetries(prepared: PreparedMap, cfg: PipelineConfig) -> list[np.ndarray]:
    """
    Return the turns of a map that put it onto itself (4x4 each, map frame), found once.

    A room, a hall or a box-like store whose floor plan is near-square looks alike turned a
    quarter or half of the way about its vertical: every pose in it has such twins, whatever
    the scans show of the room. The map is turned by 90, -90 and 180 degrees about each
    principal axis of its normals' scatter, through its centroid (a symmetric room's centre);
    a turn that puts at least ``SYMMETRY_START`` of about ``SYMMETRY_POINTS`` evenly spread
    map points back on the map is refined map onto map (point-to-plane), and one that then
    puts at least ``SYMMETRY_FIT`` of them there is a symmetry. Kept on ``prepared``.
    """
    if prepared.symmetries is not None:
        return prepared.symmetries
    ft = prepared.features
    final = cfg.refine.max_correspondence_distance_factor * cfg.voxel_size
    points = ft.points[::max(1, len(ft.points) // SYMMETRY_POINTS)]
    found = []
    if len(points) >= 6:
        centre = ft.points.mean(axis=0)
        _, axes = np.linalg.eigh(ft.normals.T @ ft.normals)
        for axis in axes.T:
            for angle in (np.pi / 2, -np.pi / 2, np.pi):
                start = _turned(np.eye(4), axis, angle, centre)
                if evaluate_alignment(points, ft.tree, start, final).fitness < SYMMETRY_START:
                    continue
                S = staged_point_to_plane(points, ft.points, ft.normals, ft.tree, start,
                                          SLIDE * cfg.voxel_size, final, 2 * ITERATIONS,
                                          cfg.refine.coarse_stage_tolerance)
                if evaluate_alignment(points, ft.tree, S, final).fitness >= SYMMETRY_FIT:
                    found.append(S)
    prepared.symmetries = found
    return found
