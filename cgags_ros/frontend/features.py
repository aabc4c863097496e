"""
Features of one cloud: clean, voxel-downsample, normals, FPFH.

Open3D is used in the front end only, never in the registration core. All lengths are
metres; every radius is a multiple of the voxel size ``v``. Arrays are numpy at every
boundary; each cloud stays in its own frame (nothing is transformed here).
"""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
from scipy.spatial import cKDTree

from .descriptor_index import DescriptorIndex
from .fpfh import fpfh_with_spacing
from .matching import informative_index
from ..config.frontend import FrontEndConfig
from ..errors import EmptyCloudError, InvalidInputError
from ..geometry import point_resolution
from ..open3d_import import open3d as o3d
from ..timing import timed

# A normal is the PCA of at most this many nearest neighbours within its radius.
NORMAL_MAX_NN = 30
# A cloud with fewer points after downsampling is refused as too small (too_few_points).
MIN_POINTS = 10

# Two threads may build one cloud's index at once: a pair's own and its target's beside it
# (pipeline.register), when source and target are one cached cloud.
_INDEX_LOCK = threading.Lock()


@dataclasses.dataclass
class CloudFeatures:
    """
    One downsampled cloud and what the front end computed on it (cloud's own frame).

    :ivar points: (M, 3) voxel centroids, metres.
    :ivar normals: (M, 3) unit normals, oriented per ``FrontEndConfig.normal_orientation``.
    :ivar descriptors: (M, 33) FPFH histograms.
    :ivar resolution: pr, the mean nearest-neighbour distance of ``points``, metres.
    :ivar tree: k-d tree over ``points`` (built for ``resolution``, reused by the gates).
    :ivar sensor_at_origin: whether the frame's origin may be the sensor that saw the points
        (False for a map, or a cloud moved from far coordinates,
        :mod:`cgags_ros.coordinates`): free space is judged from such a view only.
    """

    points: np.ndarray
    normals: np.ndarray
    descriptors: np.ndarray
    resolution: float
    tree: cKDTree
    sensor_at_origin: bool = True
    _index: list = dataclasses.field(default_factory=list, repr=False, compare=False)

    def with_sensor(self, at_origin: bool) -> CloudFeatures:
        """Return these features with ``sensor_at_origin`` set (a copy: cached ones are shared)."""
        if self.sensor_at_origin == at_origin:
            return self
        return dataclasses.replace(self, sensor_at_origin=at_origin)

    def descriptor_index(self, workers: int = 1) -> DescriptorIndex | None:
        """
        Return the index of these descriptors that matching searches as its target.

        Built on the first call and kept: a latched target or a map (these features are
        cached, :mod:`~cgags_ros.pipeline.cache`) pays for it once. None when no
        descriptor is informative.
        """
        with _INDEX_LOCK:  # one module lock: the features stay plain, picklable data
            if not self._index:
                self._index.append(informative_index(self.descriptors, workers))
            return self._index[0]


def finite_points(points: np.ndarray, name: str = 'cloud') -> np.ndarray:
    """
    Return the (N, 3) float64 ``points`` without their non-finite rows.

    The result is ``points`` itself, not a copy, when it is already a clean float64 array:
    the front end never writes to it.

    :raises InvalidInputError: for a wrong shape or non-numeric data.
    :raises EmptyCloudError: when no finite point is left.
    """
    try:
        pts = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f'{name}: points are not numeric ({exc})') from exc
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidInputError(f'{name}: expected an (N, 3) array of x, y, z in metres, '
                                f'got shape {pts.shape}')
    # One flat pass first: the per-row mask is far dearer, and clouds are nearly always
    # all finite.
    if not np.isfinite(pts).all():
        pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        raise EmptyCloudError(f'{name}: no finite points (got {len(points)} rows, all '
                              'empty or NaN/inf); check the sensor driver or the file')
    return pts


def downsample(points: np.ndarray, voxel_size: float, min_points: int,
               name: str = 'cloud') -> np.ndarray:
    """
    Return the voxel-grid centroids of ``points`` (metres).

    :raises EmptyCloudError: when fewer than ``min_points`` remain.
    """
    return _voxel_means(_o3d_cloud(points), voxel_size, min_points, name)[0]


