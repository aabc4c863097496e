r"""
A submap's descriptor index: cut from cells fitted once to the map, or fitted to the submap.

Run by hand from the repository root (~2 min a map; one thread, nothing registered)::

    .venv/bin/python -m bench.studies.submap_index [--maps campus floor growth12] \
        [--queries 6] [--shares 2 4 8 16 32]

For ``bench.maps``' campus and four-room floor (and ``growth12``, its twelve look-alike
rooms, on which the share was not chosen), and each map's first ``--queries`` queries, the
places :mod:`cgags_ros.pipeline.locate` tests are ranked as it ranks them (without the
consensus place). Each submap's index is built three ways: as the map's cache holds it
(:meth:`~cgags_ros.pipeline.places.PlaceIndex.submap`, cells for
:data:`~cgags_ros.pipeline.places.SUBMAP_SHARE` of the map), fitted to the submap alone (a
:class:`~cgags_ros.frontend.descriptor_index.DescriptorIndex` of its rows), and cut from cells
fitted for each of ``--shares``. Prints, per way, the median over submaps of the build, of
the test's match (the scan's keypoints) and of a registration's (5000 scan points), and
checks that every way matches the same correspondences (the index is exact).
"""

from __future__ import annotations

from pathlib import Path
import tempfile
import time

from bench.common import argument_parser
import bench.maps as built_maps
from cgags_ros.config import pipeline_config_from
from cgags_ros.coordinates import local_origin, moved
from cgags_ros.frontend.descriptor_index import Cells
from cgags_ros.frontend.features import CloudFeatures
from cgags_ros.frontend.matching import match_features
from cgags_ros.io.clouds import write_cloud
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import places
from cgags_ros.pipeline.cache import cached_features
from cgags_ros.pipeline.locate import PLACE_KEYPOINTS, TESTED
from cgags_ros.pipeline.map import load_map
import numpy as np


def measure(built: dict, queries: int, shares: list[int]) -> dict[str, list[tuple]]:
    """Return, per way, (build s, test match s, registration match s) a submap."""
    cfg = pipeline_config_from({'voxel_size': built['voxel']})
    seen: dict[str, list[tuple]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / 'map.ply'
        write_cloud(path, built['points'], built['normals'])
        prepared = load_map(path, cfg, Path(tmp) / 'cache')
        features = prepared.features
        whole = features.descriptor_index().rows
        cells = {share: Cells.fit(features.descriptors[whole], len(whole) // share)
                 for share in shares}
        ways = {'cached': lambda rows: prepared.places.submap(features, rows),
                'fitted': lambda rows: places.submap_features(features, rows),
                **{f'share {s}': _cut(features, cells[s]) for s in shares}}
        for _, scan, _ in built['queries'][:queries]:
            own = cached_features(moved(scan, local_origin(scan, None)), built['voxel'],
                                  cfg.frontend, 'source')
            ranked = prepared.places.rank(own, built['voxel'], TESTED, features.tree)
            every = np.linspace(0, len(own.points) - 1,
                                min(PLACE_KEYPOINTS, len(own.points))).astype(np.int64)
            for place in ranked.places:
                answers = []
                for way, build in ways.items():
                    start = time.perf_counter()
                    part = build(place.rows)
                    part.descriptor_index()  # a fitted one is fitted here
                    built_s = time.perf_counter() - start
                    times = [built_s]
                    for rows in (ranked.keypoints, every):
                        start = time.perf_counter()
                        corr = match_features(own.descriptors[rows], part.descriptors,
                                              cfg.frontend, 1, part.descriptor_index())
                        times.append(time.perf_counter() - start)
                        answers.append((way, corr.source_index, corr.target_index))
                    seen.setdefault(way, []).append((*times, len(place.rows)))
                _same(answers, len(ways))
    return seen


def _cut(features: CloudFeatures, cells: Cells):
    """Return a builder of submaps whose indexes are cut from ``cells``."""
    return lambda rows: places.submap_features(features, rows, cells)


def _same(answers: list[tuple], ways: int) -> None:
    """Fail unless every way matched the same correspondences as the first."""
    for i, (way, src, dst) in enumerate(answers):
        first = answers[i % 2]
        if not (np.array_equal(src, first[1]) and np.array_equal(dst, first[2])):
            raise AssertionError(f'{way}: other correspondences than {first[0]}')


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser('bench.studies.submap_index', __doc__)
    parser.add_argument('--maps', nargs='+', default=['campus', 'floor'],
                        choices=['campus', 'floor', 'growth12'])
    parser.add_argument('--queries', type=int, default=6)
    parser.add_argument('--shares', nargs='+', type=int, default=[2, 4, 8, 16, 32])
    args = parser.parse_args(argv)
    data = shared_data_dir()
    for name in args.maps:
        rooms = (built_maps.growth_rooms(data, 12)[0] if name == 'growth12'
                 else built_maps.four_rooms(data))
        built = built_maps.campus(data) if name == 'campus' else built_maps.floor(data, 5, rooms)
        for way, rows in measure(built, args.queries, args.shares).items():
            build, test, register, points = np.median(np.array(rows), axis=0)
            print(f'{name:7s} {way:9s} {len(rows)} submaps of {points:,.0f} points (median): '
                  f'build {1e3 * build:5.1f} ms, test match {1e3 * test:5.1f} ms, '
                  f'registration match {1e3 * register:6.1f} ms', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
