"""
Regenerated correspondences: poses proposed by local re-matching, judged by what survives ICP.

The putative correspondences come from one global match of FPFH descriptors: on a pair
with little overlap few of them are right, and the core's best consensus may be a wrong
pose whose support is as large as the right one's. Around a right correspondence the two
clouds show the same surface, so matching descriptors again inside a small sphere about
each end (a few hundred points each, instead of the whole cloud) finds many more right
matches there (the idea of Regor, CVPR 2025, for one seed at a time).

This stage:

1. ranks the correspondences by second-order compatibility (for each, the compatible
   triangles it closes among the best-connected ones: SC² of SC²-PCR) and keeps up to
   :data:`SEEDS` of the best (among the :data:`RANKED` of highest compatibility degree),
   at least :data:`SEED_SPACING` voxels apart;
2. for each seed, re-matches the descriptors of the source points within
   :data:`RADIUS` voxels of its source point against those of the target points within
   the same radius of its target point (the nearest, kept when the source point is among
   the three nearest to it: a relaxed mutual check), keeps the matches whose distance to
   the seed agrees in both clouds (within the compatibility threshold), and fits a pose to
   them (a least-squares fit repeated on the matches within tau);
3. settles every distinct proposed pose (or the ``regenerate.judged`` that the most
   original correspondences support as proposed), and the core's estimate, alike
   (:func:`~.settle.settle`, :data:`~.settle.PROPOSAL`: a short point-to-plane ICP on a
   sample of the source), and counts the **original** correspondences within tau of each.

A wrong pose supported by a chance cluster of correspondences loses them as ICP settles
it on the surfaces; a right pose keeps them. The proposals distinct from the estimate
contend for its place: the contender with the largest support that passes the free-space
gate replaces the estimate when its support exceeds the estimate's.
The replacement is judged as the core's estimate is: its inliers are the original
correspondences' (never the regenerated matches, which cluster around their seeds and would
fool the chance level), its chance level is the core's, and its best distinct alternative
is the largest support of the other poses, counted the same way.

6-DoF pairs of clouds only (not a map, not 4-DoF); ``regenerate.enabled``. Measured in
docs/method.md and docs/benchmarks_3dmatch.md.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .candidates import distinct
from .settle import Pair, PROPOSAL, settle, Settled, support
from ..config.pipeline import PipelineConfig
from ..frontend.features import CloudFeatures
from ..frontend.matching import Correspondences
from ..geometry import cross_spread
from ..parallel import map_ordered
from ..registration import RegistrationResult
from ..registration.cgags import MIN_PAIR_DISTANCE_FACTOR, REFIT_ITERATIONS
from ..registration.compatibility import build_compatibility_graph
from ..registration.hypotheses import refit
from ..registration.rigid import kabsch, residuals
from ..validity import passes_free_space
from ..validity.consensus import consensus_refusal

RELAXED_RANK = 3  # a local match is kept when its source point ranks below this for its target
MIN_MATCHES = 4  # a sphere proposes a pose from at least this many consistent matches
FIT_ROUNDS = 5  # least-squares fits of a sphere's pose, each on the matches within tau
SEEDS = 60  # seed correspondences (highest second-order compatibility, spread apart)
SEED_SPACING = 2.0  # seeds are at least this many voxel sizes apart in the source
RANKED = 1000  # correspondences (highest compatibility degree) among which seeds are ranked
RADIUS = 6.0  # the local spheres' radius, in voxel sizes


def seed_rows(src: np.ndarray, dst: np.ndarray, delta: float, min_pair_distance: float,
              cfg: PipelineConfig, workers: int = 1) -> np.ndarray:
    """
    Return the correspondences' rows chosen as seeds, best first (step 1 of the module doc).

    :param src, dst: (N, 3) corresponding points; ``delta`` the core's compatibility
        threshold and ``min_pair_distance`` its shortest pair, metres.
    """
    graph = build_compatibility_graph(src, dst, delta, min_pair_distance, workers)
    top = np.argsort(-graph.degree, kind='stable')[:RANKED]
    top = np.sort(top[graph.degree[top] > 0])
    if len(top) == 0:
        return np.zeros(0, np.int64)
    A = graph.adjacency(top).astype(np.float32)
    closed = np.einsum('ij,ij->i', A @ A, A)  # compatible triangles through each row
    ranked = top[np.argsort(-closed, kind='stable')]
    spacing = SEED_SPACING * cfg.voxel_size
    chosen: list[int] = []
    for row in ranked:
        if len(chosen) >= SEEDS:
            break
        if not chosen or np.min(np.linalg.norm(src[chosen] - src[row], axis=1)) > spacing:
            chosen.append(int(row))
    return np.asarray(chosen, dtype=np.int64)


def local_matches(fs: CloudFeatures, ft: CloudFeatures, p: np.ndarray, q: np.ndarray,
                  radius: float, delta: float) -> tuple[np.ndarray, np.ndarray]:
    """
    Return (source rows, target rows) re-matched inside the spheres about ``p`` and ``q``.

    Step 2 of the module doc: descriptors matched between the two spheres only, kept when
    mutual within :data:`RELAXED_RANK` and consistent with the seed's own distances.
    """
    rows_s = np.asarray(fs.tree.query_ball_point(p, radius), dtype=np.int64)
    rows_t = np.asarray(ft.tree.query_ball_point(q, radius), dtype=np.int64)
    if len(rows_s) < MIN_MATCHES or len(rows_t) < MIN_MATCHES:
        return rows_s[:0], rows_t[:0]
    ds, dt = fs.descriptors[rows_s], ft.descriptors[rows_t]
    squared = ((ds * ds).sum(axis=1)[:, None] + (dt * dt).sum(axis=1)[None, :]
               - 2.0 * ds @ dt.T)
    nearest = squared.argmin(axis=1)
    mine = squared[np.arange(len(rows_s)), nearest]
    rank = np.count_nonzero(squared[:, nearest] < mine[None, :], axis=0)
    keep = rank < RELAXED_RANK
    i, j = rows_s[keep], rows_t[nearest[keep]]
    agree = np.abs(np.linalg.norm(fs.points[i] - p, axis=1)
                   - np.linalg.norm(ft.points[j] - q, axis=1)) < delta
    return i[agree], j[agree]


def local_pose(a: np.ndarray, b: np.ndarray, tau: float) -> np.ndarray | None:
    """Return the pose fitted to matches ``a -> b`` (refitted on those within tau), or None."""
    inside = np.ones(len(a), dtype=bool)
    T = None
    for _ in range(FIT_ROUNDS):
        if np.count_nonzero(inside) < 3:
            return None
        T = kabsch(a[inside], b[inside])
        now = residuals(T, a, b) < tau
        if (now == inside).all():
            break
        inside = now
    return T if np.count_nonzero(inside) >= 3 else None


def proposed_poses(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
                   core: RegistrationResult, cfg: PipelineConfig,
                   workers: int = 1) -> list[np.ndarray]:
    """Return the distinct poses the seeds' spheres propose (steps 1 and 2), in seed order."""
    src, dst = fs.points[corr.source_index], ft.points[corr.target_index]
    tau, delta = core.inlier_threshold, core.compatibility_threshold
    seeds = seed_rows(src, dst, delta, MIN_PAIR_DISTANCE_FACTOR * tau, cfg, workers)
    radius = RADIUS * cfg.voxel_size
    poses: list[np.ndarray] = []
    for s in seeds:
        i, j = local_matches(fs, ft, src[s], dst[s], radius, delta)
        if len(i) < MIN_MATCHES:
            continue
        T = local_pose(fs.points[i], ft.points[j], tau)
        if T is not None and all(distinct(T, other, cfg) for other in poses):
            poses.append(T)
    return poses


