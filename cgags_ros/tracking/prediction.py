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

AGREEMENT_DEG = 2.0  # a periodic check agrees with the prediction within this rotation...
AGREEMENT_VOXELS = 2.0  # ...and this translation, in voxel sizes


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
    """
    Tell whether a global result agrees with the prediction (else the velocity is reset).

    Within :data:`AGREEMENT_DEG` of rotation and :data:`AGREEMENT_VOXELS` voxel sizes of
    translation.
    """
    angle, shift = difference(prediction, transform)
    return angle <= AGREEMENT_DEG and shift <= AGREEMENT_VOXELS * cfg.voxel_size
