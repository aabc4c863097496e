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