def best_supported(poses: list[np.ndarray], src: np.ndarray, dst: np.ndarray, tau: float,
                   keep: int) -> list[np.ndarray]:
    """Return the ``keep`` poses that most correspondences support within ``tau`` (0: all)."""
    if keep == 0 or len(poses) <= keep:
        return poses
    counts = [np.count_nonzero(support(src, dst, T, tau)) for T in poses]
    return [poses[k] for k in np.argsort(-np.asarray(counts), kind='stable')[:keep]]


def settled_support(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
                    starts: list[np.ndarray], tau: float, cfg: PipelineConfig,
                    workers: int = 1) -> list[Settled]:
    """
    Return each start settled (step 3), its support counted.

    The support is the count of the original correspondences within ``tau`` of the settled
    pose; the starts settle side by side (their ICP runs outside the GIL).
    """
    pair = Pair(fs, ft, cfg, correspondences=(fs.points[corr.source_index],
                                              ft.points[corr.target_index]), tau=tau)
    return map_ordered(lambda start: settle(pair, start, tau, PROPOSAL).measured('support'),
                       starts, workers)


def regenerates(core: RegistrationResult, cfg: PipelineConfig, map_target: bool) -> bool:
    """
    Tell whether the regenerated correspondences run (this module).

    6-DoF pairs of clouds, when enabled; by default (``when: refused``) only for an estimate
    the core refuses, a collinear consensus included: the stage's proposals put right more
    of those than the gates settle.
    """
    if not (cfg.regenerate.enabled and not map_target and cfg.core.motion_model == '6dof'
            and cfg.refine.method != 'none'):
        return False
    return cfg.regenerate.when == 'always' or core.refusal is not None


def regenerated_estimate(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
                         core: RegistrationResult, cfg: PipelineConfig,
                         workers: int = 1) -> RegistrationResult | None:
    """
    Return the core's result with a proposed pose in its place, or None to keep the estimate.

    Steps 1 to 3 of the module doc. The returned result's transform is the winner's
    short-refined pose re-fitted on the original correspondences within tau (the core's
    step 8), its inliers those correspondences, and its refusal decided as the core's.
    """
    poses = proposed_poses(fs, ft, corr, core, cfg, workers)
    if not poses:
        return None
    tau = core.inlier_threshold
    src, dst = fs.points[corr.source_index], ft.points[corr.target_index]
    poses = best_supported(poses, src, dst, tau, cfg.regenerate.judged)
    estimate, *proposals = settled_support(fs, ft, corr, [core.transform, *poses], tau, cfg,
                                           workers)
    contenders = [s for s in proposals if distinct(s.transform, estimate.transform, cfg)]
    # The best supported contender that passes the free-space gate (NaN: no test), best first.
    best = None
    for s in sorted(contenders, key=lambda s: -s.support):
        if s.support <= estimate.support:
            return None
        if passes_free_space(s.free_space, cfg):
            best = s
            break
    if best is None:
        return None
    T, inliers, _ = refit(src, dst, best.transform, tau, REFIT_ITERATIONS)
    others = [s.support for s in [estimate, *contenders]
              if distinct(s.transform, best.transform, cfg)]
    replaced = dataclasses.replace(
        core, transform=T, inliers=inliers, runner_up=max(others, default=0),
        inlier_spread=cross_spread(src[inliers]) if len(inliers) >= 3 else float('nan'),
        stats={**core.stats, 'regenerated_from': len(poses)},  # how many poses competed
        timings=dict(core.timings))
    replaced.refusal = consensus_refusal(replaced, cfg.core)
    return replaced
