"""
Relocalization benchmark: map load (cold vs cached) and time per relocalization.

The map is the redkitchen fragments 0 and 4 merged at full resolution (571k points, ground
truth from gt_pairs.txt); its size grows as the voxel size shrinks. Scans: fragment 6 and
fragment 4 under random any-angle motions. Ours: ``load_map`` (cold: features computed and
cached; cached: read back) then ``register_clouds`` onto the prepared map; baseline:
``kiss_matcher.KISSMatcher(KISSMatcherConfig(v)).estimate(scan, map)`` on the same pairs
(its own voxelization and features every call: it has no prepared-map path). Success: RE
<= 15 deg and TE <= 0.3 m. Writes a Markdown table and ``docs/bench_relocalize.png``.

Usage: ``OMP_NUM_THREADS=1 python bench/bench_relocalize.py [--voxels 0.08 0.05 0.035]
[--trials 3] [--output docs]``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
import tempfile
import time

from cgags_ros.config import pipeline_config_from
from cgags_ros.datasets.gt_pairs import find_pair
from cgags_ros.datasets.synthetic import shared_data_dir
from cgags_ros.geometry import apply_transform, make_transform, rotation_error_deg
from cgags_ros.geometry import translation_error
from cgags_ros.io.clouds import read_cloud
from cgags_ros.pipeline import register_clouds
from cgags_ros.pipeline.map import load_map
import numpy as np
from scipy.spatial.transform import Rotation


def _kiss(scan: np.ndarray, target: np.ndarray, voxel: float) -> np.ndarray:
    import kiss_matcher

    matcher = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(voxel))
    sol = matcher.estimate(scan.astype(np.float32), target.astype(np.float32))
    T = np.eye(4)
    T[:3, :3] = np.asarray(sol.rotation, dtype=np.float64).reshape(3, 3)
    T[:3, 3] = np.asarray(sol.translation, dtype=np.float64).reshape(3)
    return T


def main() -> None:
    """Run the benchmark and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--voxels', type=float, nargs='+', default=[0.08, 0.05, 0.035])
    ap.add_argument('--trials', type=int, default=3)
    ap.add_argument('--output', type=Path, default=Path('docs'))
    args = ap.parse_args()
    folder = shared_data_dir() / 'indoor_3dmatch'
    f4, f0, T40 = find_pair(folder / 'gt_pairs.txt', 'cloud_bin_4.ply', 'cloud_bin_0.ply')
    frag4 = read_cloud(f4)
    merged = np.vstack([read_cloud(f0), apply_transform(T40, frag4)])
    demo = folder / 'geotransformer_demo'
    scans = [('fragment 6', np.load(demo / 'src.npy'), np.load(demo / 'gt.npy')),
             ('fragment 4', frag4, T40)]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / 'map.npy'
        np.save(path, merged)
        for v in args.voxels:
            cfg = pipeline_config_from({'voxel_size': v,
                                        'frontend.normal_orientation': 'centroid'})
            cold = load_map(path, cfg, Path(tmp) / 'cache')
            warm = load_map(path, cfg, Path(tmp) / 'cache')
            rng = np.random.default_rng(0)
            ours, kiss = [], []
            for _, scan, gt in scans:
                for _ in range(args.trials):
                    A = make_transform(Rotation.random(random_state=rng).as_matrix(),
                                       rng.uniform(-3, 3, 3))
                    moved, T_gt = apply_transform(A, scan), gt @ np.linalg.inv(A)
                    for name, fn, out in (
                            ('ours', lambda: register_clouds(moved, warm, config=cfg).transform,
                             ours),
                            ('kiss', lambda: _kiss(moved, merged, v), kiss)):
                        t0 = time.perf_counter()
                        T = fn()
                        dt = time.perf_counter() - t0
                        ok = (rotation_error_deg(T, T_gt) <= 15.0
                              and translation_error(T, T_gt) <= 0.3)
                        out.append((dt, ok))
            rows.append((v, len(warm.features.points), cold.load_s, warm.load_s, ours, kiss))
    print('| voxel [m] | map points | load cold [s] | load cached [s] | ours: success, '
          'median s | KISS-Matcher estimate: success, median s |')
    print('|---:|---:|---:|---:|---|---|')
    for v, n, cold_s, warm_s, ours, kiss in rows:
        cell = [f'{sum(ok for _, ok in r)}/{len(r)}, {np.median([t for t, _ in r]):.2f}'
                for r in (ours, kiss)]
        print(f'| {v:g} | {n} | {cold_s:.2f} | {warm_s:.3f} | {cell[0]} | {cell[1]} |')
    _plot(rows, args.output / 'bench_relocalize.png')


def _plot(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    n = [r[1] for r in rows]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(n, [r[2] for r in rows], 'o-', label='map load, cold')
    ax.plot(n, [r[3] for r in rows], 'o-', label='map load, cached')
    ax.plot(n, [np.median([t for t, _ in r[4]]) for r in rows], 's-', label='ours, per scan')
    ax.plot(n, [np.median([t for t, _ in r[5]]) for r in rows], 's-',
            label='KISS-Matcher estimate, per scan')
    ax.set_xlabel('map points after voxel downsampling')
    ax.set_ylabel('seconds')
    ax.set_yscale('log')
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == '__main__':
    main()
