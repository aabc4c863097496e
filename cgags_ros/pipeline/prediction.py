"""
The motion of a tracked stream: its prediction, and the checks a tracked pose must pass.

Beside the gates every result passes (:mod:`.gates`), a pose refined from a prediction
(:mod:`.tracking`) must stay near it and fit about as well as the last pose did: smooth
motion moves little and changes the overlap little, a jump does neither. Transforms are
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


def _difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Return the rotation (degrees) and translation (metres) between two poses."""
    return rotation_error_deg(b, a), translation_error(b, a)


def agree(prediction: np.ndarray, transform: np.ndarray, cfg: PipelineConfig) -> bool:
    """Tell whether a global result is within ``tracking.agreement_*`` of the prediction."""
    track = cfg.tracking
    angle, shift = _difference(prediction, transform)
    return (angle <= track.agreement_rotation_deg
            and shift <= track.agreement_translation_factor * cfg.voxel_size)


def correction_reason(prediction: np.ndarray, transform: np.ndarray,
                      cfg: PipelineConfig) -> str:
    """Return why the refinement moved the prediction too far to be a tracked pose, or ''."""
    track = cfg.tracking
    angle, shift = _difference(prediction, transform)
    limit = track.max_correction_factor * cfg.voxel_size
    if angle <= track.max_correction_deg and shift <= limit:
        return ''
    return (f'tracking: the refinement moved the predicted pose by {shift:.3g} m and '
            f'{angle:.3g} deg (> tracking.max_correction_factor {limit:.3g} m or '
            f'tracking.max_correction_deg {track.max_correction_deg:g} deg): a jump, not a '
            'tracked motion')


def fitness_drop_reason(fitness: float, last_fitness: float, cfg: PipelineConfig) -> str:
    """Return why ``fitness`` fell too far below the last accepted pose's, or ''."""
    if fitness >= cfg.tracking.min_fitness_ratio * last_fitness:
        return ''
    return (f'tracking: fitness {fitness:.3f} < tracking.min_fitness_ratio times the last '
            f"pose's {last_fitness:.3f}: the prediction converged where far fewer points "
            'fit (a jump or a changed scene)')
