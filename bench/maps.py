r"""
Maps robots carry: a street and a floor of rooms built from the shared data, queries held out.

Run by hand::

    .venv/bin/python -m bench.maps [--maps street floor] [--per-room 5] [--kiss 3] \
        [--output out/bench/maps]

``street``: the 16 KITTI scans (``kitti/seq00_16scans``), every fourth (0, 4, 8, 12) fused by
the pseudo ground truth into scan 0's frame as the map; the 12 scans between are the queries,
in their own sensor frames (voxel 0.3 m, the README's LiDAR value; right: 5 deg, 0.6 m).
``floor``: the four 3DMatch scenes, each fused from its even fragments (normals facing the
fragment's sensor, as a mapper writes them), turned by a seeded yaw and placed as rooms 30 m
apart on one floor; the queries are ``--per-room`` odd fragments a room (seeded), in their own
frames (voxel 5 cm; right: 15 deg, 0.3 m). ``floor-growth`` registers the first room's
queries as the floor grows from one room to four (the cost curve).

Each map is also moved to UTM coordinates (512345.678 E, 5412345.678 N, 265.4 m up) and
queried again. Per map: found (valid and right), wrong (valid, not right), refused; median and
p90 seconds a query (``register_clouds`` onto the prepared map, the node's path); the map's
load cold (features computed and cached) and cached (memory-mapped), its points, the cache's
size and the process's resident memory after the load; and ``--kiss N`` queries of KISS-Matcher
on the same scan and raw map (its ``estimate``; no flag, every estimate counts). Writes
``<output>/maps.{md,json}``.
"""

from __future__ import annotations

import json
import multiprocessing
import os
from pathlib import Path
import queue
import resource
import tempfile
import time

from bench.baselines import kiss_matcher_estimate
from bench.common import argument_parser, write_text
from bench.datasets import threedmatch as tdm
from bench.datasets.rigs import kitti_scans
from cgags_ros.config import pipeline_config_from
from cgags_ros.frontend.features import estimate_normals
from cgags_ros.geometry import apply_transform, make_transform, rotation_error_deg
from cgags_ros.geometry import translation_error
from cgags_ros.io.clouds import write_cloud
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import register_clouds
from cgags_ros.pipeline.map import load_map
import numpy as np
from scipy.spatial.transform import Rotation

UTM = np.array([512345.678, 5412345.678, 265.4])
ROOM_SPACING = 30.0  # metres between the floor's rooms
KISS_TIMEOUT = 600.0  # seconds a KISS-Matcher estimate may take


def street(data: Path) -> dict:
    """Return the street map (points, normals None), its queries and the settings."""
    scans = kitti_scans(data, list(range(16)))
    truth = np.loadtxt(data / 'kitti' / 'seq00_16scans' / 'pseudo_gt.txt').reshape(-1, 4, 4)
    in_map = [0, 4, 8, 12]
    points = np.vstack([apply_transform(truth[k], scans[k]) for k in in_map])
    queries = [(f'scan {k}', scans[k], truth[k]) for k in range(16) if k not in in_map]
    return {'points': points, 'normals': None, 'queries': queries, 'voxel': 0.3,
            'right': (5.0, 0.6)}


