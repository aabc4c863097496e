"""
``cgags-replay``: register the clouds of a rosbag2 bag, offline or through the ROS node.

Offline (default, no ROS installation needed)::

    cgags-replay BAG [--source-topic /source_cloud] [--target-topic /target_cloud]
                 [--ground-truth-topic /ground_truth] [--voxel-size V] [--config config.yaml]
                 [--set key=value ...] [--pairing latest_target|synchronized] [--output OUT_DIR]

reads the bag (:mod:`cgags_ros.io.bag`), pairs sources and targets with the node's
:class:`~cgags_ros.engine.pairing.Pairer` (same code, same parameters) and runs
:func:`cgags_ros.pipeline.register_clouds` on every pair (:mod:`.replay_offline`).

Live (``--live [--rate R] [--no-spawn]``): starts ``python -m cgags_ros.register_node``
(or uses a running one), publishes the bag's clouds with their recorded timing divided by
``R`` and records the node's ``~/pose``; see :mod:`cgags_ros.tools.replay_live`.

Both write to OUT_DIR (default ``out/replay/<bag>``): ``poses/`` (rosbag2 MCAP,
``geometry_msgs/msg/PoseStamped`` on ``--pose-topic``, stamp = source stamp, frame_id =
target frame, pose = source frame in the target frame), ``results.csv``, ``results.json``
and ``errors.png`` (RE, TE and time per pair). With ground truth (PoseStamped
source->target, matched to sources by header stamp) every pair gets RE/TE and the summary
a recall: success = valid and RE <= ``--max-re-deg`` and TE <= ``--max-te``.

Voxel size (metres), first match wins: ``--voxel-size``; ``--set voxel_size=V``;
``voxel_size`` in ``--config``; otherwise :func:`auto_voxel_size` of the first target cloud:
the voxel at which it keeps about 5000 points after voxel downsampling (rounded to two
significant digits; 2.5 mm for the bunny, 5 cm for the redkitchen fragment, 0.3 m for the
LiDAR scan). With ``--map``, :func:`map_voxel_size` of the first source scans: the median
voxel at which each keeps about 2000 (a map wants its scans' voxel, docs/map_voxel.md). The
chosen value is printed.

Broken messages (undeserializable, or a PointCloud2 that cannot be decoded) are reported,
counted and skipped. A missing topic, an unreadable file or a path that is not a bag ends
the run with one ``cgags-replay: error: ...`` line and exit code 2.
"""

from __future__ import annotations

import argparse
from pathlib import Path
import sys
from typing import Sequence

from .cli import run_cli
from .replay_common import (
    DEFAULT_GT_TOPIC,
    DEFAULT_MAX_RE_DEG,
    DEFAULT_MAX_TE_VOXELS,
    DEFAULT_POSE_TOPIC,
    LiveOptions,
    ReplayOptions,
    user_parameters,
)
from .report import BagReport
from ..engine.pairing import MODES
from ..errors import InvalidConfigError

