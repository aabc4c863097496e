"""
Rigid-transform and point-set geometry shared by every layer (one copy of each).

Conventions: a 4x4 transform ``T`` maps source-frame points into the target frame,
``p_target = T[:3, :3] @ p_source + T[:3, 3]``; metres; quaternions are ``(x, y, z, w)`` as
in geometry_msgs. numpy and scipy only.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .errors import InvalidInputError


def make_transform(R: np.ndarray, t: Any) -> np.ndarray:
    """Build the 4x4 transform with rotation ``R`` (3x3) and translation ``t`` (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return the lowest and highest coordinate (3,) of the (N, 3) ``points`` (N >= 1).

    Column by column: numpy reduces an (N, 3) array along its first axis without
    vectorising, far slower than one column at a time, and this runs on every scan a stream
    sends.
    """
    lower = np.array([points[:, axis].min() for axis in range(3)])
    return lower, np.array([points[:, axis].max() for axis in range(3)])


def finite_transform(T: Any) -> np.ndarray:
    """
    Return ``T`` as a float64 4x4 array.

    :raises InvalidInputError: unless it is a finite 4x4 array.
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InvalidInputError(f'transform must be a finite 4x4 array, got shape {T.shape}')
    return T


def apply_transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map (N, 3) ``points`` by the 4x4 transform ``T``."""
    return points @ T[:3, :3].T + T[:3, 3]


def quaternion_to_matrix(q: Any) -> np.ndarray:
    """Convert a quaternion ``(x, y, z, w)`` to a 3x3 rotation matrix (normalised first)."""
    x, y, z, w = np.asarray(q, dtype=np.float64).reshape(4)
    norm = np.sqrt(x * x + y * y + z * z + w * w)
    if not np.isfinite(norm) or norm < 1e-12:
        raise InvalidInputError(f'quaternion {tuple(q)} has zero or non-finite norm')
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """
    Convert a 3x3 rotation matrix to a unit quaternion ``(x, y, z, w)`` with ``w >= 0``.

    Shepperd's method picks the largest diagonal term, so it is stable near 180 degrees.
    """
    R = np.asarray(R, dtype=np.float64)[:3, :3]
    trace = np.trace(R)
    diag = np.array([R[0, 0], R[1, 1], R[2, 2], trace])
    k = int(np.argmax(diag))
    if k == 3:
        w = 0.5 * np.sqrt(max(1.0 + trace, 0.0))
        q = np.array([(R[2, 1] - R[1, 2]), (R[0, 2] - R[2, 0]), (R[1, 0] - R[0, 1]), 0.0])
        q /= 4.0 * w
        q[3] = w
    else:
        i, j, m = k, (k + 1) % 3, (k + 2) % 3
        s = 0.5 * np.sqrt(max(1.0 + R[i, i] - R[j, j] - R[m, m], 0.0))
        q = np.zeros(4)
        q[i] = s
        q[j] = (R[j, i] + R[i, j]) / (4.0 * s)
        q[m] = (R[m, i] + R[i, m]) / (4.0 * s)
        q[3] = (R[m, j] - R[j, m]) / (4.0 * s)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def rpy(T: np.ndarray) -> tuple[float, float, float]:
    """
    Return (roll, pitch, yaw) in radians with ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

    Angles about the fixed axes x, y, z: the convention of tf2, URDF and a heading (yaw).
    """
    roll, pitch, yaw = Rotation.from_matrix(np.asarray(T)[:3, :3]).as_euler('xyz')
    return float(roll), float(pitch), float(yaw)


def rotation_error_deg(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """Return RE = arccos((trace(R_gt^T R) - 1) / 2) in degrees."""
    R = np.asarray(T_est)[:3, :3]
    R_gt = np.asarray(T_gt)[:3, :3]
    c = (np.trace(R_gt.T @ R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def translation_error(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """Return TE = ||t_gt - t|| in the units of the input (metres)."""
    return float(np.linalg.norm(np.asarray(T_est)[:3, 3] - np.asarray(T_gt)[:3, 3]))


def point_resolution(points: np.ndarray, tree: cKDTree | None = None,
                     nearest: np.ndarray | None = None) -> float:
    """
    Return pr, the mean distance from each point to its nearest other point (metres).

    ``tree`` is a k-d tree over ``points`` when the caller already has one. ``nearest``
    holds those distances where the caller already found them (inf elsewhere, e.g. the
    FPFH neighbour search within its radius): only the others are queried, and the result
    is the same number.
    """
    if len(points) < 2:
        return 0.0
    tree = tree if tree is not None else cKDTree(points)
    if nearest is None:
        return float(np.mean(tree.query(points, k=2)[0][:, 1]))
    unknown = ~np.isfinite(nearest)
    if unknown.any():
        nearest = nearest.copy()
        nearest[unknown] = tree.query(points[unknown], k=2)[0][:, 1]
    return float(np.mean(nearest))


def voxel_size_for(points: np.ndarray, occupied: int) -> float:
    """
    Return the voxel size (metres) at which about ``occupied`` voxels hold ``points``.

    Found by bisection on a log scale and rounded to two significant digits, so that a
    cloud's scale, not its sensor's density, picks the size. ``points`` must hold more than
    ``occupied`` points (InvalidInputError otherwise).
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) <= occupied:
        raise InvalidInputError(f'the cloud has only {len(pts)} points, not more than '
                                f'the {occupied} voxels asked for')
    lower, upper = bounds(pts)
    pts = pts - lower
    diag = float(np.linalg.norm(upper - lower)) or 1.0
    lo, hi = np.log(diag * 1e-5), np.log(diag)
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        if occupied_cells(pts, np.exp(mid)) > occupied:
            lo = mid
        else:
            hi = mid
    return float(f'{np.exp(0.5 * (lo + hi)):.2g}')


