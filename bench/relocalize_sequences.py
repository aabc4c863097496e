"""
Relocalization over sequences of 1, 2 and 3 scans with drifting odometry, in 3DMatch scenes.

For every scene of a 3DMatch benchmark folder and every start fragment ``k`` (``--starts N``
samples N a scene, seeded), the scans are fragments ``k, k+1, k+2`` in their own (sensor)
frames; the prior map is the scene fused from every other fragment with their poses, each
fragment's normals facing its sensor (a PLY map file, prepared by ``load_map`` as the node
does), turned and shifted at random (any-angle start). The odometry is the fragment poses'
steps with seeded drift: each step turned by ``--drift-deg`` about a random axis and shifted
by ``--drift-m`` plus ``--drift-fraction`` of the step's length in a random direction. The
scans go one by one into a :class:`~cgags_ros.relocalization.relocalizer.Relocalizer`
(``max_scans`` 3); "n scans" is the relocalizer allowed up to n scans, stopping at the
first confirmed answer. Right: RE < 10 deg and TE < 0.3 m for the last scan used. Counted:
sequences whose last scan (of the n) overlaps the map by at least 30 % (share of its points
within 3.75 cm of a map point). Time: the relocalizer's seconds until it stopped (the map's
preparation is not counted; one scan's registration is the single-scan row).

Every check is recorded, so the decision's thresholds can be chosen on three scenes and
reported on the fourth (``--report``: leave one scene out, rotating), without registering
again.

Usage::

    OMP_NUM_THREADS=1 python -m bench.relocalize_sequences --scenes 7-scenes-redkitchen
    python -m bench.relocalize_sequences --report      # every scene recorded in --output
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
import tempfile
import time

from bench.common import argument_parser, markdown_table, output_path, write_text
from bench.datasets import threedmatch as tdm
from cgags_ros.config import pipeline_config_from
from cgags_ros.frontend.features import estimate_normals
from cgags_ros.geometry import apply_transform, make_transform, rotation_error_deg
from cgags_ros.geometry import translation_error
from cgags_ros.io.clouds import write_cloud
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline.map import load_map
from cgags_ros.refusal import Refusal, RefusalCode, summary
from cgags_ros.relocalization.hypotheses import Check, Hypothesis, judge, SequenceConfig
from cgags_ros.relocalization.relocalizer import Relocalizer
import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

LENGTH = 3
MIN_OVERLAP = 0.3
OVERLAP_RADIUS = 0.0375
RIGHT = (10.0, 0.3)  # RE (deg), TE (m) of the last scan


def drifted_odometry(poses: list[np.ndarray], rng: np.random.Generator, deg: float,
                     metres: float, fraction: float) -> list[np.ndarray]:
    """Return odom <- sensor poses: the true steps between ``poses``, each with drift."""
    odom = [make_transform(Rotation.random(random_state=rng).as_matrix(),
                           rng.uniform(-5, 5, 3))]
    for a, b in zip(poses, poses[1:]):
        step = np.linalg.inv(a) @ b
        axis, direction = rng.normal(size=3), rng.normal(size=3)
        turn = Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)).as_matrix()
        shift = (metres + fraction * np.linalg.norm(step[:3, 3])) * direction \
            / np.linalg.norm(direction)
        odom.append(odom[-1] @ step @ make_transform(turn, shift))
    return odom


def run_scene(root: Path, scene: str, starts: int, cfg, seq: SequenceConfig, drift: tuple,
              rng: np.random.Generator) -> list[dict]:
    """Relocalize every sequence of one scene (module doc); return the records."""
    poses, fragments = tdm.fragment_poses(root, scene), tdm.Fragments(root, scene)
    sides = {k: estimate_normals(fragments[k], cfg.voxel_size, cfg.frontend) for k in poses}
    ids = [k for k in poses if all(k + i in poses for i in range(LENGTH))]
    if starts:
        ids = sorted(rng.choice(ids, min(starts, len(ids)), replace=False).tolist())
    records = []
    for k in ids:
        seq_ids = list(range(k, k + LENGTH))
        A = make_transform(Rotation.random(random_state=rng).as_matrix(),
                           rng.uniform(-3, 3, 3))
        kept = [m for m in poses if m not in seq_ids]
        world = np.vstack([apply_transform(A @ poses[m], fragments[m]) for m in kept])
        normals = np.vstack([sides[m] @ (A @ poses[m])[:3, :3].T for m in kept])
        tree = cKDTree(world)
        truth = [A @ poses[m] for m in seq_ids]
        overlap = [float(np.mean(np.isfinite(tree.query(
            apply_transform(T, fragments[m]), distance_upper_bound=OVERLAP_RADIUS)[0])))
            for m, T in zip(seq_ids, truth)]
        odom = drifted_odometry([poses[m] for m in seq_ids], rng, *drift)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / 'map.ply'
            write_cloud(path, world, normals)
            prepared = load_map(path, cfg)
        reloc = Relocalizer(prepared, cfg, seq)
        steps = []
        for m, pose, T_gt in zip(seq_ids, odom, truth):
            t0 = time.perf_counter()
            answer = reloc.add(fragments[m], pose)
            seconds = time.perf_counter() - t0
            re, te = rotation_error_deg(answer.transform, T_gt), translation_error(
                answer.transform, T_gt)
            steps.append({'confirmed': answer.confirmed, 'done': answer.done,
                          're_deg': re, 'te_m': te, 's': seconds, 'reason': answer.reason,
                          'refusal': summary(answer.refusal),
                          'single_valid': bool(answer.results[-1].valid),
                          'single_s': float(answer.results[-1].timings.get('total', 0.0)),
                          'submap_s': float(reloc.submaps[len(steps)].timings.get('total', 0.0))
                          if len(steps) in reloc.submaps else 0.0})
        records.append({'scene': scene, 'start': k, 'overlap': overlap, 'steps': steps,
                        'truth': [T.tolist() for T in truth],
                        'odom': [T.tolist() for T in odom],
                        'hypotheses': [_hypothesis_record(h) for h in reloc.hypotheses],
                        'results': [{'valid': bool(r.valid), 'reason': r.reason,
                                     'refusal': summary(r.refusal),
                                     'transform': r.transform.tolist()}
                                    for r in answer.results]})
        s = steps
        print(f'{scene[:20]:20s} {k:3d} overlap {" ".join(f"{o:.2f}" for o in overlap)} '
              + ' | '.join(f"{'C' if x['confirmed'] else '-'} {x['re_deg']:6.1f} deg "
                           f"{x['te_m']:.2f} m {x['s']:.2f} s" for x in s), flush=True)
    return records


def _hypothesis_record(h) -> dict:
    return {'map_from_odom': h.map_from_odom.tolist(), 'scan': h.scan, 'rank': h.rank,
            'source': h.source,
            'inliers': h.inliers,
            'checks': {str(i): {**{f.name: getattr(c, f.name) for f in dataclasses.fields(c)
                                   if f.name != 'transform'},
                                'transform': c.transform.tolist()}
                       for i, c in h.checks.items()}}


# The decision's thresholds tried (leave one scene out): min_fitness, refute_ratio,
# min_scans, whether the submap's candidates count, and the drift allowance a step
# (drift_deg, drift_m): a check also absorbs the error of the pose it starts from.
GRID = [(f, r, m, sub, deg, metres) for f in (0.3, 0.4, 0.5) for r in (1.2, 1.5, 2.0)
        for m in (1, 2) for sub in (True, False) for deg in (2.0, 3.0, 5.0)
        for metres in (0.05, 0.1, 0.2)]


def _refusal(recorded: dict) -> Refusal | None:
    """
    Return a recorded result's refusal (None when it was valid).

    Records made before results carried codes hold only the message: those are taken as
    ``no_estimate``; the report reads only whether an answer is confirmed and its pose.
    """
    if recorded['valid']:
        return None
    said = recorded.get('refusal')
    if said:
        return Refusal(RefusalCode(said['code']), said['message'])
    return Refusal(RefusalCode.NO_ESTIMATE, recorded['reason'])


def replay(record: dict, n: int, seq: SequenceConfig, submap: bool, cfg) -> dict:
    """Judge the first ``n`` scans of ``record`` again under ``seq`` (no registration)."""
    from types import SimpleNamespace

    hypotheses = []
    for h in record['hypotheses']:
        if h['scan'] >= n or (h['source'] == 'submap' and not submap):
            continue
        checks = {int(i): Check(np.asarray(c['transform']), c['moved_deg'], c['moved_m'],
                                c['steps'], c['travelled_m'], c['fitness'], c['free_space'],
                                c.get('descriptor_ratio', np.nan),
                                c.get('observability', np.nan))
                  for i, c in h['checks'].items() if int(i) < n}
        hypotheses.append(Hypothesis(np.asarray(h['map_from_odom']), h['scan'], h['rank'],
                                     h['inliers'], h['source'], checks))
    results = [SimpleNamespace(transform=np.asarray(r['transform']), reason=r['reason'],
                               valid=r['valid'], refusal=_refusal(r))
               for r in record['results'][:n]]
    odom = [np.asarray(T) for T in record['odom'][:n]]
    if n == 1:
        confirmed = results[0].valid and seq.min_scans <= 1
        T = results[0].transform
    else:
        answer = judge(hypotheses, results, odom, cfg, seq)
        confirmed, T = answer.confirmed, answer.transform
    T_gt = np.asarray(record['truth'][n - 1])
    return {'confirmed': bool(confirmed), 'right': bool(
        rotation_error_deg(T, T_gt) < RIGHT[0] and translation_error(T, T_gt) < RIGHT[1])}


def outcome(record: dict, scans: int, policy, cfg) -> dict:
    """Return the answer when allowed ``scans`` scans, stopping at the first confirmed one."""
    f, r, m, sub, deg, metres = policy
    seq = SequenceConfig(max_scans=LENGTH, min_scans=m, min_fitness=f, refute_ratio=r,
                         submap=sub, drift_deg=deg, drift_m=metres)
    seconds = 0.0
    for n in range(1, scans + 1):
        step = record['steps'][n - 1]
        seconds += step['s'] - (0.0 if sub else step['submap_s'])
        got = replay(record, n, seq, sub, cfg)
        if got['confirmed'] or n == scans:
            return {**got, 's': seconds, 'single_s': record['steps'][0]['s'], 'used': n}


def table(records: list[dict], policy_of, cfg) -> list[list]:
    """Return the rows of 1, 2 and 3 scans: right & confirmed, confirmed wrong, refused, time."""
    rows = []
    for scans in range(1, LENGTH + 1):
        got = [outcome(r, scans, policy_of(r), cfg) for r in records
               if r['overlap'][scans - 1] >= MIN_OVERLAP]
        ok = sum(g['confirmed'] and g['right'] for g in got)
        wrong = sum(g['confirmed'] and not g['right'] for g in got)
        ratio = [g['s'] / g['single_s'] for g in got]
        rows.append([scans, len(got), f'{ok}/{len(got)} ({100 * ok / max(len(got), 1):.1f} %)',
                     wrong, len(got) - ok - wrong,
                     f"{np.median([g['s'] for g in got]):.2f}" if got else '-',
                     f'{np.median(ratio):.2f}' if got else '-'])
    return rows


def choose(records: list[dict], cfg, grid: list[tuple] = GRID):
    """Return the policy with the most right & confirmed in 3 scans, none confirmed wrong."""
    def merit(policy):
        got = [outcome(r, LENGTH, policy, cfg) for r in records
               if r['overlap'][LENGTH - 1] >= MIN_OVERLAP]
        wrong = sum(g['confirmed'] and not g['right'] for g in got)
        ok = sum(g['confirmed'] and g['right'] for g in got)
        return (-wrong, ok, -np.median([g['s'] for g in got]))
    return max(grid, key=merit)


def report(paths: list[Path]) -> str:
    """Return the tables of the recorded scenes: defaults, and leave one scene out."""
    cfg = pipeline_config_from({'voxel_size': 0.05})
    records = [r for p in paths for r in json.loads(p.read_text())['records']]
    scenes = sorted({r['scene'] for r in records})
    headers = ['scans (at most)', 'sequences', 'right & confirmed', 'confirmed but wrong',
               'refused', 'median s', 'median s / one scan']
    d = SequenceConfig()
    default = (d.min_fitness, d.refute_ratio, d.min_scans, d.submap, d.drift_deg, d.drift_m)
    out = [f'{len(records)} sequences of {len(scenes)} scenes; last scan overlapping the map '
           f'by >= {MIN_OVERLAP:g}.', '', f'Defaults {default} (min_fitness, refute_ratio, '
           'min_scans, submap, drift_deg, drift_m):', '',
           markdown_table(headers, table(records, lambda r: default, cfg))]
    # min_scans 2 is what confirming over scans means (one scan with odometry would be
    # confirmed on its own evidence alone); the other thresholds are chosen. The second
    # table lets the folds choose min_scans too.
    folds = [('min_scans 2, the other thresholds chosen on the other scenes',
              [g for g in GRID if g[2] == 2]), ('every threshold chosen, min_scans too', GRID)]
    picked = set()
    for title, grid in folds:
        chosen = {s: choose([r for r in records if r['scene'] != s], cfg, grid) for s in scenes}
        picked |= set(chosen.values())
        out += ['', f'Leave one scene out ({title}): '
                + '; '.join(f'{s[:20]}: {p}' for s, p in chosen.items()), '',
                markdown_table(headers, table(records, lambda r: chosen[r['scene']], cfg))]
    others = {default[:2] + (m, sub) + default[4:] for m in (1, 2) for sub in (True, False)}
    for policy in sorted(picked | {default} | others):
        out += ['', f'All scenes under {policy}:', '',
                markdown_table(headers, table(records, lambda r: policy, cfg))]
    return '\n'.join(out)


def main(argv: list[str] | None = None) -> None:
    """Run the scenes asked for, or report on every scene recorded."""
    ap = argument_parser(__spec__.name, __doc__)
    ap.add_argument('--root', type=Path, default=None, help='3DMatch benchmark folder')
    ap.add_argument('--scenes', nargs='*', default=None, help='scene folders (default: all)')
    ap.add_argument('--starts', type=int, default=0, help='start fragments a scene (0: all)')
    ap.add_argument('--voxel', type=float, default=0.05)
    ap.add_argument('--drift-deg', type=float, default=0.5)
    ap.add_argument('--drift-m', type=float, default=0.02)
    ap.add_argument('--drift-fraction', type=float, default=0.01)
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--output', type=Path, default=output_path('relocalize_sequences'),
                    help='folder of the records and the report (default: %(default)s)')
    ap.add_argument('--report', action='store_true', help='report on the recorded scenes')
    args = ap.parse_args(argv)
    if args.report:
        text = report(sorted(args.output.glob('relocalize_sequences_*.json')))
        write_text(args.output / 'relocalize_sequences.md', text + '\n')
        print(text)
        return
    root = args.root or shared_data_dir() / '3dmatch_benchmark'
    cfg = pipeline_config_from({'voxel_size': args.voxel})
    args.output.mkdir(parents=True, exist_ok=True)
    for scene in args.scenes or tdm.scenes(root):
        rng = np.random.default_rng([args.seed, sum(map(ord, scene))])
        records = run_scene(root, scene, args.starts, cfg, SequenceConfig(max_scans=LENGTH),
                            (args.drift_deg, args.drift_m, args.drift_fraction), rng)
        (args.output / f'relocalize_sequences_{scene}.json').write_text(
            json.dumps({'scene': scene, 'voxel': args.voxel,
                        'drift': [args.drift_deg, args.drift_m, args.drift_fraction],
                        'records': records}) + '\n', encoding='utf-8')


if __name__ == '__main__':
    main()
