"""
Configuration of the point-cloud front end and of the refinement after the core.

Every radius is a multiple of the voxel size, so one number tunes them all. No Open3D
import here: the node reads these to declare its parameters.
"""

from __future__ import annotations

import dataclasses

from .fields import option


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
        "in the target's descriptor index, but fewer correspondences; 0 matches every point.",
        low=0)


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
