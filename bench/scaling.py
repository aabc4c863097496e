r"""
Scaling benchmark: time and memory of one registration against points per cloud.

Run by hand::

    .venv/bin/python -m bench.scaling [--sizes redkitchen:0.05 lidar:0.3] \
        [--methods cgags kiss_matcher open3d_fpfh_ransac] [--trials 3] \
        [--set frontend.max_keypoints=5000] \
        [--output out/bench/scaling.json] [--markdown out/bench/scaling.md] \
        [--plot out/bench/scaling.png]

Data: the 3DMatch redkitchen fragments 4 -> 0 at 5, 3.5, 2.5 and 1.8 cm voxels and the
small_gicp LiDAR pair at 0.5, 0.3, 0.2 and 0.12 m. Each trial rotates the source about its
frame origin by a seeded random rotation (any angle; the ground truth is updated to match).

Methods (as ``python -m bench.pipeline`` runs them):

``cgags``
    :func:`cgags_ros.pipeline.register_clouds`, default parameters or those changed by
    ``--set KEY=VALUE``, cold (:func:`~cgags_ros.pipeline.clear_feature_cache` before each
    pair); per-stage seconds from ``result.timings``.
``kiss_matcher``
    ``KISSMatcher(KISSMatcherConfig(voxel_size=v)).estimate(src, tgt)`` (its own front end).
``open3d_fpfh_ransac``
    Open3D FPFH + RANSAC on our front end's features (:func:`bench.baselines.open3d_fpfh_ransac`).

Each (size, method) runs in its own subprocess, so that its peak resident memory
(``VmHWM`` of ``/proc/self/status``: native memory included) is that of the registrations
alone on top of the process's start (``rss_before`` = ``VmRSS`` after imports, loading
the clouds and one untimed warm-up registration at a 4x coarser voxel, reported too).
Times are wall seconds from the raw (N, 3) clouds to the 4x4.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import platform
import subprocess
import sys
import time

from bench.baselines import kiss_matcher_estimate, open3d_fpfh_ransac
from bench.common import (add_set_option, argument_parser, cell, LIMITS, markdown_table,
                          output_path, parse_overrides, pyplot, save_figure, write_json,
                          write_text)
from bench.datasets.gt_pairs import find_pair
from cgags_ros.config import PipelineConfig
from cgags_ros.config.fields import parse_key_values, update_from_flat
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.clouds import read_cloud
from cgags_ros.io.shared_data import shared_data_dir
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATASETS = {'redkitchen': (0.05, 0.035, 0.025, 0.018), 'lidar': (0.5, 0.3, 0.2, 0.12)}
METHODS = ('cgags', 'kiss_matcher', 'open3d_fpfh_ransac')
_MARK = 'BENCH_SCALING_RECORD '
STAGES = ('downsample', 'normals', 'fpfh', 'matching', 'registration', 'refinement',
          'validation', 'candidates')


def load_dataset(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (source, target, 4x4 source->target ground truth) of a dataset, metres."""
    data = shared_data_dir()
    if name == 'redkitchen':
        src, tgt, T = find_pair(data / 'indoor_3dmatch' / 'gt_pairs.txt', 'cloud_bin_4.ply',
                                'cloud_bin_0.ply')
        return read_cloud(src), read_cloud(tgt), T
    folder = data / 'lidar' / 'small_gicp'
    return (read_cloud(folder / 'source.ply'), read_cloud(folder / 'target.ply'),
            np.loadtxt(folder / 'T_target_source.txt'))


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Return a uniformly random 3x3 rotation (any angle)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _memory_kb(field: str) -> int:
    for line in Path('/proc/self/status').read_text().splitlines():
        if line.startswith(field + ':'):
            return int(line.split()[1])
    return -1


def _run_method(method: str, src: np.ndarray, tgt: np.ndarray, voxel: float,
                sets: tuple[str, ...] = ()) -> dict:
    """Register once; return the transform, validity, points and per-stage timings."""
    from cgags_ros.pipeline import clear_feature_cache, register_clouds

    if method == 'cgags':
        clear_feature_cache()
        config = update_from_flat(PipelineConfig(), parse_key_values(sets))
        r = register_clouds(src, tgt, voxel_size=voxel, config=config)
        return {'T': r.transform, 'valid': bool(r.valid), 'reason': r.reason,
                'points': [r.num_source_points, r.num_target_points],
                'stages': {k: float(t) for k, t in r.timings.items()}}
    if method == 'kiss_matcher':
        out = kiss_matcher_estimate(src, tgt, voxel)
        return {'T': out.transform, 'valid': out.valid, 'reason': ''}
    return {'T': open3d_fpfh_ransac(src, tgt, voxel), 'valid': True, 'reason': ''}


