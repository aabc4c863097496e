r"""
How places are ranked: the share of chance votes a place's score discounts.

Run by hand from the repository root (~5 min; ranks only, nothing is registered)::

    .venv/bin/python -m bench.studies.place_ranking [--maps floor growth12 campus] \
        [--shares 0 0.25 0.5 1]

For each of ``bench.maps``' maps (``floor``: four rooms; ``growth12``: twelve look-alike
rooms; ``campus``: a street among look-alike streets and a building) and each share of
chance discounted (:data:`cgags_ros.pipeline.places.CHANCE_SHARE`), every query's places
are ranked (:meth:`~cgags_ros.pipeline.places.PlaceIndex.rank`, ``RANKED`` of them) and the
rank of its own place noted: the first ranked place within 1.5 of the scan's reaches of
its true centroid. Prints, per map and share, how many queries have their own place first,
among the first ``TESTED`` (the ones :mod:`cgags_ros.pipeline.locate` tests) and among
the first ``RANKED``.
"""

from __future__ import annotations

from pathlib import Path
import tempfile

from bench.common import argument_parser
import bench.maps as built_maps
from cgags_ros.config import pipeline_config_from
from cgags_ros.coordinates import local_origin, moved
from cgags_ros.geometry import apply_transform
from cgags_ros.io.clouds import write_cloud
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import places
from cgags_ros.pipeline.cache import cached_features
from cgags_ros.pipeline.locate import TESTED
from cgags_ros.pipeline.map import load_map
import numpy as np

RANKED = 8


def maps(names: list[str], data: Path):
    """Yield (name, built map) of ``bench.maps`` for each of ``names``."""
    for name in names:
        if name == 'floor':
            yield name, built_maps.floor(data, 5, built_maps.four_rooms(data))
        elif name == 'campus':
            yield name, built_maps.campus(data)
        else:
            shapes, _ = built_maps.growth_rooms(data, int(name[len('growth'):]))
            yield name, built_maps.floor(data, 5, shapes)


def own_ranks(built: dict, shares: list[float]) -> dict[float, list[int]]:
    """Return, for each share, the rank of each query's own place (RANKED: not ranked)."""
    cfg = pipeline_config_from({'voxel_size': built['voxel']})
    ranks = {share: [] for share in shares}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / 'map.ply'
        write_cloud(path, built['points'], built['normals'])
        prepared = load_map(path, cfg, Path(tmp) / 'cache')
        for _, scan, truth in built['queries']:
            scan_features = cached_features(moved(scan, local_origin(scan, None)),
                                            built['voxel'], cfg.frontend, 'source')
            centroid = apply_transform(truth, scan).mean(axis=0) - prepared.origin
            for share in shares:
                places.CHANCE_SHARE = share
                ranked = prepared.places.rank(scan_features, built['voxel'], RANKED,
                                              prepared.features.tree)
                if ranked.whole:
                    ranks[share].append(0)
                    continue
                own = [i for i, p in enumerate(ranked.places)
                       if np.linalg.norm(p.centre - centroid) < 1.5 * ranked.reach]
                ranks[share].append(own[0] if own else RANKED)
    return ranks


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser('bench.studies.place_ranking', __doc__)
    parser.add_argument('--maps', nargs='+', default=['floor', 'growth12', 'campus'])
    parser.add_argument('--shares', nargs='+', type=float, default=[0.0, 0.25, 0.5, 1.0])
    args = parser.parse_args(argv)
    shipped = places.CHANCE_SHARE
    for name, built in maps(args.maps, shared_data_dir()):
        for share, ranks in own_ranks(built, args.shares).items():
            r = np.array(ranks)
            print(f'{name:9s} share {share:4.2f}: own place first {int(np.sum(r == 0))}, '
                  f'in the first {TESTED} {int(np.sum(r < TESTED))}, in the first {RANKED} '
                  f'{int(np.sum(r < RANKED))} of {len(r)}', flush=True)
    places.CHANCE_SHARE = shipped
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