PROG = 'cgags-replay'


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``cgags-replay``."""
    summary = __doc__.strip().split('\n\n')[0].replace('``', '')
    p = argparse.ArgumentParser(prog=PROG, description=summary,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('bag', type=Path, help='rosbag2 directory or .mcap file')
    p.add_argument('--source-topic', default='/source_cloud',
                   help='PointCloud2 topic of the clouds to align (default: %(default)s)')
    p.add_argument('--target-topic', default='/target_cloud',
                   help='PointCloud2 topic of the reference clouds (default: %(default)s)')
    p.add_argument('--ground-truth-topic', default=None,
                   help=f'PoseStamped source->target, matched to sources by stamp (default: '
                        f'{DEFAULT_GT_TOPIC} when the bag has it; given explicitly, it must '
                        'exist)')
    p.add_argument('--voxel-size', type=float, default=None,
                   help='metres (default: --set/--config, else chosen from the target cloud; '
                   'with --map, from the source scans)')
    p.add_argument('--config', default=None, help='YAML of node/pipeline keys '
                   '(ROS format or a plain mapping), e.g. config/register_node.yaml')
    p.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                   help='override one parameter (repeatable), e.g. --set core.p1=0.95')
    p.add_argument('--4dof', action='store_true', dest='yaw_only',
                   help='levelled clouds: yaw + translation only (same as --set '
                   'core.motion_model=4dof)')
    p.add_argument('--pairing', choices=MODES, default=None,
                   help="how sources meet targets, as the node's pairing.mode (default: "
                   "the parameters', latest_target)")
    p.add_argument('--output', type=Path, default=None, help='default: out/replay/<bag>')
    p.add_argument('--pose-topic', default=DEFAULT_POSE_TOPIC, help='topic in the output bag')
    p.add_argument('--max-re-deg', type=float, default=DEFAULT_MAX_RE_DEG,
                   help='success: rotation error at most this (degrees)')
    p.add_argument('--max-te', type=float, default=None, help='success: translation error at '
                   f'most this (metres; default {DEFAULT_MAX_TE_VOXELS:g} voxel sizes)')
    p.add_argument('--quiet', action='store_true', help='no progress, no tables')
    p.add_argument('--map', type=Path, default=None, metavar='FILE',
                   help='localize every source scan in this prior map (PLY, PCD, NPY, '
                   'XYZ/CSV/TXT; the target topic is ignored); offline only')
    p.add_argument('--map-cache-dir', default='', metavar='DIR',
                   help="with --map: the map's feature cache (default: none)")
    live = p.add_argument_group('live replay through the ROS node')
    live.add_argument('--live', action='store_true',
                      help='publish the bag over DDS into a register_node and record its ~/pose')
    live.add_argument('--rate', type=float, default=1.0, help='playback speed factor (> 0)')
    live.add_argument('--no-spawn', dest='spawn', action='store_false',
                      help='use a running register_node instead of starting one')
    live.add_argument('--node-name', default='register_node',
                      help='name of the node to start or listen to (default: %(default)s)')
    live.add_argument('--timeout', type=float, default=60.0,
                      help='seconds without progress from the node before giving up')
    live.add_argument('--startup-timeout', type=float, default=60.0,
                      help="seconds to wait for the node's topics")
    return p


def options_from_args(args: argparse.Namespace) -> tuple[ReplayOptions, LiveOptions | None]:
    """Return the replay options of the command line, and the live ones with ``--live``."""
    if args.rate <= 0:
        raise InvalidConfigError(f'--rate must be > 0, got {args.rate}')
    opts = ReplayOptions(
        bag=args.bag, source_topic=args.source_topic, target_topic=args.target_topic,
        ground_truth_topic=args.ground_truth_topic or DEFAULT_GT_TOPIC,
        require_ground_truth=args.ground_truth_topic is not None,
        parameters=user_parameters(args.config,
                                   args.set + (['core.motion_model=4dof'] if args.yaw_only
                                               else []),
                                   args.voxel_size, args.pairing),
        output=args.output, pose_topic=args.pose_topic, max_re_deg=args.max_re_deg,
        max_te=args.max_te, quiet=args.quiet, map_file=args.map,
        map_cache_dir=args.map_cache_dir)
    if args.map is not None and args.live:
        raise InvalidConfigError('--map runs offline; for a live node set its map.file '
                                 'parameter')
    live = LiveOptions(rate=args.rate, spawn=args.spawn, node_name=args.node_name,
                       timeout=args.timeout, startup_timeout=args.startup_timeout)
    return opts, live if args.live else None


def run(opts: ReplayOptions, live: LiveOptions | None = None) -> BagReport:
    """Replay offline, or through a register_node when ``live`` is given."""
    if live is None and opts.map_file is not None:
        from .replay_map import replay_map  # imports the pipeline (Open3D)

        return replay_map(opts)
    if live is None:
        from .replay_offline import replay_offline  # imports the pipeline (Open3D)

        return replay_offline(opts)
    from .replay_live import replay_live  # imports rclpy

    return replay_live(opts, live)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgags-replay``."""
    args = build_parser().parse_args(argv)

    def body() -> int:
        run(*options_from_args(args))
        return 0

    return run_cli(PROG, body)


if __name__ == '__main__':
    sys.exit(main())
