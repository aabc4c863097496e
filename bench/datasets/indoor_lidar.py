"""
A spinning LiDAR indoors, simulated on the real rooms of the 3DMatch scenes.

No indoor LiDAR scan is in the shared data, so one is ray-cast: a 32-beam spinning LiDAR
(:class:`SpinningLidar`: beams evenly from -15 to +15 degrees of elevation, one column every
0.4 degree of azimuth, returns from 0.3 to 12 m, 1 cm range noise) stands level at the
sensor position of an odd fragment of a scene, and each ray returns the first surface of the
scene's **odd fragments fused** it meets: geometry held out of a map fused from the even
fragments, as the benchmark's floor is (``bench.maps``).

Ray casting marches each ray through the fused points' distance field (a k-d tree): a step
is the free distance ahead (looked for up to ``LOOK_AHEAD``) less the hit radius
``HIT_RADIUS``, so that it crosses no point's ball of that radius, and at least half that
radius; a ray ends where it comes within ``HIT_RADIUS`` of a point. The fragments are
voxelized at 2.5 cm, so balls of 2.5 cm about their points close every surface and no ray
slips through one. The range is that nearest point's distance along the ray, which puts the
return on the surface rather than a radius before it, plus the noise. What no fragment saw
returns nothing, as an open door or a window does.

Level: a handheld camera is held without roll, so each camera's x axis is horizontal; the
scene's up is the direction closest to perpendicular to all of them (:func:`scene_up`),
signed against the cameras' mean y axis (image down). The LiDAR's z is that up and its x
the camera's viewing direction made horizontal.

A scan is in the sensor frame, the sensor at its origin (``p_scene = pose p_scan``), as a
driver publishes it. Units: metres, degrees where named.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from cgags_ros.geometry import apply_transform, make_transform
import numpy as np
from scipy.spatial import cKDTree

from .threedmatch import fragment_poses, Fragments

HIT_RADIUS = 0.025  # metres: the fragments' voxel, so that no ray slips through a surface
LOOK_AHEAD = 0.3  # metres: the free distance a step looks for (far searches cost most)
MAX_STEPS = 600  # marching steps a ray may take before it counts as no return


@dataclasses.dataclass(frozen=True)
class SpinningLidar:
    """
    A spinning multi-beam LiDAR: its beams, azimuth step, ranges and noise.

    :ivar beams: beams, their elevations evenly spread over ``elevation`` (degrees).
    :ivar azimuth_step: degrees between two columns of a revolution.
    :ivar min_range, max_range: metres; returns outside are dropped.
    :ivar noise: standard deviation of the range noise, metres.
    """

    beams: int = 32
    elevation: tuple[float, float] = (-15.0, 15.0)
    azimuth_step: float = 0.4
    min_range: float = 0.3
    max_range: float = 12.0
    noise: float = 0.01

    def directions(self) -> np.ndarray:
        """Return the (beams x columns, 3) unit ray directions in the sensor frame."""
        elevation = np.radians(np.linspace(*self.elevation, self.beams))
        azimuth = np.radians(np.arange(0.0, 360.0, self.azimuth_step))
        el, az = np.meshgrid(elevation, azimuth, indexing='ij')
        return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)],
                        axis=-1).reshape(-1, 3)


def scene_up(poses: dict[int, np.ndarray]) -> np.ndarray:
    """Return the scene's unit up vector (scene frame) from its cameras' poses."""
    x_axes = np.array([P[:3, 0] for P in poses.values()])
    up = np.linalg.svd(x_axes, full_matrices=False)[2][-1]
    down = np.mean([P[:3, 1] for P in poses.values()], axis=0)
    return -up if up @ down > 0 else up


def lidar_pose(camera: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Return the level LiDAR pose at ``camera``'s position: z up, x its view made level."""
    view = camera[:3, 2] - (camera[:3, 2] @ up) * up
    if np.linalg.norm(view) < 1e-6:  # looking straight up or down: any heading is level
        view = camera[:3, 0] - (camera[:3, 0] @ up) * up
    x = view / np.linalg.norm(view)
    return make_transform(np.column_stack([x, np.cross(up, x), up]), camera[:3, 3])


def cast(tree: cKDTree, pose: np.ndarray, lidar: SpinningLidar,
         rng: np.random.Generator) -> np.ndarray:
    """
    Return the scan (M, 3) that ``lidar`` at ``pose`` takes of the points in ``tree``.

    In the sensor frame; ``pose`` maps it into the points' frame.
    """
    local = lidar.directions()
    rays = local @ pose[:3, :3].T
    origin = pose[:3, 3]
    t = np.full(len(rays), max(tree.query(origin)[0] - HIT_RADIUS, 0.0))  # the free sphere
    hit = np.full(len(rays), -1)
    active = np.arange(len(rays))
    for _ in range(MAX_STEPS):
        if not len(active):
            break
        free, nearest = tree.query(origin + t[active, None] * rays[active],
                                   distance_upper_bound=LOOK_AHEAD)
        free = np.minimum(free, LOOK_AHEAD)
        ended = free <= HIT_RADIUS
        hit[active[ended]] = nearest[ended]
        t[active] += np.maximum(free - HIT_RADIUS, 0.5 * HIT_RADIUS)
        active = active[~ended & (t[active] <= lidar.max_range)]
    rays_hit = hit >= 0
    points = tree.data[hit[rays_hit]]
    ranges = np.einsum('ij,ij->i', points - origin, rays[rays_hit])
    ranges = ranges + rng.normal(0.0, lidar.noise, len(ranges))
    keep = (ranges >= lidar.min_range) & (ranges <= lidar.max_range)
    return local[rays_hit][keep] * ranges[keep, None]


def scans(root: str | Path, scene: str, fragments: list[int],
          lidar: SpinningLidar = SpinningLidar(), seed: int = 0
          ) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """
    Return ``(k, scan, pose)`` of the LiDAR at each odd fragment ``k`` of ``fragments``.

    ``pose`` maps the scan (sensor frame) into the scene's frame; the surfaces are the
    scene's odd fragments fused.
    """
    if any(k % 2 == 0 for k in fragments):
        raise ValueError('the LiDAR stands at odd fragments: the even ones make the map')
    poses, clouds = fragment_poses(root, scene), Fragments(root, scene)
    surface = np.vstack([apply_transform(P, clouds[k]) for k, P in poses.items() if k % 2])
    tree, up = cKDTree(surface), scene_up(poses)
    rng = np.random.default_rng(seed)
    out = []
    for k in fragments:
        pose = lidar_pose(poses[k], up)
        out.append((k, cast(tree, pose, lidar, rng), pose))
    return out
