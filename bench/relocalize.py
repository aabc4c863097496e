"""
Relocalization benchmark: map load (cold vs cached) and time per relocalization.

The map is the redkitchen fragments 0 and 4 merged at full resolution (571k points, ground
truth from gt_pairs.txt); its size grows as the voxel size shrinks. Scans: fragment 6 and
fragment 4 under random any-angle motions. Ours: ``load_map`` (cold: features computed and
cached; cached: read back) then ``register_clouds`` onto the prepared map; baseline:
``kiss_matcher.KISSMatcher(KISSMatcherConfig(v)).estimate(scan, map)`` on the same pairs
(its own voxelization and features every call: it has no prepared-map path). Success: RE
<= 15 deg and TE <= 0.3 m. Prints a Markdown table and writes ``<output>/bench_relocalize.png``
(``--output`` default ``out/bench/relocalize``).

Usage: ``OMP_NUM_THREADS=1 python -m bench.relocalize [--voxels 0.08 0.05 0.035]
[--trials 3] [--output out/bench/relocalize]``.

``--scene-maps ROOT`` (a 3DMatch benchmark folder, :mod:`bench.datasets.threedmatch`)
runs the indoor-map study instead: for every scene and every fragment k (``--fragments K``
samples K a scene, seeded), the prior map is the scene fused from all its other fragments
with their poses (k left out), written to a PLY map file and prepared by ``load_map`` as the
node does; fragment k, in its own frame (its sensor frame), is relocalized in it by
``register_clouds`` onto the prepared map (the node's path), beside KISS-Matcher's
``estimate`` on the same scan and raw map. The map file carries each fragment's normals
facing that fragment's sensor (as a mapper writes them) and the defaults apply
(``normal_orientation`` 'origin'); ``--no-map-normals`` writes x, y, z only and runs with
'centroid' orientation instead. The map is turned by a random rotation and
shifted (seeded) per query, so the start is any-angle. Ground truth: ``T = A P_k``
(``P_k`` the fragment pose, ``A`` the map's turn). Overlap of k with the rest of the map:
share of its points with a map point within 3.75 cm (1.5x the fragments' 2.5-cm voxel).
Success: RE <= 15 deg and TE <= 0.3 m and flagged valid (ours); KISS-Matcher has no flag,
every estimate counts. Writes ``<output>/bench_relocalize_3dmatch.{md,json}``.
"""

from __future__ import annotations

import json
from pathlib import Path
import tempfile
import time

from bench.baselines import kiss_matcher_estimate
from bench.common import (argument_parser, markdown_table, output_path, pyplot, save_figure,
                          write_text)
from bench.datasets import threedmatch as tdm
from bench.datasets.gt_pairs import find_pair
from cgags_ros.config import pipeline_config_from
from cgags_ros.frontend.features import estimate_normals
from cgags_ros.geometry import apply_transform, make_transform, rotation_error_deg
from cgags_ros.geometry import translation_error
from cgags_ros.io.clouds import read_cloud, write_cloud
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import register_clouds
from cgags_ros.pipeline.map import load_map
import numpy as np
from scipy.spatial.transform import Rotation


def _kiss(scan: np.ndarray, target: np.ndarray, voxel: float) -> np.ndarray:
    return kiss_matcher_estimate(scan, target, voxel).transform


def main(argv: list[str] | None = None) -> None:
    """Run the benchmark and print the table."""
    ap = argument_parser(__spec__.name, __doc__)
    ap.add_argument('--voxels', type=float, nargs='+', default=[0.08, 0.05, 0.035])
    ap.add_argument('--trials', type=int, default=3)
    ap.add_argument('--output', type=Path, default=output_path('relocalize'),
                    help='folder of the results (default: %(default)s)')
    ap.add_argument('--scene-maps', type=Path, default=None,
                    help='3DMatch benchmark root: run the leave-one-out indoor-map study')
    ap.add_argument('--voxel', type=float, default=0.05, help='with --scene-maps: voxel, m')
    ap.add_argument('--fragments', type=int, default=0,
                    help='with --scene-maps: fragments a scene (0: all)')
    ap.add_argument('--no-kiss', action='store_true', help='with --scene-maps: ours only')
    ap.add_argument('--no-map-normals', action='store_true',
                    help="with --scene-maps: a map file without normals, 'centroid' normals")
    args = ap.parse_args(argv)
    if args.scene_maps is not None:
        scene_maps(args.scene_maps, args.voxel, args.fragments, not args.no_kiss,
                   not args.no_map_normals, args.output)
        return
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


MIN_OVERLAP = 0.3  # the study's target counts fragments at least this much inside the map
OVERLAP_RADIUS = 0.0375


