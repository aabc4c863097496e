"""
A scan refined from a predicted pose and judged: the tracked path, without the stream's state.

:func:`refine_prediction` downsamples the scan, refines the prediction against the target's
features (no FPFH, no matching, no core; against a map, a scan of few voxels once more with
its own points, as the global path does) and judges the pose by the gates a global result
passes on its overlap (:func:`~cgags_ros.validity.overlap_refusal`), the tracked pose's own
(:func:`~cgags_ros.validity.tracking_refusal`) and the usable-covariance bound. The
:class:`~.tracker.Tracker` calls it for each scan it tracks. Transforms are 4x4
source->target, metres.
"""

from __future__ import annotations

import time

import numpy as np

from .prediction import difference
from ..config.pipeline import PipelineConfig
from ..coordinates import local_origin, moved, sensor_at_origin, to_local
from ..errors import EmptyCloudError
from ..frontend.features import CloudFeatures, downsample, finite_points, MIN_POINTS
from ..frontend.refine import refine_finer, refine_transform
from ..geometry import cross_spread
from ..parallel import DEFAULT_WORKERS
from ..pipeline.cache import cached_features
from ..pipeline.covariance import loosest_sigma, overlap_covariance
from ..pipeline.gates import measure_overlap
from ..pipeline.map import PreparedMap
from ..pipeline.result import PipelineResult
from ..timing import timed
from ..validity import (line_cloud_refusal, overlap_refusal, tracking_refusal,
                        uncertainty_refusal)

# The tracked refinement stops once fitness and inlier RMSE change by less than this
# (relative): from a close start, further iterations move the pose far less than the gates
# or the sensor can tell apart (the global path's final stage keeps 1e-6).
REFINE_TOLERANCE = 1e-3


def target_features(target: np.ndarray | PreparedMap, cfg: PipelineConfig,
                    timings: dict[str, float]) -> tuple[CloudFeatures, np.ndarray]:
    """
    Return the target's features at ``cfg.voxel_size`` and the local origin they are about.

    A map's are returned as they are; a cloud's are those :func:`register_clouds` computes
    (:mod:`cgags_ros.coordinates`, about ``frontend.target_sensor`` when set), so a scan
    that went global makes this a cache hit.
    """
    if isinstance(target, PreparedMap):
        return target.features, target.origin
    points = finite_points(target, 'target')
    sensor = cfg.frontend.target_sensor
    origin = local_origin(points, sensor)
    with timed(timings, 'target_features'):
        features = cached_features(moved(points, origin), cfg.voxel_size, cfg.frontend,
                                   'target', None, DEFAULT_WORKERS)
    return features.with_sensor(sensor_at_origin(origin, sensor is not None)), origin


def refine_prediction(source: np.ndarray, ft: CloudFeatures, prediction: np.ndarray,
                      cfg: PipelineConfig, last_fitness: float, map_target: bool,
                      target_origin: np.ndarray | None = None) -> PipelineResult:
    """
    Refine ``prediction`` of ``source`` (sensor frame) onto ``ft``; gate it (see the module doc).

    :param ft: the target's features about ``target_origin`` (:func:`target_features`).
    :param last_fitness: the fitness of the stream's last accepted pose (0: none), which
        the refined pose's must not fall far below.
    :returns: a result with ``path`` 'tracked', invalid with why when a gate refuses; its
        transforms in the caller's frames, as ``prediction``.
    """
    target_origin = np.zeros(3) if target_origin is None else target_origin
    sensor = cfg.frontend.source_sensor
    source_origin = local_origin(source, sensor)
    result = _refined(moved(source, source_origin), ft,
                      to_local(prediction, source_origin, target_origin), cfg, last_fitness,
                      map_target, sensor_at_origin(source_origin, sensor is not None))
    return result.in_caller_frames(source_origin, target_origin)


def _refined(source: np.ndarray, ft: CloudFeatures, prediction: np.ndarray,
             cfg: PipelineConfig, last_fitness: float, map_target: bool,
             source_sensor: bool) -> PipelineResult:
    """Return :func:`refine_prediction` of a source and prediction near their local origins."""
    start = time.perf_counter()
    v = cfg.voxel_size
    result = PipelineResult(voxel_size=v, path='tracked')
    result.coarse_transform = prediction.copy()
    try:
        with timed(result.timings, 'downsample'):
            points = downsample(source, v, MIN_POINTS, 'source')
    except EmptyCloudError as exc:
        return result.finish(start, exc.refusal)
    result.num_source_points, result.num_target_points = len(points), len(ft.points)
    result.resolution = ft.resolution
    refusal = line_cloud_refusal(cross_spread(points), 'source', v)
    if refusal:
        return result.finish(start, refusal)
    gravity = cfg.core.gravity_axis if cfg.core.motion_model == '4dof' else None
    with timed(result.timings, 'refinement'):
        result.transform = refine_transform(
            points, ft.points, prediction, voxel_size=v, config=cfg.refine,
            target_normals=ft.normals,
            gravity=gravity, workers=DEFAULT_WORKERS, tolerance=REFINE_TOLERANCE)
        if map_target and gravity is None:  # the global path's last stage (pipeline/polish.py)
            result.transform = refine_finer(source, len(points), ft.points, ft.normals, ft.tree,
                                            result.transform, voxel_size=v, config=cfg.refine,
                                            workers=DEFAULT_WORKERS)
        result.refined = True
    with timed(result.timings, 'validation'):
        # no source tree: the target side of the overlap is for settling candidates only
        align = measure_overlap(points, None, ft, result, cfg, map_target, source_sensor)
        refusal = (overlap_refusal(result, cfg)
                   or tracking_refusal(*difference(prediction, result.transform),
                                       result.fitness, last_fitness, cfg))
    # The global path's covariance (the whole overlap, point-to-plane) and its usable
    # bound: a stream's poses keep one meaning whichever path made them.
    result.covariance = overlap_covariance(
        points, ft.points, ft.normals, ft.tree, result.transform,
        cfg.refine.max_correspondence_distance_factor * v, v, gravity,
        (align.source_index, align.target_index))
    return result.finish(start, refusal or uncertainty_refusal(
        loosest_sigma(result.covariance), cfg))
