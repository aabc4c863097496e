"""
A/B of the registration core against an earlier git revision: same results, and how fast.

A speed pass on the core should leave every result bit for bit as it was. This script
imports the core of ``--rev`` next to the working tree's (:mod:`bench.revision`: ``git
archive`` of the package into a temporary directory, renamed ``cgags_prev``), runs both on
the same problems with the same seeds, alternating, and reports per cell whether every
result is identical (transform, validity, inliers, hypotheses drawn) and the median time of
each.

Problems: the core benchmark's (:mod:`bench.problems`: bunny, uniform outliers, noise
0.01, tau 0.05; ``--motion 4dof`` its yaw-only problems and the 4-DoF core, ``--outliers``
its other layouts), each differing result printed with what changed, and, with
``--pipeline``, the correspondences the pipeline hands the core
on the LiDAR pair at 0.3 m and the redkitchen pair at 5 cm (one rotation each; their many
inliers make the dense-graph work visible, which the benchmark's cells do not).

Example::

    .venv/bin/python -m bench.ab_core --rev f288eca --pipeline
    .venv/bin/python -m bench.ab_core --rev main --motion 4dof --outliers uniform,cube

Exit status 1 when any result differs (for a pass that must not change any). The old
revision's numba code compiles cold in the temporary directory (~20 s).
"""

from __future__ import annotations

from pathlib import Path
import sys
import tempfile
import time

from bench.common import argument_parser
from bench.datasets.synthetic import load_bunny, make_correspondences
from bench.problems import problem
from bench.revision import load_previous, previous_config
from cgags_ros.registration import CoreConfig, register_correspondences
import numpy as np


def same(a, b) -> bool:
    """Tell whether two core results are identical in everything a caller reads."""
    return (np.array_equal(a.transform, b.transform) and a.valid == b.valid
            and a.num_hypotheses == b.num_hypotheses
            and np.array_equal(np.asarray(a.inliers), np.asarray(b.inliers)))


def compare(label: str, problems: list, new, old, repeats: int, verbose: bool = True) -> bool:
    """Run ``new`` and ``old`` alternately on (src, dst, kwargs) problems; print one line."""
    t_new, t_old, differ = [], [], 0
    for src, dst, kwargs in problems:
        # A configuration is each side's own class: kwargs['config'] = (new's, old's).
        new_kw, old_kw = dict(kwargs), dict(kwargs)
        if 'config' in kwargs:
            new_kw['config'], old_kw['config'] = kwargs['config']
        for _ in range(repeats):
            t0 = time.perf_counter()
            b = old(src, dst, **old_kw)
            t_old.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            a = new(src, dst, **new_kw)
            t_new.append(time.perf_counter() - t0)
        if not same(a, b):
            differ += 1
            if verbose:
                print(f'  differs: hypotheses {b.num_hypotheses} -> {a.num_hypotheses}, valid '
                      f'{b.valid} -> {a.valid}, inliers {len(b.inliers)} -> {len(a.inliers)}, '
                      f'stopped_by {b.stats.get("stopped_by")} -> {a.stats.get("stopped_by")}',
                      flush=True)
    ratio = np.median(t_new) / np.median(t_old)
    print(f'{label:28s} old {np.median(t_old) * 1e3:8.2f} ms  new {np.median(t_new) * 1e3:8.2f} '
          f'ms  ({ratio:.2f}x)  results differing: {differ} of {len(problems)}', flush=True)
    return differ == 0


def pipeline_problems() -> list:
    """Return the correspondences (and thresholds) the pipeline gives the core on two pairs."""
    from bench.scaling import load_dataset, random_rotation
    from cgags_ros.pipeline import clear_feature_cache, register_clouds
    from cgags_ros.pipeline import register as pipeline_register

    captured = []

    def capture(src, dst, **kwargs):
        captured.append((src.copy(), dst.copy(), kwargs))
        return register_correspondences(src, dst, **kwargs)

    pipeline_register.register_correspondences = capture
    try:
        out = []
        for name, voxel in (('lidar', 0.3), ('redkitchen', 0.05)):
            src, tgt, _ = load_dataset(name)
            clear_feature_cache()
            captured.clear()
            register_clouds(src @ random_rotation(np.random.default_rng(0)).T, tgt,
                            voxel_size=voxel)
            s, d, kwargs = captured[0]
            kwargs['config'] = (kwargs['config'], previous_config(kwargs['config']))
            out.append((f'{name} {voxel:g} m pipeline', [(s, d, kwargs)]))
        return out
    finally:
        pipeline_register.register_correspondences = register_correspondences


def _problem(model, motion: str, layout: str, n: int, ratio: float, trial: int) -> tuple:
    """Return (src, dst, kwargs) of the core benchmark's problem; 4dof: its yaw-only one."""
    seed, p = problem(model, n, ratio, trial, motion=motion, outliers=layout)
    kwargs = {'inlier_threshold': 0.05, 'seed': seed}
    if motion == '4dof':
        config = CoreConfig(motion_model='4dof')
        kwargs['config'] = (config, previous_config(config))
    return p.src, p.dst, kwargs


def main(argv=None) -> int:
    ap = argument_parser(__spec__.name, __doc__)
    ap.add_argument('--rev', required=True, help='git revision to compare against')
    ap.add_argument('--ratios', default='0.9,0.98,0.99', help='outlier ratios')
    ap.add_argument('--sizes', default='1000,5000', help='correspondence counts N')
    ap.add_argument('--trials', type=int, default=6, help='problems a cell')
    ap.add_argument('--repeats', type=int, default=2, help='timed calls a problem and side')
    ap.add_argument('--motion', choices=('6dof', '4dof'), default='6dof',
                    help="the core's motion model; 4dof: the core benchmark's yaw-only problems")
    ap.add_argument('--outliers', default='uniform',
                    help='comma list of outlier layouts (make_correspondences)')
    ap.add_argument('--pipeline', action='store_true',
                    help="also the pipeline's correspondences on the LiDAR and redkitchen pairs")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        old = load_previous(args.rev, Path(tmp))
        model = load_bunny()
        warm = make_correspondences(model, 300, 0.5, rng=12345)
        for fn in (old, register_correspondences):
            fn(warm.src, warm.dst, inlier_threshold=0.05)
        ok = True
        for layout in args.outliers.split(','):
            for n in (int(x) for x in args.sizes.split(',')):
                for ratio in (float(x) for x in args.ratios.split(',')):
                    problems = [_problem(model, args.motion, layout, n, ratio, trial)
                                for trial in range(args.trials)]
                    ok &= compare(f'{args.motion} {layout} N = {n}, {ratio:.1%} outliers',
                                  problems, register_correspondences, old, args.repeats)
        if args.pipeline:
            for label, problems in pipeline_problems():
                ok &= compare(label, problems, register_correspondences, old, 10)
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