def floor(data: Path, per_room: int, rooms: int = 4, seed: int = 0) -> dict:
    """Return the floor of ``rooms`` 3DMatch scenes, its queries (``per_room`` a room)."""
    root = data / '3dmatch_benchmark'
    cfg = pipeline_config_from({'voxel_size': 0.05})
    rng = np.random.default_rng(seed)
    points, normals, queries = [], [], []
    for r, scene in enumerate(tdm.scenes(root)[:rooms]):
        poses, fragments = tdm.fragment_poses(root, scene), tdm.Fragments(root, scene)
        place = make_transform(Rotation.from_euler('z', rng.uniform(0, 360),
                                                   degrees=True).as_matrix(),
                               [ROOM_SPACING * (r % 2), ROOM_SPACING * (r // 2), 0.0])
        for k, P in poses.items():
            if k % 2 == 0:
                points.append(apply_transform(place @ P, fragments[k]))
                normals.append(estimate_normals(fragments[k], 0.05, cfg.frontend)
                               @ (place @ P)[:3, :3].T)
        odd = sorted(k for k in poses if k % 2)
        for k in sorted(rng.choice(odd, min(per_room, len(odd)), replace=False)):
            queries.append((f'{scene[:20]} {k}', fragments[k], place @ poses[k]))
    return {'points': np.vstack(points), 'normals': np.vstack(normals), 'queries': queries,
            'voxel': 0.05, 'right': (15.0, 0.3)}


def run(name: str, built: dict, kiss: int, out_dir: Path) -> list[dict]:
    """Query ``built``'s map at the origin and in UTM; return a row of each."""
    rows = []
    for frame, offset in (('origin', np.zeros(3)), ('UTM', UTM)):
        cfg = pipeline_config_from({'voxel_size': built['voxel']})
        move = make_transform(np.eye(3), offset)
        with tempfile.TemporaryDirectory(dir=out_dir) as tmp:
            path, cache = Path(tmp) / 'map.ply', Path(tmp) / 'cache'
            write_cloud(path, built['points'] + offset, built['normals'])
            cold = load_map(path, cfg, cache)
            prepared = load_map(path, cfg, cache)
            cache_mb = sum(f.stat().st_size for f in Path(prepared.cache_path).iterdir()) / 2**20
            rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            outcomes, seconds, kiss_out = [], [], []
            for i, (label, scan, truth) in enumerate(built['queries']):
                t0 = time.perf_counter()
                result = register_clouds(scan, prepared, config=cfg)
                seconds.append(time.perf_counter() - t0)
                right = _right(result.transform, move @ truth, built['right'])
                outcomes.append('found' if result.valid and right else
                                'WRONG' if result.valid else 'refused')
                print(f'{name:6s} {frame:6s} {label:26s} {outcomes[-1]:8s} {seconds[-1]:.2f} s '
                      f'{result.reason[:70]}', flush=True)
                if i < kiss:
                    t0 = time.perf_counter()
                    T = _kiss(scan, built['points'] + offset, built['voxel'])
                    kiss_out.append((T is not None and _right(T, move @ truth, built['right']),
                                     time.perf_counter() - t0, T is None))
        rows.append({
            'map': name, 'frame': frame, 'queries': len(outcomes),
            'found': outcomes.count('found'), 'wrong': outcomes.count('WRONG'),
            'refused': outcomes.count('refused'), 'median_s': float(np.median(seconds)),
            'p90_s': float(np.percentile(seconds, 90)), 'raw_points': len(built['points']),
            'map_points': len(prepared.features.points), 'load_cold_s': cold.load_s,
            'load_cached_s': prepared.load_s, 'cache_mb': cache_mb, 'max_rss_mb': rss_mb,
            'kiss': [{'right': bool(r), 's': s, 'crashed': c} for r, s, c in kiss_out]})
    return rows


def _kiss(scan: np.ndarray, target: np.ndarray, voxel: float) -> np.ndarray | None:
    """
    Return KISS-Matcher's estimate, run in a forked process; None when that process died.

    It segfaults on some maps in UTM coordinates (after printing 'voxel coord is out of
    range' for every point, silenced here), which would end the benchmark.
    """
    ctx = multiprocessing.get_context('fork')
    out = ctx.Queue()
    child = ctx.Process(target=_kiss_child, args=(scan, target, voxel, out))
    child.start()
    try:
        T = out.get(timeout=KISS_TIMEOUT)
    except queue.Empty:
        T = None
    child.join(10)
    if child.is_alive():
        child.kill()
    return T


def _kiss_child(scan, target, voxel, out) -> None:
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)
    out.put(kiss_matcher_estimate(scan, target, voxel).transform)


def _right(T: np.ndarray, truth: np.ndarray, limits: tuple[float, float]) -> bool:
    return rotation_error_deg(T, truth) <= limits[0] and translation_error(T, truth) <= limits[1]


def table(rows: list[dict]) -> str:
    lines = ['| map | frame | raw / map points | found / wrong / refused | median / p90 s a query '
             '| load cold / cached s | cache MB | max RSS MB | KISS-Matcher right, median s |',
             '|---|---|---|---|---|---|---|---|---|']
    for r in rows:
        k = r['kiss']
        crashed = sum(x['crashed'] for x in k)
        kiss = (f"{sum(x['right'] for x in k)} of {len(k)}, "
                f"{np.median([x['s'] for x in k]):.1f}"
                + (f' ({crashed} crashed)' if crashed else '') if k else '')
        lines.append(f"| {r['map']} | {r['frame']} | {r['raw_points']:,} / {r['map_points']:,} "
                     f"| {r['found']} / {r['wrong']} / {r['refused']} of {r['queries']} "
                     f"| {r['median_s']:.2f} / {r['p90_s']:.2f} "
                     f"| {r['load_cold_s']:.1f} / {r['load_cached_s']:.2f} "
                     f"| {r['cache_mb']:.0f} | {r['max_rss_mb']:.0f} | {kiss} |")
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser('bench.maps', __doc__)
    parser.add_argument('--maps', nargs='+', default=['street', 'floor'],
                        choices=['street', 'floor', 'floor-growth'])
    parser.add_argument('--per-room', type=int, default=5, help='queries a room of the floor')
    parser.add_argument('--kiss', type=int, default=3, help='KISS-Matcher queries a map')
    parser.add_argument('--output', type=Path, default=Path('out/bench/maps'))
    args = parser.parse_args(argv)
    args.output.mkdir(parents=True, exist_ok=True)
    data = shared_data_dir()
    rows = []
    for name in args.maps:
        if name == 'street':
            rows += run('street', street(data), args.kiss, args.output)
        elif name == 'floor':
            rows += run('floor', floor(data, args.per_room), args.kiss, args.output)
        else:
            first_room = floor(data, args.per_room, rooms=1)['queries']
            for rooms in range(1, 5):
                built = floor(data, args.per_room, rooms)
                built['queries'] = first_room
                rows += [r for r in run(f'{rooms} rooms', built, 0, args.output)
                         if r['frame'] == 'origin']
    text = table(rows)
    print(text)
    write_text(args.output / 'maps.md', text + '\n')
    write_text(args.output / 'maps.json', json.dumps(rows, indent=1) + '\n')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
