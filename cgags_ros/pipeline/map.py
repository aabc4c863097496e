"""
A prior map from a file: its features computed once, cached on disk, reused by every scan.

:func:`load_map` reads the map file (PLY, PCD, NPY, XYZ/CSV/TXT; metres, map frame, any
coordinates: :mod:`cgags_ros.coordinates`), drops non-finite points (counted), and returns the
map's :class:`PreparedMap`: the downsampled points, normals, FPFH descriptors, their
descriptor index and k-d tree :func:`register_clouds` needs, its places
(:mod:`.places`: where a scan is looked for before it is registered), and nothing of the
raw cloud.
With a cache directory they are stored (:mod:`cgags_ros.io.map_cache`) under a key of the
file's content hash and every setting that changes them (:data:`FEATURE_SETTINGS`, the voxel
size, the Open3D version), and every load, the first included, returns them memory-mapped from
there: the processes that load one map share one copy, and a later load (``cache == 'hit'``)
costs the k-d tree alone. A changed setting or file is a ``'miss'`` and recomputes.
``cgags-map`` prepares and inspects a map's cache ahead of time.

Normal orientation: a scan's normals face its sensor (``normal_orientation`` 'origin'); a
map fused from many views has no one sensor, so with 'origin' a map file that carries
normals (PLY ``nx ny nz``, PCD ``normal_x normal_y normal_z``, as mappers write them facing
the sensors that saw each surface) gives the map's normals their sign; FPFH then describes
both clouds alike. Without normals in the file the map's face its frame origin, which is
right for a single scan kept in its sensor frame only: use 'centroid' for both then
(docs/relocalization.md).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
import time
from typing import Any
import warnings

import numpy as np
from scipy.spatial import cKDTree

from .places import PlaceIndex
from ..config.pipeline import PipelineConfig
from ..coordinates import (coarse_coordinates, CoarseCoordinatesWarning, local_origin, moved,
                           translation)
from ..errors import EmptyCloudError, InvalidInputError
from ..frontend.descriptor_index import DescriptorIndex
from ..frontend.features import CloudFeatures, extract_features, MIN_POINTS, NORMAL_MAX_NN
from ..frontend.fpfh import FPFH_MAX_NN
from ..frontend.matching import informative_rows
from ..geometry import bounds
from ..io import map_cache
from ..io.clouds import read_cloud_and_normals

# FrontEndConfig fields that change a cloud's features (the matching options do not); the
# front end's constants that change them are in the settings too.
FEATURE_SETTINGS = ('normal_radius_factor', 'normal_orientation', 'fpfh_radius_factor')


@dataclasses.dataclass
class PreparedMap:
    """
    A map's features and where they came from.

    :ivar features: the downsampled map (points, normals, FPFH, tree; map frame, metres).
    :ivar settings: the feature settings they were computed with (:func:`feature_settings`).
    :ivar path: the map file.
    :ivar digest: blake2b hex digest of the file's bytes.
    :ivar cache: 'hit' (read from the cache), 'miss' (computed and stored) or 'off' (no
        cache directory).
    :ivar cache_path: the cache entry ('' when off).
    :ivar num_raw_points: points in the file.
    :ivar num_nonfinite: of those, rows with a NaN or inf coordinate (dropped).
    :ivar load_s: seconds to read, hash and featurise (or read back) the map.
    :ivar oriented_by: what signed the map's normals: 'file normals' or the configured
        ``normal_orientation``.
    :ivar symmetries: the turns that map the map onto itself (4x4 each,
        :func:`~.twins.map_symmetries`, between local frames), found when first asked for;
        None until then.
    :ivar origin: (3,) where the map's local frame sits in the map frame (metres): the
        features' points are the map's less it (:func:`~cgags_ros.coordinates.local_origin`:
        zeros unless the map is georeferenced, far from its frame's origin).
    :ivar places: the map's places (:class:`~.places.PlaceIndex`); None for a map that
        is registered whole (:meth:`whole`, a place's submap).
    """

    features: CloudFeatures
    settings: dict[str, Any]
    path: str
    digest: str
    cache: str
    cache_path: str
    num_raw_points: int
    num_nonfinite: int
    load_s: float
    oriented_by: str = ''
    symmetries: list[np.ndarray] | None = None
    origin: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    places: PlaceIndex | None = None

    def whole(self) -> PreparedMap:
        """Return this map without its places: a scan is registered against all of it."""
        return dataclasses.replace(self, places=None)

    def part(self, features: CloudFeatures) -> PreparedMap:
        """Return a part of this map (a place's submap: ``features``, local frame) as a map."""
        return dataclasses.replace(self, features=features, places=None)

    def to_local(self, T: np.ndarray) -> np.ndarray:
        """Return a pose in the map frame (4x4, target side) in the features' local frame."""
        return translation(-self.origin) @ np.asarray(T, dtype=np.float64)

    def to_map(self, T: np.ndarray) -> np.ndarray:
        """Return a pose in the features' local frame in the map frame (undoing to_local)."""
        return translation(self.origin) @ np.asarray(T, dtype=np.float64)

    def info(self) -> dict[str, Any]:
        """Return a small, picklable summary (what the node reports; no arrays)."""
        return {'path': self.path, 'digest': self.digest, 'cache': self.cache,
                'cache_path': self.cache_path, 'raw_points': self.num_raw_points,
                'nonfinite_points': self.num_nonfinite,
                'points': len(self.features.points), 'voxel_size': self.settings['voxel_size'],
                'normals': self.oriented_by, 'load_s': round(self.load_s, 3),
                'origin': [float(x) for x in self.origin],
                'places': 0 if self.places is None else len(self.places)}


def feature_settings(config: PipelineConfig) -> dict[str, Any]:
    """Return every setting that changes a cloud's features (voxel size, front end, Open3D)."""
    from ..open3d_import import open3d

    out = {name: getattr(config.frontend, name) for name in FEATURE_SETTINGS}
    out.update(normal_max_nn=NORMAL_MAX_NN, fpfh_max_nn=FPFH_MAX_NN, min_points=MIN_POINTS)
    out.update(voxel_size=float(config.voxel_size), open3d=open3d.__version__)
    return out


def load_map(path: str | Path, config: PipelineConfig,
             cache_dir: str | Path | None = None) -> PreparedMap:
    """
    Read the map file and return its features (from the cache when they are there).

    :param path: the map file, points in the map frame, metres.
    :param config: the pipeline configuration whose voxel size and front end apply.
    :param cache_dir: directory of the feature cache; None or '' disables it.
    :raises InvalidInputError: the file is missing, unreadable or not a point cloud, or the
        cache directory cannot be written.
    :raises EmptyCloudError: the map has no finite point, or too few after downsampling.
    """
    start = time.perf_counter()
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f'map.file {str(path)!r}: no such file')
    settings = feature_settings(config)
    digest = map_cache.file_digest(path)
    key = map_cache.cache_key(digest, settings)
    stored = map_cache.load_entry(cache_dir, key) if cache_dir else None
    status = 'hit'
    if stored is None:
        features, places, meta = _prepare(path, config)
        if not cache_dir:
            return _prepared(features, places, meta, settings, path, digest, 'off', '', start)
        map_cache.save_entry(cache_dir, key, _arrays(features, places), {
            **meta, 'map': str(path.resolve()), 'digest': digest, 'settings': settings})
        # Read back: the memory-mapped copy is the one every process that loads this map
        # shares; the one just computed is freed.
        stored, status = map_cache.load_entry(cache_dir, key), 'miss'
        if stored is None:
            return _prepared(features, places, meta, settings, path, digest, status,
                             str(map_cache.entry_path(cache_dir, key)), start)
    arrays, meta = stored
    return _prepared(_features_from(arrays), PlaceIndex.from_arrays(arrays), meta, settings,
                     path, digest, status, str(map_cache.entry_path(cache_dir, key)), start)


def _prepare(path: Path, config: PipelineConfig
             ) -> tuple[CloudFeatures, PlaceIndex | None, dict[str, Any]]:
    """Read the map file; return its features (descriptor index built), places and meta."""
    points, sides = read_cloud_and_normals(path)
    if config.frontend.normal_orientation != 'origin':
        sides = None  # the file's normals sign the map's only where a scan's face its sensor
    finite = np.isfinite(points).all(axis=1)
    raw, nonfinite = len(points), int(len(points) - np.count_nonzero(finite))
    if not finite.any():
        raise EmptyCloudError(f'map.file {str(path)!r}: no finite points ({raw} rows, all '
                              'empty or NaN/inf)')
    oriented_by = config.frontend.normal_orientation if sides is None else 'file normals'
    points = points[finite]
    warning = coarse_coordinates(points, config.voxel_size, f'map.file {str(path)!r}')
    if warning:
        warnings.warn(warning, CoarseCoordinatesWarning, stacklevel=3)
    origin = local_origin(points)
    features = extract_features(moved(points, origin), config.voxel_size, config.frontend,
                                'map', sides=None if sides is None else sides[finite])
    features.descriptor_index()  # built with the map, not on the first scan
    places = PlaceIndex.build(features, config.voxel_size)
    low, high = (side + origin for side in bounds(features.points))
    return features, places, {
        'raw_points': raw, 'nonfinite_points': nonfinite, 'oriented_by': oriented_by,
        'origin': origin.tolist(), 'resolution': features.resolution,
        'points': len(features.points), 'extent': [low.tolist(), high.tolist()],
        'places': 0 if places is None else len(places)}


def _prepared(features: CloudFeatures, places: PlaceIndex | None, meta: dict[str, Any],
              settings: dict[str, Any], path: Path, digest: str, status: str, entry: str,
              start: float) -> PreparedMap:
    return PreparedMap(features, settings, str(path), digest, status, entry,
                       int(meta['raw_points']), int(meta['nonfinite_points']),
                       time.perf_counter() - start, str(meta['oriented_by']),
                       origin=np.asarray(meta['origin'], dtype=np.float64), places=places)


def _arrays(features: CloudFeatures, places: PlaceIndex | None) -> dict[str, np.ndarray]:
    """Return what the cache stores of ``features``: the arrays, the index's, the places'."""
    arrays = {'points': features.points, 'normals': features.normals,
              'descriptors': features.descriptors,
              'resolution': np.array([features.resolution])}
    index = features.descriptor_index()
    if index is not None:
        arrays.update({f'index.{k}': v for k, v in index.to_arrays().items()})
    if places is not None:
        arrays.update(places.to_arrays())
    return arrays


def matches_config(prepared: PreparedMap, config: PipelineConfig) -> bool:
    """Tell whether ``prepared`` was computed with the feature settings of ``config``."""
    return prepared.settings == feature_settings(config)


def _features_from(arrays: dict[str, np.ndarray]) -> CloudFeatures:
    """Return the features of a cache entry's arrays, as they are (memory-mapped)."""
    points = arrays['points']
    # The tree indexes the mapped points in place (its own arrays are a few bytes a point).
    features = CloudFeatures(points, arrays['normals'], arrays['descriptors'],
                             float(arrays['resolution'][0]), cKDTree(points))
    index = {k[len('index.'):]: v for k, v in arrays.items() if k.startswith('index.')}
    kept = DescriptorIndex.from_arrays(index) if index else None
    if kept is not None and kept.rows is None:  # a cache written before it kept them
        kept.rows = informative_rows(features.descriptors)
    features._index.append(kept)
    return features


class MapHolder:
    """
    The last map loaded in this process, reloaded when its path or the settings change.

    The registration process keeps one: a restart of the map (new file, new voxel size)
    replaces it, so at most one map's features are held.
    """

    def __init__(self) -> None:
        self.prepared: PreparedMap | None = None
        self._source: tuple[str, str] | None = None

    def get(self, path: str, config: PipelineConfig, cache_dir: str = '') -> PreparedMap:
        """Return the map of ``path`` for ``config``, loading (or re-loading) it if needed."""
        current = self.prepared
        if (current is not None and self._source == (path, cache_dir)
                and matches_config(current, config)):
            return current
        self.prepared = None  # free the old map before the new one is built
        self.prepared = load_map(path, config, cache_dir or None)
        self._source = (path, cache_dir)
        return self.prepared
