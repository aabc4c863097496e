r"""
Leave-one-scene-out study of the valid flag, the covariance and a confidence (3DMatch).

Run by hand from the repository root, one run at a time (it takes a while)::

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.studies.loso_trust measure \
        [--root <shared data>/3dmatch_benchmark] [--scenes S ...] [--pairs K] \
        [--set KEY=VALUE ...] [--output out/loso_trust/records.jsonl]

``measure`` registers every pair of both lists (3DMatch, 3DLoMatch) of every scene once,
with the default pipeline (``--gates-only``: without the twins and the
confidence threshold, so that every estimate the gates pass has its twins recorded, the
base :mod:`bench.studies.trust_shift` chooses those levers on; each fragment featurised once a
scene: the estimates are those of a cold run, the whole-pair times are not) and writes one
JSON line a pair holding every
measurement the pipeline has: the gates' values (inliers, chance level and its bound,
runner-up ratio and the candidates' support, fitness, overlap, observability, free-space
violation, RMSE, tilt), the refusal reason, the covariance and the timings; the ground
truth's RE/TE and the error vector ``e = (t_gt - t, log(R_gt R^T))`` in the covariance's
convention (geometry_msgs order x, y, z, rx, ry, rz); what alternative covariances need
(the point-to-plane and point-to-point information matrices over the refined overlap with
their residual sums, the overlap's cells at coarser grids, its principal axes); and the
twins: the estimate turned 180 degrees about each principal axis of the overlap
(through its centroid) and slid both ways along its least constrained direction, each
refined as the pipeline refines it and judged like the estimate (fitness, free-space
violation, distance from the estimate, error against the truth), for the estimates the
pipeline calls valid (a twin can only refuse).

``twins`` measures the twins of the valid estimates of such records again
with today's code (the starts and the settling of :mod:`cgags_ros.pipeline.twins`),
from the recorded estimates, and writes the records with them (minutes, not the hour a
full ``measure`` takes)::

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.studies.loso_trust twins \
        [out/loso_trust/records.jsonl] [--output out/loso_trust/records_twins.jsonl]

``timing`` registers a sample of pairs (``--pairs`` a scene and list) cold with the
defaults, with the twins and the confidence threshold off, and with
KISS-Matcher, interleaved pair by pair, and prints the median seconds of each.

The offline study of those records (each lever chosen on three scenes, reported on the
fourth) is ``bench/studies/loso_trust_study.py``. Results go under the git-ignored ``out/``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
import time

from bench.common import add_set_option, argument_parser, parse_overrides
from bench.datasets import threedmatch as tdm
from cgags_ros import fitted
from cgags_ros.config import GatesConfig, PipelineConfig
from cgags_ros.config.fields import update_from_flat
from cgags_ros.frontend.refine import evaluate_alignment
from cgags_ros.geometry import rotation_error_deg, spread, translation_error
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import cached_features, clear_feature_cache, register_clouds
from cgags_ros.pipeline import set_feature_cache_size, twins
from cgags_ros.pipeline.free_space import measured_free_space
from cgags_ros.pipeline.settle import Pair, settle, TWIN
import numpy as np
from scipy.spatial.transform import Rotation

MAX_RE_DEG, MAX_TE_M = tdm.MAX_RE_DEG, tdm.MAX_TE_M
GRID_FACTORS = (2, 4, 8, 16)  # coarse grids (voxel sizes) over which overlap cells are counted
PROMISING = 0.25  # the smallest share of T's fitness at which the study may settle a twin


def pose_error(T: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Return ``(t_gt - t, log(R_gt R^T))``: the covariance's perturbation from T to gt."""
    rot = Rotation.from_matrix(gt[:3, :3] @ T[:3, :3].T).as_rotvec()
    return np.concatenate([gt[:3, 3] - T[:3, 3], rot])


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def overlap_information(fs, ft, T: np.ndarray, distance: float, voxel: float) -> dict:
    """
    Return the information matrices and residual sums of ``T`` over the refined overlap.

    Convention of :func:`cgags_ros.pipeline.covariance.pose_covariance`: a perturbation
    ``(dt, dphi)`` moves a source point to ``exp([dphi]x) R p + t + dt``, so a residual's
    Jacobian is ``[n, (R p) x n]`` point-to-plane and ``[I, -[R p]x]`` point-to-point.
    """
    align = evaluate_alignment(fs.points, ft.tree, T, distance)
    k = len(align.source_index)
    out = {'overlap_points': k}
    if k < 6:
        return out
    p = fs.points[align.source_index]
    rotated = p @ T[:3, :3].T
    moved = rotated + T[:3, 3]
    q, n = ft.points[align.target_index], ft.normals[align.target_index]
    J = np.hstack([n, np.cross(rotated, n)])
    r = np.einsum('ij,ij->i', n, moved - q)
    out['plane_info'] = (J.T @ J).tolist()
    out['plane_r2'] = float(r @ r)
    out['plane_r_abs_q'] = np.quantile(np.abs(r), [0.5, 0.9, 0.99]).tolist()
    d = moved - q
    out['point_r2'] = float(np.sum(d * d))
    info = np.zeros((6, 6))
    info[:3, :3] = k * np.eye(3)
    s = _skew(rotated.sum(axis=0))
    info[:3, 3:], info[3:, :3] = s, s.T
    info[3:, 3:] = np.sum(rotated ** 2) * np.eye(3) - rotated.T @ rotated
    out['point_info'] = info.tolist()
    out['cells'] = {str(g): int(len(np.unique(np.floor(moved / (g * voxel)).astype(np.int64),
                                              axis=0))) for g in GRID_FACTORS}
    centred = moved - moved.mean(axis=0)
    w, vec = np.linalg.eigh(centred.T @ centred / k)
    out['centroid'] = moved.mean(axis=0).tolist()
    out['axes'] = vec.T.tolist()  # rows: principal axes, least spread first
    out['axis_rms'] = np.sqrt(np.maximum(w, 0.0)).tolist()
    return out


