"""
The motion of a tracked stream: its prediction, and the checks a tracked pose must pass.

Beside the gates every result passes (:mod:`.gates`), a pose refined from a prediction
(:mod:`.tracking`) must stay near it and fit about as well as the last pose did: smooth
motion moves little and changes the overlap little, a jump does neither
(:func:`cgags_ros.validity.tracking_refusal` decides on :func:`difference`). Transforms are
4x4 source->target, metres.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..config.pipeline import PipelineConfig
from ..geometry import rotation_error_deg, translation_error


def scaled_motion(motion: np.ndarray, scale: float) -> np.ndarray:
    """Return ``motion`` (4x4) scaled in time: rotation angle and translation times ``scale``."""
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(
        scale * Rotation.from_matrix(motion[:3, :3]).as_rotvec()).as_matrix()
    out[:3, 3] = scale * motion[:3, 3]
    return out


def difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Return the rotation (degrees) and translation (metres) between two poses."""
    return rotation_error_deg(b, a), translation_error(b, a)


def agree(prediction: np.ndarray, transform: np.ndarray, cfg: PipelineConfig) -> bool:
    """Tell whether a global result is within ``tracking.agreement_*`` of the prediction."""
    track = cfg.tracking
    angle, shift = difference(prediction, transform)
    return (angle <= track.agreement_rotation_deg
            and shift <= track.agreement_translation_factor * cfg.voxel_size)
