"""
What stage one's minimal subsets explain by chance, per motion model and outlier layout.

The chance level of the significance test (``significance.ConsensusRecord``) estimates
lambda, the mean chance inliers of a wrong hypothesis, from the share of zero counts among
hypotheses taken as unselected. This script draws stage-one minimal subsets on the core
benchmark's problems (:mod:`bench.problems`) exactly as the search does (6-DoF: edge and
vertex tournaments; 4-DoF: the edge tournament) and, for comparison, uniform ones
(tournament size 1), fits them, and reports:
the share that is all-inlier (ground truth), lambda as the zero-share estimate reads it from
all of them, and lambda of the wrong ones alone. When many drawn subsets are all-inlier the
estimate from all of them is far above the wrong ones' (docs/ablation.md, 4-DoF chance level).
``--pure K`` also runs the 4-DoF core on K pure-outlier problems a layout (run to the cap):
how many come back valid, their best consensus and chance level.

Example::

    .venv/bin/python -m bench.studies.chance_sample --outliers uniform,cube --ratio 0.99 --trials 4
"""

from __future__ import annotations

import dataclasses
import sys

from bench.common import argument_parser
from bench.datasets.synthetic import load_bunny, make_correspondences
from bench.problems import problem
from cgags_ros.registration import compiled
from cgags_ros.registration import CoreConfig, register_correspondences
from cgags_ros.registration.motion import motion_model
from cgags_ros.registration.search import Search
from cgags_ros.registration.yaw import vertical_offsets
import numpy as np

TAU = 0.05


def measure(src, dst, truth: np.ndarray, motion: str, tournament: bool, draws: int) -> dict:
    """Draw ``draws`` stage-one subsets; return the all-inlier share and lambda estimates."""
    delta = TAU * 10 / 6
    cfg = CoreConfig(motion_model=motion)
    model = motion_model(motion)
    if motion == '4dof':
        order = np.argsort(vertical_offsets(src, dst), kind='stable')
        src, dst, truth = src[order], dst[order], truth[order]
    graph = model.compatibility_graph(src, dst, delta, 0.0, 1)
    if not tournament:
        cfg = dataclasses.replace(cfg, edge_tournament=1, vertex_tournament=1)
    search = Search(src, dst, graph, model, cfg, TAU, delta, np.random.default_rng(0))
    subsets, _ = model.draw(search, draws)
    R, t = model.fit(search.corr, subsets)
    inside = compiled.residual_matrix(search.corr, R, t) <= TAU
    counts = np.maximum(inside.sum(axis=1) - model.size, 0)
    right = truth[subsets].all(axis=1)
    wrong = counts[~right]
    zero_share = lambda c: -np.log(max(np.count_nonzero(c == 0), 1) / len(c))  # noqa: E731
    return {'edges': graph.num_edges, 'all_inlier': right.mean(),
            'lambda_all': zero_share(counts), 'lambda_wrong': zero_share(wrong)}


def main(argv=None) -> int:
    ap = argument_parser(__spec__.name, __doc__)
    ap.add_argument('--outliers', default='uniform,surface,cube,cube-surface')
    ap.add_argument('--ratio', type=float, default=0.99)
    ap.add_argument('--n', type=int, default=1000)
    ap.add_argument('--trials', type=int, default=4)
    ap.add_argument('--draws', type=int, default=4000)
    ap.add_argument('--pure', type=int, default=0, help='pure-outlier problems a layout')
    args = ap.parse_args(argv)
    model = load_bunny()
    for layout in args.outliers.split(',') if args.pure else ():
        runs = [register_correspondences(p.src, p.dst, inlier_threshold=TAU, seed=s,
                                         config=CoreConfig(motion_model='4dof'))
                for s, p in ((s, make_correspondences(model, args.n, 1.0, rng=s,
                                                      outliers=layout))
                             for s in range(args.pure))]
        print(f'pure outliers, {layout}: valid {sum(r.valid for r in runs)} of {len(runs)}; '
              f'best consensus {[len(r.inliers) for r in runs]}; chance level '
              f'{[r.chance_level for r in runs]}', flush=True)
    print('| outliers | motion | subsets | graph edges | all-inlier share | lambda, all '
          '| lambda, wrong only |\n|---|---|---|---:|---:|---:|---:|')
    for layout in args.outliers.split(','):
        for motion in ('4dof', '6dof'):
            for tournament in (True, False):
                rows = []
                for trial in range(args.trials):
                    _, p = problem(model, args.n, args.ratio, trial, motion='4dof',
                                   outliers=layout)
                    rows.append(measure(p.src, p.dst, p.inlier_mask, motion, tournament,
                                        args.draws))
                mean = {k: np.mean([r[k] for r in rows]) for k in rows[0]}
                print(f"| {layout} | {motion} | {'tournament' if tournament else 'uniform'} | "
                      f"{mean['edges']:.0f} | {mean['all_inlier']:.3f} | "
                      f"{mean['lambda_all']:.3f} | {mean['lambda_wrong']:.3f} |", flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