def worker(dataset: str, voxel: float, method: str, trials: int, seed: int,
           sets: tuple[str, ...] = ()) -> dict:
    """Run ``trials`` rotated pairs of one size and method in this process; return a record."""
    from cgags_ros.frontend.features import downsample

    src, tgt, T_gt = load_dataset(dataset)
    points = [len(downsample(src, voxel, 3)), len(downsample(tgt, voxel, 3))]
    # Warm-up at a 4x coarser voxel: imports and one-time initialisation are not timed.
    _run_method(method, src, tgt, 4.0 * voxel, sets)
    rss_before = _memory_kb('VmRSS')
    rng = np.random.default_rng([seed, int(round(voxel * 1e4))])
    rows = []
    for trial in range(trials):
        R = random_rotation(rng)
        H = np.eye(4)
        H[:3, :3] = R
        gt = T_gt @ np.linalg.inv(H)  # ground truth of the rotated source
        t0 = time.perf_counter()
        out = _run_method(method, src @ R.T, tgt, voxel, sets)
        dt = time.perf_counter() - t0
        re, te = rotation_error_deg(out['T'], gt), translation_error(out['T'], gt)
        lim = LIMITS[dataset]
        rows.append({'trial': trial, 'time_s': dt, 're_deg': re, 'te_m': te,
                     'success': bool(re <= lim[0] and te <= lim[1]), 'valid': out['valid'],
                     'reason': out['reason'], 'points': out.get('points', points),
                     'stages': out.get('stages', {})})
    return {'dataset': dataset, 'voxel': voxel, 'method': method, 'points': points,
            'rss_before_kb': rss_before, 'peak_rss_kb': _memory_kb('VmHWM'), 'trials': rows}


def run_subprocess(dataset: str, voxel: float, method: str, trials: int, seed: int,
                   timeout: float, sets: tuple[str, ...] = ()) -> dict:
    cmd = [sys.executable, '-m', __spec__.name, '--worker', f'{dataset}:{voxel}',
           '--methods', method, '--trials', str(trials), '--seed', str(seed)]
    for item in sets:
        cmd += ['--set', item]
    try:
        done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {'dataset': dataset, 'voxel': voxel, 'method': method,
                'error': f'timeout after {timeout:g} s', 'trials': []}
    # KISS-Matcher's warnings end without a newline: find the record anywhere in a line.
    lines = [x.split(_MARK, 1)[1] for x in done.stdout.splitlines() if _MARK in x]
    if done.returncode != 0 or not lines:
        return {'dataset': dataset, 'voxel': voxel, 'method': method, 'trials': [],
                'error': ' '.join(done.stderr.strip().splitlines()[-1:]) or 'no result'}
    return json.loads(lines[-1])


def summarize(rec: dict) -> dict:
    t = rec['trials']
    if not t:
        return {'error': rec.get('error', 'no trials')}
    ok = [r for r in t if r['success']]
    stages = {}
    for s in STAGES:
        vals = [r['stages'].get(s) for r in t if s in r['stages']]
        if vals:
            stages[s] = float(np.median(vals))
    floors = [_floor(r) for r in t if 'registration' in r['stages']]
    return {'points': float(np.mean([np.mean(r['points']) for r in t])),
            'median_time_s': float(np.median([r['time_s'] for r in t])),
            'successes': len(ok), 'trials': len(t),
            'median_re_deg': float(np.median([r['re_deg'] for r in t])),
            'median_te_m': float(np.median([r['te_m'] for r in t])),
            'peak_mb': rec['peak_rss_kb'] / 1024, 'rss_before_mb': rec['rss_before_kb'] / 1024,
            'stages': stages,
            'median_floor_s': float(np.median(floors)) if floors else None}


def _floor(trial: dict) -> float:
    """
    Return a pair's wall seconds less the core and the gates beside the candidate search.

    What is left is downsampling, normals, FPFH, mutual matching, refinement and the glue
    between stages (with default parameters, the stages whose results are kept exact): a
    floor that no change to the core, the gates or the candidate search can go below
    (docs/design.md, "What bounds the speed").
    """
    st = trial['stages']
    beside = max(st.get('validation', 0.0), st.get('candidates', 0.0))
    return trial['time_s'] - st['registration'] - beside


def _floor_rows(records: list[dict]) -> list[tuple]:
    """Rows (size, ours, floor, KISS-Matcher, floor / KISS-Matcher) where both ran."""
    rows = []
    for rec in records:
        if rec['method'] != 'cgags':
            continue
        ours = summarize(rec)
        kiss = [summarize(r) for r in records if r['method'] == 'kiss_matcher'
                and (r['dataset'], r['voxel']) == (rec['dataset'], rec['voxel'])]
        if not kiss or 'error' in kiss[0] or ours.get('median_floor_s') is None:
            continue
        floor, theirs = ours['median_floor_s'], kiss[0]['median_time_s']
        rows.append((f"{rec['dataset']} {rec['voxel']:g}", ours['median_time_s'], floor, theirs,
                     round(floor / theirs, 2)))
    return rows


