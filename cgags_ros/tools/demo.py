"""
``cgags-demo`` (``bash scripts/demo.sh``): the bundled bags, live through the ROS node.

For each bag in ``<shared data>/bags`` (``bunny``, ``redkitchen``, ``lidar``; located with
:func:`cgags_ros.io.shared_data.shared_data_dir`, which honours ``CGAGS_DATA_DIR``)
this runs ``cgags-replay BAG --live`` (a register_node is started per bag and stopped
after it), prints each pair's RE/TE against the bag's ``/ground_truth`` and the recall,
and writes ``OUT/<bag>/`` (default ``out/demo``): ``errors.png``, ``results.csv``,
``results.json``, the estimated poses as a rosbag2 MCAP (``poses/``) and ``node.log``.
``--offline`` runs the same replay in-process, without ROS.

Success thresholds are the usual ones for each kind of data:

=============  ==========  =========  ==============================================
bag            RE [deg]    TE [m]     convention
=============  ==========  =========  ==============================================
bunny          5           0.01       object scans (~15 cm object)
redkitchen     15          0.3        3DMatch registration recall
lidar          5           0.6        outdoor LiDAR (KITTI-style)
=============  ==========  =========  ==============================================

The voxel size of each bag is chosen from its target cloud
(:func:`cgags_ros.tools.replay_common.auto_voxel_size`) unless ``--voxel-size`` is given.
"""

from __future__ import annotations

import argparse
from pathlib import Path
import sys
from typing import Sequence

from .cli import error_line, EXIT_ERROR
from .replay import run
from .replay_common import LiveOptions, ReplayOptions
from .report import BagReport, summary_table
from ..errors import CgagsError
from ..io.shared_data import shared_data_dir

PROG = 'cgags-demo'
# bag -> (max RE degrees, max TE metres)
DEMO_BAGS: dict[str, tuple[float, float]] = {
    'bunny': (5.0, 0.01),
    'redkitchen': (15.0, 0.3),
    'lidar': (5.0, 0.6),
}


def bags_dir() -> Path:
    """Return the folder of the bundled bags."""
    return shared_data_dir() / 'bags'


def demo_options(bag: str, out: Path, *, voxel_size: float | None = None,
                 quiet: bool = False) -> ReplayOptions:
    """Return the replay of one bundled bag with its success thresholds."""
    max_re, max_te = DEMO_BAGS[bag]
    params = {} if voxel_size is None else {'voxel_size': voxel_size}
    return ReplayOptions(bag=bags_dir() / bag, parameters=params, output=out / bag,
                         max_re_deg=max_re, max_te=max_te, quiet=quiet)


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``cgags-demo``."""
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.strip().split('\n\n')[0])
    p.add_argument('--bags', nargs='+', choices=sorted(DEMO_BAGS), default=list(DEMO_BAGS))
    p.add_argument('--output', type=Path, default=Path('out') / 'demo')
    p.add_argument('--offline', action='store_true', help='in-process replay, no ROS')
    p.add_argument('--rate', type=float, default=1.0, help='live playback speed factor')
    p.add_argument('--voxel-size', type=float, default=None,
                   help='metres, for every bag (default: chosen per bag)')
    p.add_argument('--quiet', action='store_true', help='only the final table')
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgags-demo``."""
    args = build_parser().parse_args(argv)
    if args.rate <= 0:
        print(f'{PROG}: error: --rate must be > 0, got {args.rate:g}', file=sys.stderr)
        return EXIT_ERROR
    if not bags_dir().is_dir():
        print(f'{PROG}: error: no bags at {bags_dir()}; set CGAGS_DATA_DIR to the shared data '
              'folder', file=sys.stderr)
        return EXIT_ERROR
    reports: list[BagReport] = []
    failed: list[str] = []
    for bag in args.bags:
        mode = 'offline' if args.offline else f'live, rate {args.rate:g}'
        print(f'\n=== {bag} ({mode}) ===', flush=True)
        opts = demo_options(bag, args.output, voxel_size=args.voxel_size, quiet=args.quiet)
        try:
            reports.append(run(opts, None if args.offline else LiveOptions(rate=args.rate)))
        except CgagsError as exc:
            print(error_line(PROG, exc, bag), file=sys.stderr)
            failed.append(bag)
    print('\n' + summary_table(reports))
    print(f'\nplots and results: {args.output}/<bag>/errors.png, results.csv, results.json, '
          'poses/ (rosbag2 MCAP)')
    for rep in reports:
        print(f"  {rep.bag}: {args.output / rep.bag / 'errors.png'}")
    if failed:
        print(f"{PROG}: failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
