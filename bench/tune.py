r"""
``cgags-tune`` on the bundled bags, started from a voxel size ten times too large and too small.

Run by hand from the repository root, nothing else running (minutes a start)::

    .venv/bin/python -m bench.tune [--bags bunny lidar redkitchen] [--trials 30] \
        [--factors 10 0.1] [--output out/bench/tune]

For every bag and start (the documented voxel size of the bag, the one ``cgags-demo``
chooses, times each factor) it runs a fresh study (seed 0, hold-out 0.3, at most ``--trials`` trials) and prints
the best settings, the pairs right and valid and valid but wrong on the whole bag (the
pairs tuned on and the held-out ones), and the trial that first reached that recall. Success
as ``cgags-demo`` counts it.
"""

from __future__ import annotations

from pathlib import Path

from bench.common import argument_parser, markdown_table
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.tools.demo import DEMO_BAGS
from cgags_ros.tools.tune import Options, tune

DOCUMENTED = {'bunny': 0.0024, 'redkitchen': 0.05, 'lidar': 0.3}  # metres, README's table


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('--bags', nargs='+', default=sorted(DEMO_BAGS))
    parser.add_argument('--trials', type=int, default=30)
    parser.add_argument('--factors', type=float, nargs='+', default=[10.0, 0.1])
    parser.add_argument('--output', type=Path, default=Path('out/bench/tune'))
    args = parser.parse_args(argv)
    rows = []
    for bag in args.bags:
        voxel = DOCUMENTED[bag]
        max_re, max_te = DEMO_BAGS[bag]
        for factor in args.factors:
            name = f'{bag}_x{factor:g}'
            outcome = tune(Options(
                bags=[shared_data_dir() / 'bags' / bag], voxel_size=voxel * factor,
                trials=args.trials, output=args.output / name,
                storage=f"sqlite:///{args.output / f'{name}.db'}", max_re_deg=max_re,
                max_te=max_te, quiet=True))
            best = [s for (which, _), s in outcome.scores.items() if which == 'best']
            right, wrong = sum(s.right for s in best), sum(s.wrong for s in best)
            pairs = sum(s.pairs for s in best)
            reached = next((t['number'] for t in outcome.trials
                            if t['right'] == max(x['right'] for x in outcome.trials)), None)
            rows.append((bag, f'{voxel * factor:g}', f'{voxel:g}',
                         ', '.join(f'{k}={v}' for k, v in outcome.best.items()),
                         f'{right}/{pairs}', wrong, reached, len(outcome.trials),
                         outcome.warning or '-'))
            print(rows[-1], flush=True)
    print(markdown_table(('bag', 'start voxel', 'documented voxel', 'best settings',
                          'right and valid (whole bag)', 'valid but wrong',
                          'first trial at the best tuned-on recall', 'trials', 'warning'),
                         rows))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
