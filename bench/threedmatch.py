r"""
The 3DMatch / 3DLoMatch test benchmark: ours beside KISS-Matcher and Open3D FPFH + RANSAC.

Run by hand (under ``flock /tmp/cgags-bench.lock``)::

    .venv/bin/python -m bench.threedmatch [--root <shared data>/3dmatch_benchmark] \
        [--scenes S ...] [--benchmarks 3DMatch 3DLoMatch] [--pairs K] \
        [--methods cgags kiss_matcher open3d_fpfh_ransac] [--set KEY=VALUE] \
        [--variant NAME:KEY=VALUE[,KEY=VALUE ...]] \
        [--output out/bench/threedmatch] [--records out/bench/threedmatch_run]

Every registration pair (``j - i > 1``) of every scene folder under ``--root`` (any scene
in that layout, :mod:`bench.datasets.threedmatch`), both lists; ``--pairs K`` samples
K pairs a scene and list (seeded) for quick runs. Every method gets the same raw
fragments and the same voxel (``--voxel``, 5 cm) and is timed from the raw (N, 3) points
to the 4x4 transform, one pair at a time, the methods interleaved pair by pair:

``cgags``
    :func:`cgags_ros.pipeline.register_clouds`, defaults or ``--set``; cold (its feature
    cache cleared before each pair, as the baselines featurise both clouds every pair)
    unless ``--warm-features`` (each fragment featurised once a scene: for quick gate
    studies; its times are then not comparable and the output says so).
``cgags[NAME]``
    ours again with ``--variant NAME:KEY=VALUE,...`` (repeatable; on top of ``--set``):
    settings compared in one run, interleaved pair by pair with the rest, so their times
    are ratios under the same machine load (a recall/time curve).
``kiss_matcher``
    ``KISSMatcher(KISSMatcherConfig(voxel)).estimate(src, tgt)`` (kiss-matcher 1.0.2,
    float32, its own front end, no refinement); its ``valid`` is its flag.
``open3d_fpfh_ransac``
    Open3D RANSAC on feature matching over our front end's features, as
    :func:`bench.baselines.open3d_fpfh_ransac` (1e5 iterations, 0.999, no refinement); no
    validity flag (every estimate counts as flagged valid).

Metrics, per scene (columns, as the seed paper's table) and overall, per list: registration
recall RR (RE < 15 deg and TE < 0.3 m, counted on every estimate whatever its flag), mean
RE/TE over the successes, the official RMSE recall (``gt.info``, RMSE < 0.2 m), median and
p95 seconds a pair, the median CPU seconds a pair (the process's, every thread: against the
wall time it says how much of both cores a method keeps busy), and the valid flag's
quality: ``valid keeps`` = right and valid / right,
``valid but wrong`` = wrong and valid (count and share of the valid estimates).

Outputs: ``--output`` + ``.md`` / ``.json`` / ``.png`` (tables, summary, plot; default
``out/bench/threedmatch``), and one JSON line per pair and method under ``--records``
(git-ignored ``out/``) with what our
gates and candidate search saw (inliers, chance level, hypotheses, fitness and overlap,
candidates with their inliers, fitness both ways and their geometry relative to the best
and to the ground truth): gate changes can be studied on them without re-running
(``python -m bench.studies.gate_study``).
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path
import platform
import sys
import time

from bench.baselines import kiss_matcher_estimate, open3d_fpfh_ransac
from bench.common import (add_set_option, argument_parser, cell, machine, markdown_table,
                          output_path, parse_overrides, pyplot, save_figure, write_json,
                          write_text)
from bench.datasets import threedmatch as tdm
from cgags_ros.config import PipelineConfig
from cgags_ros.config.fields import update_from_flat
from cgags_ros.geometry import rotation_error_deg, spread, translation_error
from cgags_ros.io.shared_data import shared_data_dir
import numpy as np

MAX_RE_DEG, MAX_TE_M = tdm.MAX_RE_DEG, tdm.MAX_TE_M
METHODS = ('cgags', 'kiss_matcher', 'open3d_fpfh_ransac')


# --- methods: (source, target, voxel) -> (4x4 source->target, valid, diagnostics) ----------

def run_cgags(src: np.ndarray, tgt: np.ndarray, voxel: float, gt: np.ndarray,
              config: PipelineConfig, warm: bool) -> tuple[np.ndarray, bool, dict]:
    from cgags_ros.pipeline import clear_feature_cache, register_clouds

    if not warm:
        clear_feature_cache()
    result, times = timed_call(register_clouds, src, tgt, voxel_size=voxel, config=config)
    return result.transform, result.valid, {**times,
                                            **diagnostics(result, src, tgt, gt, config)}


def timed_call(fn, *args, **kwargs) -> tuple:
    """Return ``fn(*args, **kwargs)`` and its seconds: wall ``time_s``, process CPU ``cpu_s``."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    return out, {'time_s': time.perf_counter() - t0, 'cpu_s': time.process_time() - c0}


