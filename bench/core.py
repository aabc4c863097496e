r"""
Core benchmark: our registration core vs Open3D RANSAC vs KISS-Matcher.

All solvers run on the SAME synthetic putative correspondences (Stanford bunny, unit-scaled:
largest extent 1; :mod:`bench.problems`), one problem at a time,
and are scored with the literature's RE/TE: success = RE < 5 deg and TE < 0.1 (model units).
Time = wall time of the whole solver call as a user makes it (input conversion included),
median and p90 over the trials of a cell; CPU time (all threads of the process) goes to --json.
``--order interleaved`` (default) runs every solver on a problem before the next problem
(the order rotated across trials); ``--order blocks`` runs each solver on all of a cell's
problems in a row, so no solver's call follows another library's (whose idle threads and
cached data slow the next call: docs/bench_core.md).

Defaults: outlier ratios 0.9 0.95 0.98 0.99 0.995, N = 1000 and 5000, 20 trials per cell,
noise sigma 0.01, inlier threshold tau 0.05 (= 5 sigma; an inlier's residual norm
|N(0, sigma^2 I_3)| exceeds 0.05 with probability ~1e-5), outliers 'uniform' (dst uniform in the
bounding box of the transformed model, TEASER++ protocol) or 'surface' (dst on another model
point); 'cube' and 'cube-surface' spread them three times wider than the model (uniform in a
cube, on the model scaled 3x), as matches into a larger scene. ``--outliers`` takes a comma
list: each layout is a block of cells in one run.
Every solver gets the same tau: ours as ``inlier_threshold``, Open3D as
``max_correspondence_distance``, KISS-Matcher as both ROBIN and solver noise bounds. The exact
baseline calls are documented in :mod:`bench.baselines`.

Open3D evaluates every hypothesis with an N-point KD-tree query and, at outlier ratios >= 0.95,
runs all 1e5 iterations: ~0.2 ms/iteration at N = 1000 and ~1 ms at N = 5000 on an idle-ish
2-core dev machine (so 20-80 s and 95-300 s per problem, depending on load). A full grid would
take hours, so by default Open3D gets ``--solver-trials open3d=1`` trial per cell (the first
trial's problem, shared with the other solvers) and ``--solver-max-n open3d=1000`` (not run at
N = 5000); the table says so. ``--solver-trials '' --solver-max-n ''`` lifts both limits.

``kiss@F`` runs KISS-Matcher with both noise bounds = F * tau (sensitivity of its ROBIN max-core
pruning to the bound; ``kiss`` is ``kiss@1``).

Solvers are pluggable: ``--solvers`` takes built-in names (``ours``, ``open3d``, ``kiss``) and/or
``module:function`` entries, where the function is ``(src, dst, tau) -> 4x4``. A built-in solver
that cannot be imported (e.g. ``ours`` before the core lands) is skipped with a note.

``--motion 4dof``: yaw-only problems (yaw uniform in [-180, 180) deg about +z,
translation uniform in [-1, 1]^3, plus an optional ``--tilt-noise`` in degrees about a random
horizontal axis), default solvers ``ours-4dof`` (``CoreConfig(motion_model='4dof')``),
``ours-6dof`` (the default 6-DoF core) and ``kiss-quatro`` (KISS-Matcher with
``KISSMatcherConfig(use_quatro=True)``), all on the same problems, in all four outlier
layouts (a sparse wide layout changes what a hypothesis explains by chance).
``ours-4dof@REV`` / ``ours-6dof@REV`` run our core as of git revision REV next to the
working tree's (a before/after in one run).

Results: the Markdown tables (printed too) to ``--output`` (default
``out/bench/core.md``), every record to ``--json`` (default ``out/bench/core.json``).

Examples::

    .venv/bin/python -m bench.core --quick
    .venv/bin/python -m bench.core --solvers open3d,kiss --json /tmp/b.json
    .venv/bin/python -m bench.core --outliers surface --trials 10
    .venv/bin/python -m bench.core --motion 4dof --output out/bench/core_4dof.md
    .venv/bin/python -m bench.core --motion 4dof --outliers cube --ratios 0.99 \
        --solvers ours-4dof@main,ours-4dof,ours-6dof
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import os
from pathlib import Path
import platform
import sys
import time
import traceback
from typing import Any, Callable

from bench import baselines
from bench.common import argument_parser, output_path, write_json, write_text
from bench.datasets.synthetic import load_bunny, make_correspondences, OUTLIER_LAYOUTS
from bench.problems import problem, problem_seed
from cgags_ros.geometry import rotation_error_deg, translation_error
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_RATIOS = (0.9, 0.95, 0.98, 0.99, 0.995)
DEFAULT_SIZES = (1000, 5000)
QUICK_RATIOS = (0.9, 0.99)
QUICK_SIZES = (1000, 5000)
DEFAULT_SOLVERS = ('ours', 'open3d', 'kiss')
DEFAULT_SOLVER_TRIALS = 'open3d=1'
DEFAULT_SOLVER_MAX_N = 'open3d=1000'
DEFAULT_SOLVERS_4DOF = ('ours-4dof', 'ours-6dof', 'kiss-quatro')
DEFAULT_OUTLIERS = ('uniform',)
# Both extents (the model's bounding box and a cube three times wider), uniform and on a
# surface: a sparse wide layout changes what a hypothesis explains by chance.
DEFAULT_OUTLIERS_4DOF = ('uniform', 'surface', 'cube', 'cube-surface')


# ------------------------------------------------------------------------------- solvers


@dataclasses.dataclass
class SolverOutput:
    transform: np.ndarray
    valid: bool | None = None
    info: dict[str, Any] = dataclasses.field(default_factory=dict)


SolverFn = Callable[[np.ndarray, np.ndarray, float, int], SolverOutput]


@dataclasses.dataclass
class Solver:
    name: str
    fn: SolverFn
    description: str


def _make_ours(motion: str = '6dof', name: str = 'ours') -> Solver:
    from cgags_ros.registration import CoreConfig, register_correspondences

    config = CoreConfig(motion_model=motion)

    def run(src, dst, tau, seed):
        res = register_correspondences(src, dst, inlier_threshold=tau, seed=seed,
                                       config=config)
        return SolverOutput(np.asarray(res.transform, dtype=float), bool(res.valid), {
            'reason': res.reason,
            'num_inliers': int(len(res.inliers)),
            'num_hypotheses': int(res.num_hypotheses),
            'restarts': int(res.stats.get('restarts', 0)),
            'chance_level': res.chance_level,
            'stopped_by': res.stats.get('stopped_by'),
            'core_total_s': float(res.timings.get('total', float('nan'))),
        })

    return Solver(name, run, 'cgags_ros.registration.register_correspondences('
                  'src, dst, inlier_threshold=tau, seed=problem seed), '
                  + ('default CoreConfig' if motion == '6dof'
                     else f"CoreConfig(motion_model='{motion}'), gravity +z"))


def _make_open3d() -> Solver:
    import open3d  # noqa: F401  (fail early if missing)

    def run(src, dst, tau, seed):
        r = baselines.open3d_ransac_detailed(src, dst, tau, seed=seed)
        return SolverOutput(r.transform, r.valid, r.info)

    return Solver('open3d', run, 'Open3D 0.19 registration_ransac_based_on_correspondence, '
                  'max_correspondence_distance=tau, PointToPoint(False), ransac_n=3, no checkers, '
                  'RANSACConvergenceCriteria(100000, 0.999)')


def _make_kiss() -> Solver:
    import kiss_matcher  # noqa: F401

    def run(src, dst, tau, seed):
        r = baselines.kiss_prune_and_solve_detailed(src, dst, tau)
        return SolverOutput(r.transform, r.valid, r.info)

    return Solver('kiss', run, 'KISS-Matcher 1.0.2 KISSMatcher(KISSMatcherConfig(voxel_size=tau, '
                  'robin_noise_bound_gain=1, solver_noise_bound_gain=1))'
                  '.prune_and_solve(src, dst) (ROBIN and solver noise bounds = tau)')


def _make_ours_variant(name: str) -> Solver:
    """``ours-4dof[key=value;...]``: the 4-DoF core with CoreConfig overrides (ablation)."""
    from cgags_ros.config import fields
    from cgags_ros.registration import CoreConfig, register_correspondences

    items = [item for item in name[len('ours-4dof['):-1].split(';') if item]
    config = fields.update_from_flat(CoreConfig(motion_model='4dof'),
                                     fields.parse_key_values(items))

    def run(src, dst, tau, seed):
        res = register_correspondences(src, dst, inlier_threshold=tau, seed=seed,
                                       config=config)
        return SolverOutput(np.asarray(res.transform, dtype=float), bool(res.valid), {
            'reason': res.reason, 'num_inliers': int(len(res.inliers)),
            'num_hypotheses': int(res.num_hypotheses),
            'stopped_by': res.stats.get('stopped_by')})

    return Solver(name, run, f"CoreConfig(motion_model='4dof', {', '.join(items)})")


def _make_ours_at(name: str) -> Solver:
    """``ours-4dof@REV``, ``ours-6dof@REV``: our core as of git revision REV (before/after)."""
    import tempfile

    from bench.revision import load_previous

    motion, rev = name[len('ours-'):].split('@', 1)
    previous = load_previous(rev, Path(tempfile.mkdtemp(prefix='bench_core_')))
    from cgags_prev.registration import CoreConfig  # the package load_previous made importable

    config = CoreConfig(motion_model=motion)

    def run(src, dst, tau, seed):
        res = previous(src, dst, inlier_threshold=tau, seed=seed, config=config)
        return SolverOutput(np.asarray(res.transform, dtype=float), bool(res.valid), {
            'reason': res.reason, 'num_inliers': int(len(res.inliers)),
            'num_hypotheses': int(res.num_hypotheses),
            'restarts': int(res.stats.get('restarts', 0)),
            'chance_level': res.chance_level,
            'stopped_by': res.stats.get('stopped_by')})

    return Solver(name, run, f'as ours-{motion}, the core of git revision {rev} '
                  '(bench.revision.load_previous)')


def _make_kiss_quatro() -> Solver:
    import kiss_matcher  # noqa: F401

    def run(src, dst, tau, seed):
        r = baselines.kiss_prune_and_solve_detailed(src, dst, tau, quatro=True)
        return SolverOutput(r.transform, r.valid, r.info)

    return Solver('kiss-quatro', run, 'as kiss, with KISSMatcherConfig(use_quatro=True): '
                  'Quatro 4-DoF rotation (yaw about +z) instead of GNC-TLS 6-DoF')


def _make_kiss_scaled(factor: float) -> Solver:
    """``kiss@F``: KISS-Matcher with both noise bounds = F * tau (sensitivity check)."""
    import kiss_matcher  # noqa: F401

    def run(src, dst, tau, seed):
        r = baselines.kiss_prune_and_solve_detailed(src, dst, factor * tau)
        return SolverOutput(r.transform, r.valid, r.info)

    return Solver(f'kiss@{factor:g}', run, f'as kiss, but ROBIN and solver noise bounds = '
                  f'{factor:g} * tau (voxel_size = {factor:g} * tau)')


def _make_plugin(spec: str) -> Solver:
    module, _, attr = spec.partition(':')
    fn = getattr(importlib.import_module(module), attr)

    def run(src, dst, tau, seed):
        return SolverOutput(np.asarray(fn(src, dst, tau), dtype=float))

    return Solver(spec, run, f'{spec}(src, dst, tau) -> 4x4')


BUILTIN_SOLVERS: dict[str, Callable[[], Solver]] = {
    'ours': _make_ours,
    'open3d': _make_open3d,
    'kiss': _make_kiss,
    'kiss-quatro': _make_kiss_quatro,
    'ours-6dof': lambda: _make_ours('6dof', 'ours-6dof'),
    'ours-4dof': lambda: _make_ours('4dof', 'ours-4dof'),
}


def load_solvers(names: list[str]) -> tuple[list[Solver], dict[str, str]]:
    """Solvers that could be built, and {name: reason} for those that could not."""
    solvers, skipped = [], {}
    for name in names:
        try:
            if name in BUILTIN_SOLVERS:
                solvers.append(BUILTIN_SOLVERS[name]())
            elif name.startswith('ours-4dof[') and name.endswith(']'):
                solvers.append(_make_ours_variant(name))
            elif name.startswith(('ours-4dof@', 'ours-6dof@')):
                solvers.append(_make_ours_at(name))
            elif name.startswith('kiss@'):
                solvers.append(_make_kiss_scaled(float(name[5:])))
            elif ':' in name:
                solvers.append(_make_plugin(name))
            else:
                raise ValueError(f'unknown solver {name!r} '
                                 f"(built-ins: {', '.join(BUILTIN_SOLVERS)}, "
                                 'or module:function)')
        except ValueError:
            raise
        except Exception as exc:  # ImportError, AttributeError, ...
            skipped[name] = f'{type(exc).__name__}: {exc}'
    return solvers, skipped


# ------------------------------------------------------------------------------ running


def run_one(solver: Solver, src, dst, tau, seed, gt, max_re, max_te) -> dict[str, Any]:
    err = None
    c0, t0 = time.process_time(), time.perf_counter()
    try:
        out = solver.fn(src, dst, tau, seed)
    except Exception as exc:  # a crash counts as a failure
        out = SolverOutput(np.eye(4), False, {})
        err = f'{type(exc).__name__}: {exc}'
        traceback.print_exc(file=sys.stderr)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    re, te = rotation_error_deg(out.transform, gt), translation_error(out.transform, gt)
    rec = {'wall_ms': wall * 1e3, 'cpu_ms': cpu * 1e3, 're_deg': re, 'te': te,
           'success': bool(re < max_re and te < max_te), 'valid': out.valid, 'info': out.info}
    if err:
        rec['error'] = err
    return rec


def warm_up(solvers: list[Solver], model: np.ndarray, tau: float, noise: float) -> None:
    """One untimed call per solver (imports, lazy initialisation, thread pools)."""
    p = make_correspondences(model, 300, 0.5, noise_sigma=noise, rng=12345)
    for s in solvers:
        try:
            s.fn(p.src, p.dst, tau, 0)
        except Exception:
            traceback.print_exc(file=sys.stderr)


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    if not records:
        return {'n': 0}
    wall = np.array([r['wall_ms'] for r in records])
    succ = np.array([r['success'] for r in records])
    valid = [r['valid'] for r in records]
    out = {
        'n': len(records),
        'successes': int(succ.sum()),
        'success_pct': 100.0 * float(succ.mean()),
        'median_ms': float(np.median(wall)),
        'p90_ms': float(np.percentile(wall, 90)),
        'mean_cpu_ms': float(np.mean([r['cpu_ms'] for r in records])),
        'errors': sum('error' in r for r in records),
    }
    hyps = [r['info']['num_hypotheses'] for r in records if 'num_hypotheses' in r['info']]
    if len(hyps) == len(records):  # our core: how long the search ran
        out['median_hypotheses'] = float(np.median(hyps))
        out['at_cap'] = sum(r['info'].get('stopped_by') == 'max_iterations' for r in records)
    if all(v is not None for v in valid):
        out['valid'] = int(sum(valid))
        out['valid_but_wrong'] = int(sum(v and not s for v, s in zip(valid, succ)))
        out['invalid_but_right'] = int(sum((not v) and s for v, s in zip(valid, succ)))
    return out


def parse_caps(text: str) -> dict[str, int]:
    caps = {}
    for item in filter(None, (s.strip() for s in (text or '').split(','))):
        name, _, k = item.partition('=')
        caps[name.strip()] = int(k)
    return caps


def _schedule(args, model, solvers, caps, max_n, n, ratio, layout) -> list[tuple]:
    """
    Return (trial, seed, solver, problem) in the order the solvers run on a cell's problems.

    'interleaved': problem by problem, every solver on it, the order rotated across trials;
    'blocks': each solver on all of the cell's problems in a row, so that each runs after
    its own previous call (as a user's loop would), not after another library's (which
    leaves its thread pool spinning and the caches full of its data: docs/bench_core.md).
    """
    problems = [(trial, *problem(model, n, ratio, trial, seed=args.seed, motion=args.motion,
                                 outliers=layout, noise=args.noise,
                                 tilt_noise=args.tilt_noise))
                for trial in range(args.trials)]
    order = []
    for trial, seed, p in problems:
        active = [s for s in solvers if trial < caps[s.name] and n <= max_n.get(s.name, n)]
        k = trial % len(active) if active else 0
        order += [(trial, seed, s, p) for s in active[k:] + active[:k]]
    if args.order == 'blocks':
        order.sort(key=lambda run: solvers.index(run[2]))  # stable: trials stay in order
    return order


def run_benchmark(args: argparse.Namespace) -> dict[str, Any]:
    model = load_bunny(args.data_dir)
    solvers, skipped = load_solvers(args.solvers)
    for name, why in skipped.items():
        print(f'[bench.core] solver {name!r} skipped: {why}', file=sys.stderr)
    if not solvers:
        raise SystemExit('no solver could be loaded')
    caps = {s.name: min(args.trials, args.caps.get(s.name, args.trials)) for s in solvers}
    max_n = {s.name: args.max_n[s.name] for s in solvers if s.name in args.max_n}
    env = environment()  # at start: the core's sources as imported, not as edited later
    warm_up(solvers, model, args.tau, args.noise)

    cells = []
    t_start = time.perf_counter()
    for layout, n, ratio in ((lay, n, r) for lay in args.outliers for n in args.sizes
                             for r in args.ratios):
        per_solver: dict[str, list] = {s.name: [] for s in solvers}
        for trial, seed, s, p in _schedule(args, model, solvers, caps, max_n, n, ratio,
                                           layout):
            rec = run_one(s, p.src, p.dst, args.tau, seed, p.transform,
                          args.max_re, args.max_te)
            rec.update(trial=trial, seed=seed)
            per_solver[s.name].append(rec)
        cell = {'outliers': layout, 'ratio': ratio, 'n': n,
                'num_inliers': int(round((1 - ratio) * n)),
                'summary': {k: summarise(v) for k, v in per_solver.items()}}
        # Fairness for capped solvers: the other solvers on the same (first k) problems.
        subsets = {}
        for s in solvers:
            if caps[s.name] < args.trials and per_solver[s.name]:
                subsets[s.name] = {o.name: summarise([r for r in per_solver[o.name]
                                                      if r['trial'] < caps[s.name]])
                                   for o in solvers if o.name != s.name}
        if subsets:
            cell['on_capped_subset'] = subsets
        if not args.no_records:
            cell['records'] = per_solver
        cells.append(cell)
        line = '  '.join(f"{k}: {v['success_pct']:.0f}% {v['median_ms']:.0f}ms (n={v['n']})"
                         for k, v in cell['summary'].items() if v['n'])
        print(f'[bench.core] {layout} ratio={ratio} N={n}: {line}  '
              f'[{time.perf_counter() - t_start:.0f}s]', file=sys.stderr, flush=True)

    breakdown = {}
    if any(s.name == 'kiss' for s in solvers) and not args.no_breakdown:  # 6-DoF only
        for n in args.sizes:
            ratio = args.ratios[len(args.ratios) // 2]
            p = make_correspondences(model, n, ratio, noise_sigma=args.noise,
                                     rng=problem_seed(args.seed, ratio, n, 0),
                                     outliers=args.outliers[0])
            breakdown[str(n)] = dict(ratio=ratio, **baselines.kiss_prune_and_solve_breakdown(
                p.src, p.dst, args.tau))

    return {
        'settings': {
            'ratios': list(args.ratios), 'sizes': list(args.sizes), 'trials': args.trials,
            'trials_per_solver': caps, 'max_n_per_solver': max_n, 'noise_sigma': args.noise,
            'tau': args.tau,
            'outliers': args.outliers, 'seed': args.seed, 'motion': args.motion,
            'order': args.order,
            'tilt_noise_deg': args.tilt_noise, 'max_re_deg': args.max_re,
            'max_te': args.max_te, 'quick': args.quick, 'model': 'Stanford bunny bun_zipper_res3, '
            '1889 points, unit-scaled (largest extent 1)',
        },
        'solvers': {s.name: s.description for s in solvers},
        'skipped': skipped,
        'environment': dict(env, loadavg_after=list(os.getloadavg())),
        'total_s': time.perf_counter() - t_start,
        'kiss_breakdown_ms': breakdown,
        'cells': cells,
    }


def environment() -> dict[str, Any]:
    import cgags_ros

    env = {'python': platform.python_version(), 'machine': platform.machine(),
           'cpu_count': os.cpu_count(), 'loadavg_before': list(os.getloadavg()),
           'cgags_ros_path': str(Path(cgags_ros.__file__).resolve().parent),
           'threads_env': {k: os.environ[k]
                           for k in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS')
                           if k in os.environ}}
    # Versions from the installed metadata: importing Open3D here, when no solver uses it,
    # made our core run 3x slower right after each KISS-Matcher call (two TBB runtimes in
    # one process; docs/bench_core.md).
    from importlib import metadata
    for mod, dist in (('numpy', 'numpy'), ('scipy', 'scipy'), ('open3d', 'open3d'),
                      ('kiss_matcher', 'kiss-matcher')):
        try:
            env[mod] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            pass
    try:
        import hashlib
        h = hashlib.sha256()
        for f in sorted((Path(cgags_ros.__file__).resolve().parent / 'registration').glob('*.py')):
            h.update(f.name.encode() + f.read_bytes())
        env['core_sources_sha256'] = h.hexdigest()[:12]  # the core is not committed yet
    except Exception:
        pass
    try:
        import subprocess
        git = ['git', '-C', str(ROOT)]
        env['git'] = subprocess.run(git + ['rev-parse', '--short', 'HEAD'],
                                    capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(git + ['status', '--porcelain', '--', 'cgags_ros/registration'],
                               capture_output=True, text=True).stdout.strip()
        if dirty:
            env['git'] += ' (+ uncommitted changes in cgags_ros/registration)'
    except Exception:
        pass
    return env


# ------------------------------------------------------------------------------ output


def to_markdown(res: dict[str, Any]) -> str:
    st, env = res['settings'], res['environment']
    names = list(res['solvers'])
    caps = st['trials_per_solver']
    layouts = st['outliers'] if isinstance(st['outliers'], list) else [st['outliers']]
    by_layout = len(layouts) > 1  # a column of the layout: one table for them all
    lines = [
        f"### Core benchmark: {', '.join(names)}",
        '',
        f"Bunny (1889 pts, unit-scaled), motion = {st.get('motion', '6dof')}"
        + (f" (yaw about +z, tilt noise {st['tilt_noise_deg']} deg)"
           if st.get('motion') == '4dof' else ' (any rotation)')
        + f", noise sigma = {st['noise_sigma']}, tau = {st['tau']}, "
        f"outliers = {', '.join(layouts)}, seed = {st['seed']}; "
        f"success = RE < {st['max_re_deg']} deg "
        f"and TE < {st['max_te']}; time = wall ms per problem (whole solver call); solvers run "
        f"{st.get('order', 'interleaved')}. "
        f"{st['trials']} trials per cell" + ''.join(
            f'; **{k}: {v} trial(s) per cell** (the first {v} problem(s) of each cell)'
            for k, v in caps.items() if v < st['trials']) + ''.join(
            f"; **{k} not run for N > {v}** ('-' in the table)"
            for k, v in st.get('max_n_per_solver', {}).items()
            if any(n > v for n in st['sizes'])) + '.',
        '',
    ]
    head = ('| outliers ' if by_layout else '') + '| outlier ratio | N | inliers |'
    sep = ('|---' if by_layout else '') + '|---:|---:|---:|'
    for k in names:
        tag = f' (n={caps[k]})' if caps[k] < st['trials'] else ''
        head += f' {k} succ %{tag} | {k} med ms | {k} p90 ms |'
        sep += '---:|---:|---:|'
    lines += [head, sep]
    for c in res['cells']:
        row = (f"| {c['outliers']} " if by_layout else '') + \
            f"| {c['ratio']} | {c['n']} | {c['num_inliers']} |"
        for k in names:
            s = c['summary'][k]
            if not s.get('n'):
                row += ' - | - | - |'
                continue
            row += f" {s['success_pct']:.0f} | {s['median_ms']:.1f} | {s['p90_ms']:.1f} |"
        lines.append(row)
    # validity totals
    lines += ['', "Validity flags over all cells (success vs the solver's own valid flag):", '',
              '| solver | problems | successes | reported valid | valid but wrong '
              '| invalid but right |',
              '|---|---:|---:|---:|---:|---:|']
    for k in names:
        ss = [c['summary'][k] for c in res['cells'] if c['summary'][k].get('n')]
        tot = lambda key: sum(s.get(key, 0) for s in ss)  # noqa: E731
        has_valid = all('valid' in s for s in ss)
        lines.append(f"| {k} | {tot('n')} | {tot('successes')} | "
                     + (f"{tot('valid')} | {tot('valid_but_wrong')} | {tot('invalid_but_right')} |"
                        if has_valid else 'n/a | n/a | n/a |'))
    ours = [k for k in names if all('median_hypotheses' in c['summary'][k]
                                    for c in res['cells'] if c['summary'][k].get('n'))]
    if ours:
        lines += ['', 'Hypotheses our core drew (median; in brackets the problems that ran '
                  'to the max_iterations cap):', '',
                  ('| outliers ' if by_layout else '') + '| outlier ratio | N |'
                  + ''.join(f' {k} |' for k in ours),
                  ('|---' if by_layout else '') + '|---:|---:|' + '---:|' * len(ours)]
        for c in res['cells']:
            row = (f"| {c['outliers']} " if by_layout else '') + f"| {c['ratio']} | {c['n']} |"
            for k in ours:
                s = c['summary'][k]
                row += f" {s['median_hypotheses']:.0f} ({s['at_cap']}) |" if s.get('n') else ' - |'
            lines.append(row)
    subs = [(c, k, v) for c in res['cells'] for k, v in c.get('on_capped_subset', {}).items()]
    if subs:
        lines += ['', "Other solvers on the capped solver's problems only (succ % / median ms):",
                  '']
        for c, k, v in subs:
            lines.append(f"- {c.get('outliers', layouts[0])} ratio {c['ratio']}, N {c['n']} "
                         f"({k}'s {c['summary'][k]['n']} problem(s)): " + ', '.join(
                             f"{o} {s['success_pct']:.0f}% / {s['median_ms']:.1f} ms"
                             for o, s in v.items() if s.get('n')))
    if res['kiss_breakdown_ms']:
        lines += ['', 'KISS-Matcher `prune_and_solve` time split (median ms; see '
                  '`baselines.kiss_prune_and_solve_breakdown`):', '',
                  '| N | ratio | total | GNC+COTE solve (get_solver_time) | pybind conversion '
                  '(upper bound) | ROBIN prune + copies | float32 copy (wrapper) |',
                  '|---:|---:|---:|---:|---:|---:|---:|']
        for n, b in res['kiss_breakdown_ms'].items():
            lines.append(f"| {n} | {b['ratio']} | {b['total']:.2f} | {b['solver']:.2f} | "
                         f"{b['pybind_conversion_upper']:.2f} | {b['prune_and_rest']:.2f} | "
                         f"{b['to_float32']:.3f} |")
    lines += ['', 'Solvers:', ''] + [f'- `{k}`: {d}' for k, d in res['solvers'].items()]
    for k, why in res['skipped'].items():
        lines.append(f'- `{k}`: **skipped** ({why})')
    lines += ['', f"How this was measured: {env.get('cpu_count')} CPUs, shared (load average "
              f"{env['loadavg_before'][0]:.2f} before, {env['loadavg_after'][0]:.2f} after; "
              'timings include contention). Open3D and KISS-Matcher (each its own TBB) use all '
              f"cores. Versions: numpy {env.get('numpy')}, open3d {env.get('open3d')}, "
              f"kiss_matcher {env.get('kiss_matcher')}, git {env.get('git')}, "
              f"registration/*.py sha256 {env.get('core_sources_sha256')}. "
              f"Total {res['total_s']:.0f} s."]
    return '\n'.join(lines) + '\n'


def _floats(text: str) -> tuple[float, ...]:
    return tuple(float(x) for x in text.split(',') if x.strip())


def _ints(text: str) -> tuple[int, ...]:
    return tuple(int(x) for x in text.split(',') if x.strip())


def parse_args(argv=None) -> argparse.Namespace:
    ap = argument_parser(__spec__.name, __doc__,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--solvers', default=None,
                    help='comma list of ours, ours-6dof, ours-4dof, open3d, kiss, kiss-quatro '
                         f"and/or module:function (default: {','.join(DEFAULT_SOLVERS)}; "
                         f"with --motion 4dof: {','.join(DEFAULT_SOLVERS_4DOF)})")
    ap.add_argument('--motion', choices=('6dof', '4dof'), default='6dof',
                    help='6dof: random rotations; 4dof: yaw-only problems')
    ap.add_argument('--tilt-noise', type=float, default=0.0,
                    help='with --motion 4dof: tilt (deg) about a random horizontal axis')
    ap.add_argument('--ratios', type=_floats, default=None,
                    help=f"outlier ratios (default {','.join(map(str, DEFAULT_RATIOS))})")
    ap.add_argument('--sizes', type=_ints, default=None,
                    help=f"correspondence counts N (default {','.join(map(str, DEFAULT_SIZES))})")
    ap.add_argument('--trials', type=int, default=None,
                    help='trials per cell (default 20, quick 5)')
    ap.add_argument('--solver-trials', default=DEFAULT_SOLVER_TRIALS,
                    help="per-solver cap on trials per cell, e.g. 'open3d=1,kiss=10' "
                         "(default: %(default)s; '' for no cap)")
    ap.add_argument('--solver-max-n', default=DEFAULT_SOLVER_MAX_N,
                    help="per-solver largest N to run, e.g. 'open3d=1000' (default: %(default)s; "
                         "'' to run every solver at every N)")
    ap.add_argument('--quick', action='store_true',
                    help=f'5 trials, ratios {QUICK_RATIOS}, N {QUICK_SIZES} (explicit flags win)')
    ap.add_argument('--noise', type=float, default=0.01, help='inlier noise sigma (default 0.01)')
    ap.add_argument('--tau', type=float, default=0.05,
                    help='inlier threshold given to every solver (default 0.05)')
    ap.add_argument('--outliers', default=None,
                    help='comma list of outlier layouts, each a block of cells: '
                         f"{', '.join(OUTLIER_LAYOUTS)} (make_correspondences; default "
                         f"{','.join(DEFAULT_OUTLIERS)}, with --motion 4dof "
                         f"{','.join(DEFAULT_OUTLIERS_4DOF)})")
    ap.add_argument('--order', choices=('interleaved', 'blocks'), default='interleaved',
                    help='interleaved: every solver on each problem in turn (rotated); blocks: '
                         "each solver on a cell's problems in a row (default: %(default)s)")
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--max-re', type=float, default=5.0, help='success: RE below (deg)')
    ap.add_argument('--max-te', type=float, default=0.1, help='success: TE below (model units)')
    ap.add_argument('--data-dir', default=None, help='shared data dir (default ../shared/data)')
    ap.add_argument('--output', type=Path, default=output_path('core.md'),
                    help='write the markdown tables here (default: %(default)s)')
    ap.add_argument('--json', type=Path, default=output_path('core.json'),
                    help='write all results as JSON here (default: %(default)s)')
    ap.add_argument('--no-records', action='store_true', help='omit per-trial records from JSON')
    ap.add_argument('--no-breakdown', action='store_true',
                    help='skip the KISS-Matcher prune_and_solve time split')
    args = ap.parse_args(argv)
    if args.solvers is None:
        args.solvers = ','.join(DEFAULT_SOLVERS_4DOF if args.motion == '4dof'
                                else DEFAULT_SOLVERS)
    args.solvers = [s.strip() for s in args.solvers.split(',') if s.strip()]
    args.ratios = args.ratios or (QUICK_RATIOS if args.quick else DEFAULT_RATIOS)
    args.outliers = ([x.strip() for x in args.outliers.split(',') if x.strip()]
                     if args.outliers else
                     list(DEFAULT_OUTLIERS_4DOF if args.motion == '4dof' else DEFAULT_OUTLIERS))
    unknown = [x for x in args.outliers if x not in OUTLIER_LAYOUTS]
    if unknown or not args.outliers:
        ap.error(f'--outliers takes a comma list of {OUTLIER_LAYOUTS}, got {unknown}')
    args.sizes = args.sizes or (QUICK_SIZES if args.quick else DEFAULT_SIZES)
    args.trials = args.trials or (5 if args.quick else 20)
    args.caps = parse_caps(args.solver_trials)
    args.max_n = parse_caps(args.solver_max_n)
    if not all(0.0 <= r < 1.0 for r in args.ratios):
        ap.error('outlier ratios must be in [0, 1)')
    if args.tau <= 0 or args.trials < 1:
        ap.error('--tau must be > 0 and --trials >= 1')
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    res = run_benchmark(args)
    md = to_markdown(res)
    print(md)
    print(f'wrote {write_text(args.output, md)}, '
          f'{write_json(args.json, res, default=_json_default)}', file=sys.stderr)
    return 0


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return str(o)


if __name__ == '__main__':
    sys.exit(main())
