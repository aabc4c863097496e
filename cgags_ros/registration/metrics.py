"""Registration error metrics (the literature's RE/TE)."""

from __future__ import annotations

import numpy as np


def rotation_error_deg(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """RE = arccos((trace(R_gt^T R) - 1) / 2), degrees."""
    R = np.asarray(T_est)[:3, :3]
    R_gt = np.asarray(T_gt)[:3, :3]
    c = (np.trace(R_gt.T @ R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def translation_error(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """TE = ||t_gt - t||, in the units of the input (metres)."""
    return float(np.linalg.norm(np.asarray(T_est)[:3, 3] - np.asarray(T_gt)[:3, 3]))


def is_success(T_est: np.ndarray, T_gt: np.ndarray, max_re_deg: float, max_te: float) -> bool:
    return rotation_error_deg(T_est, T_gt) <= max_re_deg and translation_error(T_est, T_gt) <= max_te
