"""
``cgags-calibrate``: the extrinsic between two sensors from several frames, no initial guess.

Thin edge tool: reads synchronized frames (pairs of files, or pairs of PointCloud2
messages of a bag within ``--max-time-offset``), hands them to
:func:`cgags_ros.calibration.calibrate` and prints the result: a
``static_transform_publisher`` line, a URDF joint, YAML, or everything as JSON. Errors the
user can fix are one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
from pathlib import Path
import sys
from typing import Iterator, Sequence

from .calibrate_input import bag_frames, file_frames
from .cli import EXIT_ERROR, Parser, run_cli
from ..calibration import Calibrator, TRANSFORM_WORDS
from ..calibration.formats import to_json, to_text
from ..config import fields
from ..config.calibration import CalibrationConfig
from ..config.node import calibration_from_keys
from ..config.pipeline import load_yaml
from ..errors import InvalidInputError
from ..io.clouds import SUFFIXES

PROG = 'cgags-calibrate'
EXIT_FAIL = 1  # frames read, but they disagree or leave a motion unobservable

EPILOG = f"""\
The result is the {TRANSFORM_WORDS}: the pose of the child sensor in the parent frame,
what 'static_transform_publisher --frame-id PARENT --child-frame-id CHILD' and a URDF
joint from the parent link to the child link take.
Frames: --parent P1 P2 ... --child C1 C2 ... pairs Pk with Ck (files: {', '.join(SUFFIXES)});
or a bag: cgags-calibrate BAG --parent-topic /top/points --child-topic /left/points
pairs messages whose stamps differ by at most --max-time-offset and takes one pair per
--min-interval seconds (nearby frames repeat one scene; different scenes settle it).
Exit status: 0 calibrated, {EXIT_FAIL} FAIL (its refusal printed: code and message,
docs/refusals.md), {EXIT_ERROR} bad input or option.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog=PROG, epilog=EPILOG,
                    formatter_class=argparse.RawDescriptionHelpFormatter,
                    description='Calibrate the extrinsic parent <- child of two sensors from '
                                'several synchronized frames, with no initial guess.')
    parser.add_argument('bag', nargs='?', type=Path, help='rosbag2 directory or .mcap file')
    parser.add_argument('--parent', nargs='+', type=Path, default=[], metavar='CLOUD',
                        help='parent clouds, one per frame (parent sensor frame)')
    parser.add_argument('--child', nargs='+', type=Path, default=[], metavar='CLOUD',
                        help='child clouds, in the same frame order (child sensor frame)')
    parser.add_argument('--parent-topic', metavar='TOPIC', help='bag: parent PointCloud2 topic')
    parser.add_argument('--child-topic', metavar='TOPIC', help='bag: child PointCloud2 topic')
    parser.add_argument('--max-time-offset', type=float, default=0.05, metavar='S',
                        help='bag: largest |child stamp - parent stamp| of a frame, seconds '
                             '(default 0.05)')
    parser.add_argument('--min-interval', type=float, default=1.0, metavar='S',
                        help='bag: seconds between the frames taken (default 1.0)')
    parser.add_argument('--parent-frame', metavar='ID',
                        help="parent frame id in the outputs (default: the bag's header "
                             "frame_id, else 'parent')")
    parser.add_argument('--child-frame', metavar='ID',
                        help="child frame id in the outputs (default: the bag's, else 'child')")
    parser.add_argument('--voxel-size', type=float, metavar='V',
                        help='voxel size in metres (default '
                             f'{CalibrationConfig().pipeline.voxel_size:g}, LiDAR scale)')
    parser.add_argument('--max-frames', type=int, metavar='N',
                        help=f'frames taken at most (default {CalibrationConfig().max_frames})')
    parser.add_argument('--min-frames', type=int, metavar='N',
                        help='frames taken before it may stop, converged (default '
                             f'{CalibrationConfig().min_frames})')
    parser.add_argument('--config', type=Path, metavar='YAML',
                        help="YAML of configuration keys, the node's format (the pipeline "
                             'keys at the top level, the calibration keys under '
                             "calibration.; the node's config_file reads the same)")
    parser.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                        dest='overrides',
                        help='override one key, e.g. calibration.min_agreement=1 or '
                             'refine.method=gicp (repeatable)')
    parser.add_argument('--json', action='store_true',
                        help='print everything as JSON (covariance, per-frame agreement)')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgags-calibrate``."""
    args = build_parser().parse_args(argv)
    return run_cli(PROG, lambda: _calibrate(args))


def _calibrate(args: argparse.Namespace) -> int:
    config = _config(args)
    frames, parent_id, child_id = _frames(args)
    cal = Calibrator(config, parent_frame=args.parent_frame or parent_id or 'parent',
                     child_frame=args.child_frame or child_id or 'child')
    for frame in frames:
        cal.add(frame)
        if len(cal.evidence) >= config.min_frames:
            cal.solve()
        if cal.done:
            break
    if not cal.evidence:
        raise InvalidInputError('no frame to calibrate from: no parent/child pair was found')
    result = cal.result if cal.result is not None else cal.solve()
    print(to_json(result) if args.json else to_text(result))
    return 0 if result.valid else EXIT_FAIL


def _frames(args: argparse.Namespace) -> tuple[Iterator, str, str]:
    if args.bag is not None:
        if args.parent or args.child:
            raise InvalidInputError('give either a bag or --parent/--child files, not both')
        if not (args.parent_topic and args.child_topic):
            raise InvalidInputError('a bag needs --parent-topic and --child-topic')
        return bag_frames(args.bag, args.parent_topic, args.child_topic,
                          args.max_time_offset, args.min_interval)
    if not args.parent or len(args.parent) != len(args.child):
        raise InvalidInputError(
            f'--parent and --child need one cloud each per frame (got {len(args.parent)} '
            f'and {len(args.child)})')
    return file_frames(args.parent, args.child), '', ''


def _config(args: argparse.Namespace) -> CalibrationConfig:
    values = fields.flatten_mapping(load_yaml(args.config)) if args.config else {}
    values.update(fields.parse_key_values(args.overrides))
    if args.voxel_size is not None:
        values['voxel_size'] = args.voxel_size
    if args.max_frames is not None:
        values['calibration.max_frames'] = args.max_frames
    if args.min_frames is not None:
        values['calibration.min_frames'] = args.min_frames
    return calibration_from_keys(values)


if __name__ == '__main__':
    sys.exit(main())
