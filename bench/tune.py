r"""
``cgags-tune`` on the bundled bags, started from a voxel size ten times too large and too small.

Run by hand from the repository root, nothing else running (minutes a start)::

    .venv/bin/python -m bench.tune [--bags bunny lidar redkitchen] [--trials 30] \
        [--factors 10 0.1] [--output out/bench/tune]

For every bag and start (the documented voxel size of the bag, the one ``cgags-demo``
chooses, times each factor) it runs ``cgags-tune`` in a fresh study (seed 0, hold-out 0.3,
at most ``--trials`` trials; success as ``cgags-demo`` counts it) and prints the best
settings, the pairs right and valid and valid but wrong on the whole bag (the pairs tuned on
and the held-out ones), and the trial that first reached the best tuned-on recall.
"""

from __future__ import annotations

import json
from pathlib import Path
import subprocess
import sys

from bench.common import argument_parser, LIMITS, markdown_table
from cgags_ros.io.shared_data import shared_data_dir

DOCUMENTED = {'bunny': 0.0024, 'redkitchen': 0.05, 'lidar': 0.3}  # metres, README's table


def run_start(bag: str, voxel: float, trials: int, out: Path) -> dict:
    """Run ``cgags-tune`` on ``bag`` from ``voxel`` in a fresh study; return its summary."""
    max_re, max_te = LIMITS[bag]
    out.mkdir(parents=True, exist_ok=True)
    (out.parent / f'{out.name}.db').unlink(missing_ok=True)
    subprocess.run([sys.executable, '-m', 'cgags_ros.tools.tune',
                    str(shared_data_dir() / 'bags' / bag), '--voxel-size', f'{voxel:g}',
                    '--trials', str(trials), '--output', str(out), '--quiet',
                    '--storage', f"sqlite:///{out.parent / f'{out.name}.db'}",
                    '--max-re-deg', str(max_re), '--max-te', str(max_te)], check=True)
    return json.loads((out / 'summary.json').read_text(encoding='utf-8'))


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('--bags', nargs='+', default=sorted(DOCUMENTED))
    parser.add_argument('--trials', type=int, default=30)
    parser.add_argument('--factors', type=float, nargs='+', default=[10.0, 0.1])
    parser.add_argument('--output', type=Path, default=Path('out/bench/tune'))
    args = parser.parse_args(argv)
    rows = []
    for bag in args.bags:
        voxel = DOCUMENTED[bag]
        for factor in args.factors:
            summary = run_start(bag, voxel * factor, args.trials,
                                args.output / f'{bag}_x{factor:g}')
            best = [s for s in summary['scores'] if s['settings'] == 'best']
            top = max(t['right'] for t in summary['trials'])
            rows.append((bag, f'{voxel * factor:g}', f'{voxel:g}',
                         ', '.join(f'{k}={v}' for k, v in summary['best'].items()),
                         f"{sum(s['right'] for s in best)}/{sum(s['pairs'] for s in best)}",
                         sum(s['wrong'] for s in best),
                         next(t['number'] for t in summary['trials'] if t['right'] == top),
                         len(summary['trials']), summary['warning'] or '-'))
            print(rows[-1], flush=True)
    print(markdown_table(('bag', 'start voxel', 'documented voxel', 'best settings',
                          'right and valid (whole bag)', 'valid but wrong',
                          'first trial at the best tuned-on recall', 'trials', 'warning'),
                         rows))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
