"""
Sensor rigs for extrinsic calibration: the OpenCalib rigs and rigs built from real scans.

The OpenCalib lidar2lidar samples (``calibration/opencalib_lidar2lidar`` under the shared
data) are read with their reference extrinsics; rigs are built from the KITTI scans by
splitting each real scan between two made-up sensors with a known extrinsic. Transforms
are parent <- child: ``p_parent = R p_child + t``, metres.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
import re

from cgags_ros.geometry import apply_transform
from cgags_ros.io.clouds import read_cloud
import numpy as np
from scipy.spatial.transform import Rotation


OPENCALIB = 'calibration/opencalib_lidar2lidar'
REFERENCE = 'croon_extrinsics_recovered_DERIVED.txt'
OPENCALIB_RIGS = {'carla_data': ('front', 'back', 'left', 'right'),
                  'real_world': ('left', 'right')}
KITTI_SCANS = 'kitti/seq00_16scans/pcd'


@dataclasses.dataclass
class RigFrame:
    """One frame of a rig: clouds (each in its sensor frame, metres), stamps in ns."""

    name: str
    parent: np.ndarray
    child: np.ndarray
    parent_stamp_ns: int = 0
    child_stamp_ns: int = 0


def read_reference(path: str | Path) -> dict[tuple[str, str], np.ndarray]:
    """
    Read CROON's recovered extrinsics: ``{('carla_data/004069', 'front'): T_top<-front}``.

    The sensor key is the file name up to its first '-' (``front-004069.pcd``: 'front').
    """
    lines = Path(path).read_text(encoding='utf-8').splitlines()
    out = {}
    for line, following in zip(lines, lines[1:]):
        m = re.match(r'(\S+) device_\d+ ([A-Za-z]+)-\S*\.pcd', line)
        if m:
            values = [float(x) for x in following.split('=', 1)[1].split()]
            out[(m.group(1), m.group(2))] = np.array(values).reshape(4, 4)
    return out


def mean_transform(transforms: list[np.ndarray]) -> np.ndarray:
    """Return the chordal mean rotation and the mean translation of 4x4 transforms."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_matrix([t[:3, :3] for t in transforms]).mean().as_matrix()
    T[:3, 3] = np.mean([t[:3, 3] for t in transforms], axis=0)
    return T


def opencalib_rig(data_dir: str | Path, rig: str, sensor: str
                  ) -> tuple[list[RigFrame], np.ndarray, list[np.ndarray]]:
    """
    Return the frames of one OpenCalib sensor against the top LiDAR (parent = top).

    :returns: (frames in folder order, the reference extrinsic top <- sensor averaged over
        the frames, the per-frame references).
    """
    root = Path(data_dir) / OPENCALIB
    reference = read_reference(root / REFERENCE)
    frames, refs = [], []
    for folder in sorted((root / rig).iterdir()):
        top = next(folder.glob('top-*.pcd'))
        child = next(folder.glob(f'{sensor}-*.pcd'))
        frames.append(RigFrame(folder.name, read_cloud(top), read_cloud(child),
                               _stamp_ns(top.stem), _stamp_ns(child.stem)))
        refs.append(reference[(f'{rig}/{folder.name}', sensor)])
    return frames, mean_transform(refs), refs


def _stamp_ns(stem: str) -> int:
    """Stamp from a real-rig file name ('left-2022-02-15-17-31-37-040': ms of the day)."""
    parts = stem.split('-')
    if len(parts) < 7:
        return 0
    h, m, s, ms = (int(p) for p in parts[-4:])
    return ((h * 60 + m) * 60 + s) * 1_000_000_000 + ms * 1_000_000


def kitti_scans(data_dir: str | Path, indices: list[int]) -> list[np.ndarray]:
    """Return the KITTI scans with these indices (0-15), Velodyne frame, metres."""
    files = sorted((Path(data_dir) / KITTI_SCANS).glob('*.pcd'))
    return [read_cloud(files[i]) for i in indices]


def split_scan(scan: np.ndarray, extrinsic: np.ndarray, rng: np.random.Generator, *,
               azimuth_deg: tuple[float, float] = (-72.0, 72.0),
               elevation_deg: tuple[float, float] = (-90.0, 90.0),
               max_range: float = np.inf, parent_bands: int = 2, child_density: float = 0.5,
               child_noise: float = 0.02, band_deg: float = 0.4
               ) -> tuple[np.ndarray, np.ndarray]:
    """
    Split one real scan between a parent and a child sensor; return (parent, child).

    Points are binned by elevation in ``band_deg`` bands (about a laser ring each): the
    parent keeps every ``parent_bands``-th band (a sparser LiDAR); the child takes the
    bands the parent does not keep, inside its field of view (azimuth and elevation
    ranges in degrees, about the scanner's x axis, and ``max_range`` metres), keeps a
    random ``child_density`` share, gets Gaussian noise of ``child_noise`` metres per axis,
    and is expressed in the child frame: ``extrinsic`` is parent <- child. No point is in
    both clouds.
    """
    finite = scan[np.isfinite(scan).all(axis=1)]
    r = np.linalg.norm(finite, axis=1)
    finite, r = finite[r > 1.0], r[r > 1.0]
    elevation = np.degrees(np.arcsin(finite[:, 2] / r))
    azimuth = np.degrees(np.arctan2(finite[:, 1], finite[:, 0]))
    band = np.floor(elevation / band_deg).astype(int)
    parent_mask = band % parent_bands == 0
    view = ((azimuth >= azimuth_deg[0]) & (azimuth <= azimuth_deg[1])
            & (elevation >= elevation_deg[0]) & (elevation <= elevation_deg[1])
            & (r <= max_range))
    child = finite[~parent_mask & view]
    child = child[rng.random(len(child)) < child_density]
    child = child + rng.normal(0.0, child_noise, child.shape)
    return finite[parent_mask], apply_transform(np.linalg.inv(extrinsic), child)


