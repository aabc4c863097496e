r"""
Extrinsic calibration benchmark: ours with 1, 2 and 3 frames against single-frame peers.

Run by hand (under the bench lock)::

    flock /tmp/cgags-bench.lock .venv/bin/python -m bench.calibration \
        [--rigs carla_data/left real_world/right kitti_lidar] [--output out/bench/calibration.json]

Rigs: the OpenCalib lidar2lidar samples (simulated: front, back, left, right against the
top LiDAR; real: left, right), reference = CROON's extrinsic averaged over the three
frames, tolerance = its spread (simulated 0.2 deg / 3 cm, real 0.5 deg / 5 cm); and two
rigs built from KITTI scans with a known extrinsic (``bench.datasets.rigs``:
a second LiDAR, a depth camera against a sparse LiDAR; 0.5 deg / 5 cm).

Methods, per rig:

``ours_k`` (k = 1, 2, 3)
    :func:`cgags_ros.calibration.calibrator.solve` over every subset of k of the three
    frames (3, 3 and 1 runs); success = valid and within tolerance. Time = the frames'
    pipeline runs plus the solve.
``pipeline``
    :func:`cgags_ros.pipeline.register_clouds` on each frame alone (3 runs); success =
    valid and within tolerance.
``kiss_matcher``, ``open3d_fpfh_ransac``
    Each frame alone, as ``python -m bench.pipeline`` runs them (same voxel); they report
    no validity we gate on, so success = within tolerance.

Covariance against the observed spread: for each valid ours_1 and ours_2 run, the error
against the reference per axis (the covariance's convention: x, y, z of the child origin,
rotation about the parent axes) divided by the reported standard deviation; the table
gives the share of |error| / sigma within 1 and 2 (a calibrated Gaussian: 68 % / 95 %).
"""

from __future__ import annotations

import itertools
from pathlib import Path
import platform
import sys
import time

from bench.baselines import kiss_matcher_estimate, open3d_fpfh_ransac
from bench.common import argument_parser, cell, markdown_table, output_path, write_json
from bench.datasets.rigs import (kitti_depth_rig, kitti_lidar_rig, opencalib_rig,
                                 OPENCALIB_RIGS)
from cgags_ros.calibration import Frame, joint
from cgags_ros.calibration.calibrator import solve
from cgags_ros.calibration.frames import gather
from cgags_ros.config import PipelineConfig
from cgags_ros.config.calibration import CalibrationConfig
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import clear_feature_cache, register_clouds
import numpy as np

VOXEL = {'kitti_depth': 0.2}  # others 0.3 m
TOLERANCE = {'carla_data': (0.2, 0.03)}  # others (0.5, 0.05)
RIGS = ([f'{rig}/{s}' for rig, sensors in OPENCALIB_RIGS.items() for s in sensors]
        + ['kitti_lidar', 'kitti_depth'])


def load_rig(name: str, data_dir: Path) -> tuple[list[Frame], np.ndarray]:
    if name == 'kitti_lidar':
        rig, truth = kitti_lidar_rig(data_dir)
    elif name == 'kitti_depth':
        rig, truth = kitti_depth_rig(data_dir)
    else:
        rig, truth, _ = opencalib_rig(data_dir, *name.split('/'))
    return [Frame(f.parent, f.child, f.name, f.parent_stamp_ns, f.child_stamp_ns)
            for f in rig], truth


def _errors(T: np.ndarray | None, truth: np.ndarray) -> tuple[float, float]:
    if T is None:
        return float('nan'), float('nan')
    return rotation_error_deg(T, truth), translation_error(T, truth)


