"""
Ablation of the core's INFERRED choices (docs/method.md) on bunny-derived correspondences.

Each variant overrides CoreConfig fields, or (upper case) constants of
cgags_ros.registration.cgags that this study sets for its own runs; every variant sees the
same problems and seeds.
Reports success (RE < 5 deg, TE < 0.1 on the unit-scaled bunny), median/p90 time and median
hypotheses per cell. Time is noisy on a shared machine; hypotheses are not.

    .venv/bin/python -m bench.studies.ablation_core --trials 20 --output out/bench/ablation_core.md
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path
import time
from unittest import mock

from bench.common import argument_parser, output_path, write_text
from bench.datasets.synthetic import load_bunny, make_correspondences
from cgags_ros.config import fields
from cgags_ros.registration import (
    cgags,
    CoreConfig,
    register_correspondences,
    rotation_error_deg,
    translation_error,
)
import numpy as np

# The options still open. The settled questions' variants (uniform samplers, binary
# compatibility, kernel seeds, ...) have no option any more: docs/method.md names the
# revision whose ablation_core.py runs them.
VARIANTS: dict[str, dict] = {
    'default': {},
    'default, uniform edge + uniform vertex (tournaments of 1)': {
        'edge_tournament': 1, 'vertex_tournament': 1},
    'default, no guided sampling': {'guided_sampling': False},
    'default, single re-fit': {'REFIT_ITERATIONS': 1},
    'default, edge tournament 64': {'edge_tournament': 64},
    'default, vertex tournament 32': {'vertex_tournament': 32},
}


def variant(name: str) -> tuple[CoreConfig, contextlib.ExitStack]:
    """Return a variant's CoreConfig and a context holding its core constants set."""
    values = VARIANTS[name]
    cfg = fields.update_from_flat(CoreConfig(), {k: v for k, v in values.items()
                                                 if not k.isupper()})
    stack = contextlib.ExitStack()
    for constant, value in values.items():
        if constant.isupper():
            stack.enter_context(mock.patch.object(cgags, constant, value))
    return cfg, stack


def run_cell(model, n, ratio, cfg, trials, tau, noise, outliers):
    ok, times, hyps = 0, [], []
    for seed in range(trials):
        prob = make_correspondences(model, n, ratio, noise_sigma=noise, rng=seed,
                                    outliers=outliers)
        t0 = time.perf_counter()
        res = register_correspondences(prob.src, prob.dst, inlier_threshold=tau, config=cfg,
                                       seed=seed)
        times.append(time.perf_counter() - t0)
        hyps.append(res.num_hypotheses)
        ok += (res.valid and rotation_error_deg(res.transform, prob.transform) < 5.0
               and translation_error(res.transform, prob.transform) < 0.1)
    return ok / trials, np.median(times), np.percentile(times, 90), np.median(hyps)


def main(argv=None) -> None:
    ap = argument_parser(__spec__.name, __doc__, description=__doc__.strip(),
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--trials', type=int, default=10)
    ap.add_argument('--cells', default='1000:0.95,1000:0.99,5000:0.99,5000:0.995',
                    help='comma-separated N:outlier_ratio')
    ap.add_argument('--variants', default='', help='comma-separated substrings to select variants')
    ap.add_argument('--tau', type=float, default=0.05, help='inlier threshold (unit-scaled bunny)')
    ap.add_argument('--noise', type=float, default=0.01)
    ap.add_argument('--outliers', default='uniform', choices=('uniform', 'surface'))
    ap.add_argument('--output', type=Path, default=output_path('ablation_core.md'),
                    help='write the markdown table here (default: %(default)s)')
    args = ap.parse_args(argv)
    model = load_bunny()
    cells = [(int(c.split(':')[0]), float(c.split(':')[1])) for c in args.cells.split(',')]
    names = [v for v in VARIANTS
             if not args.variants or any(s in v for s in args.variants.split(','))]
    header = '| variant | ' + ' | '.join(f'N={n} r={r}' for n, r in cells) + ' |'
    lines = [f'outliers={args.outliers}, noise={args.noise}, tau={args.tau}, '
             f'trials={args.trials}; '
             'cell = success % / median ms / median hypotheses', '', header,
             '|' + '---|' * (len(cells) + 1)]
    print('\n'.join(lines), flush=True)
    for name in names:
        cfg, constants = variant(name)
        cols = []
        with constants:
            for n, r in cells:
                s, med, _, h = run_cell(model, n, r, cfg, args.trials, args.tau, args.noise,
                                        args.outliers)
                cols.append(f'{100 * s:.0f} / {1000 * med:.0f} / {h:.0f}')
        line = f'| {name} | ' + ' | '.join(cols) + ' |'
        lines.append(line)
        print(line, flush=True)
    text = '\n'.join(lines) + '\n'
    print(f'wrote {write_text(args.output, text)}')


if __name__ == '__main__':
    main()
