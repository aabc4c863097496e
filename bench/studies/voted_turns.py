r"""
The structured rivals' voted turns on real pairs: what they refuse, and what they cost.

Run by hand from the repository root, nothing else running (about ten minutes)::

    .venv/bin/python -m bench.studies.voted_turns [--pairs K] [--peaks 3] \
        [--turns + - h] [--output out/bench/voted_turns]

Every pair of both 3DMatch lists of the shared scenes (``--pairs K``: K sampled a scene
and list) is registered twice, with the voted turns (``--peaks`` translations each of the
``--turns``) and without them (0), in alternating order, each fragment featurised once a
scene: only the rivals differ, and their stage's seconds (``structured_rivals``) compare
side by side.
It prints, per list, how many valid estimates each setting has, how many of those are
wrong (RE > 15 deg or TE > 0.3 m), the estimates whose flag the voted turns change (right
or wrong), and the median and total seconds of the rivals' stage and of a pair.
"""

from __future__ import annotations

import json
from pathlib import Path
import time

from bench.common import argument_parser
from bench.datasets import threedmatch as tdm
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import register_clouds, rivals, set_feature_cache_size
import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark')
    parser.add_argument('--pairs', type=int, default=None)
    parser.add_argument('--output', type=Path, default=Path('out/bench/voted_turns'))
    parser.add_argument('--peaks', type=int, default=3, help='VOTED_PEAKS of the "on" runs')
    parser.add_argument('--turns', nargs='+', default=sorted(rivals.VOTED_ANGLES),
                        choices=sorted(rivals.VOTED_ANGLES),
                        help='the turns voted on: + and - a quarter, h a half')
    args = parser.parse_args(argv)
    rivals.VOTED_ANGLES = {k: rivals.VOTED_ANGLES[k] for k in args.turns}
    shipped = args.peaks
    args.output.mkdir(parents=True, exist_ok=True)
    set_feature_cache_size(1000)
    rows = []
    with open(args.output / 'records.jsonl', 'w', encoding='utf-8') as sink:
        for benchmark in tdm.BENCHMARKS:
            for scene in tdm.scenes(args.root, benchmark):
                pairs = tdm.registration_pairs(args.root, benchmark, scene)
                if args.pairs:
                    pick = np.random.default_rng(0).permutation(len(pairs))[:args.pairs]
                    pairs = [pairs[i] for i in sorted(pick)]
                fragments = tdm.Fragments(args.root, scene)
                for n, pair in enumerate(pairs):
                    src, tgt = fragments[pair.source], fragments[pair.target]
                    gt = tdm.nearest_rigid(pair.transform)
                    row = {'benchmark': benchmark, 'scene': scene, 'pair': pair.key}
                    for peaks in ((shipped, 0) if n % 2 else (0, shipped)):
                        rivals.VOTED_PEAKS = peaks
                        t0 = time.perf_counter()
                        r = register_clouds(src, tgt, voxel_size=0.05)
                        seconds = time.perf_counter() - t0
                        right = (rotation_error_deg(r.transform, gt) < 15
                                 and translation_error(r.transform, gt) < 0.3)
                        key = 'on' if peaks else 'off'
                        row[key] = {'valid': bool(r.valid), 'right': bool(right),
                                    'code': r.refusal.code.value if r.refusal else '',
                                    'rivals_s': r.timings.get('structured_rivals', 0.0),
                                    'seconds': seconds}
                    rivals.VOTED_PEAKS = shipped
                    rows.append(row)
                    sink.write(json.dumps(row) + '\n')
                    sink.flush()
                print(f'{benchmark} {scene}: {len(pairs)} pairs', flush=True)
    for benchmark in tdm.BENCHMARKS:
        mine = [r for r in rows if r['benchmark'] == benchmark]
        print(f'\n{benchmark}: {len(mine)} pairs')
        for key in ('off', 'on'):
            valid = [r for r in mine if r[key]['valid']]
            wrong = sum(not r[key]['right'] for r in valid)
            print(f'  voted turns {key}: {len(valid)} valid, {wrong} valid but wrong, '
                  f"rivals median {np.median([r[key]['rivals_s'] for r in valid] or [0]):.4f} s, "
                  f"rivals total {sum(r[key]['rivals_s'] for r in mine):.1f} s, pair median "
                  f"{np.median([r[key]['seconds'] for r in mine]):.3f} s")
        for r in mine:
            if r['off']['valid'] != r['on']['valid']:
                print(f"  changed: {r['pair']} {'right' if r['off']['right'] else 'WRONG'} "
                      f"valid {r['off']['valid']} -> {r['on']['valid']} ({r['on']['code']})")
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
