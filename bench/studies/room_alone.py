r"""
What places lose: each query of the four-room floor against the floor and against its room alone.

Run by hand from the repository root (about a minute a voxel at 10 queries a room)::

    .venv/bin/python -m bench.studies.room_alone [--per-room 10] [--voxels 0.05 0.075] \
        [--lidar] [--set frontend.fpfh_radius_factor=4]

The floor is ``bench.maps``' four-room floor (its rooms 30 m apart, the queries held-out odd
fragments). Each query is registered onto the prepared floor (its places ranked, tested and
one registered) and onto a map of its own room alone (the same points and normals, prepared
on their own: a map within one place, registered whole). The room alone is what the front
end and the gates find with the place known and the room whole: the most the floor's places
could find. Prints, per voxel, found / wrong / refused each way and the queries the two ways
answer differently. ``--lidar``: the queries are ``bench.maps_voxel``'s simulated LiDAR scans
at the same sites (right: 5 deg, 0.3 m; its voxels ``--voxels 0.12 0.15``). ``--set`` changes
a parameter for both ways (a front-end one changes the map's features too: each setting is
prepared on its own).
"""

from __future__ import annotations

from pathlib import Path
import tempfile

from bench.common import add_set_option, argument_parser, parse_overrides
from bench.map_truth import with_settled
import bench.maps as built_maps
from bench.maps_voxel import lidar
from cgags_ros.config import pipeline_config_from
from cgags_ros.io.clouds import write_cloud
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import clear_feature_cache, register_clouds
from cgags_ros.pipeline.map import load_map


def outcomes(built: dict, voxel: float, tmp: Path,
             overrides: dict | None = None) -> dict[str, list[str]]:
    """Return each query's outcome on the floor's places and on its room alone."""
    cfg = pipeline_config_from({'voxel_size': voxel, **(overrides or {})})
    scenes = [scene for scene, _, _ in built['sites']]
    paths = {'floor': tmp / 'floor.ply'}
    write_cloud(paths['floor'], built['points'], built['normals'])
    for scene, (start, stop) in zip(dict.fromkeys(scenes), built['spans']):
        paths[scene] = tmp / f'{scene}.ply'
        write_cloud(paths[scene], built['points'][start:stop], built['normals'][start:stop])
    prepared = {name: load_map(path, cfg, tmp / 'cache') for name, path in paths.items()}
    got: dict[str, list[str]] = {'places': [], 'room alone': []}
    for scene, (label, scan, truth) in zip(scenes, built['queries']):
        for way, target in (('places', prepared['floor']), ('room alone', prepared[scene])):
            clear_feature_cache()
            result = register_clouds(scan, target, config=cfg)
            got[way].append(built_maps.outcome(result, truth, built['right'],
                                               built['settled'].get(label)))
        print(f'{voxel:g} {label:28s} places {got["places"][-1]:8s} '
              f'room alone {got["room alone"][-1]}', flush=True)
    return got


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser('bench.studies.room_alone', __doc__)
    parser.add_argument('--per-room', type=int, default=10, help='queries a room')
    parser.add_argument('--voxels', type=float, nargs='+', default=[0.05, 0.075])
    parser.add_argument('--lidar', action='store_true',
                        help="query with bench.maps_voxel's simulated LiDAR scans")
    add_set_option(parser)
    args = parser.parse_args(argv)
    overrides = parse_overrides(args.set)
    data = shared_data_dir()
    built = with_settled(lidar(data, args.per_room) if args.lidar
                         else built_maps.floor(data, args.per_room, built_maps.four_rooms(data)))
    labels = [label for label, _, _ in built['queries']]
    for voxel in args.voxels:
        with tempfile.TemporaryDirectory() as tmp:
            got = outcomes(built, voxel, Path(tmp), overrides)
        for way, seen in got.items():
            print(f'voxel {voxel:g} {way:10s}: found {seen.count("found")} wrong '
                  f'{seen.count("WRONG")} refused {seen.count("refused")} of {len(seen)}')
        differ = [f'{label} ({a} / {b})' for label, a, b in
                  zip(labels, got['places'], got['room alone']) if a != b]
        print(f'voxel {voxel:g} places / room alone differ: {", ".join(differ) or "none"}',
              flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
