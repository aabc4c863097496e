r"""
Maps robots carry: a street, floors of rooms and a campus built from the shared data.

Run by hand::

    .venv/bin/python -m bench.maps [--maps street floor campus growth] [--per-room 5] \
        [--floor-voxel 0.05] [--kiss 3] [--output out/bench/maps]

``street``: the 16 KITTI scans (``kitti/seq00_16scans``), every fourth (0, 4, 8, 12) fused by
the pseudo ground truth into scan 0's frame (normals facing each scan's sensor, as a mapper
writes them); the 12 between are the queries, in their own sensor frames (voxel 0.3 m, the
README's LiDAR value; right: 5 deg, 0.6 m). It also relocalizes three held-out scans with
odometry (``SEQUENCES``, each also reversed; drift as ``bench.relocalize_sequences``') with a
``Relocalizer``, until it answers.
``floor``: the four 3DMatch scenes, each fused from its even fragments (normals facing the
fragment's sensor, as a mapper writes them), turned by a seeded yaw and placed as rooms 30 m
apart on one floor; the queries are ``--per-room`` odd fragments a room (seeded), in their own
frames (voxel 5 cm, or ``--floor-voxel``; right: 15 deg, 0.3 m, of the logged pose or of where
the fragment settles on the map from it, :mod:`bench.map_truth`), and ``FLOOR_SEQUENCES`` runs of
three consecutive odd fragments a room, each also reversed, are relocalized as the street's
scans are. Each map is also moved to UTM coordinates (512345.678 E, 5412345.678 N, 265.4 m
up) and queried again, and ``--kiss N`` queries a map are given to KISS-Matcher on the same
scan and raw map (its ``estimate``; no flag, every estimate counts).

``campus``: the street among seven look-alikes and the floor as a building, 250 m apart on a
grid (6.0 M raw points), each turned by a seeded yaw; the look-alikes are the street
mirrored, and shrunk or enlarged (0.8, 1.25, 1.5) as is and mirrored: no query fits them
under a rigid motion. Queries: the street's, and the two small_gicp scans (in no map); its
sequences are the street's.

``growth``: floors of 1, 3, 6 and 12 rooms at the origin. The first three are three of the
scenes (redkitchen, home_at, hotel_uc); then the same three mirrored, then all six enlarged
by 1.25: rooms no query fits under any rigid motion, which look like the real ones. The
queries are the real rooms' (``--per-room`` each) and five fragments of the fourth scene
(mit_lab), which is in no map: they are right only when refused.

Every query is registered three ways in the same process, one after the other, the feature
cache cleared before each so that each pays for the scan's features: ``whole`` (the whole
prepared map, as before places: ``prepared.whole()``), ``places`` (``register_clouds`` onto the
prepared map: its places ranked, the best tested and registered) and ``hint`` (places, with
a hint of radius ``HINT_RADIUS`` around the true sensor position; the outside queries get the
first room's centre). Per map and way: found (valid and right), wrong (valid and not right,
or an outside query accepted), refused; median and p90 seconds; and the median over queries
of the whole map's time over the places' (the ratio). Per map: the load cold (features and
places computed and cached) and cached (memory-mapped), its points and places, the cache's
size and the process's peak resident memory; the places' tests (what put each place there,
its test's inliers, the one registered) a query. Writes ``<output>/maps.{md,json}``.
"""

from __future__ import annotations

import json
from pathlib import Path
import resource
import tempfile
import time

from bench import map_truth
from bench.baselines import kiss_matcher_forked
from bench.common import argument_parser, write_text
from bench.datasets import threedmatch as tdm
from bench.datasets.rigs import kitti_scans
from bench.relocalize_sequences import drifted_odometry
from cgags_ros.config import pipeline_config_from
from cgags_ros.frontend.features import estimate_normals
from cgags_ros.geometry import apply_transform, make_transform, rotation_error_deg
from cgags_ros.geometry import translation_error
from cgags_ros.io.clouds import read_cloud, write_cloud
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import clear_feature_cache, register_clouds
from cgags_ros.pipeline.hint import Hint
from cgags_ros.pipeline.map import load_map
from cgags_ros.relocalization.relocalizer import Relocalizer
import numpy as np
from scipy.spatial.transform import Rotation

