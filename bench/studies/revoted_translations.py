r"""
A refused estimate's translation voted again under its rotation: is another one right.

Run by hand from the repository root, after a ``bench.threedmatch`` run whose records it
reads (a few minutes)::

    .venv/bin/python -m bench.studies.revoted_translations out/refused/full/records.jsonl \
        [--method 'cgags[refined]'] [--refusals free_space ambiguous ...]

Many wrong estimates have the right rotation and a translation off along what the overlap
constrains least (a slide). For every refused estimate of the records (``--refusals``: only
those refused with these codes), each correspondence votes for a translation under the
estimate's rotation (``q - R p``); the PEAKS fullest cubes of side tau (each at least
2 tau from those before) and the estimate's own translation are settled as the twins
are, then measured (fitness within 1.5 voxels, free-space violation). It counts,
for the refused estimates that are wrong and those that are right, how often one of them is
right, and how often each rule picks a right one: the best fitness, or the best fitness
among those clear of free space (``gates.max_free_space_violation``).
"""

from __future__ import annotations

import json
from pathlib import Path

from bench.common import argument_parser, pair_features
from bench.datasets import threedmatch as tdm
from cgags_ros.config import PipelineConfig
from cgags_ros.geometry import make_transform
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import clear_feature_cache
from cgags_ros.pipeline.free_space import measured_free_space
from cgags_ros.pipeline.settle import Pair, settle, TWIN
import numpy as np

PEAKS = 8


def peaks(votes: np.ndarray, tau: float) -> list[np.ndarray]:
    """Return the mean votes of the PEAKS fullest cubes of side tau, 2 tau apart."""
    keys = np.floor(votes / tau).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    chosen: list[np.ndarray] = []
    for c in np.argsort(-counts, kind='stable')[:5 * PEAKS]:
        t = votes[inverse.ravel() == c].mean(axis=0)
        if all(np.linalg.norm(t - q) > 2 * tau for q in chosen):
            chosen.append(t)
        if len(chosen) == PEAKS:
            break
    return chosen


def revoted(src: np.ndarray, tgt: np.ndarray, record: dict, truth: np.ndarray,
            cfg: PipelineConfig) -> list[dict]:
    """Return each voted translation's settled pose: fitness, free space, right (estimate last)."""
    v = cfg.voxel_size
    clear_feature_cache()
    fs, ft, corr = pair_features(src, tgt, cfg)
    T = np.asarray(record['transform'])
    R, tau = T[:3, :3], record['inlier_threshold']
    votes = ft.points[corr.target_index] - fs.points[corr.source_index] @ R.T
    out = []
    for t in [*peaks(votes, tau), T[:3, 3]]:
        S = settle(Pair(fs, ft, cfg), make_transform(R, t), tau, TWIN).transform
        d, _ = ft.tree.query(fs.points @ S[:3, :3].T + S[:3, 3], k=1,
                             distance_upper_bound=1.5 * v)
        out.append({'fitness': float(np.isfinite(d).mean()),
                    'free_space': measured_free_space(fs, ft, S, cfg),
                    'right': tdm.registered(S, truth)})
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('records', type=Path)
    parser.add_argument('--method', default='cgags[refined]')
    parser.add_argument('--refusals', nargs='*', default=[],
                        help='refusal codes (default: every refusal)')
    parser.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark')
    args = parser.parse_args(argv)
    cfg = PipelineConfig()
    limit = cfg.gates.max_free_space_violation
    records = [json.loads(line) for line in args.records.read_text(encoding='utf-8').splitlines()]
    refused = [r for r in records if r['method'] == args.method and not r['valid']
               and (not args.refusals or r.get('refusal') in args.refusals)]
    counts = {k: dict.fromkeys(('pairs', 'any right', 'best fitness right',
                                'best clear of free space right'), 0)
              for k in ('wrong, rotation right', 'wrong, rotation wrong', 'right')}
    fragments: dict[str, tdm.Fragments] = {}
    truths: dict[tuple, np.ndarray] = {}
    for r in refused:
        scene = r['scene']
        if scene not in fragments:
            fragments[scene] = tdm.Fragments(args.root, scene)
            for b in tdm.BENCHMARKS:
                for p in tdm.registration_pairs(args.root, b, scene):
                    truths[b, scene, p.target, p.source] = tdm.nearest_rigid(p.transform)
        truth = truths[r['benchmark'], scene, r['target'], r['source']]
        poses = revoted(fragments[scene][r['source']], fragments[scene][r['target']], r, truth,
                        cfg)
        clear = [p for p in poses if not p['free_space'] > limit]
        kind = ('right' if r['success'] else
                'wrong, rotation right' if r['re_deg'] < 15 else 'wrong, rotation wrong')
        c = counts[kind]
        c['pairs'] += 1
        c['any right'] += any(p['right'] for p in poses)
        c['best fitness right'] += max(poses, key=lambda p: p['fitness'])['right']
        c['best clear of free space right'] += bool(
            clear and max(clear, key=lambda p: p['fitness'])['right'])
    print(json.dumps(counts, indent=1))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