def write_report(records: list[dict], markdown: Path | None, plot: Path | None,
                 trials: int, sets: tuple[str, ...] = ()) -> str:
    rows, stage_rows = [], []
    for rec in records:
        s = summarize(rec)
        size = f"{rec['dataset']} {rec['voxel']:g}"
        if 'error' in s:
            rows.append((size, rec['method'], '', '', '', '', '', '', s['error'][:60]))
            continue
        rows.append((size, rec['method'], round(s['points']), s['median_time_s'],
                     f"{s['successes']}/{s['trials']}", s['median_re_deg'], s['median_te_m'],
                     f"{s['peak_mb']:.0f} ({s['peak_mb'] - s['rss_before_mb']:.0f})", ''))
        if s['stages']:
            stage_rows.append((size, round(s['points']),
                               *(s['stages'].get(k) for k in STAGES)))
    table = markdown_table(('size (voxel m)', 'method', 'points a cloud', 'median time [s]',
                            'success', 'median RE [deg]', 'median TE [m]',
                            'peak RSS MB (above start)', 'error'), rows)
    stage_table = markdown_table(('size', 'points', *(f'{k} [s]' for k in STAGES)),
                                 stage_rows)
    text = (f'# Scaling benchmark (python -m bench.scaling)\n\n{trials} random rotation(s) a '
            f'size; {platform.platform()}, Python {platform.python_version()}.\n'
            'Points: mean of source and target after our voxel downsampling. Peak RSS: '
            'VmHWM of one subprocess per row (in brackets: above its RSS after imports, '
            'loading the clouds and a warm-up at 4x the voxel). Success: RE/TE within '
            '15 deg / 0.3 m (redkitchen), 5 deg / 0.6 m (LiDAR). cgags: '
            + (f"--set {' '.join(sets)}" if sets else 'default parameters') + '.\n\n' + table +
            '\n\n## cgags stages (median seconds, both clouds)\n\n' + stage_table + '\n')
    floors = _floor_rows(records)
    if floors:
        text += ('\n## Floor against KISS-Matcher\n\nFloor: our time a pair less the core '
                 'and the gates beside the candidate search (median over the trials): '
                 'downsampling, normals, FPFH, mutual matching, refinement and the glue '
                 'between them (with default parameters, the stages whose results are kept '
                 'exact).\n\n' + markdown_table(
                     ('size', 'ours [s]', 'floor [s]', 'KISS-Matcher [s]', 'floor / KISS'),
                     floors) + '\n')
    if markdown:
        write_text(markdown, text)
    if plot:
        _plot(records, plot)
    return text


def _plot(records: list[dict], path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    colours = dict(zip(METHODS, ('C0', 'C1', 'C2')))
    for dataset, style in zip(DATASETS, ('-o', '--s')):
        for method in METHODS:
            pts = sorted((summarize(r)['points'], summarize(r)['median_time_s'])
                         for r in records if r['dataset'] == dataset and r['method'] == method
                         and r['trials'])
            if pts:
                ax.plot(*zip(*pts), style, color=colours[method], label=f'{method} ({dataset})')
    ax.set_xscale('log')
    ax.set_yscale('log')
    ax.set_xlabel('points a cloud after downsampling')
    ax.set_ylabel('median time a pair [s]')
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)


def main(argv: list[str] | None = None) -> int:
    p = argument_parser(__spec__.name, __doc__)
    p.add_argument('--sizes', nargs='+', default=None,
                   help='DATASET:VOXEL (e.g. lidar:0.3) or DATASET; default: all')
    p.add_argument('--methods', nargs='+', choices=METHODS, default=list(METHODS))
    p.add_argument('--trials', type=int, default=3)
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--timeout', type=float, default=900.0, help='seconds per size and method')
    add_set_option(p)
    p.add_argument('--output', type=Path, default=output_path('scaling.json'),
                   help='JSON records (default: %(default)s)')
    p.add_argument('--markdown', type=Path, default=output_path('scaling.md'),
                   help='the tables (default: %(default)s)')
    p.add_argument('--plot', type=Path, default=output_path('scaling.png'),
                   help='time against points (default: %(default)s)')
    p.add_argument('--worker', default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        dataset, voxel = args.worker.split(':')
        record = worker(dataset, float(voxel), args.methods[0], args.trials, args.seed,
                        tuple(args.set))
        print(_MARK + json.dumps(record))  # libraries may print to stdout too
        return 0
    parse_overrides(args.set)
    sizes = []
    for spec in args.sizes or list(DATASETS):
        name, _, voxel = spec.partition(':')
        sizes += [(name, float(voxel))] if voxel else [(name, v) for v in DATASETS[name]]
    records = []
    for dataset, voxel in sizes:
        for method in args.methods:
            rec = run_subprocess(dataset, voxel, method, args.trials, args.seed, args.timeout,
                                 tuple(args.set))
            records.append(rec)
            s = summarize(rec)
            print(f'{dataset} {voxel:g} {method}: ' + (
                s['error'] if 'error' in s else
                f"{s['points']:.0f} pts, {cell(s['median_time_s'])} s, "
                f"{s['successes']}/{s['trials']} ok, peak {s['peak_mb']:.0f} MB"), flush=True)
    write_json(args.output, {'machine': platform.platform(), 'trials': args.trials,
                             'set': args.set, 'records': records})
    print(write_report(records, args.markdown, args.plot, args.trials, tuple(args.set)))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
