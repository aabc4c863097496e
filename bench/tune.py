r"""
``cgags-tune`` on the bundled bags, started from a voxel size ten times too large and too small.

Run by hand from the repository root, nothing else running (minutes a start)::

    .venv/bin/python -m bench.tune [--bags bunny lidar redkitchen] [--trials 30] \
        [--factors 10 0.1] [--consistency] [--live] [--output out/bench/tune]

For every bag and start (the documented voxel size of the bag, the one ``cgags-demo``
chooses, times each factor) it runs ``cgags-tune`` in a fresh study (seed 0, hold-out 0.3,
at most ``--trials`` trials; success as ``cgags-demo`` counts it), then replays the bag
with the written ``params.yaml`` (``cgags-replay --config``) and prints the best settings,
the pairs right and valid and valid but wrong on the whole bag, and the trial that first
reached the best tuned-on score.

``--consistency`` tunes without the ground truth (``--ignore-ground-truth``: pairs judged
by consistency), the replay still judging against it. ``--live`` also replays the bag
through a register_node started with ``params.yaml`` over DDS (``cgags-replay --live``,
ROS domain 43, localhost), as a user would after tuning.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys

from bench.common import argument_parser, LIMITS, markdown_table
from cgags_ros.io.shared_data import shared_data_dir

DOCUMENTED = {'bunny': 0.0024, 'redkitchen': 0.05, 'lidar': 0.3}  # metres, README's table


def run_start(bag: str, voxel: float, trials: int, out: Path, consistency: bool) -> dict:
    """Run ``cgags-tune`` on ``bag`` from ``voxel`` in a fresh study; return its summary."""
    max_re, max_te = LIMITS[bag]
    out.mkdir(parents=True, exist_ok=True)
    (out.parent / f'{out.name}.db').unlink(missing_ok=True)
    subprocess.run([sys.executable, '-m', 'cgags_ros.tools.tune',
                    str(shared_data_dir() / 'bags' / bag), '--voxel-size', f'{voxel:g}',
                    '--trials', str(trials), '--output', str(out), '--quiet',
                    '--storage', f"sqlite:///{out.parent / f'{out.name}.db'}",
                    '--max-re-deg', str(max_re), '--max-te', str(max_te)]
                   + (['--ignore-ground-truth'] if consistency else []), check=True)
    return json.loads((out / 'summary.json').read_text(encoding='utf-8'))


def replay_params(bag: str, params: Path, out: Path, live: bool) -> tuple[int, int, int]:
    """Replay ``bag`` with ``params`` (offline or live); return (right, valid wrong, pairs)."""
    max_re, max_te = LIMITS[bag]
    subprocess.run([sys.executable, '-m', 'cgags_ros.tools.replay',
                    str(shared_data_dir() / 'bags' / bag), '--config', str(params),
                    '--output', str(out), '--quiet', '--max-re-deg', str(max_re),
                    '--max-te', str(max_te)] + ['--live'] * live, check=True)
    rows = json.loads((out / 'results.json').read_text(encoding='utf-8'))['pairs']
    return (sum(bool(r['success']) for r in rows),
            sum(bool(r['valid'] and not r['success']) for r in rows), len(rows))


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('--bags', nargs='+', default=sorted(DOCUMENTED))
    parser.add_argument('--trials', type=int, default=30)
    parser.add_argument('--factors', type=float, nargs='+', default=[10.0, 0.1])
    parser.add_argument('--consistency', action='store_true',
                        help='tune without the ground truth (judged by consistency)')
    parser.add_argument('--live', action='store_true',
                        help='also replay params.yaml through a register_node over DDS')
    parser.add_argument('--output', type=Path, default=Path('out/bench/tune'))
    args = parser.parse_args(argv)
    if args.live:
        os.environ.update(ROS_DOMAIN_ID='43', ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    rows = []
    for bag in args.bags:
        voxel = DOCUMENTED[bag]
        for factor in args.factors:
            out = args.output / f"{bag}_x{factor:g}{'_consistency' * args.consistency}"
            summary = run_start(bag, voxel * factor, args.trials, out, args.consistency)
            params = out / 'params.yaml'
            right, wrong, pairs = replay_params(bag, params, out / 'replay', live=False)
            live = (replay_params(bag, params, out / 'replay_live', live=True)
                    if args.live else None)
            scored = [t for t in summary['trials'] if 'right' in t]
            top = max(t['right'] - 1000 * t['wrong'] for t in scored)
            rows.append((bag, f'{voxel * factor:g}', f'{voxel:g}',
                         ', '.join(f'{k}={v}' for k, v in summary['best'].items()),
                         f'{right}/{pairs}', wrong,
                         f'{live[0]}/{live[2]}, {live[1]} wrong' if live else '-',
                         next(t['number'] for t in scored
                              if t['right'] - 1000 * t['wrong'] == top),
                         len(summary['trials']), summary['warning'] or '-'))
            print(rows[-1], flush=True)
    print(markdown_table(('bag', 'start voxel', 'documented voxel', 'best settings',
                          'right and valid (whole bag)', 'valid but wrong', 'live over DDS',
                          'first trial at the best tuned-on score', 'trials', 'warning'),
                         rows))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
