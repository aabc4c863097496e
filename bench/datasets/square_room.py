"""
A near-square room scanned by a depth sensor: the case that a half-turn twin cannot catch.

A room whose floor plan is (nearly) square looks alike turned a quarter of the way about the
vertical; furniture placed around it four-fold (shelves against each wall, boxes in the
corners) keeps that symmetry, and a few pieces off the pattern (``clutter``) break it only
weakly, as in a real room. :func:`scan` ray-casts such a room from a sensor pose: each
point is the first surface a ray meets, in the sensor's frame (the sensor at the origin,
as a depth camera's or a LiDAR's cloud), so the free-space test sees what a real sensor
would. Two scans of one room and the truth between them make a registration pair whose
wrong answers are quarter turns.

Units: metres; the room's floor is ``z = 0``, its vertical ``+z``.
"""

from __future__ import annotations

import dataclasses

from cgags_ros.geometry import make_transform
import numpy as np
from scipy.spatial.transform import Rotation


@dataclasses.dataclass(frozen=True)
class Box:
    """An axis-aligned box (``lo``..``hi``, metres, room frame)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]


def square_room(side: float = 5.0, height: float = 2.6, aspect: float = 1.0,
                clutter: int = 2, seed: int = 0) -> tuple[Box, list[Box]]:
    """
    Return the room (its inside is the first box) and the furniture in it.

    ``side``: the floor's side along x; along y it is ``side * aspect`` (1: square). A shelf
    stands against the middle of each wall and a low box in each corner: a quarter turn maps
    the furniture onto itself. ``clutter`` more boxes stand at random places (``seed``).
    """
    hx, hy = side / 2, side * aspect / 2
    room = Box((-hx, -hy, 0.0), (hx, hy, height))
    boxes = []
    for angle in (0.0, 0.5 * np.pi, np.pi, 1.5 * np.pi):
        c, s = round(np.cos(angle)), round(np.sin(angle))
        # a shelf 1.2 m wide, 0.4 m deep, 1.8 m tall against the wall the direction faces
        centre = np.array([c * (hx - 0.2), s * (hy - 0.2)])
        half = np.abs(np.array([c * 0.2 + s * 0.6, s * 0.2 + c * 0.6]))
        boxes.append(Box((*(centre - half), 0.0), (*(centre + half), 1.8)))
        # a low box in the corner to the left of that wall
        corner = np.array([c - s, s + c]) * np.array([hx - 0.45, hy - 0.45])
        boxes.append(Box((*(corner - 0.3), 0.0), (*(corner + 0.3), 0.7)))
    rng = np.random.default_rng(seed)
    for _ in range(clutter):
        centre = rng.uniform(-0.5, 0.5, 2) * np.array([hx, hy])
        half = rng.uniform(0.15, 0.4, 2)
        boxes.append(Box((*(centre - half), 0.0), (*(centre + half), rng.uniform(0.4, 1.1))))
    return room, boxes


def sensor_pose(x: float, y: float, yaw_deg: float, z: float = 1.3,
                pitch_deg: float = 0.0) -> np.ndarray:
    """
    Return a sensor's pose in the room (4x4, ``p_room = T p_sensor``).

    The sensor looks along its own +x, yawed by ``yaw_deg`` about the vertical and pitched
    down by ``pitch_deg``.
    """
    R = Rotation.from_euler('zy', [yaw_deg, pitch_deg], degrees=True).as_matrix()
    return make_transform(R, [x, y, z])


def scan(room: Box, boxes: list[Box], pose: np.ndarray, fov_deg: tuple[float, float] =
         (90.0, 60.0), step_deg: float = 0.35, noise: float = 0.005,
         seed: int = 0) -> np.ndarray:
    """
    Return the points a sensor at ``pose`` sees, in its own frame ((N, 3), metres).

    Rays on a grid of ``step_deg`` over the field of view (horizontal, vertical; 360 makes a
    spinning sensor), each ending at the nearest surface it meets: the room's inside or a
    box's outside. Range noise ``noise`` (metres, Gaussian, ``seed``).
    """
    h = np.deg2rad(np.arange(-fov_deg[0] / 2, fov_deg[0] / 2, step_deg))
    v = np.deg2rad(np.arange(-fov_deg[1] / 2, fov_deg[1] / 2 + 1e-9, step_deg))
    az, el = np.meshgrid(h, v)
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)],
                    axis=-1).reshape(-1, 3)
    origin = pose[:3, 3]
    world = dirs @ pose[:3, :3].T
    depth = _exit_distance(origin, world, room)
    for box in boxes:
        depth = np.minimum(depth, _entry_distance(origin, world, box))
    ok = np.isfinite(depth)
    rng = np.random.default_rng(seed)
    depth = depth[ok] + rng.normal(0.0, noise, int(ok.sum()))
    return dirs[ok] * depth[:, None]


def _slabs(origin: np.ndarray, dirs: np.ndarray, box: Box) -> tuple[np.ndarray, np.ndarray]:
    """Return each ray's entry and exit distance of ``box`` (the slab method)."""
    with np.errstate(divide='ignore', invalid='ignore'):
        inv = 1.0 / dirs
        t1 = (np.asarray(box.lo) - origin) * inv
        t2 = (np.asarray(box.hi) - origin) * inv
    near = np.nanmax(np.minimum(t1, t2), axis=1)
    far = np.nanmin(np.maximum(t1, t2), axis=1)
    return near, far


def _exit_distance(origin: np.ndarray, dirs: np.ndarray, box: Box) -> np.ndarray:
    """Return where each ray leaves ``box`` from inside (its walls seen from within)."""
    return _slabs(origin, dirs, box)[1]


def _entry_distance(origin: np.ndarray, dirs: np.ndarray, box: Box) -> np.ndarray:
    """Return where each ray first meets ``box`` from outside (inf when it misses)."""
    near, far = _slabs(origin, dirs, box)
    return np.where((near <= far) & (near > 0), near, np.inf)


def pair(room: Box, boxes: list[Box], source_pose: np.ndarray, target_pose: np.ndarray,
         **scan_options) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (source scan, target scan, truth) with ``p_target = truth p_source``."""
    source = scan(room, boxes, source_pose, seed=1, **scan_options)
    target = scan(room, boxes, target_pose, seed=2, **scan_options)
    return source, target, np.linalg.inv(target_pose) @ source_pose


def room_map(room: Box, boxes: list[Box], voxel_size: float, frontend,
             positions: tuple = ((-1.2, -1.2), (1.2, -1.2), (1.2, 1.2), (-1.2, 1.2), (0, 0))
             ) -> tuple[np.ndarray, np.ndarray]:
    """
    Return a prior map of the room: points and normals (room frame), each facing its sensor.

    Spinning scans (360 x 90 degrees) from ``positions`` (x, y at sensor height), fused; each
    scan's normals estimated in its own frame with ``frontend`` (a ``FrontendConfig``), as a
    map fused from a robot's scans carries them.
    """
    from cgags_ros.frontend.features import estimate_normals
    from cgags_ros.geometry import apply_transform

    points, normals = [], []
    for x, y in positions:
        P = sensor_pose(x, y, 0.0)
        cloud = scan(room, boxes, P, fov_deg=(360.0, 90.0), step_deg=0.5)
        points.append(apply_transform(P, cloud))
        normals.append(estimate_normals(cloud, voxel_size, frontend) @ P[:3, :3].T)
    return np.vstack(points), np.vstack(normals)
