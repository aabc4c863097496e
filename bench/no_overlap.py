r"""
Clouds that share no surface: fragments of two different 3DMatch scenes, registered anyway.

Run by hand from the repository root, one run at a time::

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.no_overlap cross [--pairs 1000] [--seed 0] \
        [--root <shared data>/3dmatch_benchmark] [--set KEY=VALUE ...] \
        [--output out/no_overlap/cross.jsonl]
    OMP_NUM_THREADS=1 .venv/bin/python -m bench.no_overlap benchmark [--pairs K] \
        [--output out/no_overlap/benchmark.jsonl]
    OMP_NUM_THREADS=1 .venv/bin/python -m bench.no_overlap lidar \
        [--output out/no_overlap/lidar.jsonl]
    .venv/bin/python -m bench.no_overlap summary out/no_overlap/cross.jsonl \
        [out/no_overlap/benchmark.jsonl]
    OMP_NUM_THREADS=1 .venv/bin/python -m bench.no_overlap remeasure RECORDS.jsonl \
        --output out/no_overlap/remeasured.jsonl

``cross`` draws ``--pairs`` distinct (source, target) fragment pairs, seeded, the source
uniformly over every fragment of the scenes under ``--root`` and the target uniformly over
the fragments of the *other* scenes (different buildings: none of them can be right), and
registers each at 5 cm with the defaults (:func:`cgags_ros.pipeline.register_clouds`).
``benchmark`` registers the 3DMatch and 3DLoMatch pairs (every pair, or ``--pairs K`` a
scene and list, seeded) the same way, with the truth, for the right poses of low overlap
the same measures must keep. ``lidar`` registers four KITTI scans against the two
small_gicp scans (two streets), both ways, at 0.3 and 0.5 m. Each fragment is featurised
once (the estimates are those of a cold run, the times are not).

One JSON line a pair: the scenes and fragments, ``valid``, ``confidence``, the refusal code,
what each gate reads (inliers, chance bound, runner-up ratio, fitness, overlap,
observability, free-space violation), and what this study adds (:func:`shared_surface`):
the shared surface's points, its area and extent in each cloud, how the descriptors agree
over it (:func:`descriptor_agreement`) and the surfaces the pose puts in free space as both
sensors see it (:func:`free_space_surface`); ``remeasure`` adds the last two to older
records from their transforms, and reads the benchmark records of
:mod:`bench.studies.loso_trust` too. ``summary`` prints the
accepted share, the refusal codes and the measures' quantiles of each kind of pair.
Results go under the git-ignored ``out/``.
"""

from __future__ import annotations

import collections
import json
import math
from pathlib import Path
import time

from bench.common import add_set_option, argument_parser, parse_overrides
from bench.datasets import threedmatch as tdm
from cgags_ros.config import PipelineConfig
from cgags_ros.config.fields import update_from_flat
from cgags_ros.frontend.refine import evaluate_alignment
from cgags_ros.geometry import rotation_error_deg, spread, translation_error
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import cached_features, register_clouds, set_feature_cache_size
from cgags_ros.pipeline.free_space import free_space_surface
import numpy as np

GATE_FIELDS = ('confidence', 'num_inliers', 'num_correspondences', 'num_hypotheses',
               'chance_inliers', 'chance_bound', 'runner_up_ratio', 'fitness', 'overlap',
               'observability', 'free_space_violation', 'inlier_threshold')