def measured_twins(fs, ft, T: np.ndarray, cfg: PipelineConfig, tau: float,
                   gt: np.ndarray, fitness: float, candidates=()) -> list[dict]:
    """
    Return the twins of ``T`` (see the module doc), settled and measured.

    The pipeline's own starts and settling (:mod:`cgags_ros.pipeline.twins`). A twin
    whose start already fits far worse than ``T`` (below ``PROMISING`` times its
    ``fitness``) is measured where it starts, not settled: the pipeline never settles it.
    """
    v = cfg.voxel_size
    distance = cfg.refine.max_correspondence_distance_factor * v
    out = []
    pair = Pair(fs, ft, cfg)
    for name, start in twins.twin_starts(fs, ft, T, distance, v, candidates):
        t0 = time.perf_counter()
        first = evaluate_alignment(fs.points[::TWIN.stride], ft.tree, start, distance)
        promising = twins.worth_refining(first.fitness, fitness, PROMISING)
        R = settle(pair, start, tau, TWIN).transform if promising else start
        ahead = evaluate_alignment(fs.points, ft.tree, R, distance)
        out.append({
            'name': name, 'transform': R.tolist(), 'fitness': ahead.fitness,
            'refined': bool(promising), 'start_fitness': first.fitness,
            'rmse': _num(ahead.inlier_rmse),
            'free_space_violation': _num(measured_free_space(fs, ft, R, cfg)),
            'from_estimate_deg': rotation_error_deg(R, T),
            'from_estimate_m': translation_error(R, T),
            're_deg': rotation_error_deg(R, gt), 'te_m': translation_error(R, gt),
            'time_s': time.perf_counter() - t0})
    return out


