"""
Clouds in, result out: the one registration path of the node, the CLIs and benchmarks.

``register_clouds(source, target)`` runs: input checks -> voxel downsampling -> normals ->
FPFH -> mutual-nearest-neighbour correspondences -> the CGAGS core (global, no initial
guess) -> where the core refuses its estimate, poses proposed by re-matching the
descriptors locally (:mod:`.regenerate`) -> optional ICP/GICP refinement -> validity
gating with the candidates and twins settled (:mod:`.settle`) -> against a map, an accepted
scan of few voxels refined once more with its own points (:mod:`.polish`). An estimate the
core still refuses is refined (``refine.refused``) but not gated: nothing after the core
lifts its refusal. Numpy in, numpy out; transforms are 4x4 source->target
(``p_target = R p_source + t``), metres. With ``core.motion_model='4dof'`` the core, the
refinement and the gates solve yaw + translation only (roll and pitch stay zero about the
gravity axis) and a tilt between the clouds is reported.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable
import warnings

import numpy as np

from .cache import cached_features
from .candidates import rank_candidates, search_candidates, settle_candidates
from .confidence import capped, features, probability
from .covariance import loosest_sigma, result_covariance, with_confidence
from .gates import measure, measure_shared_surface
from .hint import Hint
from .locate import locate
from .map import matches_config, PreparedMap
from .polish import polished
from .regenerate import regenerated_estimate, regenerates
from .result import PipelineResult
from .twins import add_twin, find_twin
from ..config import fields
from ..config.frontend import MAP_TARGET_SENSOR
from ..config.pipeline import PipelineConfig
from ..coordinates import (coarse_coordinates, CoarseCoordinatesWarning, local_origin, moved,
                           sensor_at_origin)
from ..errors import (DegenerateCorrespondencesError, EmptyCloudError, InvalidConfigError,
                      InvalidInputError)
from ..frontend.features import CloudFeatures, finite_points
from ..frontend.keypoints import match_keypoints
from ..frontend.matching import Correspondences
from ..frontend.refine import Alignment, refine_transform
from ..geometry import cross_spread
from ..parallel import DEFAULT_WORKERS, in_background
from ..refusal import Refusal, RefusalCode as Code
from ..registration import register_correspondences, RegistrationResult, single_blas_thread
from ..timing import timed
from ..validity import (ambiguity_refusal, confidence_refusal, gate_refusal,
                        line_cloud_refusal, outnumbered, said_over_ambiguity,
                        shared_surface_refusal, still_ambiguous, uncertainty_refusal, unsettled)


def register_clouds(source: np.ndarray, target: np.ndarray | PreparedMap, *,
                    voxel_size: float | None = None,
                    config: PipelineConfig | None = None,
                    source_sensor: np.ndarray | None = None,
                    target_sensor: np.ndarray | None = None,
                    hint: Hint | None = None) -> PipelineResult:
    """
    Register ``source`` onto ``target`` with no initial guess.

    :param source, target: (N, 3) points in metres, each in its own frame; non-finite rows
        are dropped. ``target`` may also be a map's :class:`~.map.PreparedMap`
        (:func:`~.map.load_map`), whose features are then used as they are; the scan is
        then registered against its best places (:mod:`.locate`), and the result is in the
        map frame as against the whole map.
    :param voxel_size: metres; overrides ``config.voxel_size`` (every radius derives from
        it).
    :param config: :class:`PipelineConfig`; defaults when None.
    :param source_sensor, target_sensor: (3,) the position of the sensor that saw a cloud,
        in that cloud's frame (metres), for a cloud not in its sensor frame (a scan in UTM
        and its GNSS position). None (the default): ``config.frontend``'s ``source_sensor``,
        ``target_sensor``, and where that is unset too the frame's origin when the cloud is
        within 1 km of it, else unknown (:mod:`cgags_ros.coordinates`). A map target takes
        none. Clouds anywhere up to 10^7 m from their origins register as near it; the
        result is in the caller's frames.
    :param hint: with a map target, where the source's sensor is believed to be
        (:class:`~.hint.Hint`, map frame): only the places it covers are searched, and a
        hint that covers none refuses the scan as ``no_shared_surface``. A map without
        places (:meth:`~.map.PreparedMap.whole`) is searched whole, hint or not.
    :returns: a :class:`PipelineResult`. Its ``refusal`` (a code and a message; ``valid``
        False) says why not to trust it when the clouds are too small after downsampling,
        yield too few or degenerate correspondences, when the estimate fails a validity
        check (core inliers, chance-level inliers, degenerate overlap geometry, fitness,
        free space; decided by :mod:`cgags_ros.validity`) or is ambiguous (see
        :mod:`.candidates`). ``candidates`` holds up to ``num_candidates`` distinct poses,
        best first. Never raises for such data-dependent failures.
    :raises InvalidInputError: when an array is not (N, 3) numeric, or a hint is given
        without a map target.
    :raises EmptyCloudError: when a cloud has no finite point.
    :raises InvalidConfigError: when a configuration value is out of range, a prepared
        map was computed with other feature settings than ``config``'s, or is given a sensor.
    """
    cfg = _effective_config(config, voxel_size)
    source_sensor = cfg.frontend.source_sensor if source_sensor is None else source_sensor
    target_sensor = cfg.frontend.target_sensor if target_sensor is None else target_sensor
    src = finite_points(source, 'source')
    if hint is not None and not isinstance(target, PreparedMap):
        raise InvalidInputError('a hint places the source in a map: the target must be a '
                                'prepared map (load_map)')
    if isinstance(target, PreparedMap) and target_sensor is not None:
        raise InvalidConfigError(MAP_TARGET_SENSOR)
    if isinstance(target, PreparedMap) and target.places is not None:
        return locate(src, target, cfg, hint, source_sensor, lambda part, c: register_clouds(
            src, part, config=c, source_sensor=source_sensor))
    if isinstance(target, PreparedMap):
        dst, target_origin = target, target.origin
    else:
        dst = finite_points(target, 'target')
        target_origin = local_origin(dst, target_sensor)
        _warn_coarse(dst, cfg.voxel_size, 'target')
    _warn_coarse(src, cfg.voxel_size, 'source')
    source_origin = local_origin(src, source_sensor)
    local_target = dst if isinstance(dst, PreparedMap) else moved(dst, target_origin)
    # BLAS held to one thread: idle OpenBLAS workers would spin into Open3D's time; the
    # compiled FPFH, descriptor index and graph run on the package's own threads.
    with single_blas_thread():
        result = _register_clouds(
            moved(src, source_origin), local_target, cfg, DEFAULT_WORKERS,
            sensor_at_origin(source_origin, source_sensor is not None),
            sensor_at_origin(target_origin, target_sensor is not None))
    return result.in_caller_frames(source_origin, target_origin)


def _warn_coarse(points: np.ndarray, voxel_size: float, name: str) -> None:
    message = coarse_coordinates(points, voxel_size, name)
    if message:
        warnings.warn(message, CoarseCoordinatesWarning, stacklevel=3)


def _judged(result: PipelineResult, fs: CloudFeatures, ft: CloudFeatures,
            cfg: PipelineConfig, start: float, refusal: Refusal | None,
            map_target: bool = False, overlap: Alignment | None = None) -> PipelineResult:
    """
    Finish a result that has an estimate: its covariance and confidence, then the verdict.

    ``refusal`` is the gates' (None when they pass); a confidence below ``min_confidence``
    refuses a 6-DoF pair's estimate the gates let through, and the covariance opens by the
    chance that the pose is wrong (:func:`~.covariance.with_confidence`). Against a map or in
    4-DoF mode the confidence is reported but decides nothing and the covariance is the
    overlap's alone: it was calibrated on 6-DoF pairs of scans, and a map's overlap and
    candidates, or a yaw-only search, read differently. ``overlap``: the gates' overlap of the
    final transform, when they measured one (the covariance's point pairs).
    """
    four_dof = cfg.core.motion_model == '4dof'
    result.covariance = result_covariance(
        result, fs.points, ft.points, ft.normals, ft.tree,
        cfg.refine.max_correspondence_distance_factor * cfg.voxel_size,
        cfg.core.gravity_axis if four_dof else None,
        None if overlap is None else (overlap.source_index, overlap.target_index))
    result.confidence = probability(features(result, cfg.gates.significance,
                                             2 if four_dof else 3))
    if refusal is not None:  # refused before the confidence: the pose may be right, not trusted
        result.confidence = capped(result.confidence, refusal.code.value)
    if map_target or four_dof:
        return result.finish(start, refusal)
    result.covariance = with_confidence(result.covariance, result.confidence, cfg.voxel_size)
    return result.finish(start, refusal
                         or confidence_refusal(result, cfg.gates.min_confidence)
                         or uncertainty_refusal(loosest_sigma(result.covariance), cfg))


def _register_clouds(src: np.ndarray, target: np.ndarray | PreparedMap, cfg: PipelineConfig,
                     workers: int, source_sensor: bool, target_sensor: bool) -> PipelineResult:
    """
    Register finite clouds near their local origins (a map's features are so already).

    ``source_sensor``, ``target_sensor``: whether a cloud's origin may be its sensor
    (:func:`~cgags_ros.coordinates.sensor_at_origin`); free space is judged from those views
    only.
    """
    start = time.perf_counter()
    v = cfg.voxel_size
    if isinstance(target, PreparedMap) and not matches_config(target, cfg):
        raise InvalidConfigError(
            f'the map {target.path} was prepared with other feature settings '
            f'({target.settings}) than this registration; load it again with this config')
    map_target = isinstance(target, PreparedMap)
    dst = None if map_target else target
    result = PipelineResult(voxel_size=v, map_info=target.info() if map_target else None)
    # The target's features (and its descriptor index) beside the source's: much of the
    # front end runs on one thread (downsampling, normals, the grids), so two clouds at
    # once fill both cores. Stage times are summed over the two clouds.
    target_timings: dict[str, float] = {}
    target_features = in_background(
        lambda: _target_features(target, dst, cfg, target_timings, workers), workers > 1)
    try:
        fs = cached_features(src, v, cfg.frontend, 'source', result.timings,
                             workers).with_sensor(source_sensor)
    except EmptyCloudError as exc:  # data too small for this voxel size: not a crash
        _target_or_error(target_features)
        return result.finish(start, exc.refusal)
    ft = _target_or_error(target_features)
    for stage, seconds in target_timings.items():
        result.timings[stage] = result.timings.get(stage, 0.0) + seconds
    if isinstance(ft, EmptyCloudError):
        return result.finish(start, ft.refusal)
    ft = ft.with_sensor(target_sensor)
    result.num_source_points, result.num_target_points = len(fs.points), len(ft.points)
    result.resolution = 0.5 * (fs.resolution + ft.resolution)
    refusal = (line_cloud_refusal(cross_spread(fs.points), 'source', v)
               or line_cloud_refusal(cross_spread(ft.points), 'target', v))
    if refusal:
        return result.finish(start, refusal)
    with timed(result.timings, 'matching'):
        corr = match_keypoints(fs.points, fs.descriptors, ft.descriptors, v, cfg.frontend,
                               workers, ft.descriptor_index(workers))
    result.stats.update(num_source_points=len(fs.points), num_target_points=len(ft.points))
    try:
        with timed(result.timings, 'registration'):
            core = _global_estimate(fs, ft, corr, result.resolution, cfg)
    except DegenerateCorrespondencesError as exc:
        result.num_correspondences = len(corr)
        return result.finish(start, exc.refusal)
    if regenerates(core, cfg, map_target):
        with timed(result.timings, 'regeneration'):
            replaced = regenerated_estimate(fs, ft, corr, core, cfg, workers)
        core = replaced or core
    _copy_core(core, result)
    result.inlier_source_points = fs.points[corr.source_index[core.inliers]]
    result.inlier_target_points = ft.points[corr.target_index[core.inliers]]
    left_to_gates = unsettled(core, cfg)  # a collinear consensus: the overlap may settle it
    if core.refusal and not left_to_gates:
        # The verdict is certain, but the refined pose is the better guess to report.
        if cfg.refine.refused:
            _refine(fs, ft, core, result, cfg, workers)
        refusal = _candidates(fs, ft, corr, result, cfg) or core.refusal
        if refusal.code in (Code.AMBIGUOUS, Code.CHANCE_LEVEL):  # or no shared surface?
            measure_shared_surface(fs, ft, result, cfg, map_target)
            refusal = shared_surface_refusal(result, cfg) or refusal
        return _judged(result, fs, ft, cfg, start, refusal, map_target)
    _refine(fs, ft, core, result, cfg, workers)
    # The candidate search reads only the core's estimate and the final transform, never
    # what the gates set: it runs beside them (both spend most of their time outside the
    # GIL, in compiled numba functions and k-d tree queries).
    searched = in_background(lambda: _search_candidates(fs, ft, corr, result, cfg), workers > 1)
    with timed(result.timings, 'validation'):
        overlap = measure(fs, ft, corr, result, cfg, map_target)
        refusal = gate_refusal(result, cfg, left_to_gates)
    found, result.timings['candidates'] = searched()
    rank_candidates(result, found)
    result.ambiguous = outnumbered(result.runner_up_ratio, cfg)
    with timed(result.timings, 'candidates_settled'):
        settlement = settle_candidates(fs, ft, result, cfg, map_target, workers)
        if settlement is not None:
            result.ambiguous = still_ambiguous(settlement, cfg)
        if settlement is not None and settlement.replaces:  # the geometry prefers it now
            result.transform = settlement.chosen.transform
            overlap = measure(fs, ft, corr, result, cfg, map_target)
            refusal = gate_refusal(result, cfg, left_to_gates)
            settlement.chosen.fitness = result.fitness
    refusal = said_over_ambiguity(refusal, ambiguity_refusal(result, cfg))
    if not refusal and cfg.gates.check_twins:
        with timed(result.timings, 'twins'):
            twin = find_twin(fs, ft, corr, result, cfg, map_target, workers)
        if twin is not None:  # plausible (validity.plausible_twin): the estimate is ambiguous
            add_twin(result, twin)
            result.ambiguous = True
            refusal = ambiguity_refusal(result, cfg)
    if not refusal and map_target:
        overlap = polished(src, fs, ft, corr, result, cfg, overlap, left_to_gates, workers)
    return _judged(result, fs, ft, cfg, start, refusal, map_target, overlap)


def _refine(fs: CloudFeatures, ft: CloudFeatures, core: RegistrationResult,
            result: PipelineResult, cfg: PipelineConfig, workers: int) -> None:
    """Refine the core's estimate into ``result.transform`` (``refine.method``)."""
    gravity = cfg.core.gravity_axis if cfg.core.motion_model == '4dof' else None
    with timed(result.timings, 'refinement'):
        result.transform = refine_transform(
            fs.points, ft.points, core.transform, voxel_size=cfg.voxel_size,
            config=cfg.refine, target_normals=ft.normals, coarse_distance=core.inlier_threshold,
            gravity=gravity, workers=workers)
        result.refined = cfg.refine.method != 'none'


def _target_features(target: np.ndarray | PreparedMap, points: np.ndarray | None,
                     cfg: PipelineConfig, timings: dict[str, float],
                     workers: int) -> CloudFeatures:
    """Return the target's features with their descriptor index built (a map's as they are)."""
    if points is None:
        return target.features
    features = cached_features(points, cfg.voxel_size, cfg.frontend, 'target', timings,
                               workers)
    with timed(timings, 'matching'):  # the index is matching's, as when built there
        features.descriptor_index(workers)
    return features


def _target_or_error(wait: Callable[[], CloudFeatures]) -> CloudFeatures | EmptyCloudError:
    """Wait for :func:`_target_features`; return the features or the EmptyCloudError raised."""
    try:
        return wait()
    except EmptyCloudError as exc:
        return exc


def _search_candidates(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
                       result: PipelineResult, cfg: PipelineConfig) -> tuple[list, float]:
    """Return :func:`~.candidates.search_candidates` and its seconds."""
    timings: dict[str, float] = {}
    with timed(timings, 'candidates'):
        found = search_candidates(fs, ft, corr, result, cfg)
    return found, timings['candidates']


def _candidates(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
                result: PipelineResult, cfg: PipelineConfig) -> Refusal | None:
    """Search the ranked candidates; return the ambiguity refusal (None when not ambiguous)."""
    with timed(result.timings, 'candidates'):
        rank_candidates(result, search_candidates(fs, ft, corr, result, cfg))
    result.ambiguous = outnumbered(result.runner_up_ratio, cfg)
    return ambiguity_refusal(result, cfg)


def terrain_patch(rng: np.random.Generator, n: int = 4000) -> np.ndarray:
    """
    Sample (n, 3) points of a 4 m x 4 m terrain patch with three Gaussian bumps (metres).

    The patch has enough relief for FPFH and a fully constrained rigid fit: the pair that
    :func:`warm_up` registers (the node's tests use it too).
    """
    xy = rng.uniform(-2.0, 2.0, (n, 2))
    bumps = ((0.7, 0.5, 0.8, 0.3), (-0.9, -0.2, 0.5, 0.1), (0.1, -1.1, -0.6, 0.5))
    z = sum(h * np.exp(-((xy[:, 0] - x) ** 2 + (xy[:, 1] - y) ** 2) / w)
            for x, y, h, w in bumps)
    return np.c_[xy, z]


def warm_up(config: PipelineConfig | None = None) -> PipelineResult:
    """
    Register a small synthetic pair once, to pay one-time start-up costs.

    These costs (Open3D's lazy initialisation, first calls into SciPy/BLAS and the
    refinement library) are then not paid by the first real pair. For a node to call at
    start-up with its own ``config`` (every stage, its refinement method included, then
    runs once). It is short and safe to call again.

    :returns: the result (valid, refined unless ``refine.method`` is 'none') of registering
        a 4 m terrain patch with three bumps (0.15 m voxels) onto itself rotated by 17
        degrees.
    """
    terrain = terrain_patch(np.random.default_rng(0))
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return register_clouds(terrain @ R.T + 0.2, terrain, voxel_size=0.15, config=config)


def _effective_config(config: PipelineConfig | None, voxel_size: float | None) -> PipelineConfig:
    overrides = {} if voxel_size is None else {'voxel_size': voxel_size}
    return fields.update_from_flat(config or PipelineConfig(), overrides)  # validated copy


def _global_estimate(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
                     resolution: float, cfg: PipelineConfig) -> RegistrationResult:
    """
    Return the core's estimate (its own ``refusal`` says whether it is trusted).

    :raises DegenerateCorrespondencesError: too few or degenerate matches for any estimate.
    """
    need = 2 if cfg.core.motion_model == '4dof' else 3
    if len(corr) < need:
        raise DegenerateCorrespondencesError(
            f'only {len(corr)} putative correspondence(s) (need {need}): the FPFH features '
            'do not match; check the voxel size and that the clouds overlap')
    tau = cfg.core.inlier_threshold or None
    try:
        return register_correspondences(
            fs.points[corr.source_index], ft.points[corr.target_index], inlier_threshold=tau,
            resolution=resolution, config=cfg.core, seed=cfg.seed)
    except DegenerateCorrespondencesError as exc:
        raise DegenerateCorrespondencesError(f'degenerate correspondences: {exc}',
                                             code=exc.code) from exc


def _copy_core(core: RegistrationResult, result: PipelineResult) -> None:
    for f in dataclasses.fields(RegistrationResult):
        if f.name not in ('timings', 'refusal'):
            setattr(result, f.name, getattr(core, f.name))
    result.stats = {**result.stats, **core.stats}
    result.coarse_transform = core.transform.copy()
    result.transform = core.transform.copy()
    result.timings.update({f'core_{k}': t for k, t in core.timings.items()})
