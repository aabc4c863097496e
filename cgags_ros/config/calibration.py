"""
Configuration of extrinsic calibration from several frames (:mod:`cgags_ros.calibration`).

Lengths are in voxel sizes of the pipeline (``PipelineConfig.voxel_size``), so one number
still sets the scale.
"""

from __future__ import annotations

import dataclasses

from .fields import option
from .pipeline import PipelineConfig


@dataclasses.dataclass
class CalibrationConfig:
    """How frames are combined into one extrinsic, and when the answer is refused."""

    pipeline: PipelineConfig = dataclasses.field(
        default_factory=lambda: PipelineConfig(voxel_size=0.3))
    min_frames: int = option(
        3, 'Frames taken before the estimate may be called converged.', low=1, high=1000)
    max_frames: int = option(
        10, 'Frames taken at most; the estimate is final then, converged or not.',
        low=1, high=1000)
    min_agreement: float = option(
        0.75, 'Share of the frames that must agree on the pose; below it the set disagrees '
        'and the result is a FAIL. Frames that disagree never enter the estimate.',
        low=0.0, high=1.0)
    min_agreeing_frames: int = option(
        2, 'Frames that must agree for a valid result: agreement is the evidence that a '
        'pose is no coincidence of one scene. A single frame is accepted only when the '
        'pipeline alone accepted it with the same pose.', low=1, high=1000)
    agreement_shift_factor: float = option(
        0.15, 'A frame agrees when refining the joint pose on that frame alone moves its '
        'overlapping points along their normals by at most this many voxel sizes (RMS), '
        'and no pose of its own fits it ambiguity_ratio times better.', low=0.0, high=10.0)
    min_observability: float = option(
        0.02, 'Smallest / largest eigenvalue of the joint point-to-plane information (rotation '
        'scaled by the overlap radius); a direction below it is unobservable and the result '
        'a FAIL naming it.', low=0.0, high=1.0)
    ambiguity_ratio: float = option(
        1.5, 'The estimate is refused as ambiguous when another pose every frame agrees on '
        'has more than 1/ambiguity_ratio of its joint overlap.', low=1.0, high=100.0)
    iterations: int = option(30, 'Gauss-Newton iterations of each joint refinement stage.',
                             low=1, high=1000)