def diagnostics(result, src: np.ndarray, tgt: np.ndarray, gt: np.ndarray,
                config: PipelineConfig) -> dict:
    """Return what the gates and the candidate search saw, each candidate against the truth."""
    from cgags_ros.frontend.refine import evaluate_alignment
    from cgags_ros.pipeline.cache import cached_features
    from cgags_ros.pipeline.gates import observability

    out = {
        'reason': result.reason, 'refusal': result.refusal and result.refusal.code.value,
        'ambiguous': bool(result.ambiguous),
        'num_inliers': int(result.num_inliers) if hasattr(result, 'num_inliers') else None,
        'num_correspondences': int(result.num_correspondences),
        'num_hypotheses': int(result.num_hypotheses),
        # the core's draws in all, and how many it had made when it last improved its best
        'draws': int(result.stats.get('compatible_samples', 0)
                     + result.stats.get('guided_samples', 0)),
        'best_found_at': int(result.stats.get('best_found_at', 0)),
        'chance_inliers': _num(result.chance_inliers), 'fitness': _num(result.fitness),
        'overlap': _num(result.overlap), 'inlier_rmse': _num(result.inlier_rmse),
        'observability': _num(result.observability),
        'free_space_violation': _num(result.free_space_violation),
        'runner_up_ratio': _num(result.runner_up_ratio),
        'inlier_threshold': _num(result.inlier_threshold),
        'num_source_points': int(result.num_source_points),
        'num_target_points': int(result.num_target_points),
        'coarse_re_deg': rotation_error_deg(result.coarse_transform, gt),
        'coarse_te_m': translation_error(result.coarse_transform, gt),
        'timings': {k: float(v) for k, v in result.timings.items()},
    }
    pts = result.inlier_source_points
    out['inlier_spread_m'] = (spread(pts) / math.sqrt(len(pts))).tolist() if len(pts) > 2 \
        else None
    if not result.candidates:
        out['candidates'] = []
        return out
    # Outside the timed call: the clouds' features are still in the cache (both of them).
    v = config.voxel_size
    fs = cached_features(src, v, config.frontend, 'source')
    ft = cached_features(tgt, v, config.frontend, 'target')
    distance = config.refine.max_correspondence_distance_factor * v
    best = result.candidates[0].transform
    cands = []
    for c in result.candidates:
        a = evaluate_alignment(fs.points, ft.tree, c.transform, distance)
        b = evaluate_alignment(ft.points, fs.tree, np.linalg.inv(c.transform), distance)
        cands.append({
            'num_inliers': int(c.num_inliers), 'fitness': a.fitness, 'back_fitness': b.fitness,
            'rmse': _num(a.inlier_rmse), 'back_rmse': _num(b.inlier_rmse),
            'observability': observability(fs.points, ft.normals, a),
            're_deg': rotation_error_deg(c.transform, gt),
            'te_m': translation_error(c.transform, gt),
            'from_best_deg': rotation_error_deg(c.transform, best),
            'from_best_m': translation_error(c.transform, best),
            'transform': np.asarray(c.transform).tolist()})
    out['candidates'] = cands
    return out


def run_kiss(src: np.ndarray, tgt: np.ndarray, voxel: float) -> tuple[np.ndarray, bool, dict]:
    out, times = timed_call(kiss_matcher_estimate, src, tgt, voxel)
    return out.transform, out.valid, {**times, **out.info}


def run_open3d(src: np.ndarray, tgt: np.ndarray, voxel: float) -> tuple[np.ndarray, bool, dict]:
    T, times = timed_call(open3d_fpfh_ransac, src, tgt, voxel)
    return T, True, times


