"""
``cgags-relocalize``: find scans in a prior map file, confirmed over a few scans with odometry.

Thin edge tool: prepares the map as the node does (:func:`~cgags_ros.pipeline.map.load_map`,
its normals and feature cache), feeds the scans in time order, each with its odometry pose,
to a :class:`~cgags_ros.relocalization.relocalizer.Relocalizer` and stops at the first confirmed
answer. Errors the user can fix are one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys
from typing import Sequence

import numpy as np

from .cli import EXIT_ERROR, Parser, run_cli
from .register_cli import add_config_options, option_keys
from .replay_common import MAP_SCAN_VOXELS, map_voxel_size
from ..config.node import pipeline_from_keys
from ..errors import InvalidInputError
from ..geometry import make_transform, quaternion_to_matrix
from ..io.clouds import read_cloud, SUFFIXES
from ..refusal import summary as refusal_summary

PROG = 'cgags-relocalize'
EXIT_NOT_CONFIRMED = 1

EPILOG = f"""\
point cloud formats: {', '.join(SUFFIXES)} (x, y, z in metres); a PLY or PCD map with
normals facing the sensors that saw each surface (as mappers write them) signs the map's.
--odometry FILE: one line a scan, 'x y z qx qy qz qw', the sensor's pose in the odometry
frame when that scan was taken (p_odom = R p_sensor + t); needed with more than one scan.
The transform maps the last scan used into the map: p_map = R p_scan + t.
Without --voxel-size (or voxel_size in --config/--set) the scans choose it: the median voxel
that leaves each about {MAP_SCAN_VOXELS} voxels (printed; docs/map_voxel.md).
Prepare the map (cgags-map prepare) and start the node with that voxel.
Exit status: 0 confirmed, {EXIT_NOT_CONFIRMED} not confirmed (see 'refusal': code and message,
docs/refusals.md), {EXIT_ERROR} bad input or option.
example: cgags-relocalize site.ply s1.pcd s2.pcd s3.pcd --odometry odom.txt --voxel-size 0.05
"""


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog=PROG, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
        description='Relocalize in MAP with no initial guess: register each SCAN onto the '
                    'prepared map and keep the poses of the odometry frame in the map that '
                    'every scan so far supports, until one is confirmed.')
    parser.add_argument('map', type=Path, help='prior map file (map frame, metres)')
    parser.add_argument('scans', type=Path, nargs='+', metavar='SCAN',
                        help='scans in time order, each in its sensor frame')
    parser.add_argument('--odometry', type=Path, metavar='FILE',
                        help="one 'x y z qx qy qz qw' line a scan (sensor pose in odometry)")
    add_config_options(parser, f'chosen from the scans: ~{MAP_SCAN_VOXELS} voxels each')
    parser.add_argument('--min-scans', type=int, default=2, metavar='N',
                        help='scans a confirmation needs, at most those given (default 2: a '
                        'second scan must agree; one scan given is judged alone)')
    parser.add_argument('--hint', type=float, nargs=4, metavar=('X', 'Y', 'Z', 'RADIUS'),
                        help='the sensor is within RADIUS metres of X Y Z (map frame) for '
                        "every scan: only the map's places that covers are searched")
    parser.add_argument('--map-cache-dir', type=Path, metavar='DIR',
                        help="cache of the map's features (default: none)")
    parser.add_argument('--json', action='store_true',
                        help='print the answer as one JSON object on stdout instead of text')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgags-relocalize``."""
    args = build_parser().parse_args(argv)
    return run_cli(PROG, lambda: _relocalize(args))