def _num(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _extent(points: np.ndarray) -> list[float]:
    """Return the RMS spread (metres) of ``points`` along their principal axes, largest first."""
    if len(points) < 3:
        return [0.0, 0.0, 0.0]
    return (spread(points) / math.sqrt(len(points))).tolist()


def shared_surface(fs, ft, T: np.ndarray, cfg: PipelineConfig) -> dict:
    """
    Return what ``T`` (source -> target) makes of the surface the clouds share.

    The overlap both ways at the refinement's distance (1.5 voxels): its downsampled points
    in each cloud and their area (points times voxel squared: one point a surface cell),
    its RMS extent along its principal axes in each cloud against the cloud's own, and the
    coarse cells (4 voxels) it covers.
    """
    v = cfg.voxel_size
    distance = cfg.refine.max_correspondence_distance_factor * v
    a = evaluate_alignment(fs.points, ft.tree, T, distance)
    b = evaluate_alignment(ft.points, fs.tree, np.linalg.inv(T), distance)
    src, tgt = fs.points[a.source_index], ft.points[b.source_index]
    cells = len(np.unique(np.floor(src / (4 * v)).astype(np.int64), axis=0)) if len(src) \
        else 0
    return {
        'shared_points': int(min(len(src), len(tgt))),
        'shared_area_m2': float(min(len(src), len(tgt)) * v * v),
        'shared_cells_4v': int(cells),
        'shared_extent_source_m': _extent(src), 'shared_extent_target_m': _extent(tgt),
        'source_extent_m': _extent(fs.points), 'target_extent_m': _extent(ft.points),
    }


def descriptor_agreement(fs, ft, T: np.ndarray, cfg: PipelineConfig) -> dict:
    """
    Return how the FPFH descriptors agree over ``T``'s overlap, against a random pairing.

    For each overlapping source point and its nearest target point under ``T``: the L2
    distance of their (unit-normalised) descriptors; its median, and the median of the
    same points paired at random (seeded), and their ratio (below 1: the shared surface
    looks alike at the descriptors' scale too, as one surface seen twice does).
    """
    distance = cfg.refine.max_correspondence_distance_factor * cfg.voxel_size
    a = evaluate_alignment(fs.points, ft.tree, T, distance)
    if len(a.source_index) < 10:
        return {}
    ds = fs.descriptors[a.source_index].astype(np.float64)
    dt = ft.descriptors[a.target_index].astype(np.float64)
    ds /= np.maximum(np.linalg.norm(ds, axis=1, keepdims=True), 1e-12)
    dt /= np.maximum(np.linalg.norm(dt, axis=1, keepdims=True), 1e-12)
    paired = np.linalg.norm(ds - dt, axis=1)
    shuffled = np.linalg.norm(ds - dt[np.random.default_rng(0).permutation(len(dt))], axis=1)
    return {'desc_paired': float(np.median(paired)), 'desc_random': float(np.median(shuffled)),
            'desc_ratio': float(np.median(paired) / max(np.median(shuffled), 1e-12)),
            'desc_close_share': float(np.mean(paired < 0.5 * np.median(shuffled)))}


def remeasure(records: list[dict], root: Path, cfg: PipelineConfig) -> list[dict]:
    """
    Return ``records`` with what today's gates measure of their recorded transforms.

    :func:`descriptor_agreement` and the surfaces put in free space as both sensors see it
    (:func:`free_space_surface`), for each
    record with an estimate; the verdicts stay the recorded ones. Records of
    :mod:`bench.studies.loso_trust` (the benchmark's pairs, keyed ``benchmark``, ``scene``)
    are given this module's keys.
    """
    frags: dict[str, tdm.Fragments] = {}
    out = []
    for rec in records:
        if 'benchmark' in rec:
            rec = {**rec, 'kind': rec['benchmark'], 'source_scene': rec['scene'],
                   'target_scene': rec['scene']}
        if rec.get('transform') is not None and (rec.get('fitness') or 0) > 0:
            for scene in (rec['source_scene'], rec['target_scene']):
                frags.setdefault(scene, tdm.Fragments(root, scene))
            fs = cached_features(frags[rec['source_scene']][rec['source']], cfg.voxel_size,
                                 cfg.frontend, 'source')
            ft = cached_features(frags[rec['target_scene']][rec['target']], cfg.voxel_size,
                                 cfg.frontend, 'target')
            T = np.asarray(rec['transform'])
            rec = {**rec, **descriptor_agreement(fs, ft, T, cfg),
                   'free_space_surface': free_space_surface(fs, ft, T, cfg.voxel_size)}
        out.append(rec)
    return out


def measure(src: np.ndarray, tgt: np.ndarray, cfg: PipelineConfig) -> dict:
    """Register one pair; return the verdict, the gates' measures and :func:`shared_surface`."""
    t0 = time.perf_counter()
    result = register_clouds(src, tgt, config=cfg)
    rec = {'valid': bool(result.valid), 'time_s': time.perf_counter() - t0,
           'refusal': result.refusal.code.value if result.refusal else None,
           'transform': np.asarray(result.transform).tolist()}
    rec.update({name: _num(getattr(result, name)) for name in GATE_FIELDS})
    pts = result.inlier_source_points
    rec['inlier_extent_m'] = _extent(pts) if pts is not None else None
    if result.candidates and result.fitness > 0:
        fs = cached_features(src, cfg.voxel_size, cfg.frontend, 'source')
        ft = cached_features(tgt, cfg.voxel_size, cfg.frontend, 'target')
        rec.update(shared_surface(fs, ft, np.asarray(result.transform), cfg))
        rec.update(descriptor_agreement(fs, ft, np.asarray(result.transform), cfg))
        # the pipeline's own where its gate measured it; the study records it everywhere
        measured = result.free_space_surface
        rec['free_space_surface'] = measured if math.isfinite(measured) else \
            free_space_surface(fs, ft, np.asarray(result.transform), cfg.voxel_size)
    return rec


def cross_pairs(sizes: dict[str, int], n: int, seed: int) -> list[tuple[str, int, str, int]]:
    """
    Return ``n`` distinct (source scene, fragment, target scene, fragment) of two scenes.

    The source uniform over every fragment, the target uniform over the other scenes'.
    """
    rng = np.random.default_rng(seed)
    every = [(s, k) for s, count in sizes.items() for k in range(count)]
    total = sum(len([e for e in every if e[0] != s]) for s, _ in every)
    if n > total:
        raise ValueError(f'only {total} cross-scene pairs exist')
    chosen: dict[tuple, None] = {}
    while len(chosen) < n:
        s_scene, s = every[rng.integers(len(every))]
        others = [e for e in every if e[0] != s_scene]
        t_scene, t = others[rng.integers(len(others))]
        chosen[(s_scene, s, t_scene, t)] = None
    return list(chosen)


def _fragment_counts(root: Path) -> dict[str, int]:
    out = {}
    for scene in tdm.scenes(root, '3DMatch'):
        with np.load(root / 'fragments' / f'{scene}.npz') as npz:
            out[scene] = len([k for k in npz.files if k.startswith('cloud_bin_')])
    return out


def run_cross(args, cfg: PipelineConfig) -> None:
    sizes = _fragment_counts(args.root)
    pairs = cross_pairs(sizes, args.pairs, args.seed)
    frags = {scene: tdm.Fragments(args.root, scene) for scene in sizes}
    with _sink(args.output) as out:
        for i, (ss, s, ts, t) in enumerate(pairs):
            rec = {'kind': 'cross', 'source_scene': ss, 'source': s, 'target_scene': ts,
                   'target': t, 'success': False}
            rec.update(measure(frags[ss][s], frags[ts][t], cfg))
            out.write(json.dumps(rec) + '\n')
            out.flush()
            if (i + 1) % 50 == 0:
                print(f'{i + 1}/{len(pairs)}', flush=True)


def run_benchmark(args, cfg: PipelineConfig) -> None:
    with _sink(args.output) as out:
        for benchmark, scene, frags, pairs in tdm.benchmark_scenes(args.root):
            if args.pairs:
                idx = np.random.default_rng(args.seed).permutation(len(pairs))[:args.pairs]
                pairs = [pairs[i] for i in sorted(idx)]
            for pair in pairs:
                rec = {'kind': benchmark, 'source_scene': scene, 'source': pair.source,
                       'target_scene': scene, 'target': pair.target,
                       'gt_overlap': _num(pair.overlap)}
                rec.update(measure(frags[pair.source], frags[pair.target], cfg))
                T, gt = np.asarray(rec['transform']), tdm.nearest_rigid(pair.transform)
                rec.update(re_deg=rotation_error_deg(T, gt), te_m=translation_error(T, gt),
                           success=tdm.registered(T, gt))
                out.write(json.dumps(rec) + '\n')
                out.flush()
            print(f'{benchmark} {scene}: {len(pairs)} pairs', flush=True)


def run_lidar(args, cfg: PipelineConfig) -> None:
    """KITTI scans 0, 5, 10, 15 against each small_gicp scan (two streets), both ways."""
    from cgags_ros.io.clouds import read_cloud

    data = args.root.parent
    gicp = [read_cloud(data / 'lidar' / 'small_gicp' / f'{n}.ply') for n in ('source', 'target')]
    kitti = sorted((data / 'kitti' / 'seq00_16scans' / 'pcd').glob('*.pcd'))
    with _sink(args.output) as out:
        for voxel in (0.3, 0.5):
            c = update_from_flat(cfg, {'voxel_size': voxel})
            for k in (0, 5, 10, 15):
                scan = read_cloud(kitti[k])
                for g, other in enumerate(gicp):
                    for name, (src, tgt) in (('kitti_on_gicp', (scan, other)),
                                             ('gicp_on_kitti', (other, scan))):
                        rec = {'kind': 'lidar_cross', 'source_scene': name, 'source': k,
                               'target_scene': f'small_gicp_{g}', 'target': g,
                               'voxel': voxel, 'success': False}
                        rec.update(measure(src, tgt, c))
                        out.write(json.dumps(rec) + '\n')


def _sink(path: Path):
    path.parent.mkdir(parents=True, exist_ok=True)
    return open(path, 'w', encoding='utf-8')


def read_records(paths: list[Path]) -> list[dict]:
    """Return the JSON lines of ``paths``."""
    return [json.loads(line) for p in paths for line in Path(p).read_text().splitlines()
            if line.strip()]


def summary(records: list[dict]) -> str:
    """Return, per kind of pair, accepted / right / wrong-valid counts and refusal codes."""
    lines = []
    by_kind = collections.defaultdict(list)
    for r in records:
        by_kind[r['kind']].append(r)
    for kind, recs in by_kind.items():
        valid = [r for r in recs if r['valid']]
        right = [r for r in recs if r['success']]
        wrong_valid = [r for r in valid if not r['success']]
        codes = collections.Counter(r['refusal'] for r in recs if r['refusal'])
        conf = [r['confidence'] for r in valid]
        lines.append(
            f'{kind}: {len(recs)} pairs, valid {len(valid)}, right {len(right)}, right and '
            f'valid {sum(r["success"] for r in valid)}, valid but wrong {len(wrong_valid)}'
            + (f', valid confidence {min(conf):.3f}-{max(conf):.3f}' if conf else ''))
        lines.append('  refusals: ' + ', '.join(f'{c} {k}' for c, k in codes.most_common()))
        high = [r for r in recs if (r['confidence'] or 0) >= 0.9]
        if high:
            lines.append(f'  confidence >= 0.9: {len(high)}, right '
                         f'{sum(r["success"] for r in high)}')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argument_parser('bench.no_overlap', __doc__)
    parser.add_argument('mode', choices=('cross', 'benchmark', 'lidar', 'summary',
                                         'remeasure'))
    parser.add_argument('records', nargs='*', type=Path, help='summary: the JSONL files')
    parser.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark')
    parser.add_argument('--pairs', type=int, default=None,
                        help='cross: pairs drawn (1000); benchmark: pairs a scene and list')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--voxel', type=float, default=0.05)
    parser.add_argument('--output', type=Path, default=None)
    add_set_option(parser)
    args = parser.parse_args(argv)
    if args.mode == 'summary':
        print(summary(read_records(args.records)))
        return
    cfg = update_from_flat(PipelineConfig(), {'voxel_size': args.voxel,
                                              **parse_overrides(args.set)})
    set_feature_cache_size(256)  # every fragment of the four scenes, featurised once
    if args.mode == 'remeasure':
        with _sink(args.output) as out:
            for rec in remeasure(read_records(args.records), args.root, cfg):
                out.write(json.dumps(rec) + '\n')
        return
    if args.mode == 'lidar':
        args.output = args.output or Path('out/no_overlap/lidar.jsonl')
        run_lidar(args, cfg)
        return
    if args.mode == 'cross':
        args.pairs = args.pairs or 1000
        args.output = args.output or Path('out/no_overlap/cross.jsonl')
        run_cross(args, cfg)
    else:
        args.output = args.output or Path('out/no_overlap/benchmark.jsonl')
        run_benchmark(args, cfg)


if __name__ == '__main__':
    main()
