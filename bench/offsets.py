r"""
Georeferenced coordinates: every bag pair and a sample of benchmark pairs, at the origin and moved.

Run by hand::

    .venv/bin/python -m bench.offsets [--pairs 120] [--magnitudes 1e5 1e6 1e7] \
        [--output out/bench/offsets.json]

Each pair (every source with ground truth in the bundled bags, paired as ``cgags-replay``
pairs them; a seeded sample of the 3DMatch and 3DLoMatch pairs at 5 cm) is registered with
the defaults at the origin, then moved by one offset of each magnitude (a seeded direction)
three ways: both clouds, their sensors' positions given (``source_sensor``,
``target_sensor``: two scans in one UTM frame with their GNSS positions); both clouds, the
sensors unknown; the target alone, its sensor unknown (a cloud in UTM as a map is, the scan in
its sensor frame). Per case: how often the valid flag is the origin's, the largest pose
difference (moved back) among pairs valid in both, and right / valid-but-wrong counts against
the truth. docs/frames.md reports the numbers.
"""

from __future__ import annotations

import json
from pathlib import Path

from bench.common import argument_parser
from bench.datasets import threedmatch as tdm
from bench.pipeline import load_pairs, thresholds
from cgags_ros.coordinates import to_local, translation
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import register_clouds
import numpy as np

SAME = (0.01, 0.01)  # m, deg: the origin's answer


def pairs(data: Path, sample: int, seed: int):
    """Yield ``(name, source, target, truth, voxel, (max RE deg, max TE m))``."""
    for bag in sorted((data / 'bags').iterdir()):
        if not bag.is_dir() or bag.name == 'faulty':
            continue
        found, voxel = load_pairs(bag)
        for stamp, source, target, truth in found:
            yield f'{bag.name}/{stamp}', source, target, truth, voxel, thresholds(bag.name, voxel)
    root = data / '3dmatch_benchmark'
    listed = [(benchmark, scene, fragments, p)
              for benchmark, scene, fragments, ps in tdm.benchmark_scenes(root) for p in ps]
    rng = np.random.default_rng(seed)
    for i in sorted(rng.choice(len(listed), min(sample, len(listed)), replace=False)):
        benchmark, scene, fragments, p = listed[i]
        yield (f'{benchmark}/{scene}/{p.target}-{p.source}', fragments[p.source],
               fragments[p.target], tdm.nearest_rigid(p.transform), 0.05, (15.0, 0.3))


def direction(seed: int) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=3)
    return d / np.linalg.norm(d)


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser('bench.offsets', __doc__)
    parser.add_argument('--pairs', type=int, default=120, help='benchmark pairs sampled')
    parser.add_argument('--magnitudes', type=float, nargs='+', default=[1e5, 1e6, 1e7])
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--output', type=Path, default=Path('out/bench/offsets.json'))
    args = parser.parse_args(argv)
    cases = [(m, moved) for m in args.magnitudes
             for moved in ('both, sensors given', 'both, sensors unknown', 'target')]
    counts = {f'{m:g} {moved}': {'pairs': 0, 'same_flag': 0, 'both_valid': 0, 'max_dt': 0.0,
                                 'max_dr': 0.0, 'right': 0, 'wrong_valid': 0}
              for m, moved in cases}
    origin = {'pairs': 0, 'right': 0, 'wrong_valid': 0}
    records = []
    for k, (name, source, target, truth, voxel, (max_re, max_te)) in enumerate(
            pairs(shared_data_dir(), args.pairs, args.seed)):
        at_origin = register_clouds(source, target, voxel_size=voxel)

        def right(T):
            return rotation_error_deg(T, truth) < max_re and translation_error(T, truth) < max_te
        origin['pairs'] += 1
        origin['right'] += at_origin.valid and right(at_origin.transform)
        origin['wrong_valid'] += at_origin.valid and not right(at_origin.transform)
        record = {'pair': name, 'origin': {'valid': at_origin.valid, 'refusal': at_origin.reason}}
        for m, moved in cases:
            d = m * direction(args.seed + k)
            sensors = {'source_sensor': d, 'target_sensor': d} if 'given' in moved else {}
            s = source if moved == 'target' else source + d
            result = register_clouds(s, target + d, voxel_size=voxel, **sensors)
            back = (translation(-d) @ result.transform if moved == 'target'
                    else to_local(result.transform, d, d))
            c = counts[f'{m:g} {moved}']
            c['pairs'] += 1
            c['same_flag'] += result.valid == at_origin.valid
            c['right'] += result.valid and right(back)
            c['wrong_valid'] += result.valid and not right(back)
            if result.valid and at_origin.valid:
                c['both_valid'] += 1
                c['max_dt'] = max(c['max_dt'], translation_error(back, at_origin.transform))
                c['max_dr'] = max(c['max_dr'], rotation_error_deg(back, at_origin.transform))
            record[f'{m:g} {moved}'] = {'valid': result.valid, 'refusal': result.reason}
        records.append(record)
        print(name, at_origin.valid, *(r['valid'] for r in list(record.values())[2:]),
              flush=True)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps({'origin': origin, 'cases': counts, 'records': records},
                                      indent=1), encoding='utf-8')
    print(f"\norigin: {origin['pairs']} pairs, {origin['right']} right and valid, "
          f"{origin['wrong_valid']} valid but wrong")
    print('| case | same flag | valid in both: max dt (m) / dR (deg) | right | valid but wrong |')
    print('|---|---|---|---|---|')
    for key, c in counts.items():
        print(f"| {key} | {c['same_flag']} of {c['pairs']} | {c['both_valid']}: "
              f"{c['max_dt']:.2g} / {c['max_dr']:.2g} | {c['right']} | {c['wrong_valid']} |")
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