def grid_cells(points: np.ndarray, size: float, origin: Any = None) -> np.ndarray:
    """
    Return an int64 code of the cubic cell of ``size`` metres that holds each point.

    Cells are counted from ``origin`` (default: the points' lower bound). The codes sort as
    the cells' (i, j, k) rows sort, so ``np.unique`` of them groups and orders the points as
    ``np.unique(ijk, axis=0)`` does, at a fraction of its cost (one column is sorted, not
    rows).
    """
    low = points.min(axis=0) if origin is None else np.asarray(origin, dtype=np.float64)
    ijk = np.floor((points - low) / size).astype(np.int64)
    ijk -= ijk.min(axis=0)
    span = ijk.max(axis=0) + 1
    if float(np.prod(span.astype(np.float64))) >= 2.0 ** 62:  # too far apart for one code
        return np.unique(ijk, axis=0, return_inverse=True)[1].reshape(-1)
    return (ijk[:, 0] * span[1] + ijk[:, 1]) * span[2] + ijk[:, 2]


def occupied_cells(points: np.ndarray, size: float) -> int:
    """Return how many cubic cells of ``size`` metres (a grid through the origin) hold points."""
    return len(np.unique(grid_cells(points, size, np.zeros(3))))


def spread(points: np.ndarray) -> np.ndarray:
    """
    Return the singular values of the centred (N, 3) ``points``, largest first.

    ``s[1] / sqrt(N)`` is the RMS spread across the main axis: near 0 for a line, which
    leaves the rotation about it undetermined; ``s[0]`` near 0 means identical points.
    """
    return np.linalg.svd(points - points.mean(axis=0), compute_uv=False)


def cross_spread(points: np.ndarray) -> float:
    """
    Return the RMS spread (metres) of (N, 3) ``points`` along their second principal axis.

    How far they reach across their main axis: near 0 for a line, whose rotation about
    itself no point can fix.
    """
    return float(spread(points)[1] / np.sqrt(len(points)))


class GravityFrame:
    """
    The rotation ``A`` with ``A @ g = e_z``, and the maps into and out of its frame.

    For g = +z, ``A`` is the identity exactly (no rounding is introduced).
    """

    def __init__(self, gravity: tuple[float, float, float]):
        g = np.asarray(gravity, dtype=np.float64)
        g = g / np.linalg.norm(g)
        # x' = the world axis least aligned with g, made orthogonal to it; y' = g x x'.
        seed = np.eye(3)[int(np.argmin(np.abs(g)))] if abs(g[0]) > 0.9 else np.eye(3)[0]
        x = seed - (seed @ g) * g
        x /= np.linalg.norm(x)
        self.A = np.stack([x, np.cross(g, x), g])
        self.identity = bool(np.array_equal(self.A, np.eye(3)))

    def to_gravity(self, points: np.ndarray) -> np.ndarray:
        """Express (N, 3) points in the gravity frame."""
        return points if self.identity else points @ self.A.T

    def from_gravity(self, T: np.ndarray) -> np.ndarray:
        """Express a 4x4 transform of the gravity frame in the clouds' frames."""
        if self.identity:
            return T
        return make_transform(self.A.T @ T[:3, :3] @ self.A, self.A.T @ T[:3, 3])

    def to_gravity_transform(self, T: np.ndarray) -> np.ndarray:
        """Express a 4x4 transform of the clouds' frames in the gravity frame."""
        if self.identity:
            return T
        return make_transform(self.A @ T[:3, :3] @ self.A.T, self.A @ T[:3, 3])
