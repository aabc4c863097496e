r"""
Refusals certain before the refinement: what the pipeline gives up by not refining them.

Run by hand from the repository root (a few minutes for ``--pairs 40``)::

    .venv/bin/python -m bench.studies.certain_refusals [--benchmarks 3DLoMatch 3DMatch] \
        [--pairs 40] [--seed 0] [--output out/bench/certain_refusals.jsonl]

``register_clouds`` refines, gates and searches candidates only for an estimate the core (or
the regenerated correspondences after it) did not refuse, or whose only fault is a collinear
consensus. Every other refusal (no consensus above chance, a runner-up as large, too few
inliers) returns right after the core: the refinement, the gates and the candidates are
skipped. For each such pair of a seeded sample this study does the skipped work anyway
(the refinement from the refused estimate, the gates' measurements and verdict) and
counts how often it would have given a right pose, and a pose the gates pass: what the
skip costs in recall and what it saves in time. The pipeline runs with ``refine.refused``
off, as before this study (it now refines such an estimate, and keeps its verdict).
"""

from __future__ import annotations

import json
from pathlib import Path
import time

from bench.common import argument_parser, pair_features
from bench.datasets import threedmatch as tdm
from cgags_ros.config import PipelineConfig
from cgags_ros.config.fields import update_from_flat
from cgags_ros.frontend.refine import refine_transform
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import clear_feature_cache, register_clouds
from cgags_ros.pipeline.gates import measure
from cgags_ros.validity import gate_refusal
import numpy as np


def forced(src: np.ndarray, tgt: np.ndarray, cfg: PipelineConfig, result) -> dict:
    """Refine and gate a refused estimate as the pipeline would have; return what it gives."""
    v = cfg.voxel_size
    fs, ft, corr = pair_features(src, tgt, cfg)
    t0 = time.perf_counter()
    result.transform = refine_transform(
        fs.points, ft.points, result.coarse_transform, voxel_size=v, config=cfg.refine,
        target_normals=ft.normals, coarse_distance=result.inlier_threshold)
    measure(fs, ft, corr, result, cfg)
    refusal = gate_refusal(result, cfg)
    return {'forced_s': time.perf_counter() - t0, 'forced_T': result.transform,
            'gates': refusal.code.value if refusal else ''}


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark')
    parser.add_argument('--benchmarks', nargs='+', choices=tdm.BENCHMARKS,
                        default=['3DLoMatch', '3DMatch'])
    parser.add_argument('--pairs', type=int, default=40, help='pairs a scene and list')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--output', type=Path,
                        default=Path('out/bench/certain_refusals.jsonl'))
    args = parser.parse_args(argv)
    cfg = update_from_flat(PipelineConfig(), {'refine.refused': False})
    rng = np.random.default_rng(args.seed)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    with open(args.output, 'w', encoding='utf-8') as out:
        for benchmark, scene, fragments, pairs in tdm.benchmark_scenes(args.root,
                                                                       args.benchmarks):
            for k in rng.choice(len(pairs), min(args.pairs, len(pairs)), replace=False):
                p = pairs[k]
                src, tgt = fragments[p.source], fragments[p.target]
                truth = tdm.nearest_rigid(p.transform)
                clear_feature_cache()
                result = register_clouds(src, tgt, config=cfg)
                row = {'benchmark': benchmark, 'scene': scene, 'key': p.key,
                       'valid': result.valid, 'right': tdm.registered(result.transform, truth),
                       'skipped': 'refinement' not in result.timings,
                       'code': result.refusal.code.value if result.refusal else '',
                       'seconds': result.timings['total']}
                if row['skipped'] and result.refusal is not None:
                    f = forced(src, tgt, cfg, result)
                    row.update(forced_s=f['forced_s'], gates=f['gates'],
                               forced_right=tdm.registered(f['forced_T'], truth))
                out.write(json.dumps(row) + '\n')
                rows.append(row)
    print(summary(rows))
    return 0


def summary(rows: list[dict]) -> str:
    lines = []
    for benchmark in dict.fromkeys(r['benchmark'] for r in rows):
        mine = [r for r in rows if r['benchmark'] == benchmark]
        skipped = [r for r in mine if 'forced_s' in r]
        refused = [r for r in mine if not r['valid']]
        lines.append(f'{benchmark}: {len(mine)} pairs, {len(refused)} refused, '
                     f'{len(skipped)} refused before the refinement')
        for code in sorted({r['code'] for r in skipped}):
            these = [r for r in skipped if r['code'] == code]
            passed = [r for r in these if not r['gates']]
            lines.append(
                f'  {code}: {len(these)}; right before {sum(r["right"] for r in these)}, '
                f'right refined {sum(r["forced_right"] for r in these)}; the gates pass '
                f'{len(passed)} ({sum(r["forced_right"] for r in passed)} right); '
                f'skipped work {np.median([r["forced_s"] for r in these]):.3f} s median, '
                f'pair {np.median([r["seconds"] for r in these]):.3f} s')
    return '\n'.join(lines)


if __name__ == '__main__':
    raise SystemExit(main())
