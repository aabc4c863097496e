"""
Algorithm 1: compatibility graph + accelerated guided sampling (Remote Sensing 2024, 16, 2789).

Read :func:`register_correspondences` top to bottom: it is the paper's algorithm. Its steps
carry one numbering, shared by the code, its docstrings and docs/method.md:

1. compatibility graph;
2. minimal compatible subsets (graph edge sampling, then graph vertex sampling);
3. hypotheses (closed-form fits of minimal subsets, pre-screen, scores);
4. preference lists and the intersection kernel K;
5. guided sampling;
6. max_up (refreshes of K);
7. stopping (the P1 and P2 bounds, the significance test);
8. final re-fit;

then the measurements its validity is decided on (ours; the decision is
:mod:`cgags_ros.validity`'s). :class:`~.search.Search` holds the sampling state of
the two stages, :mod:`.motion` what a minimal subset is (a 6-DoF triangle, a 4-DoF edge).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from .blas import with_single_blas_thread
from .hypotheses import refit
from .motion import motion_model
from .result import RegistrationResult
from .search import Search
from .yaw import GravityFrame, measure_tilt, vertical_offsets
from ..config import fields
from ..config.core import CoreConfig
from ..coordinates import local_origin, moved, to_caller
from ..errors import DegenerateCorrespondencesError, InvalidInputError
from ..geometry import cross_spread, spread
from ..parallel import DEFAULT_WORKERS
from ..refusal import RefusalCode
from ..timing import timed
from ..validity.consensus import consensus_refusal, no_graph_refusal, no_model_refusal

# The compatibility threshold delta in units of the point resolution pr (paper: 10), and
# delta / tau when only an inlier threshold (no resolution) is given: the paper's 10 / 6.
COMPATIBILITY_FACTOR = 10.0
COMPATIBILITY_TO_INLIER = 10.0 / 6.0
# INFERRED: graph edges whose source pair is closer than this many tau are dropped (short
# edges constrain rotation poorly); 0 keeps all.
MIN_PAIR_DISTANCE_FACTOR = 0.0
# Step 8: the final re-fit is repeated while its inlier set changes, at most this often.
REFIT_ITERATIONS = 10


@with_single_blas_thread
def register_correspondences(src, dst, *, inlier_threshold: float | None = None,
                             resolution: float | None = None, config: CoreConfig | None = None,
                             seed: int = 0, workers: int = DEFAULT_WORKERS
                             ) -> RegistrationResult:
    """
    Estimate the rigid transform mapping ``src`` onto ``dst`` from putative correspondences.

    :param src, dst: (N, 3) arrays in metres; row i of each is one putative correspondence
        (most may be wrong).
    :param inlier_threshold: tau in metres. Default: ``inlier_threshold_factor * resolution``.
    :param resolution: point resolution pr in metres (mean nearest-neighbour distance of the
        clouds the keypoints come from). With only ``resolution``, tau = 6 pr and the
        compatibility threshold delta = 10 pr, as in the paper.
    :param config: :class:`CoreConfig`; defaults are the paper's parameters. With
        ``motion_model='4dof'`` the rotation is a yaw about ``gravity_axis`` (roll and
        pitch exactly zero) and the minimal subsets are compatible edges.
    :param seed: random seed; the result is deterministic for a given seed.
    :param workers: threads for the compatibility graph (the result does not depend on it).
    :returns: :class:`RegistrationResult` with ``transform`` (source -> target), ``inliers``,
        ``refusal`` (None when valid; ``valid``/``reason`` read it), the measurements it
        was decided on, and per-stage ``stats``/``timings``.
    :raises InvalidInputError: wrong shapes, mismatched rows, NaN/Inf, missing thresholds.
    :raises DegenerateCorrespondencesError: fewer than 3 correspondences (4-DoF: 2), or all
        source or all target points identical or collinear (4-DoF: on one vertical line);
        a rigid transform is then undetermined.
    :raises InvalidConfigError: a configuration value is out of range (a zero gravity axis).
    """
    start = time.perf_counter()
    cfg = fields.validate(dataclasses.replace(config) if config else CoreConfig())
    motion = motion_model(cfg.motion_model)
    yaw_only = cfg.motion_model == '4dof'
    src, dst = _check_correspondences(src, dst, motion.size)
    # Far coordinates (UTM, ECEF) are worked on near zero, and the transform given back.
    source_origin, target_origin = local_origin(src), local_origin(dst)
    src, dst = moved(src, source_origin), moved(dst, target_origin)
    tau, delta = _thresholds(cfg, inlier_threshold, resolution)
    result = RegistrationResult(num_correspondences=len(src), inlier_threshold=tau,
                                compatibility_threshold=delta)
    # 4-DoF: both clouds in the gravity frame, where the rotation is a yaw about z.
    frame = GravityFrame(cfg.gravity_axis) if yaw_only else None
    if frame:
        src, dst = frame.to_gravity(src), frame.to_gravity(dst)
        _check_horizontal_spread(src, dst)
        # Sorted by the vertical offset they imply, vertical partners are contiguous.
        order = np.argsort(vertical_offsets(src, dst), kind='stable')
        src, dst = src[order], dst[order]

    # Step 1. Compatibility graph: length consistency within delta (4-DoF: and the
    # vertical offsets).
    with timed(result.timings, 'compatibility_graph'):
        graph = motion.compatibility_graph(src, dst, delta, MIN_PAIR_DISTANCE_FACTOR * tau,
                                           workers)
    result.stats.update(graph_edges=graph.num_edges, graph_density=graph.density)
    if graph.num_edges == 0:
        return result.finish(start, no_graph_refusal(delta))

    search = Search(src, dst, graph, motion, cfg, tau, delta, np.random.default_rng(seed))
    while True:
        # Steps 2-3. Minimal compatible subsets (graph edge and vertex sampling) and their
        # hypotheses, until the P1 bound (step 7).
        with timed(result.timings, 'compatible_sampling'):
            search.compatible_stage()
        # Steps 4-6. Preference lists, the intersection kernel K and guided sampling around
        # the best model, until the P2 bound (step 7); not once stage one has ruled out
        # any significant model (nothing valid is left to refine).
        if cfg.guided_sampling and search.best_inliers is not None and not search.futile:
            with timed(result.timings, 'guided_sampling'):
                search.guided_stage()
        # Step 7. Stop on a model that stands out from chance; otherwise explore again with
        # compatible sampling (until the caps).
        if search.significant() or search.exhausted() or search.fixed:
            break
        search.restarts += 1
    result.num_hypotheses = search.num_hypotheses
    result.stats.update(search.report())
    if search.best_inliers is None:
        return result.finish(start, no_model_refusal(search.stats['rejected_collinear'],
                                                     yaw_only))

    # Step 8. Final least-squares re-fit on the inliers of the best hypothesis.
    with timed(result.timings, 'refit'):
        T, inliers, done = refit(src, dst, search.best_T, tau, REFIT_ITERATIONS,
                                 *motion.refit_solver)
        result.stats['refits'] = done
    result.transform, result.inliers = T, inliers
    # What the validity of the result is decided on (cgags_ros.validity): the consensus'
    # size, shape and significance (step 7's test), and in 4-DoF mode the tilt.
    result.chance_level, result.runner_up = search.chance_level(), search.runner_up(inliers)
    result.inlier_spread = _inlier_spread(src[inliers], yaw_only)
    if frame:
        # 4-DoF: levelled input? The best 6-DoF fit of the inliers measures the tilt.
        result.tilt_deg = measure_tilt(src, dst, inliers, tau, REFIT_ITERATIONS)
        result.transform, result.inliers = frame.from_gravity(T), np.sort(order[inliers])
    result.transform = to_caller(result.transform, source_origin, target_origin)
    return result.finish(start, consensus_refusal(result, cfg))


# --- helpers ------------------------------------------------------------------------------------
def _check_correspondences(src, dst, minimum: int) -> tuple[np.ndarray, np.ndarray]:
    try:
        src = np.asarray(src, dtype=np.float64)
        dst = np.asarray(dst, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f'correspondences must be numeric (N, 3) arrays: {exc}') from exc
    for name, a in (('src', src), ('dst', dst)):
        if a.ndim != 2 or a.shape[1] != 3:
            raise InvalidInputError(f'{name} must have shape (N, 3), got {a.shape}')
    if len(src) != len(dst):
        raise InvalidInputError(
            f'src and dst must have the same number of rows (one correspondence per row), '
            f'got {len(src)} and {len(dst)}')
    bad = ~(np.isfinite(src).all(axis=1) & np.isfinite(dst).all(axis=1))
    if bad.any():
        rows = np.flatnonzero(bad)
        raise InvalidInputError(
            f'{len(rows)} correspondence(s) contain NaN or Inf (first rows: {rows[:5].tolist()}); '
            'drop non-finite points before matching')
    if len(src) < minimum:
        model = 'a rigid transform' if minimum == 3 else 'a 4-DoF (yaw + translation) transform'
        raise DegenerateCorrespondencesError(
            f'need at least {minimum} correspondences for {model}, got {len(src)}')
    for name, a in (('source', src), ('target', dst)):
        s = spread(a)
        if s[0] <= 1e-12 * max(1.0, np.abs(a).max()):
            raise DegenerateCorrespondencesError(f'all {name} points are identical')
        if minimum == 3 and s[1] <= 1e-9 * s[0]:
            raise DegenerateCorrespondencesError(
                f'all {name} points are collinear: the rotation about their line is '
                'undetermined', code=RefusalCode.COLLINEAR)
    return src, dst


def _check_horizontal_spread(src: np.ndarray, dst: np.ndarray) -> None:
    """Raise when all points of a cloud lie on one vertical line (gravity frame): no yaw."""
    for name, a in (('source', src), ('target', dst)):
        s = spread(a)
        if spread(a[:, :2])[0] <= 1e-9 * s[0]:
            raise DegenerateCorrespondencesError(
                f'all {name} points lie on one vertical line (along the gravity axis): the '
                'yaw about it is undetermined', code=RefusalCode.COLLINEAR)


def _thresholds(cfg: CoreConfig, tau: float | None, pr: float | None) -> tuple[float, float]:
    for name, v in (('inlier_threshold', tau), ('resolution', pr)):
        if v is not None and not (np.isfinite(v) and v > 0):
            raise InvalidInputError(
                f'{name} must be a positive finite number of metres, got {v!r}')
    if tau is None and pr is None:
        raise InvalidInputError(
            'give inlier_threshold (metres) or resolution (the point resolution pr in metres)')
    if tau is None:
        tau = cfg.inlier_threshold_factor * pr
    if pr is not None:
        delta = COMPATIBILITY_FACTOR * pr
    else:
        delta = COMPATIBILITY_TO_INLIER * tau
    return float(tau), float(delta)


def _inlier_spread(pts: np.ndarray, yaw_only: bool) -> float:
    """
    Return the inliers' RMS spread (metres) across the line about which they leave a rotation.

    6-DoF: across their main axis; 4-DoF (gravity frame): across the vertical, about which
    the yaw turns. NaN with fewer than 3 inliers.
    """
    if len(pts) < 3:
        return float('nan')
    if yaw_only:
        horizontal = pts[:, :2] - pts[:, :2].mean(axis=0)
        return float(np.sqrt(np.mean(np.sum(horizontal ** 2, axis=1))))
    return cross_spread(pts)
