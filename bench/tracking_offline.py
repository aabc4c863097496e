r"""
What the temporal prior allows on a stream, offline: per-stage times, share tracked, accuracy.

Run from the repository root::

    python -m bench.tracking_offline [--voxels 0.3 0.5 1.0] [--scans 64] \
        [--global-scans 8] [--set KEY=VALUE] [--output out/bench/tracking_offline.json]

The 16 real KITTI scans (``<shared data>/kitti/seq00_16scans``) go scan-to-map against scan
0 as the map through :class:`cgags_ros.tracking.Tracker` (default configuration, stamps
10 Hz apart), numpy in (decoding excluded), in two orders: ``pingpong`` (0..15, 14..0, 1..:
smooth motion, the velocity reverses at the ends) and ``looped`` (0..15, 0..15, ...: a 12 m
jump every 16 scans). Per voxel size and order: the share of scans tracked, the tracker's
counts, per-stage seconds of each path (tracked: the target's key, downsampling,
refinement, gates; global: downsampling, normals, FPFH, matching, core, refinement, gates,
candidates), compute per scan (p50/p95/max), and the accuracy of every valid pose against
``pseudo_gt.txt`` (within 1 deg / 0.2 m, beyond 5 deg / 0.6 m, worst). ``--global-scans``
scans per voxel size also run with tracking off, for the global path's stages side by side.

Reuse across scans, per voxel size: what building the map's k-d tree costs (Open3D's ICP
builds one over the target on every call; a tree kept with the map would save it), the
source normals the tracked path skips (point-to-plane needs the map's normals only), and
hashing the target (how the tracker tells a new map). The machine may be loaded by other
work: compare ratios and shares within one run, not absolute times across runs.
"""

from __future__ import annotations

import json
from pathlib import Path
import time

from bench.common import (add_set_option, argument_parser, machine, output_path,
                          parse_overrides, write_json)
from bench.datasets.rigs import KITTI_SCANS, kitti_scans
from cgags_ros.config.pipeline import pipeline_config_from, PipelineConfig
from cgags_ros.config.tracking import TrackingConfig
from cgags_ros.frontend.features import downsample, estimate_normals, MIN_POINTS
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import cached_features, register_clouds, warm_up
from cgags_ros.tracking import Tracker
from cgags_ros.tracking.tracker import target_key
import numpy as np
import open3d as o3d

PERIOD = 0.1  # seconds between scans: a 10 Hz LiDAR
TRACKED_STAGES = ('target_key', 'downsample', 'refinement', 'validation')
GLOBAL_STAGES = ('downsample', 'normals', 'fpfh', 'matching', 'registration', 'refinement',
                 'validation', 'candidates', 'candidates_settled')


def orders(count: int) -> dict[str, list[int]]:
    """Return the scan indices of each order, ``count`` scans long."""
    pingpong = list(range(16)) + list(range(14, 0, -1))
    return {'pingpong': [pingpong[i % len(pingpong)] for i in range(count)],
            'looped': [i % 16 for i in range(count)]}