def _num(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


# --- the run -------------------------------------------------------------------------------

def select_pairs(pairs: list[tdm.GtPair], k: int | None, seed: int) -> list[tdm.GtPair]:
    """Return all ``pairs``, or ``k`` of them drawn without replacement (file order kept)."""
    if k is None or k >= len(pairs):
        return pairs
    idx = np.sort(np.random.default_rng(seed).choice(len(pairs), size=k, replace=False))
    return [pairs[i] for i in idx]


def evaluate(T: np.ndarray, pair: tdm.GtPair) -> dict:
    gt = tdm.nearest_rigid(pair.transform)
    re, te = rotation_error_deg(T, gt), translation_error(T, gt)
    rmse = tdm.rmse_error(T, pair.transform, pair.info) if pair.info is not None else None
    return {'re_deg': re, 'te_m': te, 'success': bool(re < MAX_RE_DEG and te < MAX_TE_M),
            'rmse_m': rmse, 'rmse_success': None if rmse is None else bool(
                rmse < tdm.RMSE_THRESHOLD)}


def run(args, methods: dict) -> list[dict]:
    records: list[dict] = []
    sink = None
    if args.records:
        args.records.mkdir(parents=True, exist_ok=True)
        sink = open(args.records / 'records.jsonl', 'w', encoding='utf-8')
    try:
        for benchmark in args.benchmarks:
            names = args.scenes or tdm.scenes(args.root, benchmark)
            for scene in names:
                pairs = select_pairs(tdm.registration_pairs(args.root, benchmark, scene),
                                     args.pairs, args.seed)
                fragments = tdm.Fragments(args.root, scene)
                _reset_cache(args.warm_features)
                print(f'{benchmark} {scene}: {len(pairs)} pair(s)', flush=True)
                for pair in pairs:
                    src, tgt = fragments[pair.source], fragments[pair.target]
                    for name, fn in methods.items():
                        try:
                            gt = tdm.nearest_rigid(pair.transform)
                            T, valid, info = fn(src, tgt, args.voxel, gt) \
                                if _ours(name) else fn(src, tgt, args.voxel)
                            error = ''
                        except Exception as exc:  # noqa: BLE001 - a failing method is data
                            T, valid, info = np.eye(4), False, {'time_s': float('nan')}
                            error = ' '.join(f'{type(exc).__name__}: {exc}'.split())
                        rec = {'benchmark': benchmark, 'scene': scene, 'target': pair.target,
                               'source': pair.source, 'gt_overlap': _num(pair.overlap),
                               'method': name, 'valid': bool(valid), 'error': error,
                               **evaluate(T, pair), **info,
                               'transform': np.asarray(T).tolist()}
                        records.append(rec)
                        if sink:
                            sink.write(json.dumps(rec) + '\n')
                    if sink:
                        sink.flush()
                done = [r for r in records if r['scene'] == scene
                        and r['benchmark'] == benchmark]
                for name in methods:
                    s = summarize([r for r in done if r['method'] == name])
                    print(f"  {name}: RR {cell(s['rr'])}, valid-but-wrong "
                          f"{s['valid_wrong']}/{s['valid']}, median {cell(s['median_time_s'])} s",
                          flush=True)
    finally:
        if sink:
            sink.close()
    return records


def warm_up(args, methods: dict) -> None:
    """Run every method once on a first pair, untimed: compilation and lazy set-up."""
    benchmark = args.benchmarks[0]
    scene = (args.scenes or tdm.scenes(args.root, benchmark))[0]
    pair = tdm.registration_pairs(args.root, benchmark, scene)[0]
    fragments = tdm.Fragments(args.root, scene)
    src, tgt = fragments[pair.source], fragments[pair.target]
    for name, fn in methods.items():
        fn(src, tgt, args.voxel, pair.transform) if _ours(name) else fn(src, tgt, args.voxel)


def _ours(method: str) -> bool:
    return method == 'cgags' or method.startswith('cgags[')


def variants(specs: list[str], config: PipelineConfig) -> dict[str, PipelineConfig]:
    """Return {'cgags[NAME]': config} for each ``--variant NAME:KEY=VALUE,...``."""
    out = {}
    for spec in specs:
        name, sep, sets = spec.partition(':')
        if not sep or not name or f'cgags[{name}]' in out:
            raise SystemExit(f'--variant {spec!r}: expected a new NAME:KEY=VALUE[,KEY=VALUE]')
        out[f'cgags[{name}]'] = update_from_flat(config, parse_overrides(sets.split(',')))
    return out


def _reset_cache(warm: bool) -> None:
    from cgags_ros.pipeline import clear_feature_cache, set_feature_cache_size

    clear_feature_cache()
    # Warm: every fragment of a scene featurised once (a scene has at most a few hundred).
    if warm:
        set_feature_cache_size(1000)


def summarize(recs: list[dict]) -> dict:
    """Return the metrics of a set of records (one method)."""
    n = len(recs)
    ok = [r for r in recs if r['success']]
    valid = [r for r in recs if r['valid']]
    times = [r['time_s'] for r in recs if r['time_s'] == r['time_s']]
    cpu = [r['cpu_s'] for r in recs if r.get('cpu_s') is not None]  # older records: none
    rmse = [r for r in recs if r['rmse_success'] is not None]
    right_valid = sum(r['valid'] for r in ok)
    wrong_valid = len(valid) - right_valid
    return {
        'pairs': n, 'successes': len(ok), 'rr': len(ok) / n if n else None,
        'mean_re_deg': float(np.mean([r['re_deg'] for r in ok])) if ok else None,
        'mean_te_m': float(np.mean([r['te_m'] for r in ok])) if ok else None,
        'rmse_recall': (sum(r['rmse_success'] for r in rmse) / len(rmse)) if rmse else None,
        'median_time_s': float(np.median(times)) if times else None,
        'p95_time_s': float(np.percentile(times, 95)) if times else None,
        'median_cpu_s': float(np.median(cpu)) if cpu else None,
        'valid': len(valid), 'right_valid': right_valid, 'valid_wrong': wrong_valid,
        'valid_keeps': right_valid / len(ok) if ok else None,
        'valid_wrong_share': wrong_valid / len(valid) if valid else None,
        'errors': len([r for r in recs if r['error']]),
    }


def summaries(records: list[dict]) -> dict:
    """Return {benchmark: {method: {scene or 'all': summary}}}."""
    out: dict = {}
    for b in dict.fromkeys(r['benchmark'] for r in records):
        for m in dict.fromkeys(r['method'] for r in records):
            recs = [r for r in records if r['benchmark'] == b and r['method'] == m]
            per = {s: summarize([r for r in recs if r['scene'] == s])
                   for s in dict.fromkeys(r['scene'] for r in recs)}
            per['all'] = summarize(recs)
            out.setdefault(b, {})[m] = per
    return out


ROWS = (('RR [%]', 'rr', 100.0), ('mean RE [deg]', 'mean_re_deg', 1.0),
        ('mean TE [cm]', 'mean_te_m', 100.0), ('RMSE recall [%]', 'rmse_recall', 100.0),
        ('median time [s]', 'median_time_s', 1.0), ('p95 time [s]', 'p95_time_s', 1.0),
        ('median CPU time [s]', 'median_cpu_s', 1.0), ('valid keeps [%]', 'valid_keeps', 100.0),
        ('valid but wrong', None, None), ('valid but wrong [% of valid]', 'valid_wrong_share',
                                          100.0))


def tables(summary: dict) -> str:
    parts = []
    for b, per_method in summary.items():
        scenes = [s for s in next(iter(per_method.values())) if s != 'all']
        headers = ('method', 'metric', *[_short(s) for s in scenes], 'all')
        rows = []
        for m, per in per_method.items():
            pairs = [per[s]['pairs'] for s in scenes] + [per['all']['pairs']]
            rows.append((m, 'pairs', *pairs))
            for label, key, scale in ROWS:
                if key is None:
                    vals = [f"{per[s]['valid_wrong']} of {per[s]['valid']}"
                            for s in (*scenes, 'all')]
                else:
                    vals = [None if per[s][key] is None else per[s][key] * scale
                            for s in (*scenes, 'all')]
                rows.append((m, label, *vals))
        parts.append(f'### {b}\n\n' + markdown_table(headers, rows))
    return '\n\n'.join(parts)


def _short(scene: str) -> str:
    return scene.split('-')[1] if scene.startswith('sun3d-') else scene.replace('7-scenes-', '')


def plot(summary: dict, path: Path) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, len(summary) + 1, figsize=(5 * (len(summary) + 1), 4))
    for ax, (b, per_method) in zip(axes, summary.items()):
        cols = list(next(iter(per_method.values())))
        width = 0.8 / len(per_method)
        for k, (m, per) in enumerate(per_method.items()):
            ax.bar(np.arange(len(cols)) + k * width, [100 * (per[c]['rr'] or 0) for c in cols],
                   width, label=m)
        ax.set_xticks(np.arange(len(cols)) + 0.4 - width / 2, [_short(c) for c in cols],
                      rotation=20)
        ax.set_ylabel('registration recall [%]')
        ax.set_title(b)
        ax.set_ylim(0, 100)
    ax = axes[-1]
    for b, per_method in summary.items():
        for m, per in per_method.items():
            a = per['all']
            ax.scatter(a['median_time_s'], 100 * (a['rr'] or 0),
                       marker='o' if b == '3DMatch' else 's', label=f'{m} ({b})')
    ax.set_xscale('log')
    ax.set_xlabel('median seconds a pair')
    ax.set_ylabel('registration recall [%] (all scenes)')
    ax.legend(fontsize=7)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    p = argument_parser(__spec__.name, __doc__)
    p.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark')
    p.add_argument('--scenes', nargs='+', default=None, help='default: every scene folder')
    p.add_argument('--benchmarks', nargs='+', choices=tdm.BENCHMARKS, default=list(tdm.BENCHMARKS))
    p.add_argument('--methods', nargs='+', choices=METHODS, default=list(METHODS))
    p.add_argument('--pairs', type=int, default=None,
                   help='sample this many pairs a scene and list (default: all)')
    p.add_argument('--seed', type=int, default=0, help='seed of the --pairs sample')
    p.add_argument('--voxel', type=float, default=0.05, help='voxel size, metres')
    add_set_option(p)
    p.add_argument('--variant', action='append', default=[], metavar='NAME:KEY=VALUE,...',
                   help='also run ours with these changes, as method cgags[NAME] (repeatable)')
    p.add_argument('--warm-features', action='store_true',
                   help='featurise each fragment once (ours only; its times not comparable)')
    p.add_argument('--output', type=Path, default=output_path('threedmatch'),
                   help='path stem of the .md/.json/.png outputs (default: %(default)s)')
    p.add_argument('--records', type=Path, default=None,
                   help='folder for records.jsonl, one line a pair and method')
    args = p.parse_args(argv)
    config = update_from_flat(PipelineConfig(), {'voxel_size': args.voxel,
                                                 **parse_overrides(args.set)})
    table = {'cgags': functools.partial(run_cgags, config=config, warm=args.warm_features),
             'kiss_matcher': run_kiss, 'open3d_fpfh_ransac': run_open3d}
    methods = {m: table[m] for m in args.methods}
    for name, changed in variants(args.variant, config).items():
        methods[name] = functools.partial(run_cgags, config=changed, warm=args.warm_features)
    t0 = time.time()
    warm_up(args, methods)
    records = run(args, methods)
    summary = summaries(records)
    text = tables(summary)
    notes = ['command: `.venv/bin/python -m bench.threedmatch '
             + ' '.join(sys.argv[1:] if argv is None else argv) + '`',
             f'machine: {platform.platform()}, one pair at a time, methods interleaved pair '
             f'by pair; wall {time.time() - t0:.0f} s',
             f'voxel {args.voxel:g} m; RR: RE < {MAX_RE_DEG:g} deg and TE < {MAX_TE_M:g} m on '
             'every estimate; RMSE recall: official gt.info RMSE < 0.2 m; valid keeps: right '
             'and flagged valid / right; open3d_fpfh_ransac has no flag (all count as valid)',
             'pairs: ' + ('all' if args.pairs is None else f'{args.pairs} a scene and list '
                          f'(seed {args.seed})')]
    if args.set:
        notes.append('ours with --set ' + ' '.join(args.set))
    notes += [f'cgags[{v.partition(":")[0]}]: ours with {v.partition(":")[2]}'
              for v in args.variant]
    if args.warm_features:
        notes.append('ours with --warm-features: its times are NOT comparable')
    print('\n' + text + '\n\n' + '\n'.join(notes))
    write_json(args.output.with_suffix('.json'), {
        'machine': machine(), 'args': {k: str(v) for k, v in vars(args).items()},
        'notes': notes, 'wall_s': time.time() - t0, 'summary': summary})
    write_text(args.output.with_suffix('.md'),
               text + '\n\n' + '\n'.join(f'- {n}' for n in notes) + '\n')
    plot(summary, args.output.with_suffix('.png'))
    print(f'wrote {args.output}.{{md,json,png}}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