UTM = np.array([512345.678, 5412345.678, 265.4])
ROOM_SPACING = 30.0  # metres between the floor's rooms
HINT_RADIUS = {'street': 10.0, 'floor': 2.0}  # metres around the true sensor position
WAYS = ('whole', 'places', 'hint')
GROWTH = (1, 3, 6, 12)  # rooms of the growth floors
ENLARGED = 1.25  # the growth floors' enlarged rooms
CAMPUS_SPACING = 250.0  # metres between the campus's blocks: more than a street's extent
LOOK_ALIKES = [(True, 1.0)] + [(m, s) for s in (0.8, 1.25, 1.5) for m in (False, True)]
SEQUENCES = [(1, 2, 3), (5, 6, 7), (9, 10, 11), (13, 14, 15)]  # held-out scans, and reversed
DRIFT = (0.5, 0.02, 0.01)  # degrees, metres and step fraction, as bench.relocalize_sequences
FLOOR_SEQUENCES = 4  # runs of three odd fragments a room of the four-room floor, and reversed


def street(data: Path) -> dict:
    """Return the street map (points, normals None), its queries and the settings."""
    scans = kitti_scans(data, list(range(16)))
    truth = np.loadtxt(data / 'kitti' / 'seq00_16scans' / 'pseudo_gt.txt').reshape(-1, 4, 4)
    in_map = [0, 4, 8, 12]
    cfg = pipeline_config_from({'voxel_size': 0.3})
    points = np.vstack([apply_transform(truth[k], scans[k]) for k in in_map])
    # Each scan's normals facing its sensor, as a mapper writes them.
    normals = np.vstack([estimate_normals(scans[k], 0.3, cfg.frontend) @ truth[k][:3, :3].T
                         for k in in_map])
    queries = [(f'scan {k}', scans[k], truth[k]) for k in range(16) if k not in in_map]
    runs = [ids for seq in SEQUENCES for ids in (seq, seq[::-1])]
    return {'points': points, 'normals': normals, 'queries': queries, 'outside': [],
            'voxel': 0.3, 'right': (5.0, 0.6), 'hint': HINT_RADIUS['street'],
            'rooms': 1,
            'sequences': [('scans ' + '-'.join(map(str, ids)), [scans[k] for k in ids],
                           [truth[k] for k in ids]) for ids in runs]}


