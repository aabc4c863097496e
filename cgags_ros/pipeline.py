"""Clouds in, result out: the one registration path used by the ROS node, the CLIs and the
benchmarks.

``register_clouds(source, target)`` runs: input checks -> voxel downsampling -> normals ->
FPFH -> mutual-nearest-neighbour correspondences -> the CGAGS core (global, no initial
guess) -> optional ICP/GICP refinement -> validity gating. Numpy in, numpy out; transforms
are 4x4 source->target (``p_target = R p_source + t``), metres.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import os
import threading
import time
from collections import OrderedDict
from typing import Any

from .features import thread_env  # noqa: F401  (before numpy loads OpenBLAS)

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree

from . import configutil
from .config import PipelineConfig
from .datasets.synthetic import terrain_patch
from .errors import DegenerateCorrespondencesError, EmptyCloudError
from .features.config import FrontEndConfig
from .features.frontend import (CloudFeatures, Correspondences, extract_features,
                                finite_points, match_features, timed)
from .features.refine import Alignment, evaluate_alignment, refine_transform
from .registration import register_correspondences
from .registration.blas import blas_controller, single_blas_thread
from .registration.result import RegistrationResult
from .registration.stopping import poisson_isf


@dataclasses.dataclass
class PipelineResult(RegistrationResult):
    """:class:`RegistrationResult` of the whole pipeline.

    ``transform`` is the final estimate (refined when refinement is on); ``inliers`` index
    the putative correspondences given to the core. Extra attributes:

    Attributes:
        coarse_transform: the core's global estimate (4x4 source->target, metres).
        refined: whether a refinement ran (``refine.method != 'none'``).
        fitness: share of downsampled source points with a target point within the
            refinement distance (``refine.max_correspondence_distance_factor * v``) under
            ``transform``.
        inlier_rmse: RMS distance (metres) of those points to their nearest target point.
        overlap: min of the source-side and target-side shares of points with a neighbour
            in the other cloud within the refinement distance (a symmetric overlap ratio).
        observability: smallest/largest eigenvalue of the point-to-plane information matrix
            of the overlap (0: some motion is unconstrained, e.g. plane on plane).
        chance_inliers: inliers the estimate would collect if every correspondence were an
            outlier (expected value under a random pairing).
        inlier_source_points, inlier_target_points: (K, 3) the core's inlier
            correspondences (downsampled keypoints, source and target frames, metres).
        num_source_points, num_target_points: points after voxel downsampling.
        voxel_size: metres. resolution: point resolution pr (metres) given to the core.
    """

    coarse_transform: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    refined: bool = False
    fitness: float = 0.0
    inlier_rmse: float = float("nan")
    overlap: float = 0.0
    observability: float = float("nan")
    chance_inliers: float = float("nan")
    inlier_source_points: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    inlier_target_points: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    num_source_points: int = 0
    num_target_points: int = 0
    voxel_size: float = float("nan")
    resolution: float = float("nan")

    def summary(self) -> dict[str, Any]:
        out = super().summary()
        out.update(
            coarse_transform=np.asarray(self.coarse_transform, dtype=float).tolist(),
            refined=bool(self.refined), fitness=float(self.fitness),
            inlier_rmse=float(self.inlier_rmse), overlap=float(self.overlap),
            observability=float(self.observability),
            chance_inliers=float(self.chance_inliers),
            num_source_points=int(self.num_source_points),
            num_target_points=int(self.num_target_points),
            voxel_size=float(self.voxel_size), resolution=float(self.resolution))
        return out


def register_clouds(source: np.ndarray, target: np.ndarray, *, voxel_size: float | None = None,
                    config: PipelineConfig | None = None) -> PipelineResult:
    """Register ``source`` onto ``target`` with no initial guess.

    Args:
        source, target: (N, 3) points in metres, each in its own frame; non-finite rows
            are dropped.
        voxel_size: metres; overrides ``config.voxel_size`` (every radius derives from it).
        config: :class:`PipelineConfig`; defaults when None.

    Returns:
        :class:`PipelineResult`. ``valid`` is False, with a ``reason``, when the clouds are
        too small after downsampling, yield too few or degenerate correspondences, or when
        the estimate fails a validity gate (core inliers, chance-level inliers, degenerate
        overlap geometry, fitness). Never raises for such data-dependent failures.

    Raises:
        InvalidInputError: an array is not (N, 3) numeric. EmptyCloudError: no finite point.
        InvalidConfigError: a configuration value is out of range.
    """
    guard, workers = _blas_guard()
    with guard:
        return _register_clouds(source, target, voxel_size, config, workers)


def _register_clouds(source: np.ndarray, target: np.ndarray, voxel_size: float | None,
                     config: PipelineConfig | None, workers: int) -> PipelineResult:
    start = time.perf_counter()
    cfg = _effective_config(config, voxel_size)
    v = cfg.voxel_size
    src, dst = finite_points(source, "source"), finite_points(target, "target")
    result = PipelineResult(voxel_size=v)
    try:
        fs = cached_features(src, v, cfg.frontend, "source", result.timings)
        ft = cached_features(dst, v, cfg.frontend, "target", result.timings)
    except EmptyCloudError as exc:  # data too small for this voxel size: not a crash
        return _finish(result, start, str(exc))
    result.num_source_points, result.num_target_points = len(fs.points), len(ft.points)
    result.resolution = 0.5 * (fs.resolution + ft.resolution)
    reason = _line_reason(fs.points, "source", v) or _line_reason(ft.points, "target", v)
    if reason:
        return _finish(result, start, reason)
    with timed(result.timings, "matching"):
        corr = match_features(fs.descriptors, ft.descriptors, cfg.frontend, workers)
    result.stats.update(num_source_points=len(fs.points), num_target_points=len(ft.points))
    with timed(result.timings, "registration"):
        core = _global_estimate(fs, ft, corr, result.resolution, cfg)
    if isinstance(core, str):
        result.num_correspondences = len(corr)
        return _finish(result, start, core)
    _copy_core(core, result)
    result.inlier_source_points = fs.points[corr.source_index[core.inliers]]
    result.inlier_target_points = ft.points[corr.target_index[core.inliers]]
    if core.reason:  # nothing worth refining or gating further
        return _finish(result, start, core.reason)
    with timed(result.timings, "refinement"):
        result.transform = refine_transform(
            fs.points, ft.points, core.transform, voxel_size=v, config=cfg.refine,
            target_normals=ft.normals, coarse_distance=core.inlier_threshold)
        result.refined = cfg.refine.method != "none"
    with timed(result.timings, "validation"):
        reason = _gate(fs, ft, corr, result, cfg)
    return _finish(result, start, reason)


def warm_up(config: PipelineConfig | None = None) -> PipelineResult:
    """Register a small synthetic pair once, so that one-time start-up costs (Open3D's lazy
    initialisation, first calls into SciPy/BLAS and the refinement library) are not paid by
    the first real pair. For a node to call at start-up with its own ``config`` (every
    stage, its refinement method included, then runs once). ~0.1-0.2 s; safe to call again.

    Returns the result (valid, refined unless ``refine.method`` is 'none') of registering a
    4 m terrain patch with three bumps (0.15 m voxels) onto itself rotated by 17 degrees.
    """
    terrain = terrain_patch(np.random.default_rng(0))
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return register_clouds(terrain @ R.T + 0.2, terrain, voxel_size=0.15, config=config)


_MATCH_WORKERS = max(1, min(4, os.cpu_count() or 1))


def _blas_guard() -> tuple[contextlib.AbstractContextManager, int]:
    """(context keeping BLAS to one thread, descriptor-matching threads): with threadpoolctl
    one BLAS thread and _MATCH_WORKERS matching threads (own threads match faster than
    BLAS's, argmins included, and idle BLAS workers cannot spin into Open3D's time; see
    features.thread_env); without it nothing and 1 (BLAS's own threads match)."""
    if blas_controller() is None:
        return contextlib.nullcontext(), 1
    return single_blas_thread(), _MATCH_WORKERS


_CACHE_SIZE = 2  # clouds whose features are kept: a latched target plus one more
_cache: OrderedDict[tuple, CloudFeatures] = OrderedDict()
_cache_lock = threading.Lock()


def cached_features(points: np.ndarray, voxel_size: float, config: FrontEndConfig,
                    name: str = "cloud",
                    timings: dict[str, float] | None = None) -> CloudFeatures:
    """:func:`extract_features`, remembered for the last two clouds by exact content (and
    voxel size and front-end settings): a latched map target, or a target shared by
    consecutive pairs, is featurised once (~half the front end at 10 Hz). The front end is
    deterministic, so a hit returns exactly what recomputing would; the arrays returned are
    shared and must not be written to. Hashing costs ~2.5 ms per 100k points."""
    key = (hashlib.blake2b(np.ascontiguousarray(points), digest_size=16).digest(),
           points.shape, voxel_size, dataclasses.astuple(config))
    with _cache_lock:
        hit = _cache.get(key)
        if hit is not None:
            _cache.move_to_end(key)
    if hit is not None:
        for stage in ("downsample", "normals", "fpfh") if timings is not None else ():
            timings.setdefault(stage, 0.0)  # no time spent, but keep the keys
        return hit
    features = extract_features(points, voxel_size, config, name, timings)
    with _cache_lock:
        _cache[key] = features
        while len(_cache) > _CACHE_SIZE:
            _cache.popitem(last=False)
    return features


def clear_feature_cache() -> None:
    """Forget remembered features (benchmarks timing the whole front end call this)."""
    with _cache_lock:
        _cache.clear()


def _effective_config(config: PipelineConfig | None, voxel_size: float | None) -> PipelineConfig:
    overrides = {} if voxel_size is None else {"voxel_size": voxel_size}
    return configutil.update_from_flat(config or PipelineConfig(), overrides)  # validated copy


def _global_estimate(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
                     resolution: float, cfg: PipelineConfig) -> RegistrationResult | str:
    """The core's estimate, or the reason there is none (too few/degenerate matches)."""
    if len(corr) < 3:
        return (f"only {len(corr)} putative correspondence(s) (need 3): the FPFH features "
                "do not match; check the voxel size and that the clouds overlap")
    tau = cfg.frontend.inlier_threshold or None
    try:
        return register_correspondences(
            fs.points[corr.source_index], ft.points[corr.target_index], inlier_threshold=tau,
            resolution=resolution, config=cfg.core, seed=cfg.seed)
    except DegenerateCorrespondencesError as exc:
        return f"degenerate correspondences: {exc}"


def _copy_core(core: RegistrationResult, result: PipelineResult) -> None:
    for f in dataclasses.fields(RegistrationResult):
        if f.name not in ("timings", "valid", "reason"):
            setattr(result, f.name, getattr(core, f.name))
    result.stats = {**result.stats, **core.stats}
    result.coarse_transform = core.transform.copy()
    result.transform = core.transform.copy()
    result.timings.update({f"core_{k}": t for k, t in core.timings.items()})


# --- validity gating ----------------------------------------------------------------------------
def _line_reason(points: np.ndarray, name: str, voxel_size: float) -> str:
    """A cloud whose RMS spread across its main axis is below one voxel is a line: the
    rotation about it can never be determined, so the core is not even asked."""
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    if s[1] / np.sqrt(len(points)) >= voxel_size:
        return ""
    return (f"degenerate {name} cloud: it is (nearly) a line (spread across its axis "
            f"{s[1] / np.sqrt(len(points)):.3g} m < voxel size {voxel_size:g} m); the rotation "
            "about it is undetermined")


def _gate(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences, result: PipelineResult,
          cfg: PipelineConfig) -> str:
    """Why the final estimate must not be trusted, or '' when it passes every gate."""
    distance = cfg.refine.max_correspondence_distance_factor * cfg.voxel_size
    align = evaluate_alignment(fs.points, ft.tree, result.transform, distance)
    back = evaluate_alignment(ft.points, fs.tree, np.linalg.inv(result.transform), distance)
    result.fitness, result.inlier_rmse = align.fitness, align.inlier_rmse
    result.overlap = min(align.fitness, back.fitness)
    result.chance_inliers = chance_inliers(fs.points[corr.source_index],
                                           ft.points[corr.target_index], result.coarse_transform,
                                           result.inlier_threshold)
    result.observability = observability(fs.points, ft.normals, align)
    return (_significance_reason(result, cfg.refine.significance)
            or _observability_reason(result, cfg.refine.min_observability)
            or _fitness_reason(result, cfg.refine.min_fitness, distance))


def chance_inliers(src: np.ndarray, dst: np.ndarray, transform: np.ndarray, tau: float) -> float:
    """Expected inliers of ``transform`` if the correspondences were paired at random.

    Averages, over all (i, j), whether ``dst[j]`` lies within ``tau`` of ``T src[i]``: the
    exact expectation under a random permutation of the target rows. It is high where
    keypoints are dense or the threshold loose, i.e. where a count means little.
    """
    moved = src @ transform[:3, :3].T + transform[:3, 3]
    counts = cKDTree(dst).query_ball_point(moved, r=tau, return_length=True)
    return float(np.sum(counts) / max(len(src), 1))


def observability(source: np.ndarray, target_normals: np.ndarray, align: Alignment) -> float:
    """Smallest / largest eigenvalue of the 6x6 point-to-plane information matrix.

    Rows are ``[(p - c) x n / L, n]`` over the overlapping points (p: moved source point,
    n: normal of its nearest target point, c, L: centroid and RMS radius of the overlap,
    which makes rotation and translation columns commensurate). A plane leaves in-plane
    motion unconstrained, a line its axis, a sphere all rotations: the ratio is then ~0.
    """
    if len(align.source_index) < 6:
        return 0.0
    T = align.transform
    p = source[align.source_index] @ T[:3, :3].T + T[:3, 3]
    n = target_normals[align.target_index]
    centred = p - p.mean(axis=0)
    radius = np.sqrt(np.mean(np.sum(centred ** 2, axis=1)))
    if radius <= 0:
        return 0.0
    J = np.hstack([np.cross(centred / radius, n), n])
    eig = np.linalg.eigvalsh(J.T @ J / len(J))
    return float(max(eig[0], 0.0) / eig[-1]) if eig[-1] > 0 else 0.0


def _significance_reason(result: PipelineResult, significance: float) -> str:
    """Chance-level gate. If all N correspondences were outliers, the inliers of a fixed
    transform are ~Poisson(mu) (mu = chance_inliers), plus the 3 that define a hypothesis;
    the best of H hypotheses then exceeds the Poisson 1 - significance/H quantile with
    probability ~significance (union bound)."""
    if significance <= 0:
        return ""
    hypotheses = max(result.num_hypotheses, 1)
    bound = 3 + poisson_isf(significance / hypotheses, result.chance_inliers)
    if result.num_inliers > bound:
        return ""
    return (f"{result.num_inliers} inliers of {result.num_correspondences} correspondences "
            f"is no better than chance (random pairing gives {result.chance_inliers:.2g} per "
            f"estimate; the best of {hypotheses} hypotheses reaches {bound:.0f}): the clouds "
            "probably do not overlap")


def _observability_reason(result: PipelineResult, min_observability: float) -> str:
    if min_observability <= 0 or result.observability >= min_observability:
        return ""
    return (f"degenerate geometry: the overlap constrains some motion only weakly "
            f"(observability {result.observability:.2g} < {min_observability:g}; e.g. plane, "
            "line, sphere or cylinder); the pose along it is arbitrary")


def _fitness_reason(result: PipelineResult, min_fitness: float, distance: float) -> str:
    if min_fitness <= 0 or result.fitness >= min_fitness:
        return ""
    return (f"fitness {result.fitness:.3f} < refine.min_fitness {min_fitness:g}: too few "
            f"source points lie within {distance:.3g} m of the target after alignment")


def _finish(result: PipelineResult, start: float, reason: str) -> PipelineResult:
    result.valid = not reason
    result.reason = reason
    result.timings["total"] = time.perf_counter() - start
    return result