def measure_pair(src: np.ndarray, tgt: np.ndarray, pair: tdm.GtPair,
                 cfg: PipelineConfig) -> dict:
    """Register one pair and return every measurement of it (see the module doc)."""
    t0 = time.perf_counter()
    result = register_clouds(src, tgt, config=cfg)
    elapsed = time.perf_counter() - t0
    gt = tdm.nearest_rigid(pair.transform)
    T = np.asarray(result.transform, dtype=np.float64)
    re, te = rotation_error_deg(T, gt), translation_error(T, gt)
    rec = {
        'scene': pair.scene, 'target': pair.target, 'source': pair.source,
        'gt_overlap': _num(pair.overlap), 'valid': bool(result.valid), 'reason': result.reason,
        're_deg': re, 'te_m': te, 'success': bool(re < MAX_RE_DEG and te < MAX_TE_M),
        'rmse_m': tdm.rmse_error(T, pair.transform, pair.info) if pair.info is not None
        else None,
        'error': pose_error(T, gt).tolist(), 'transform': T.tolist(), 'gt': gt.tolist(),
        'coarse_re_deg': rotation_error_deg(result.coarse_transform, gt),
        'coarse_te_m': translation_error(result.coarse_transform, gt),
        'time_s': elapsed, 'timings': {k: float(x) for k, x in result.timings.items()},
        'covariance': np.asarray(result.covariance).tolist(),
        'doubt': [fitted.WRONG_POSITION_VOXELS * cfg.voxel_size, fitted.WRONG_ROTATION,
                  fitted.DOUBT_EXPONENT],
        'ambiguous': bool(result.ambiguous), 'refined': bool(result.refined),
        'confidence': float(result.confidence), 'refusal': result.refusal.code.value
        if result.refusal else None,
        'num_inliers': int(result.num_inliers),
        'num_correspondences': int(result.num_correspondences),
        'num_hypotheses': int(result.num_hypotheses),
        'inlier_threshold': _num(result.inlier_threshold),
        'chance_inliers': _num(result.chance_inliers), 'fitness': _num(result.fitness),
        'overlap': _num(result.overlap), 'inlier_rmse': _num(result.inlier_rmse),
        'observability': _num(result.observability),
        'free_space_violation': _num(result.free_space_violation),
        'runner_up_ratio': _num(result.runner_up_ratio), 'tilt_deg': _num(result.tilt_deg),
        'num_source_points': int(result.num_source_points),
        'num_target_points': int(result.num_target_points),
    }
    if math.isfinite(result.chance_bound):
        rec['chance_bound'] = float(result.chance_bound)
    pts = result.inlier_source_points
    rec['inlier_spread_m'] = (spread(pts) / math.sqrt(len(pts))).tolist() if len(pts) > 2 \
        else None
    rec['candidates'] = [{
        'num_inliers': int(c.num_inliers), 'fitness': _num(c.fitness), 'ratio': float(c.ratio),
        're_deg': rotation_error_deg(c.transform, gt), 'te_m': translation_error(c.transform, gt),
        'from_best_deg': rotation_error_deg(c.transform, T),
        'from_best_m': translation_error(c.transform, T),
        'transform': np.asarray(c.transform).tolist()} for c in result.candidates]
    if not result.candidates:
        return rec
    # Outside the timed call: both clouds' features are still in the cache.
    fs = cached_features(src, cfg.voxel_size, cfg.frontend, 'source')
    ft = cached_features(tgt, cfg.voxel_size, cfg.frontend, 'target')
    distance = cfg.refine.max_correspondence_distance_factor * cfg.voxel_size
    info = overlap_information(fs, ft, T, distance, cfg.voxel_size)
    rec['overlap_info'] = info
    if result.valid:  # twins can only refuse: measured where there is something to refuse
        rec['twins'] = measured_twins(fs, ft, T, cfg, float(result.inlier_threshold), gt,
                                      float(result.fitness),
                                      [c.transform for c in result.candidates[1:]])
    return rec


