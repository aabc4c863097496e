"""
Configuration of the point-cloud front end and of the refinement after the core.

Every radius is a multiple of the voxel size, so one number tunes them all. No Open3D
import here: the node reads these to declare its parameters.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from .fields import check_vector, option
from ..errors import InvalidConfigError

MAP_TARGET_SENSOR = ('frontend.target_sensor is for target clouds: a map (map.file, a prepared '
                     'map) has no one sensor, and free space is not judged from it; unset it')


@dataclasses.dataclass
class FrontEndConfig:
    """Downsampling, normals, FPFH and descriptor matching."""

    normal_radius_factor: float = option(
        2.0, 'Normal estimation radius in voxel sizes.', low=0.1, high=100.0)
    normal_orientation: str = option(
        'origin', "Normal sign (FPFH depends on it): 'centroid' points normals towards the "
        "cloud's centroid (frame-independent), 'origin' towards the frame origin (the sensor "
        "for raw scans in the sensor frame), 'none' keeps PCA's arbitrary, frame-dependent "
        'sign.', choices=('centroid', 'origin', 'none'), ros=True)
    fpfh_radius_factor: float = option(
        5.0, 'FPFH feature radius in voxel sizes.', low=0.5, high=100.0)
    max_correspondences: int = option(
        5000, 'Keep at most this many correspondences (best descriptor distance first); '
        '0 keeps all.', low=0)
    max_keypoints: int = option(
        0, 'Match at most this many source points (a coarser voxel grid over the '
        'downsampled source, one point a cell) against every target point: fewer searches '
        "in the target's descriptor index, but fewer correspondences; 0 matches every point, "
        "except against a prepared map's place, which has its own bound (docs/maps.md).",
        low=0)
    source_sensor: tuple[float, float, float] | None = option(
        None, '[x, y, z]: the position (metres) of the sensor that saw the source cloud, in '
        "that cloud's frame. Set it when the cloud is not in its sensor's frame (a deskewed "
        'scan in base_link, a scan moved into odom or map): normals and free space are judged '
        "from it, else from the frame's origin, refusing right poses (free_space, "
        'low_confidence). Unset (null or []): the origin (docs/frames.md).',
        allow_none=True)
    target_sensor: tuple[float, float, float] | None = option(
        None, 'frontend.source_sensor for the target cloud: the position of its sensor in '
        'its frame (metres); unset (null or []): the origin. Target clouds only: a map '
        '(map.file, a prepared map) has no one sensor and refuses it.', allow_none=True)

    def check(self) -> None:
        """Check the sensor positions; an empty one (``[]``) becomes None (unset)."""
        self.source_sensor = _sensor_position('frontend.source_sensor', self.source_sensor)
        self.target_sensor = _sensor_position('frontend.target_sensor', self.target_sensor)


def _sensor_position(name: str, value: Any) -> tuple[float, float, float] | None:
    """Return ``value`` as three finite floats, None when unset; raise otherwise."""
    items = value.tolist() if hasattr(value, 'tolist') else value
    if items is None or (isinstance(items, (list, tuple)) and not items):
        return None
    try:
        return check_vector(name, (0.0, 0.0, 0.0), items)
    except InvalidConfigError:
        raise InvalidConfigError(
            f'{name} must be [x, y, z], the sensor position in metres (three finite numbers), '
            f"or empty for the cloud frame's origin; got {value!r}") from None


@dataclasses.dataclass
class RefineConfig:
    """Local refinement of the core's estimate (the gates that judge it: :mod:`.gates`)."""

    method: str = option(
        'point_to_plane', "Refinement after the global estimate: 'none', 'point_to_plane' "
        "(Open3D ICP) or 'gicp' (small_gicp).", choices=('none', 'point_to_plane', 'gicp'))
    max_correspondence_distance_factor: float = option(
        1.5, 'Refinement correspondence distance in voxel sizes.', low=0.01, high=100.0)
    refused: bool = option(
        True, 'Refine an estimate the core refuses as well. It stays refused (no refinement '
        'lifts a consensus that does not stand out), but the pose it reports, the best '
        'guess, is the refined one (docs/benchmarks_3dmatch.md).', advanced=True)