def bench_rig(name: str, data_dir: Path) -> dict:
    frames, truth = load_rig(name, data_dir)
    voxel = VOXEL.get(name, 0.3)
    tol = TOLERANCE.get(name.split('/')[0], (0.5, 0.05))
    cfg = CalibrationConfig(pipeline=PipelineConfig(voxel_size=voxel))
    runs: list[dict] = []

    def record(method, T, valid, seconds, frames_used, sigma=None):
        re, te = _errors(T, truth)
        runs.append({'method': method, 'frames': frames_used, 'valid': bool(valid),
                     're_deg': re, 'te_m': te, 'time_s': seconds,
                     'success': bool(valid and re <= tol[0] and te <= tol[1]),
                     'z': None if sigma is None or T is None else
                     (np.abs(joint.difference(T, truth)) / sigma).tolist()})

    evidence, gather_s = [], []
    for f in frames:
        clear_feature_cache()
        t0 = time.perf_counter()
        evidence.append(gather(f, cfg.pipeline))
        gather_s.append(time.perf_counter() - t0)
        e = evidence[-1]
        record('pipeline', e.result.transform if e.result.candidates else None,
               e.result.valid, e.result.timings.get('total', float('nan')), [f.name])
    for k in (1, 2, 3):
        for subset in itertools.combinations(range(len(frames)), k):
            t0 = time.perf_counter()
            result = solve([evidence[i] for i in subset], cfg)
            seconds = time.perf_counter() - t0 + sum(gather_s[i] for i in subset)
            sigma = (np.sqrt(np.diag(result.covariance))
                     if result.covariance is not None else None)
            record(f'ours_{k}', result.transform, result.valid, seconds,
                   [frames[i].name for i in subset], sigma)
            runs[-1]['reason'] = result.reason
    for f in frames:
        t0 = time.perf_counter()
        kiss = kiss_matcher_estimate(f.child, f.parent, voxel)
        record('kiss_matcher', kiss.transform, True, time.perf_counter() - t0, [f.name])
        runs[-1]['own_valid'] = kiss.valid
        t0 = time.perf_counter()
        T = open3d_fpfh_ransac(f.child, f.parent, voxel)
        record('open3d_fpfh_ransac', T, True, time.perf_counter() - t0, [f.name])
    return {'rig': name, 'voxel_size': voxel, 'tolerance': tol, 'runs': runs}


METHODS = ('ours_1', 'ours_2', 'ours_3', 'pipeline', 'kiss_matcher', 'open3d_fpfh_ransac')


def tables(results: list[dict]) -> str:
    rows = []
    for r in results:
        for m in METHODS:
            runs = [x for x in r['runs'] if x['method'] == m]
            ok = [x for x in runs if x['success']]
            valid = [x for x in runs if x['valid']]
            res = [x['re_deg'] for x in valid]
            tes = [x['te_m'] for x in valid]
            rows.append([r['rig'], m, f'{len(ok)}/{len(runs)}',
                         f'{len(valid)}/{len(runs)}',
                         cell(max(res)) if res else '-',
                         cell(100 * max(tes), 3) if tes else '-',
                         cell(float(np.median([x['time_s'] for x in runs])), 3)])
    out = [markdown_table(['rig', 'method', 'within tolerance', 'valid (answered)',
                           'max RE of valid [deg]', 'max TE of valid [cm]',
                           'median time [s]'], rows)]
    cover = []
    for m in ('ours_1', 'ours_2'):
        z = np.array([v for r in results for x in r['runs'] if x['method'] == m
                      and x['valid'] and x['z'] is not None for v in x['z']])
        if len(z):
            cover.append([m, len(z) // 6, f'{100 * np.mean(z <= 1):.0f} %',
                          f'{100 * np.mean(z <= 2):.0f} %', cell(float(np.median(z)))])
    out.append(markdown_table(['runs', 'valid runs', '|err| <= 1 sigma', '|err| <= 2 sigma',
                               'median |err|/sigma'], cover))
    return '\n\n'.join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('--rigs', nargs='+', default=RIGS, choices=RIGS)
    parser.add_argument('--output', type=Path, default=output_path('calibration.json'),
                        help='JSON results path (default: %(default)s)')
    args = parser.parse_args(argv)
    data_dir = shared_data_dir()
    results = []
    register_clouds(np.random.default_rng(0).normal(size=(2000, 3)),
                    np.random.default_rng(1).normal(size=(2000, 3)), voxel_size=0.3)  # warm
    for name in args.rigs:
        t0 = time.perf_counter()
        results.append(bench_rig(name, data_dir))
        print(f'{name}: {time.perf_counter() - t0:.0f} s', file=sys.stderr, flush=True)
    text = tables(results)
    print(text)
    write_json(args.output, {'machine': platform.processor() or platform.machine(),
                             'results': results}, default=float)
    return 0


if __name__ == '__main__':
    sys.exit(main())