def _num(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def measure(args) -> None:
    cfg = PipelineConfig(voxel_size=args.voxel)
    if args.gates_only:
        cfg = PipelineConfig(voxel_size=args.voxel, gates=GatesConfig(
            check_twins=False, min_confidence=0.0))
    cfg = update_from_flat(cfg, parse_overrides(args.set))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    done = set()
    if args.resume and args.output.exists():
        for line in args.output.read_text(encoding='utf-8').splitlines():
            r = json.loads(line)
            done.add((r['benchmark'], r['scene'], r['target'], r['source']))
    t_start = time.time()
    with open(args.output, 'a' if args.resume else 'w', encoding='utf-8') as sink:
        for scene in args.scenes or tdm.scenes(args.root, '3DMatch'):
            fragments = tdm.Fragments(args.root, scene)
            clear_feature_cache()
            set_feature_cache_size(1000)  # every fragment of a scene featurised once
            for benchmark in tdm.BENCHMARKS:
                pairs = tdm.registration_pairs(args.root, benchmark, scene)
                if args.pairs:
                    pick = np.random.default_rng(args.seed).choice(
                        len(pairs), size=min(args.pairs, len(pairs)), replace=False)
                    pairs = [pairs[i] for i in np.sort(pick)]
                print(f'{benchmark} {scene}: {len(pairs)} pair(s), '
                      f'{time.time() - t_start:.0f} s', flush=True)
                for pair in pairs:
                    if (benchmark, scene, pair.target, pair.source) in done:
                        continue
                    rec = measure_pair(fragments[pair.source], fragments[pair.target], pair,
                                       cfg)
                    sink.write(json.dumps({'benchmark': benchmark, **rec}) + '\n')
                    sink.flush()
    print(f'wrote {args.output} in {time.time() - t_start:.0f} s')


def remeasure_twins(args) -> None:
    """Measure the twins of recorded valid estimates again, with today's code."""
    cfg = PipelineConfig(voxel_size=args.voxel)
    records = [json.loads(line) for line in args.records.read_text(encoding='utf-8').splitlines()]
    t_start = time.time()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    with open(args.output, 'w', encoding='utf-8') as sink:
        for scene in sorted({r['scene'] for r in records}):
            fragments = tdm.Fragments(args.root, scene)
            clear_feature_cache()
            set_feature_cache_size(1000)
            print(f'{scene}: {time.time() - t_start:.0f} s', flush=True)
            for r in records:
                if r['scene'] != scene:
                    continue
                if r['valid'] and ('twins' in r or 'rivals' in r):
                    fs = cached_features(fragments[r['source']], cfg.voxel_size, cfg.frontend,
                                         'source')
                    ft = cached_features(fragments[r['target']], cfg.voxel_size, cfg.frontend,
                                         'target')
                    r.pop('rivals', None)  # older records' name for them
                    r['twins'] = measured_twins(
                        fs, ft, np.asarray(r['transform']), cfg, r['inlier_threshold'],
                        np.asarray(r['gt']), r['fitness'],
                        [np.asarray(c['transform']) for c in r['candidates'][1:]])
                sink.write(json.dumps(r) + '\n')
    print(f'wrote {args.output} in {time.time() - t_start:.0f} s')


def timing(args) -> None:
    """Time the defaults against the levers off, cold, interleaved pair by pair."""
    import kiss_matcher

    from cgags_ros.pipeline import clear_feature_cache

    configs = {'defaults': PipelineConfig(voxel_size=args.voxel),
               'levers off': PipelineConfig(voxel_size=args.voxel, gates=GatesConfig(
                   check_twins=False, min_confidence=0.0))}
    times: dict = {}
    rng = np.random.default_rng(args.seed)
    for scene in args.scenes or tdm.scenes(args.root, '3DMatch'):
        fragments = tdm.Fragments(args.root, scene)
        for benchmark in tdm.BENCHMARKS:
            pairs = tdm.registration_pairs(args.root, benchmark, scene)
            for i in np.sort(rng.choice(len(pairs), size=min(args.pairs, len(pairs)),
                                        replace=False)):
                src, tgt = fragments[pairs[i].source], fragments[pairs[i].target]
                for name, cfg in configs.items():
                    clear_feature_cache()
                    t0 = time.perf_counter()
                    register_clouds(src, tgt, config=cfg)
                    times.setdefault((benchmark, name), []).append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(args.voxel)).estimate(
                    src.astype(np.float32), tgt.astype(np.float32))
                times.setdefault((benchmark, 'kiss_matcher'), []).append(
                    time.perf_counter() - t0)
    # On a shared machine the load swings within a run; a pair's time over KISS-Matcher's,
    # both measured moments apart, swings less than either median.
    for (benchmark, name), ts in sorted(times.items()):
        kiss = np.asarray(times[benchmark, 'kiss_matcher'])
        print(f'{benchmark} {name}: median {np.median(ts):.3f} s, mean {np.mean(ts):.3f} s '
              f'over {len(ts)} pairs; median per-pair ratio to KISS-Matcher '
              f'{np.median(np.asarray(ts) / kiss):.2f}')


def main(argv: list[str] | None = None) -> int:
    p = argument_parser(__spec__.name, __doc__)
    sub = p.add_subparsers(dest='command', required=True)
    m = sub.add_parser('measure', help='register every pair once and record everything')
    m.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark')
    m.add_argument('--scenes', nargs='+', default=None)
    m.add_argument('--pairs', type=int, default=None, help='sample K pairs a scene and list')
    m.add_argument('--seed', type=int, default=0)
    m.add_argument('--voxel', type=float, default=0.05)
    m.add_argument('--resume', action='store_true', help='skip pairs already recorded')
    m.add_argument('--gates-only', action='store_true',
                   help='without the twins and the confidence threshold, so that '
                   "every estimate the gates pass has its twins measured (a study's base)")
    m.add_argument('--output', type=Path, default=Path('out/loso_trust/records.jsonl'))
    add_set_option(m)
    t = sub.add_parser('timing', help='time the defaults, the levers off and KISS-Matcher')
    t.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark')
    t.add_argument('--scenes', nargs='+', default=None)
    t.add_argument('--pairs', type=int, default=10, help='pairs a scene and list')
    t.add_argument('--seed', type=int, default=0)
    t.add_argument('--voxel', type=float, default=0.05)
    r = sub.add_parser('twins', help="measure the recorded valid estimates' twins again")
    r.add_argument('records', type=Path, nargs='?',
                   default=Path('out/loso_trust/records.jsonl'))
    r.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark')
    r.add_argument('--voxel', type=float, default=0.05)
    r.add_argument('--output', type=Path, default=Path('out/loso_trust/records_twins.jsonl'))
    args = p.parse_args(argv)
    {'measure': measure, 'timing': timing, 'twins': remeasure_twins}[args.command](args)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