def scene_maps(root: Path, voxel: float, per_scene: int, with_kiss: bool, map_normals: bool,
               output: Path) -> None:
    """Relocalize every fragment of every scene in the map of the others (module doc)."""
    rng = np.random.default_rng(0)
    cfg = pipeline_config_from({'voxel_size': voxel} if map_normals else
                               {'voxel_size': voxel, 'frontend.normal_orientation': 'centroid'})
    records = []
    for scene in tdm.scenes(root):
        poses, fragments = tdm.fragment_poses(root, scene), tdm.Fragments(root, scene)
        # Each fragment's normals facing its own sensor (the origin of its frame).
        sides = {k: estimate_normals(fragments[k], voxel, cfg.frontend) for k in poses} \
            if map_normals else None
        ids = list(poses)
        if per_scene:
            ids = sorted(rng.choice(ids, min(per_scene, len(ids)), replace=False).tolist())
        for k in ids:
            records.append(_relocalize_fragment(scene, k, fragments, poses, sides, cfg, rng,
                                                with_kiss))
            r = records[-1]
            print(f"{scene[:24]:24s} {k:3d} overlap {r['overlap']:.2f} ours "
                  f"{r['ours']['outcome']:>10s} {r['ours']['re_deg']:6.2f} deg "
                  f"{r['ours']['s']:.2f} s" + (f" kiss {r['kiss']['outcome']:>6s} "
                                               f"{r['kiss']['s']:.2f} s" if with_kiss else ''),
                  flush=True)
    text = _scene_map_report(records, voxel, with_kiss, map_normals)
    print(text)
    name = 'bench_relocalize_3dmatch' + ('' if map_normals else '_centroid')
    write_text(output / f'{name}.md', text + '\n')
    write_text(output / f'{name}.json', json.dumps(
        {'voxel': voxel, 'map_normals': map_normals, 'records': records}, indent=1) + '\n')


def _relocalize_fragment(scene: str, k: int, fragments, poses, sides, cfg, rng,
                         with_kiss: bool) -> dict:
    from scipy.spatial import cKDTree

    world = tdm.scene_map(fragments, poses, left_out=k)
    d, _ = cKDTree(world).query(apply_transform(poses[k], fragments[k]),
                                distance_upper_bound=OVERLAP_RADIUS)
    overlap = float(np.mean(np.isfinite(d)))
    A = make_transform(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-3, 3, 3))
    world = apply_transform(A, world)
    T_gt = A @ poses[k]
    scan = fragments[k]
    out = {'scene': scene, 'fragment': k, 'overlap': overlap}
    normals = None if sides is None else np.vstack(
        [sides[m] @ (A @ P)[:3, :3].T for m, P in poses.items() if m != k])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / 'map.ply'
        write_cloud(path, world, normals)
        prepared = load_map(path, cfg)
    out['map_points'], out['map_load_s'] = len(prepared.features.points), prepared.load_s
    t0 = time.perf_counter()
    result = register_clouds(scan, prepared, config=cfg)
    out['ours'] = _outcome(result.transform, T_gt, time.perf_counter() - t0, result.valid)
    out['ours'].update(ambiguous=bool(result.ambiguous), reason=result.reason,
                       inliers=int(result.num_inliers), fitness=float(result.fitness),
                       overlap=float(result.overlap),
                       runner_up_ratio=float(min(result.runner_up_ratio, 1e9)))
    if with_kiss:
        t0 = time.perf_counter()
        T = _kiss(scan, world, cfg.voxel_size)
        out['kiss'] = _outcome(T, T_gt, time.perf_counter() - t0, True)
    return out


def _outcome(T: np.ndarray, T_gt: np.ndarray, seconds: float, valid: bool) -> dict:
    re, te = rotation_error_deg(T, T_gt), translation_error(T, T_gt)
    right = re <= 15.0 and te <= 0.3
    outcome = ('right' if right else 'WRONG') if valid else \
        ('refused' if right else 'invalid')
    return {'re_deg': float(re), 'te_m': float(te), 'valid': bool(valid), 'right': bool(right),
            'outcome': outcome, 's': float(seconds)}


def _scene_map_report(records: list[dict], voxel: float, with_kiss: bool,
                      map_normals: bool) -> str:
    def row(name: str, rs: list[dict]) -> list:
        eligible = [r for r in rs if r['overlap'] >= MIN_OVERLAP]
        cells = [name, len(rs), len(eligible)]
        for method in ('ours',) + (('kiss',) if with_kiss else ()):
            m = [r[method] for r in eligible]
            ok = sum(x['right'] and x['valid'] for x in m)
            cells.append(f'{ok}/{len(m)} ({100 * ok / max(len(m), 1):.1f} %)')
            if method == 'ours':
                cells += [sum(x['valid'] and not x['right'] for x in m),
                          sum(r['ours']['ambiguous'] for r in eligible),
                          sum(not x['valid'] for x in m)]
            cells.append(f"{np.median([x['s'] for x in m]):.2f}" if m else '-')
        return cells

    headers = ['scene', 'fragments', f'overlap >= {MIN_OVERLAP:g}', 'ours: right & valid',
               'ours: valid but wrong', 'ours: ambiguous', 'ours: invalid', 'ours: median s']
    if with_kiss:
        headers += ['KISS-Matcher: right', 'KISS-Matcher: median s']
    scenes = sorted({r['scene'] for r in records})
    rows = [row(s, [r for r in records if r['scene'] == s]) for s in scenes]
    rows.append(row('all', records))
    loads = [r['map_load_s'] for r in records]
    normals = ("map file with sensor-facing normals, normal_orientation 'origin'"
               if map_normals else "map file without normals, normal_orientation 'centroid'")
    return (f'Relocalization in leave-one-out scene maps ({normals}; voxel {voxel:g} m, '
            f'map points '
            f"{int(np.median([r['map_points'] for r in records]))} median, map load "
            f'{np.median(loads):.2f} s median, not counted in the per-query time)\n\n'
            + markdown_table(headers, rows))


def _plot(rows, path: Path) -> None:
    plt = pyplot()

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
    save_figure(fig, path)


if __name__ == '__main__':
    main()