def errors(transform: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Return the rotation (degrees) and translation (metres) error against ``truth``."""
    return rotation_error_deg(transform, truth), translation_error(transform, truth)


def run_stream(scans: list[np.ndarray], truth: np.ndarray, indices: list[int],
               config: PipelineConfig) -> dict:
    """Register ``indices`` in order through one Tracker; return the per-scan records."""
    tracker = Tracker()
    records = []
    for i, k in enumerate(indices):
        start = time.perf_counter()
        key_start = time.perf_counter()
        target_key(scans[0])  # what the tracker pays to recognise the map: timed alone
        key_seconds = time.perf_counter() - key_start
        result = tracker.register(scans[k], scans[0], i * PERIOD, config=config)
        seconds = time.perf_counter() - start - key_seconds
        re, te = errors(result.transform, truth[k])
        timings = dict(result.timings, target_key=key_seconds)
        records.append({'scan': k, 'path': result.path, 'valid': bool(result.valid),
                        'seconds': seconds, 're_deg': re, 'te_m': te,
                        'fitness': float(result.fitness), 'timings': timings,
                        'failure': result.stats.get('tracking_failure', '')})
    return {'records': records, 'counts': tracker.counts()}


def summarise(records: list[dict]) -> dict:
    """Return the share tracked, compute percentiles, stage times and accuracy of a stream."""
    out = {'scans': len(records)}
    for path, stages in (('tracked', TRACKED_STAGES), ('global', GLOBAL_STAGES)):
        mine = [r for r in records if r['path'] == path]
        out[f'{path}_scans'] = len(mine)
        if mine:
            out[f'{path}_stage_ms'] = {
                s: 1e3 * float(np.median([r['timings'].get(s, 0.0) for r in mine]))
                for s in stages}
            seconds = [r['seconds'] for r in mine]
            out[f'{path}_ms_p50'] = 1e3 * float(np.percentile(seconds, 50))
            out[f'{path}_ms_p95'] = 1e3 * float(np.percentile(seconds, 95))
    seconds = np.array([r['seconds'] for r in records])
    out.update(ms_p50=1e3 * float(np.percentile(seconds, 50)),
               ms_p95=1e3 * float(np.percentile(seconds, 95)),
               ms_max=1e3 * float(seconds.max()))
    valid = [r for r in records if r['valid']]
    out.update(
        valid=len(valid), share_tracked=out['tracked_scans'] / len(records),
        within_1deg_20cm=sum(r['re_deg'] <= 1.0 and r['te_m'] <= 0.2 for r in valid),
        beyond_5deg_60cm=sum(r['re_deg'] > 5.0 or r['te_m'] > 0.6 for r in valid),
        worst_re_deg=max((r['re_deg'] for r in valid), default=float('nan')),
        worst_te_m=max((r['te_m'] for r in valid), default=float('nan')))
    return out


def reuse_study(scans: list[np.ndarray], voxel: float, repeats: int = 5) -> dict:
    """Return the median ms of what reusing across scans could save, at ``voxel``."""
    config = PipelineConfig(voxel_size=voxel)
    features = cached_features(scans[0], voxel, config.frontend)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(features.points))
    times: dict[str, list[float]] = {'map_kdtree_build': [], 'source_normals': [],
                                     'target_key': []}
    for k in range(1, repeats + 1):
        points = downsample(scans[k], voxel, MIN_POINTS)
        start = time.perf_counter()
        o3d.geometry.KDTreeFlann(cloud)
        times['map_kdtree_build'].append(time.perf_counter() - start)
        start = time.perf_counter()
        estimate_normals(points, voxel, config.frontend)
        times['source_normals'].append(time.perf_counter() - start)
        start = time.perf_counter()
        target_key(scans[0])
        times['target_key'].append(time.perf_counter() - start)
    return {name: 1e3 * float(np.median(t)) for name, t in times.items()}


def global_only(scans: list[np.ndarray], truth: np.ndarray, voxel: float,
                count: int) -> dict:
    """Return the global path's stage medians over ``count`` scans with tracking off."""
    config = PipelineConfig(voxel_size=voxel, tracking=TrackingConfig(enabled=False))
    records = run_stream(scans, truth, [1 + i % 15 for i in range(count)], config)['records']
    return summarise(records)


def table(results: dict) -> str:
    """Return a markdown table of the streams."""
    lines = ['| voxel m | order | tracked | valid | within 1 deg / 0.2 m | beyond 5 deg / 0.6 m '
             '| ms p50 / p95 | tracked ms p50 / p95 | tracked ms: key / down / refine / gates '
             '| global ms p50 |',
             '|---|---|---|---|---|---|---|---|---|---|']
    for voxel, by_order in results['streams'].items():
        for order, s in by_order.items():
            st = s.get('tracked_stage_ms', {})
            nan = float('nan')
            stages = ' / '.join(f'{st.get(k, nan):.0f}' for k in TRACKED_STAGES)
            lines.append(
                f"| {voxel} | {order} | {s['tracked_scans']}/{s['scans']} | {s['valid']} | "
                f"{s['within_1deg_20cm']} | {s['beyond_5deg_60cm']} | "
                f"{s['ms_p50']:.0f} / {s['ms_p95']:.0f} | "
                f"{s.get('tracked_ms_p50', nan):.0f} / {s.get('tracked_ms_p95', nan):.0f} | "
                f"{stages} | {s.get('global_ms_p50', nan):.0f} |")
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the study; write JSON to ``--output``; print the table."""
    p = argument_parser(__spec__.name, __doc__)
    p.add_argument('--voxels', type=float, nargs='+', default=[0.3, 0.5, 1.0])
    p.add_argument('--scans', type=int, default=64, help='scans per stream (6.4 s at 10 Hz)')
    p.add_argument('--global-scans', type=int, default=8,
                   help='scans per voxel size with tracking off (0: none)')
    add_set_option(p)
    p.add_argument('--output', type=Path, default=output_path('tracking_offline.json'))
    args = p.parse_args(argv)
    overrides = parse_overrides(args.set)
    data = shared_data_dir()
    scans = kitti_scans(data, list(range(16)))
    truth = np.loadtxt((data / KITTI_SCANS).parent / 'pseudo_gt.txt').reshape(-1, 4, 4)
    warm_up()
    register_clouds(scans[1], scans[0], voxel_size=1.0)  # compile and load once, untimed
    load = [float(x) for x in Path('/proc/loadavg').read_text().split()[:3]]
    results: dict = {'streams': {}, 'global_only': {}, 'reuse_ms': {}, 'settings': overrides,
                     'machine_load': load, 'machine': machine()}
    for voxel in args.voxels:
        config = pipeline_config_from({**overrides, 'voxel_size': voxel})
        results['streams'][voxel] = {}
        for order, indices in orders(args.scans).items():
            stream = run_stream(scans, truth, indices, config)
            summary = summarise(stream['records'])
            summary['counts'] = stream['counts']
            summary['failures'] = sorted({r['failure'][:60] for r in stream['records']
                                          if r['failure']})
            results['streams'][voxel][order] = summary
            print(voxel, order, json.dumps({k: v for k, v in summary.items()
                                            if not isinstance(v, dict)}), flush=True)
        if args.global_scans:
            results['global_only'][voxel] = global_only(scans, truth, voxel, args.global_scans)
        results['reuse_ms'][voxel] = reuse_study(scans, voxel)
    print(table(results))
    print(json.dumps({'global_only': results['global_only'], 'reuse_ms': results['reuse_ms']},
                     indent=1))
    print(f'wrote {write_json(args.output, results)}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