def downsample_with_sides(points: np.ndarray, sides: np.ndarray, voxel_size: float,
                          min_points: int, name: str = 'cloud'
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Return :func:`downsample`'s centroids and the mean of ``sides`` (N, 3) in each voxel."""
    cloud = _o3d_cloud(points)
    cloud.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(sides, np.float64))
    return _voxel_means(cloud, voxel_size, min_points, name)


def _voxel_means(cloud: o3d.geometry.PointCloud, voxel_size: float, min_points: int,
                 name: str) -> tuple[np.ndarray, np.ndarray]:
    cloud = cloud.voxel_down_sample(voxel_size)
    down = np.asarray(cloud.points)
    if len(down) < min_points:
        raise EmptyCloudError(
            f'{name}: only {len(down)} point(s) left after {voxel_size:g} m voxel downsampling '
            f'(MIN_POINTS = {min_points} needed); lower the voxel size or check that '
            'the cloud is not a single repeated point')
    return down, np.asarray(cloud.normals)


def estimate_normals(points: np.ndarray, voxel_size: float, config: FrontEndConfig,
                     sides: np.ndarray | None = None) -> np.ndarray:
    """
    Estimate unit PCA normals from the neighbours within ``normal_radius_factor * v``.

    They are oriented per ``normal_orientation``: PCA's own sign changes with the frame, and
    FPFH with it. ``sides`` (M, 3), when given, overrides that sign wherever it is usable:
    each normal is turned to agree with its row, e.g. the normals a map file carries, which
    face the sensors that saw each surface as a scan's face its own sensor.
    """
    cloud = _tensor_cloud(points)
    cloud.estimate_normals(max_nn=NORMAL_MAX_NN,
                           radius=config.normal_radius_factor * voxel_size)
    normals = cloud.point.normals.numpy().copy()
    if config.normal_orientation == 'none':
        return normals
    viewpoint = points.mean(axis=0) if config.normal_orientation == 'centroid' else np.zeros(3)
    flip = np.einsum('ij,ij->i', normals, viewpoint - points) < 0
    if sides is not None:
        agree = np.einsum('ij,ij->i', normals, sides)
        usable = np.isfinite(agree) & (np.abs(agree) > 1e-6)
        flip = np.where(usable, agree < 0, flip)
    normals[flip] *= -1.0
    return normals


def extract_features(points: np.ndarray, voxel_size: float, config: FrontEndConfig,
                     name: str = 'cloud', timings: dict[str, float] | None = None,
                     workers: int = 1, sides: np.ndarray | None = None) -> CloudFeatures:
    """
    Extract features: finite points -> downsample -> normals -> FPFH.

    ``sides``: (N, 3) normals stored with ``points`` (rows matching), used for the sign of
    the estimated normals only (:func:`estimate_normals`). Each stage's seconds are added to
    ``timings``; FPFH runs on ``workers`` threads (the result does not depend on it).
    """
    timings = {} if timings is None else timings
    down_sides = None
    with timed(timings, 'downsample'):
        if sides is None:
            down = downsample(finite_points(points, name), voxel_size, MIN_POINTS, name)
        else:
            keep = np.isfinite(points).all(axis=1)
            down, down_sides = downsample_with_sides(finite_points(points[keep], name),
                                                     sides[keep], voxel_size,
                                                     MIN_POINTS, name)
    with timed(timings, 'normals'):
        normals = estimate_normals(down, voxel_size, config, down_sides)
    with timed(timings, 'fpfh'):
        descriptors, spacing = fpfh_with_spacing(down, normals, voxel_size, config, workers)
    tree = cKDTree(down)
    return CloudFeatures(down, normals, descriptors, point_resolution(down, tree, spacing),
                         tree)


def _tensor_cloud(points: np.ndarray) -> o3d.t.geometry.PointCloud:
    return o3d.t.geometry.PointCloud(o3d.core.Tensor(np.ascontiguousarray(points, np.float64)))


def _o3d_cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
