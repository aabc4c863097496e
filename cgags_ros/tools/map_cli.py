"""
``cgags-map``: prepare a map's feature cache ahead of time, and inspect what a cache holds.

``prepare`` computes what :func:`~cgags_ros.pipeline.map.load_map` needs (grid, normals, FPFH,
descriptor index, places) once and stores it where the node and ``cgags-relocalize`` read it:
a node started on that map then loads it memory-mapped, its processes sharing one copy.
``inspect`` lists the cache's entries of a map: voxel, points, places, extent, local origin,
and whether each is stale (the map file changed since). Errors are one line on stderr, exit 2.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import sys
from typing import Any, Sequence

from .cli import Parser, run_cli
from .register_cli import add_config_options, option_keys
from ..config.node import NodeConfig, pipeline_from_keys
from ..config.pipeline import PipelineConfig
from ..errors import InvalidInputError
from ..io import map_cache

PROG = 'cgags-map'
DEFAULT_CACHE = NodeConfig().map.cache_dir  # the node's: a prepared map is a hit there

EPILOG = f"""\
examples:
  {PROG} prepare campus.ply --voxel-size 0.3        # then: -p map.file:=campus.ply
  {PROG} inspect campus.ply --json
The cache directory defaults to the node's map.cache_dir ({DEFAULT_CACHE}), which
cgags-relocalize and cgags-replay read with --map-cache-dir; give the same --voxel-size (and
--config/--set of the front end) they will use, or they compute the features again under
their own settings. A map wants the voxel of the scans that query it, not of its own size:
cgags-relocalize MAP SCAN chooses and prints it; without --voxel-size, prepare uses the
default ({PipelineConfig().voxel_size:g} m, the node's too) and says so (docs/map_voxel.md).
"""


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog=PROG, epilog=EPILOG,
                    formatter_class=argparse.RawDescriptionHelpFormatter,
                    description="Prepare and inspect a map's feature cache.")
    commands = parser.add_subparsers(dest='command', required=True)
    prepare = commands.add_parser('prepare', help="compute and store the map's features")
    inspect = commands.add_parser('inspect', help="list the cache's entries of the map")
    for sub in (prepare, inspect):
        sub.add_argument('map', type=Path, help='map file (map frame, metres)')
        sub.add_argument('--cache-dir', type=Path, default=Path(DEFAULT_CACHE), metavar='DIR',
                         help=f'feature cache directory (default: {DEFAULT_CACHE})')
        sub.add_argument('--json', action='store_true', help='print JSON on stdout')
    add_config_options(prepare)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgags-map``."""
    args = build_parser().parse_args(argv)
    args.cache_dir = Path(os.path.expanduser(str(args.cache_dir)))
    return run_cli(PROG, lambda: _prepare(args) if args.command == 'prepare'
                   else _inspect(args))


def _prepare(args: argparse.Namespace) -> int:
    keys = option_keys(args)
    config = pipeline_from_keys(keys)
    from ..pipeline.map import load_map  # after the cheap checks: imports Open3D

    info = load_map(args.map, config, args.cache_dir).info()
    info['voxel'] = 'given' if 'voxel_size' in keys else 'default'
    default = ('' if 'voxel_size' in keys else " (the default, as the node's without "
               "voxel_size; a map wants its scans' voxel: see --help)")
    print(json.dumps(info, indent=2) if args.json else
          f"{info['path']}: {info['points']} points at {info['voxel_size']:g} m{default}, "
          f"{info['places']} places ({info['cache']}: {info['load_s']:.2f} s), stored in "
          f"{info['cache_path']}")
    return 0


def _inspect(args: argparse.Namespace) -> int:
    if not args.map.is_file():
        raise InvalidInputError(f'{args.map}: no such file')
    digest = map_cache.file_digest(args.map)
    found = [_entry(path, meta, digest) for path, meta in map_cache.entries(args.cache_dir)
             if meta.get('map') == str(args.map.resolve())]
    if args.json:
        print(json.dumps({'map': str(args.map), 'cache_dir': str(args.cache_dir),
                          'entries': found}, indent=2))
        return 0
    if not found:
        print(f'{args.map}: no entry in {args.cache_dir} (run {PROG} prepare)')
    for e in found:
        low, high = e['extent']
        size = ' x '.join(f'{h - lo:.1f}' for lo, h in zip(low, high))
        print(f"{e['entry']}: {'STALE (the map file changed)' if e['stale'] else 'fresh'}, "
              f"voxel {e['voxel_size']:g} m, {e['points']} points of {e['raw_points']}, "
              f"{e['places']} places, extent {size} m, "
              f"origin {' '.join(f'{x:.3f}' for x in e['origin'])}")
    return 0


def _entry(path: Path, meta: dict[str, Any], digest: str) -> dict[str, Any]:
    return {'entry': str(path), 'stale': meta.get('digest') != digest,
            'voxel_size': meta['settings']['voxel_size'], 'points': meta['points'],
            'raw_points': meta['raw_points'], 'places': meta.get('places', 0),
            'extent': meta['extent'],
            'origin': meta['origin'], 'settings': meta['settings']}


if __name__ == '__main__':
    sys.exit(main())