def kitti_lidar_rig(data_dir: str | Path, seed: int = 0
                    ) -> tuple[list[RigFrame], np.ndarray]:
    """
    Return a second LiDAR built from KITTI scans 0, 7, 14, and its extrinsic parent <- child.

    The child sees 150 of the parent's 360 degrees of azimuth (42 %), on the other scan
    rings, at half their density, with 2 cm noise, turned about every axis; the child's
    stamps are up to 50 ms off the parent's.
    """
    extrinsic = _transform((10.0, -25.0, 120.0), (0.8, -0.4, -0.3))
    return _built(data_dir, extrinsic, seed, azimuth_deg=(-30.0, 120.0), child_density=0.5,
                  child_noise=0.02), extrinsic


def kitti_depth_rig(data_dir: str | Path, seed: int = 1
                    ) -> tuple[list[RigFrame], np.ndarray]:
    """
    Return a dense short-range "depth camera" against a sparse LiDAR, from KITTI scans.

    The camera (optical frame: z forward, x right, y down) looks to the right of the car,
    10 degrees down, sees 80 x 40 degrees up to 15 m, every point of its rings, 1 cm noise;
    the LiDAR keeps every fourth ring (a 16-beam unit). Stamps up to 50 ms apart.
    """
    extrinsic = _transform((-100.0, 0.0, -180.0), (1.2, 0.1, -0.5))
    return _built(data_dir, extrinsic, seed, azimuth_deg=(-130.0, -50.0),
                  elevation_deg=(-30.0, 10.0), max_range=15.0, parent_bands=4,
                  child_density=1.0, child_noise=0.01), extrinsic


def _transform(xyz_deg: tuple[float, float, float], t: tuple[float, float, float]
               ) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler('xyz', xyz_deg, degrees=True).as_matrix()
    T[:3, 3] = t
    return T


def _built(data_dir: str | Path, extrinsic: np.ndarray, seed: int, **split) -> list[RigFrame]:
    rng = np.random.default_rng(seed)
    frames = []
    for k, scan in enumerate(kitti_scans(data_dir, [0, 7, 14])):
        parent, child = split_scan(scan, extrinsic, rng, **split)
        stamp = 10**9 * (k + 1)
        frames.append(RigFrame(f'kitti {7 * k:02d}', parent, child, stamp,
                               stamp + int(rng.uniform(-0.05, 0.05) * 1e9)))
    return frames


def raycast_planes(pose: np.ndarray, planes: list[tuple[np.ndarray, float]],
                   rng: np.random.Generator, *, rings: int = 32,
                   elevation_deg: tuple[float, float] = (-30.0, 30.0),
                   azimuth_step_deg: float = 0.5, max_range: float = 40.0,
                   noise: float = 0.01) -> np.ndarray:
    """
    Simulate a spinning LiDAR at ``pose`` (4x4, sensor -> world) in a world of planes.

    ``planes`` are ``(unit normal, offset)`` with ``normal . x = offset``; each ray stops at
    the nearest plane in front of it within ``max_range`` metres. Returns the hits in the
    sensor frame with Gaussian range noise of ``noise`` metres.
    """
    az = np.radians(np.arange(-180.0, 180.0, azimuth_step_deg))
    el = np.radians(np.linspace(elevation_deg[0], elevation_deg[1], rings))
    A, E = np.meshgrid(az, el)
    rays = np.c_[(np.cos(E) * np.cos(A)).ravel(), (np.cos(E) * np.sin(A)).ravel(),
                 np.sin(E).ravel()]
    world_rays = rays @ pose[:3, :3].T
    origin = pose[:3, 3]
    best = np.full(len(rays), np.inf)
    for normal, offset in planes:
        normal = np.asarray(normal, dtype=np.float64)
        along = world_rays @ normal
        with np.errstate(divide='ignore', invalid='ignore'):
            t = (offset - origin @ normal) / along
        best = np.where((t > 1e-6) & (t < best), t, best)
    hit = best <= max_range
    ranges = best[hit] + rng.normal(0.0, noise, int(hit.sum()))
    return rays[hit] * ranges[:, None]


def corridor(width: float = 2.5, height: float = 3.0) -> list[tuple[np.ndarray, float]]:
    """Return the planes of a corridor along the world x axis (floor at z = 0)."""
    return [(np.array([0.0, 0.0, 1.0]), 0.0), (np.array([0.0, 0.0, 1.0]), height),
            (np.array([0.0, 1.0, 0.0]), -width / 2), (np.array([0.0, 1.0, 0.0]), width / 2)]