def floor(data: Path, per_room: int, rooms: list[tuple[str, bool, float]],
          outside: str | None = None, seed: int = 0, sequences: int = 0,
          voxel: float = 0.05) -> dict:
    """
    Return a floor of ``rooms`` (scene, mirrored, scale) and its queries (``per_room`` a room).

    Only rooms as the scene was (not mirrored, scale 1) have queries; ``outside``: a scene
    of none of the rooms whose ``per_room`` fragments are queries from outside the map.
    ``sites``: (scene, fragment, the room's placement scene -> floor) of each query;
    ``spans``: each room's rows (start, stop) in ``points`` and ``normals``.
    ``sequences``: runs of three consecutive odd fragments a room (seeded apart from the
    queries), each also reversed, for the relocalizer. ``voxel``: the queries' (the map's
    normals are a mapper's, at 5 cm, whatever it is).
    """
    root = data / '3dmatch_benchmark'
    cfg = pipeline_config_from({'voxel_size': 0.05})
    rng, starts = np.random.default_rng(seed), np.random.default_rng(seed + 1)
    points, normals, queries, centres, sites, runs = [], [], [], [], [], []
    spans, rows = [], 0
    for r, (scene, mirrored, scale) in enumerate(rooms):
        poses, fragments = tdm.fragment_poses(root, scene), tdm.Fragments(root, scene)
        place = make_transform(Rotation.from_euler('z', rng.uniform(0, 360),
                                                   degrees=True).as_matrix(),
                               [ROOM_SPACING * (r % 4), ROOM_SPACING * (r // 4), 0.0])
        shape = np.diag([-scale if mirrored else scale, scale, scale, 1.0])
        room = []
        for k, P in poses.items():
            if k % 2 == 0:
                A = place @ shape @ P
                room.append(apply_transform(A, fragments[k]))
                side = estimate_normals(fragments[k], 0.05, cfg.frontend) @ np.linalg.inv(
                    A[:3, :3])
                normals.append(side / np.linalg.norm(side, axis=1, keepdims=True))
        points += room
        spans.append((rows, rows + sum(len(p) for p in room)))
        rows = spans[-1][1]
        centres.append(np.vstack(room).mean(axis=0))
        if mirrored or scale != 1.0:
            continue
        odd = sorted(k for k in poses if k % 2)
        for k in sorted(rng.choice(odd, min(per_room, len(odd)), replace=False)):
            queries.append((f'{scene[:20]} {k}', fragments[k], place @ poses[k]))
            sites.append((scene, int(k), place))
        for i in sorted(starts.choice(len(odd) - 2, min(sequences, len(odd) - 2),
                                      replace=False)):
            for ids in (odd[i:i + 3], odd[i:i + 3][::-1]):
                # Odometry is a rigid motion: 7-Scenes' logged rotations are not quite.
                runs.append((f'{scene[:12]} ' + '-'.join(map(str, ids)),
                             [fragments[k] for k in ids],
                             [tdm.nearest_rigid(place @ poses[k]) for k in ids]))
    away = []
    if outside:
        fragments = tdm.Fragments(root, outside)
        odd = sorted(k for k in tdm.fragment_poses(root, outside) if k % 2)
        away = [(f'{outside[:20]} {k}', fragments[k], None)
                for k in sorted(rng.choice(odd, min(per_room, len(odd)), replace=False))]
    return {'points': np.vstack(points), 'normals': np.vstack(normals), 'queries': queries,
            'outside': away, 'voxel': voxel, 'right': (15.0, 0.3), 'hint': HINT_RADIUS['floor'],
            'rooms': len(rooms), 'first_room': centres[0], 'sites': sites, 'sequences': runs,
            'spans': spans}


def campus(data: Path, seed: int = 0) -> dict:
    """Return the street among look-alike streets and the floor, as the module doc says."""
    own, rng = street(data), np.random.default_rng(seed)
    building = floor(data, 0, four_rooms(data), seed=seed)
    blocks, sides = [own['points']], [own['normals']]
    for b, (mirrored, scale) in enumerate(LOOK_ALIKES + [(None, 1.0)], start=1):
        place = make_transform(Rotation.from_euler('z', rng.uniform(0, 360),
                                                   degrees=True).as_matrix(),
                               CAMPUS_SPACING * np.array([b % 3, b // 3, 0.0]))
        if mirrored is None:  # the last block: the building, its centre on the grid
            blocks.append(apply_transform(place, building['points']
                                          - building['points'].mean(axis=0)))
            sides.append(building['normals'] @ place[:3, :3].T)
            continue
        A = place @ np.diag([-scale if mirrored else scale, scale, scale, 1.0])
        blocks.append(apply_transform(A, own['points']))
        side = own['normals'] @ np.linalg.inv(A[:3, :3])  # normals turn by A's inverse transpose
        sides.append(side / np.linalg.norm(side, axis=1, keepdims=True))
    away = [(f'small_gicp {n}', read_cloud(data / 'lidar' / 'small_gicp' / f'{n}.ply'), None)
            for n in ('source', 'target')]
    return {**own, 'points': np.vstack(blocks), 'normals': np.vstack(sides), 'outside': away,
            'rooms': len(blocks), 'first_room': np.zeros(3)}


def four_rooms(data: Path) -> list[tuple[str, bool, float]]:
    """Return the four scenes as rooms, as they are."""
    return [(s, False, 1.0) for s in tdm.scenes(data / '3dmatch_benchmark')[:4]]


def growth_rooms(data: Path, rooms: int) -> tuple[list[tuple[str, bool, float]], str]:
    """Return the first ``rooms`` rooms of the growth floors, and the scene left outside."""
    scenes = tdm.scenes(data / '3dmatch_benchmark')[:4]
    real, outside = scenes[:3], scenes[3]
    shapes = ([(s, False, 1.0) for s in real] + [(s, True, 1.0) for s in real]
              + [(s, m, ENLARGED) for m in (False, True) for s in real])
    return shapes[:rooms], outside


def run(name: str, built: dict, kiss: int, out_dir: Path,
        frames: tuple[str, ...] = ('origin', 'UTM')) -> list[dict]:
    """Query ``built``'s map in each frame the three ways; return a row a frame."""
    rows = []
    for frame in frames:
        offset = UTM if frame == 'UTM' else np.zeros(3)
        cfg = pipeline_config_from({'voxel_size': built['voxel']})
        move = make_transform(np.eye(3), offset)
        with tempfile.TemporaryDirectory(dir=out_dir) as tmp:
            path, cache = Path(tmp) / 'map.ply', Path(tmp) / 'cache'
            write_cloud(path, built['points'] + offset, built['normals'])
            cold_s = load_map(path, cfg, cache).load_s
            prepared = load_map(path, cfg, cache)
            cache_mb = sum(f.stat().st_size for f in Path(prepared.cache_path).iterdir()) / 2**20
            rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            seen, tested = {way: [] for way in WAYS}, []
            kiss_out = []
            queries = built['queries'] + built['outside']
            for i, (label, scan, truth) in enumerate(queries):
                truth = None if truth is None else move @ truth
                settled = built.get('settled', {}).get(label)
                settled = None if settled is None else move @ settled
                where = built.get('first_room', np.zeros(3)) + offset if truth is None else (
                    truth[:3, 3])
                hint = Hint(where, built['hint'])
                for way in WAYS:
                    clear_feature_cache()
                    target = prepared.whole() if way == 'whole' else prepared
                    t0 = time.perf_counter()
                    result = register_clouds(scan, target, config=cfg,
                                             hint=hint if way == 'hint' else None)
                    seconds = time.perf_counter() - t0
                    got = outcome(result, truth, built['right'], settled)
                    seen[way].append((got, seconds, truth is None))
                    if way == 'places':
                        tested.append({'query': label, 'outcome': got,
                                       **_tests(result.stats.get('places'))})
                    print(f'{name:9s} {frame:6s} {label:26s} {way:6s} {got:8s} '
                          f'{seconds:5.2f} s {result.reason[:60]}', flush=True)
                if i < kiss and truth is not None:
                    t0 = time.perf_counter()
                    T = kiss_matcher_forked(scan, built['points'] + offset, built['voxel'])
                    kiss_out.append((T is not None and right(T, truth, built['right'], settled),
                                     time.perf_counter() - t0, T is None))
            settled_runs = built.get('settled_sequences')
            runs = [relocalize(prepared, cfg, label, scans, [move @ T for T in truth],
                               built['right'], np.random.default_rng(i),
                               None if settled_runs is None else
                               [move @ S for S in settled_runs[i]])
                    for i, (label, scans, truth) in enumerate(built.get('sequences', []))]
        rows.append({
            'map': name, 'frame': frame, 'rooms': built['rooms'], 'sequences': runs,
            'voxel': built['voxel'],
            'queries': len(built['queries']), 'outside': len(built['outside']),
            'raw_points': len(built['points']), 'map_points': len(prepared.features.points),
            'map_places': len(prepared.places) if prepared.places is not None else 0,
            'load_cold_s': cold_s, 'load_cached_s': prepared.load_s,
            'cache_mb': cache_mb, 'max_rss_mb': rss_mb,
            **{way: tally(seen[way]) for way in WAYS},
            'ratio': float(np.median([w[1] / p[1] for w, p in zip(seen['whole'],
                                                                  seen['places'])])),
            'kiss': [{'right': bool(r), 's': s, 'crashed': c} for r, s, c in kiss_out],
            'tests': tested})
    return rows


def relocalize(prepared, cfg, label: str, scans: list[np.ndarray], truth: list[np.ndarray],
               limits: tuple[float, float], rng: np.random.Generator,
               settled: list[np.ndarray] | None = None) -> dict:
    """
    Relocalize ``scans`` with drifted odometry; return the outcome of the last scan used.

    ``settled``: where each scan settles on the map (:mod:`bench.map_truth`); the answer is
    right within ``limits`` of the last scan's logged truth or of its settled one.
    """
    reloc = Relocalizer(prepared, cfg)
    clear_feature_cache()
    t0 = time.perf_counter()
    for scan, odom in zip(scans, drifted_odometry(truth, rng, *DRIFT)):
        answer = reloc.add(scan, odom)
        if answer.done:
            break
    seconds, used = time.perf_counter() - t0, len(reloc.scans)
    got = ('refused' if not answer.confirmed else
           'found' if right(answer.transform, truth[used - 1], limits,
                            None if settled is None else settled[used - 1]) else 'WRONG')
    print(f'sequence {label:16s} {got:8s} after {used} scans {seconds:5.2f} s '
          f'{answer.reason[:60]}', flush=True)
    return {'label': label, 'outcome': got, 'scans': used, 's': seconds}


def _tests(places: dict | None) -> dict:
    """
    Return what the places' tests scored (``result.stats['places']``; empty: whole map).

    An untested consensus place's inliers are None; ``consensus`` is what the whole map's
    search found in it; ``whole_map``: the whole map's matches' support of the pose and of
    the consensus (None without a consensus).
    """
    if not places:
        return {'by': [], 'inliers': [], 'consensus': None, 'registered': None,
                'whole_map': None}
    return {'by': [p['by'] for p in places['ranked']],
            'inliers': [p['tested_inliers'] for p in places['ranked']],
            'consensus': places['consensus_inliers'], 'registered': places['registered'],
            'whole_map': places['whole_map_support']}


def outcome(result, truth: np.ndarray | None, limits: tuple[float, float],
            settled: np.ndarray | None = None) -> str:
    """
    Return 'found', 'WRONG' or 'refused' for ``result`` (``limits``: degrees, metres).

    ``settled``: where the query settles on the map from ``truth`` (:mod:`bench.map_truth`);
    a pose within the limits of either is right.
    """
    if truth is None:  # a query from outside the map: right only when refused
        return 'WRONG' if result.valid else 'refused'
    if not result.valid:
        return 'refused'
    return 'found' if right(result.transform, truth, limits, settled) else 'WRONG'


def tally(seen: list[tuple[str, float, bool]]) -> dict:
    """Return the counts and times of one way's queries (``seen``: outcome, s, outside)."""
    seconds = [s for _, s, _ in seen]
    away = [s for _, s, out in seen if out]
    return {'found': sum(o == 'found' for o, _, _ in seen),
            'wrong': sum(o == 'WRONG' for o, _, _ in seen),
            'refused': sum(o == 'refused' for o, _, out in seen if not out),
            'outside_refused': sum(o == 'refused' for o, _, out in seen if out),
            'median_s': float(np.median(seconds)), 'p90_s': float(np.percentile(seconds, 90)),
            'outside_median_s': float(np.median(away)) if away else float('nan')}


def right(T: np.ndarray, truth: np.ndarray, limits: tuple[float, float],
          settled: np.ndarray | None = None) -> bool:
    """Return whether ``T`` is within ``limits`` (degrees, metres) of ``truth`` or ``settled``."""
    return any(rotation_error_deg(T, P) <= limits[0] and translation_error(T, P) <= limits[1]
               for P in (truth, settled) if P is not None)


def table(rows: list[dict]) -> str:
    """Return the Markdown tables of ``rows``: outcomes and times, then the maps."""
    lines = ['| map (voxel m) | frame | queries (+ outside) | found / wrong / refused: whole · '
             'places · hint | outside refused (median s): whole · places | median / p90 s: '
             'whole · places · hint | whole / places time (median) |',
             '|---|---|---|---|---|---|---|']
    for r in rows:
        counts = ' · '.join(f"{r[w]['found']} / {r[w]['wrong']} / {r[w]['refused']}"
                            for w in WAYS)
        outside = (' · '.join(f"{r[w]['outside_refused']} ({r[w]['outside_median_s']:.2f} s)"
                              for w in WAYS[:2]) if r['outside'] else '')
        times = ' · '.join(f"{r[w]['median_s']:.2f} / {r[w]['p90_s']:.2f}" for w in WAYS)
        queries = f"{r['queries']}" + (f" (+ {r['outside']})" if r['outside'] else '')
        lines.append(f"| {r['map']} ({r['voxel']:g}) | {r['frame']} | {queries} | {counts} "
                     f"| {outside} | {times} | {r['ratio']:.2f} |")
    lines += ['', '| map | frame | raw / map points | places | load cold / cached s | cache MB '
              '| max RSS MB | KISS-Matcher right, median s |', '|---|---|---|---|---|---|---|---|']
    for r in rows:
        k = r['kiss']
        crashed = sum(x['crashed'] for x in k)
        kiss = (f"{sum(x['right'] for x in k)} of {len(k)}, "
                f"{np.median([x['s'] for x in k]):.1f}"
                + (f' ({crashed} crashed)' if crashed else '') if k else '')
        lines.append(f"| {r['map']} | {r['frame']} | {r['raw_points']:,} / {r['map_points']:,} "
                     f"| {r['map_places']:,} | {r['load_cold_s']:.1f} / {r['load_cached_s']:.2f} "
                     f"| {r['cache_mb']:.0f} | {r['max_rss_mb']:.0f} | {kiss} |")
    runs = [r for r in rows if r['sequences']]
    if runs:
        lines += ['', '| map | frame | sequences | found / wrong / refused | scans used (median) '
                  '| median / max s |', '|---|---|---|---|---|---|']
    for r in runs:
        got, s = [x['outcome'] for x in r['sequences']], [x['s'] for x in r['sequences']]
        lines.append(f"| {r['map']} | {r['frame']} | {len(got)} | {got.count('found')} / "
                     f"{got.count('WRONG')} / {got.count('refused')} | "
                     f"{np.median([x['scans'] for x in r['sequences']]):.0f} | "
                     f'{np.median(s):.2f} / {max(s):.2f} |')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser('bench.maps', __doc__)
    parser.add_argument('--maps', nargs='+', default=['street', 'floor'],
                        choices=['street', 'floor', 'campus', 'growth'])
    parser.add_argument('--per-room', type=int, default=5, help='queries a room of the floor')
    parser.add_argument('--floor-voxel', type=float, default=0.05,
                        help="the four-room floor's voxel (m)")
    parser.add_argument('--kiss', type=int, default=3, help='KISS-Matcher queries a map')
    parser.add_argument('--output', type=Path, default=Path('out/bench/maps'))
    args = parser.parse_args(argv)
    args.output.mkdir(parents=True, exist_ok=True)
    data = shared_data_dir()
    rows = []
    for name in args.maps:
        if name == 'street':
            rows += run('street', street(data), args.kiss, args.output)
        elif name == 'campus':
            rows += run('campus', campus(data), args.kiss, args.output)
        elif name == 'floor':
            built = floor(data, args.per_room, four_rooms(data), sequences=FLOOR_SEQUENCES,
                          voxel=args.floor_voxel)
            rows += run('floor', map_truth.with_settled(built), args.kiss, args.output)
        else:
            for rooms in GROWTH:
                shapes, outside = growth_rooms(data, rooms)
                built = map_truth.with_settled(floor(data, args.per_room, shapes, outside))
                rows += run(f'{rooms} rooms', built, 0, args.output, ('origin',))
                # Kept after each map: a long run that fails later loses nothing.
                write_text(args.output / 'maps.json', json.dumps(rows, indent=1) + '\n')
        write_text(args.output / 'maps.json', json.dumps(rows, indent=1) + '\n')
    text = table(rows)
    print(text)
    write_text(args.output / 'maps.md', text + '\n')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
