"""
Covariance and observability of the joint estimate, from the pooled point-to-plane problem.

Covariance convention (as :func:`cgags_ros.pipeline.covariance.pose_covariance`, ROS
``PoseWithCovariance`` order): 6x6, row-major, ordered ``(x, y, z, rx, ry, rz)``: a
perturbation ``t' = t + dt`` (metres, parent frame: the child origin's position) and
``R' = exp([dphi]x) R`` (radians, left side, about the parent frame's axes through the
child origin) of the transform parent <- child.

``cov = s^2 sigma^2 H^-1``: ``H`` the information of unit-variance point-to-plane
residuals, ``sigma^2`` their variance (sum of squares / (K - 6)), and ``s^2 >= 1`` the
Birge ratio of the frames: the per-frame estimates scatter about the joint one by
``chi^2 = sum_k d_k^T C_k^-1 d_k`` (``C_k`` a frame's own covariance), which is ~6(K - 1)
when the residuals are as independent as the formula assumes; neighbouring residuals are
not (voxels, normals, scan patterns), so ``s^2 = max(1, chi^2 / (6 (K - 1)))`` scales the
covariance to the scatter the frames show. With one frame there is no scatter to learn
from and the covariance is the optimistic one.
"""

from __future__ import annotations

import numpy as np

AXES = ('x', 'y', 'z')
# Smallest / largest eigenvalue of the joint point-to-plane information (rotation scaled by
# the overlap radius) below which a direction is unobservable and the calibration a FAIL.
MIN_OBSERVABILITY = 0.02


def covariance(H: np.ndarray, ssr: float, count: int) -> np.ndarray:
    """Return ``sigma^2 H^-1`` (module convention); variances of 1e6 when H is singular."""
    if count <= 6 or np.linalg.cond(H) > 1e14:
        return np.diag([1e6] * 6)
    return max(ssr / (count - 6), 1e-12) * np.linalg.inv(H)


def birge_ratio(deviations: list[np.ndarray], covariances: list[np.ndarray]) -> float:
    """
    Return ``max(1, chi^2 / (6 (K - 1)))`` of the per-frame deviations (see the module doc).

    ``deviations``: each frame's estimate minus the joint one (module convention, 6-vectors);
    ``covariances``: each frame's own 6x6 covariance. 1 with fewer than two frames.
    """
    if len(deviations) < 2:
        return 1.0
    chi2 = sum(float(d @ np.linalg.pinv(C) @ d) for d, C in zip(deviations, covariances))
    return max(1.0, chi2 / (6 * (len(deviations) - 1)))


def std_devs(cov: np.ndarray) -> dict[str, float]:
    """
    Return per-axis standard deviations.

    ``x_m, y_m, z_m`` in metres; ``rx_deg, ry_deg, rz_deg`` in degrees, rotations about the
    parent's x, y, z axes (through the child origin).
    """
    s = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return {'x_m': float(s[0]), 'y_m': float(s[1]), 'z_m': float(s[2]),
            'rx_deg': float(np.degrees(s[3])), 'ry_deg': float(np.degrees(s[4])),
            'rz_deg': float(np.degrees(s[5]))}


def scaled_information(H: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """
    Return the information in commensurate, centred coordinates.

    The rotation is taken about ``centre`` (the overlap's centroid relative to the child
    origin, parent axes: the mean of ``R p``) and multiplied by ``radius`` (the overlap's
    RMS radius about it, metres), so translation and rotation columns are both metres of
    point motion, as in :func:`cgags_ros.pipeline.gates.observability`. A rotation
    ``dphi_c`` about the centre with translation ``dt_c`` is, about the child origin,
    ``dphi = dphi_c`` and ``dt = dt_c + centre x dphi_c``.
    """
    A = np.eye(6)
    A[:3, 3:] = np.array([[0.0, -centre[2], centre[1]], [centre[2], 0.0, -centre[0]],
                          [-centre[1], centre[0], 0.0]])
    A[:, 3:] /= max(radius, 1e-12)
    return A.T @ H @ A


def unobservable(H: np.ndarray, centre: np.ndarray, radius: float,
                 min_ratio: float) -> tuple[float, list[str]]:
    """
    Return (observability, the unconstrained motions named), from the joint information.

    Observability is the smallest / largest eigenvalue of :func:`scaled_information`. The
    eigenvectors below ``min_ratio`` times the largest span the unconstrained motions; the
    translations and rotations lying (mostly) in that span are named with their axes in the
    parent frame, e.g. 'translation along x', 'translation in the plane normal to z',
    'rotation about (0.71, 0.71, 0.00)'.
    """
    S = scaled_information(H, centre, radius)
    eig, vec = np.linalg.eigh(S)
    top = eig[-1]
    if not top > 0:
        return 0.0, ['every translation', 'every rotation']
    ratio = float(max(eig[0], 0.0) / top)
    null = vec[:, eig < min_ratio * top]
    if null.shape[1] == 0:
        return ratio, []
    P = null @ null.T  # projector onto the unconstrained span
    return ratio, (_named(P[:3, :3], 'translation', 'along', 'in the plane normal to')
                   + _named(P[3:, 3:], 'rotation', 'about', 'about any axis normal to'))


def _named(block: np.ndarray, kind: str, one: str, two: str) -> list[str]:
    """Name the directions d with d^T block d > 1/2 (mostly unconstrained)."""
    w, v = np.linalg.eigh(block)
    free = v[:, w > 0.5]
    if free.shape[1] == 0:
        return []
    if free.shape[1] == 3:
        return [f'{kind} in every direction']
    if free.shape[1] == 1:
        return [f'{kind} {one} {_axis(free[:, 0])}']
    return [f'{kind} {two} {_axis(v[:, np.argmin(w)])}']


def _axis(d: np.ndarray) -> str:
    """Name a unit direction: 'x' when it is (nearly) an axis, else its components."""
    d = d / np.linalg.norm(d)
    k = int(np.argmax(np.abs(d)))
    if abs(d[k]) > 0.97:
        return AXES[k]
    d = d if d[k] > 0 else -d
    return '(' + ', '.join(f'{c:.2f}' for c in d) + ')'
