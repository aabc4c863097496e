"""
Clouds anywhere: far coordinates (UTM, MGRS, ECEF) worked on near a local origin.

A georeferenced cloud sits 10^5-10^7 m from its frame's origin. At that magnitude a float32
keeps only decimetres to metres, and sums of squared coordinates lose what the registration
needs even in float64; Open3D, the compiled kernels and the k-d trees all see such numbers.
So every entry point subtracts a cloud's :func:`local_origin` (in float64, before anything
else reads the points), works near zero, and gives its transforms back in the caller's frames
(:func:`to_caller`, :func:`result_to_caller`).

The sensor's position matters: the normals' sign (``frontend.normal_orientation`` 'origin')
and the free-space gate read each cloud as seen from its origin. A cloud whose sensor's
position the caller gives (a georeferenced scan and its GNSS position) is worked on about that
position. Otherwise a cloud within :data:`SENSOR_REACH` of its frame's origin is left where it
is (its origin may be its sensor), and a farther one, whose origin is no sensor (none sees
that far), is moved to the centre of its bounding box, where its normals then face, and no
free space is judged from its view (:func:`sensor_at_origin`).
"""

from __future__ import annotations

import numpy as np

from .errors import InvalidInputError
from .geometry import bounds

# Metres from a cloud's centre beyond which its frame's origin cannot be the sensor that saw
# it: past any LiDAR's or depth camera's range, far below georeferenced magnitudes.
SENSOR_REACH = 1000.0
# A float32 coordinate's step may be this share of the voxel size before it is worth a
# warning: the front end then reads the same grid the sensor measured.
FLOAT32_STEP_SHARE = 0.1


class CoarseCoordinatesWarning(UserWarning):
    """A cloud stored as float32 at a magnitude where its step is coarse for the voxel."""


def local_origin(points: np.ndarray, sensor: np.ndarray | None = None) -> np.ndarray:
    """
    Return the origin (3,) a cloud is worked on around, in its own frame (metres).

    ``sensor`` (the sensor's position in the cloud's frame) when given; else zeros when the
    cloud's bounding-box centre is within :data:`SENSOR_REACH` of its frame's origin
    (nothing moves), else that centre. ``points`` is an (N, 3) finite float64 array.

    :raises InvalidInputError: when ``sensor`` is not three finite numbers.
    """
    if sensor is not None:
        position = np.asarray(sensor, dtype=np.float64).reshape(-1)
        if position.shape != (3,) or not np.isfinite(position).all():
            raise InvalidInputError(f'a sensor position is three finite numbers (x, y, z in '
                                    f'metres), got {sensor!r}')
        return position
    if len(points) == 0:
        return np.zeros(3)
    lower, upper = bounds(points)
    centre = 0.5 * (lower + upper)
    return centre if np.linalg.norm(centre) > SENSOR_REACH else np.zeros(3)


def sensor_at_origin(origin: np.ndarray, sensor_given: bool = False) -> bool:
    """Tell whether a cloud worked on around ``origin`` may have its sensor there."""
    return sensor_given or not np.any(origin)


def moved(points: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Return ``points - origin`` (``points`` itself when ``origin`` is zero)."""
    return points - origin if np.any(origin) else points


def translation(offset: np.ndarray) -> np.ndarray:
    """Return the 4x4 transform that adds ``offset`` (metres)."""
    T = np.eye(4)
    T[:3, 3] = offset
    return T


def to_local(T: np.ndarray, source_origin: np.ndarray, target_origin: np.ndarray) -> np.ndarray:
    """Return the caller's source->target ``T`` between the clouds' local frames."""
    return translation(-target_origin) @ np.asarray(T, dtype=np.float64) @ translation(
        source_origin)


def to_caller(T: np.ndarray, source_origin: np.ndarray, target_origin: np.ndarray) -> np.ndarray:
    """Return a source->target ``T`` between local frames in the caller's frames."""
    return translation(target_origin) @ np.asarray(T, dtype=np.float64) @ translation(
        -source_origin)


def float32_step(magnitude: float) -> float:
    """Return the spacing of float32 numbers at ``magnitude`` (metres)."""
    return float(np.spacing(np.float32(abs(magnitude))))


def coarse_coordinates(points: np.ndarray, voxel_size: float, name: str) -> str | None:
    """
    Return a warning when ``points`` look stored as float32 at a magnitude too coarse.

    Such a cloud's every coordinate is a float32 (a float64 measurement almost never is, at
    these magnitudes) and the float32 step at its largest coordinate exceeds
    :data:`FLOAT32_STEP_SHARE` of ``voxel_size``: the precision was lost before this package
    saw the points, and no recentring brings it back. None otherwise.
    """
    if len(points) == 0:
        return None
    magnitude = float(np.abs(points).max())
    step = float32_step(magnitude)
    if step <= FLOAT32_STEP_SHARE * voxel_size:
        return None
    sample = points[:: max(1, len(points) // 1000)]
    if not np.array_equal(sample, sample.astype(np.float32).astype(np.float64)):
        return None
    return (f'{name}: coordinates up to {magnitude:.4g} m look stored as float32, whose step '
            f'there is {step:.3g} m (more than a tenth of the {voxel_size:g} m voxel): that '
            'precision is lost already. Store the cloud in doubles (PLY double, PCD F 8, '
            'FLOAT64 PointCloud2 fields), or subtract a local origin before writing float32.')
