"""
One synchronized frame and the evidence the pipeline gives on it.

A frame is a pair (parent cloud, child cloud) taken at (nearly) the same time, each in its
own sensor frame, metres. The pipeline registers the child onto the parent
(:func:`cgags_ros.pipeline.register_clouds`, source = child, target = parent), so its
transforms are parent <- child; its ranked candidates are the frame's vote.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .joint import FrameClouds, surface_normals
from ..config.pipeline import PipelineConfig
from ..coordinates import local_origin, sensor_at_origin, SENSOR_REACH
from ..errors import EmptyCloudError, InvalidInputError
from ..frontend.features import finite_points
from ..frontend.keypoints import match_keypoints
from ..parallel import DEFAULT_WORKERS
from ..pipeline import cached_features, PipelineResult, register_clouds


@dataclasses.dataclass
class Frame:
    """
    One synchronized pair of clouds.

    :ivar parent: (N, 3) parent cloud, parent sensor frame, metres.
    :ivar child: (M, 3) child cloud, child sensor frame, metres.
    :ivar name: a label for reports.
    :ivar parent_stamp_ns, child_stamp_ns: capture stamps (None when unknown).
    """

    parent: np.ndarray
    child: np.ndarray
    name: str = ''
    parent_stamp_ns: int | None = None
    child_stamp_ns: int | None = None

    @property
    def time_offset_s(self) -> float:
        """Child stamp minus parent stamp, seconds (NaN when a stamp is unknown)."""
        if self.parent_stamp_ns is None or self.child_stamp_ns is None:
            return float('nan')
        return (self.child_stamp_ns - self.parent_stamp_ns) * 1e-9


@dataclasses.dataclass
class Evidence:
    """
    What one frame contributes.

    :ivar frame: the input.
    :ivar result: the pipeline's single-frame result (child -> parent).
    :ivar clouds: the downsampled clouds for the joint problem; None when the frame is
        unusable (a cloud too small for the voxel size).
    :ivar candidates: the frame's candidate poses (4x4 parent <- child), best first.
    :ivar matches: (child points, parent points) of the frame's putative correspondences
        (FPFH matches, each in its own frame, metres), or None.
    :ivar resolution: mean nearest-neighbour distance of the downsampled clouds, metres.
    """

    frame: Frame
    result: PipelineResult
    clouds: FrameClouds | None
    candidates: list[np.ndarray]
    matches: tuple[np.ndarray, np.ndarray] | None = None
    resolution: float = float('nan')


def gather(frame: Frame, config: PipelineConfig) -> Evidence:
    """Register the frame's child onto its parent and keep what the joint problem needs."""
    try:
        child, parent = finite_points(frame.child, 'child'), finite_points(frame.parent, 'parent')
    except EmptyCloudError as exc:
        return Evidence(frame, PipelineResult(refusal=exc.refusal), None, [])
    for name, points in (('child', child), ('parent', parent)):
        if not sensor_at_origin(local_origin(points)):
            # The joint problem pairs every frame's clouds in their sensor frames; a cloud
            # in a world frame (UTM, a map's) has no extrinsic to the other sensor.
            raise InvalidInputError(
                f'{name} cloud: its centre is more than {SENSOR_REACH:g} m from its frame '
                "origin, so it is not in its sensor's frame; calibration takes each "
                "sensor's cloud as that sensor gave it")
    result = register_clouds(child, parent, config=config)
    candidates = [np.asarray(c.transform, dtype=np.float64) for c in result.candidates]
    try:
        # The pipeline has just featurised both clouds: these are cache hits.
        fc = cached_features(child, config.voxel_size, config.frontend, 'child')
        fp = cached_features(parent, config.voxel_size, config.frontend, 'parent')
    except EmptyCloudError:
        return Evidence(frame, result, None, [])
    corr = match_keypoints(fc.points, fc.descriptors, fp.descriptors, config.voxel_size,
                           config.frontend, DEFAULT_WORKERS, fp.descriptor_index(DEFAULT_WORKERS))
    matches = (fc.points[corr.source_index], fp.points[corr.target_index])
    radius = config.frontend.normal_radius_factor * config.voxel_size
    clouds = FrameClouds(fc.points, fp.points, surface_normals(fp.points, fp.tree, radius),
                         fp.tree, fc.tree, surface_normals(fc.points, fc.tree, radius))
    return Evidence(frame, result, clouds, candidates, matches,
                    0.5 * (fc.resolution + fp.resolution))
