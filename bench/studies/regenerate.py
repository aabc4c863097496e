r"""
Regenerated correspondences on real pairs: more right matches, and which judge picks the pose.

Run by hand from the repository root (a few minutes for ``--pairs 30``)::

    .venv/bin/python -m bench.studies.regenerate [--benchmark 3DLoMatch] [--pairs 30] \
        [--seed 1] [--output out/bench/regenerate.jsonl]

``--pairs K`` pairs a scene of one list (seeded), featurised as the pipeline does. For each
pair, with the default settings of :mod:`cgags_ros.pipeline.regenerate`:

- the right correspondences (within tau of the ground truth) of the single global match,
  and the right matches the spheres of the right seeds re-match;
- Regor's loop: the core run again on the putative matches plus every sphere's matches,
  refined as the pipeline refines: right or wrong, and whether the core calls it valid (its
  chance level measured on the enlarged set);
- the stage's judge: every distinct pose the spheres propose, and the core's estimate,
  refined by the stage's short ICP, with the original correspondences within tau before
  and after it (support), its free-space violation, and whether it is right.

It prints how often each way of choosing the pose is right: the core alone; the enlarged
set; the proposal with the largest support before the ICP; after it (free-space gate
passed), on every pair or only where the core refuses its estimate (the stage's default).
"""

from __future__ import annotations

import json
from pathlib import Path

from bench.common import argument_parser, pair_features
from bench.datasets import threedmatch as tdm
from cgags_ros.config import PipelineConfig
from cgags_ros.frontend.refine import refine_transform
from cgags_ros.geometry import apply_transform
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import regenerate
from cgags_ros.pipeline.candidates import distinct
from cgags_ros.pipeline.settle import support
from cgags_ros.registration import register_correspondences
import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark')
    parser.add_argument('--benchmark', choices=tdm.BENCHMARKS, default='3DLoMatch')
    parser.add_argument('--pairs', type=int, default=30, help='pairs a scene (seeded)')
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--output', type=Path, default=Path('out/bench/regenerate.jsonl'))
    args = parser.parse_args(argv)
    cfg = PipelineConfig()
    rng = np.random.default_rng(args.seed)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    with args.output.open('w', encoding='utf-8') as out:
        for scene in tdm.scenes(args.root, args.benchmark):
            fragments = tdm.Fragments(args.root, scene)
            pairs = tdm.registration_pairs(args.root, args.benchmark, scene)
            for k in rng.choice(len(pairs), min(args.pairs, len(pairs)), replace=False):
                p = pairs[k]
                row = measure(fragments[p.source], fragments[p.target],
                              tdm.nearest_rigid(p.transform), cfg)
                row['key'] = p.key
                out.write(json.dumps(row) + '\n')
                out.flush()
                rows.append(row)
    print(summary(rows))
    return 0


def measure(src: np.ndarray, tgt: np.ndarray, truth: np.ndarray, cfg: PipelineConfig) -> dict:
    """Return one pair's measurements (see the module doc)."""
    v = cfg.voxel_size
    fs, ft, corr = pair_features(src, tgt, cfg)
    ps, pt = fs.points[corr.source_index], ft.points[corr.target_index]
    resolution = 0.5 * (fs.resolution + ft.resolution)
    core = register_correspondences(ps, pt, resolution=resolution, config=cfg.core)
    tau, delta = core.inlier_threshold, core.compatibility_threshold
    right = np.linalg.norm(apply_transform(truth, ps) - pt, axis=1) < tau
    seeds = regenerate.seed_rows(ps, pt, delta, 0.0, cfg)
    radius = regenerate.RADIUS * v
    matches, right_found = [], set()
    for s in seeds:
        i, j = regenerate.local_matches(fs, ft, ps[s], pt[s], radius, delta)
        matches.append(np.c_[i, j])
        if right[s]:
            ok = np.linalg.norm(apply_transform(truth, fs.points[i]) - ft.points[j],
                                axis=1) < tau
            right_found |= set(zip(i[ok].tolist(), j[ok].tolist()))
    row = {'right_matches': int(right.sum()), 'seeds': len(seeds),
           'right_seeds': int(right[seeds].sum()), 'regenerated_right': len(right_found),
           'core_valid': core.valid}

    def refined(T: np.ndarray) -> np.ndarray:
        return refine_transform(fs.points, ft.points, T, voxel_size=v, config=cfg.refine,
                                target_normals=ft.normals, coarse_distance=tau)

    row['core_right'] = tdm.registered(refined(core.transform), truth)
    both = np.unique(np.vstack([np.c_[corr.source_index, corr.target_index], *matches]),
                     axis=0)
    enlarged = register_correspondences(fs.points[both[:, 0]], ft.points[both[:, 1]],
                                        resolution=resolution, config=cfg.core)
    row['enlarged_right'] = tdm.registered(refined(enlarged.transform), truth)
    row['enlarged_valid'] = enlarged.valid
    poses = regenerate.proposed_poses(fs, ft, corr, core, cfg)
    settled = regenerate.settled_support(fs, ft, corr, [core.transform, *poses], tau, cfg)
    row['poses'] = [{
        'estimate': n == 0, 'right': tdm.registered(s.transform, truth), 'support': s.support,
        'support_before': int(np.count_nonzero(support(ps, pt, start, tau))),
        'violation': s.free_space,
        'distinct': n == 0 or distinct(s.transform, settled[0].transform, cfg)}
        for n, (start, s) in enumerate(zip([core.transform, *poses], settled))]
    return row


def _chosen(row: dict, key: str, limit: float, only_refused: bool) -> bool:
    """Return whether the pose a rule chooses is right (the estimate's, when none beats it)."""
    estimate = row['poses'][0]
    if only_refused and row['core_valid']:
        return row['core_right']
    contenders = [p for p in row['poses'][1:] if p['distinct'] and not p['violation'] > limit]
    best = max(contenders, key=lambda p: p[key], default=None)
    if best is None or best[key] <= estimate[key]:
        return row['core_right']
    return best['right']


def summary(rows: list[dict]) -> str:
    """Return the study's table (markdown)."""
    limit = PipelineConfig().gates.max_free_space_violation
    n = len(rows)
    lines = [f'{n} pairs; right correspondences of the single match: '
             f'{sum(r["right_matches"] for r in rows)}, re-matched in the right seeds\' '
             f'spheres: {sum(r["regenerated_right"] for r in rows)}',
             '', '| the pose chosen by | right | wrong but valid |', '|---|---|---|']
    lines.append(f'| the core alone, refined | {sum(r["core_right"] for r in rows)} | |')
    lines.append(f'| the core on the enlarged set, refined | '
                 f'{sum(r["enlarged_right"] for r in rows)} | '
                 f'{sum(r["enlarged_valid"] and not r["enlarged_right"] for r in rows)} |')
    lines.append(f'| any proposed pose (the bound) | '
                 f'{sum(r["core_right"] or any(p["right"] for p in r["poses"]) for r in rows)}'
                 ' | |')
    for key, label in (('support_before', 'support before the ICP'),
                       ('support', 'support after the ICP')):
        for only_refused in (False, True):
            chosen = sum(_chosen(r, key, limit, only_refused) for r in rows)
            where = 'where the core refuses' if only_refused else 'on every pair'
            lines.append(f'| {label}, free space passed, {where} | {chosen} | |')
    return '\n'.join(lines)


if __name__ == '__main__':
    raise SystemExit(main())