def read_odometry(path: Path, count: int) -> list[np.ndarray]:
    """Return the ``count`` odom <- sensor poses of an odometry file (epilog's format)."""
    try:
        lines = [ln for ln in path.read_text(encoding='utf-8').splitlines()
                 if ln.strip() and not ln.lstrip().startswith('#')]
    except (OSError, UnicodeDecodeError) as exc:
        raise InvalidInputError(f'cannot read odometry file {path}: {exc}') from exc
    if len(lines) != count:
        raise InvalidInputError(f'odometry file {path}: {len(lines)} poses for {count} scans '
                                '(one line a scan)')
    poses = []
    for number, line in enumerate(lines, 1):
        try:
            values = [float(v) for v in line.split()]
        except ValueError as exc:
            raise InvalidInputError(f'odometry file {path}, pose {number}: {exc}') from exc
        if len(values) != 7 or not np.isfinite(values).all():
            raise InvalidInputError(f'odometry file {path}, pose {number}: need 7 finite '
                                    f"numbers 'x y z qx qy qz qw', got {line.strip()!r}")
        poses.append(make_transform(quaternion_to_matrix(values[3:]), values[:3]))
    return poses


def _relocalize(args: argparse.Namespace) -> int:
    if len(args.scans) > 1 and args.odometry is None:
        raise InvalidInputError('more than one scan needs --odometry (one pose a scan)')
    if args.min_scans < 1:
        raise InvalidInputError(f'--min-scans {args.min_scans}: at least 1')
    keys = option_keys(args)
    odometry = (read_odometry(args.odometry, len(args.scans)) if args.odometry
                else [None] * len(args.scans))
    if not args.map.is_file():
        raise InvalidInputError(f'map {str(args.map)!r}: no such file')
    scans = [read_cloud(path) for path in args.scans]
    voxel = 'given'
    if 'voxel_size' not in keys:
        keys['voxel_size'] = map_voxel_size(scans)
        voxel = f'chosen from the scans: ~{MAP_SCAN_VOXELS} voxels each'
    config = pipeline_from_keys(keys)
    from ..pipeline.map import load_map  # after the cheap checks: imports Open3D
    from ..pipeline.hint import Hint
    from ..relocalization.relocalizer import Relocalizer, SequenceConfig

    hint = None if args.hint is None else Hint(args.hint[:3], args.hint[3])
    prepared = load_map(args.map, config, args.map_cache_dir)
    sequence = SequenceConfig(max_scans=len(scans), min_scans=min(args.min_scans, len(scans)))
    reloc = Relocalizer(prepared, config, sequence)
    for scan, odom in zip(scans, odometry):
        answer = reloc.add(scan, odom, hint)
        if answer.done:
            break
    out = {'confirmed': answer.confirmed, 'transform': answer.transform.tolist(),
           'map_from_odom': answer.map_from_odom.tolist(), 'scans_used': answer.scans_used,
           'reason': answer.reason, 'refusal': refusal_summary(answer.refusal),
           'hypotheses': [h.summary(sequence, config) for h in answer.hypotheses],
           'scans': [{'file': str(path), 'valid': r.valid, 'reason': r.reason,
                      'refusal': refusal_summary(r.refusal),
                      'inliers': r.num_inliers, 'fitness': r.fitness,
                      'place': (r.map_info or {}).get('place')}
                     for path, r in zip(args.scans, answer.results)],
           'map': prepared.info(), 'voxel_size': config.voxel_size, 'voxel': voxel}
    print(json.dumps(out, indent=2) if args.json else format_answer(out))
    return 0 if answer.confirmed else EXIT_NOT_CONFIRMED


def format_answer(out: dict) -> str:
    """Format the answer for a reader: confirmed or why not, the pose, the hypotheses."""
    why = f"{out['refusal']['code']}: {out['reason']}" if out['refusal'] else out['reason']
    lines = ['confirmed: ' + ('yes' if out['confirmed'] else f'no ({why})'),
             f"scans used: {out['scans_used']}",
             f"voxel size: {out['voxel_size']:g} m ({out['voxel']})",
             'transform (last scan -> map, metres):']
    lines += ['  ' + ' '.join(f'{x: .6f}' for x in row) for row in out['transform']]
    lines += [f"hypothesis {i}: proposed by scan {h['proposed_by_scan']}, inliers "
              f"{h['inliers']}, explains {h['scans_explained']} scan(s), fitness "
              f"{' '.join(f'{f:.2f}' for f in h['fitness'])}"
              for i, h in enumerate(out['hypotheses'][:5])]
    return '\n'.join(lines)


if __name__ == '__main__':
    sys.exit(main())
