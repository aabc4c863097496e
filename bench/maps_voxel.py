r"""
The voxel for a map: what a map finds as its voxel size changes, and which rule picks it.

Run by hand::

    .venv/bin/python -m bench.maps_voxel [--maps street floor lidar rooms] \
        [--street 0.15 0.2 0.3 0.8 2.4] [--floor 0.025 0.035 0.05 0.08 0.12 0.17 0.25] \
        [--lidar 0.05 0.1 0.12 0.15 0.2 0.3 0.5] [--rooms 0.05 0.1] \
        [--counts 2000 3000 5000 10000] [--per-scan N ...] [--per-room 5] \
        [--output out/bench/maps_voxel]

The maps and queries of ``bench.maps`` at the origin: ``street`` (KITTI, queries the 12 scans
between the four fused; right: 5 deg, 0.6 m) and ``floor`` (four 3DMatch rooms fused from
their even fragments; queries ``--per-room`` odd fragments a room; 15 deg, 0.3 m). ``lidar``:
the same floor map, queried by a simulated 32-beam spinning LiDAR standing level at the same
odd fragments' sensor positions and ray-cast on the rooms' odd fragments fused
(:mod:`bench.datasets.indoor_lidar`); right: 5 deg, 0.3 m, a LiDAR's rotation as the street's
and the floor's translation; on the floor and the LiDAR, of the logged pose or of where the
query settles on the map from it (:mod:`bench.map_truth`). ``rooms`` (not by default: its
map is 6.6 M raw points): the twelve-room growth floor of ``bench.maps``, its 15 queries
and 5 from outside the map.

At each voxel size the map is prepared (``load_map`` without a cache: read, grid, normals,
FPFH, index, places; its seconds) and every query registered, the feature cache cleared
before each, ``places`` (``register_clouds`` onto the prepared map) and, on the floor maps,
``whole`` (onto ``prepared.whole()``); the street is one place, registered whole either way.
Per map, voxel and way: found / wrong / refused, median and p90 seconds, and those seconds
over the ones of the map's own voxel (0.3 m on the street, 5 cm on the floor and for the
LiDAR) in the same run, with the load average before and after: the machine is shared.

The rule: for each ``--counts`` N, the voxel ``voxel_size_for`` gives each query scan so
that it keeps about N voxels (median and range over a map's queries); those medians are
measured too, so that a rule chosen on one map kind is judged on the others. ``--per-scan
N``: each query is also registered on the map prepared at the voxel its own scan gives, as
``cgags-relocalize MAP SCAN`` chooses it, one row for all. "scan voxels": the median of the
queries' voxels at the row's voxel. Writes ``<output>/maps_voxel.{md,json}``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import tempfile
import time

from bench import map_truth
from bench.common import argument_parser, write_text
from bench.datasets import indoor_lidar
from bench.maps import floor, four_rooms, growth_rooms, outcome, street, tally
from cgags_ros.config import pipeline_config_from
from cgags_ros.geometry import rotation_error_deg, translation_error, voxel_size_for
from cgags_ros.io.clouds import write_cloud
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import clear_feature_cache, register_clouds
from cgags_ros.pipeline.map import load_map
import numpy as np

VOXELS = {'street': (0.15, 0.2, 0.3, 0.8, 2.4),
          'floor': (0.025, 0.035, 0.05, 0.08, 0.12, 0.17, 0.25),
          'lidar': (0.05, 0.1, 0.12, 0.15, 0.2, 0.3, 0.5), 'rooms': (0.05, 0.1)}
OWN_VOXEL = {'street': 0.3, 'floor': 0.05, 'lidar': 0.05, 'rooms': 0.05}  # the seconds' unit
COUNTS = (2000, 3000, 5000, 10000)  # voxels a scan keeps under the rule
LIDAR_RIGHT = (5.0, 0.3)  # degrees, metres


def lidar(data: Path, per_room: int) -> dict:
    """Return the floor map with its queries replaced by LiDAR scans at the same sites."""
    built = floor(data, per_room, four_rooms(data))
    root = data / '3dmatch_benchmark'
    queries = []
    for scene in dict.fromkeys(s for s, _, _ in built['sites']):
        ks = [k for s, k, _ in built['sites'] if s == scene]
        place = next(p for s, _, p in built['sites'] if s == scene)
        queries += [(f'{scene[:20]} {k} lidar', scan, place @ pose)
                    for k, scan, pose in indoor_lidar.scans(root, scene, ks)]
    return {**built, 'queries': queries, 'right': LIDAR_RIGHT}


def curve(name: str, built: dict, voxels: list[float], ways: tuple[str, ...],
          out_dir: Path) -> list[dict]:
    """Prepare ``built``'s map at each voxel and register its queries ``ways``; a row each."""
    rows = []
    with tempfile.TemporaryDirectory(dir=out_dir) as tmp:
        path = Path(tmp) / 'map.ply'
        write_cloud(path, built['points'], built['normals'])
        for voxel in voxels:
            load = os.getloadavg()[0]
            cfg = pipeline_config_from({'voxel_size': voxel})
            prepared = load_map(path, cfg)
            seen = {way: [] for way in ways}
            for label, scan, truth in built['queries'] + built['outside']:
                for way in ways:
                    clear_feature_cache()
                    target = prepared.whole() if way == 'whole' else prepared
                    t0 = time.perf_counter()
                    result = register_clouds(scan, target, config=cfg)
                    seconds = time.perf_counter() - t0
                    got = outcome(result, truth, built['right'],
                                  built.get('settled', {}).get(label))
                    re, te = ((np.nan, np.nan) if truth is None else
                              (rotation_error_deg(result.transform, truth),
                               translation_error(result.transform, truth)))
                    seen[way].append({'query': label, 'outcome': got, 's': seconds, 're': re,
                                      'te': te, 'reason': result.reason,
                                      'outside': truth is None})
                    print(f'{name:6s} {voxel:5.3f} {label:32s} {way:6s} {got:8s} '
                          f'{seconds:6.2f} s  RE {re:6.2f} TE {te:6.3f}  '
                          f'{result.reason[:50]}', flush=True)
            rows.append({'map': name, 'voxel': voxel, 'queries': len(built['queries']),
                         'outside': len(built['outside']),
                         'scan_voxels': float(np.median([occupied(scan, voxel) for _, scan, _
                                                         in built['queries']])),
                         'map_points': len(prepared.features.points),
                         'map_places': (len(prepared.places) if prepared.places is not None
                                        else 0),
                         'prepare_s': prepared.load_s, 'load': [load, os.getloadavg()[0]],
                         **{way: summary(seen[way]) for way in ways}, 'per_query': seen})
    return rows


def per_scan(name: str, built: dict, n: int, ways: tuple[str, ...], out_dir: Path) -> dict:
    """
    Return one row: each query registered on the map at the voxel its own scan gives.

    As ``cgags-relocalize MAP SCAN`` chooses it: the voxel leaving the scan about ``n``
    voxels. Seconds and points are the medians over those maps.
    """
    groups: dict[float, list] = {}
    for query in built['queries'] + built['outside']:
        groups.setdefault(voxel_size_for(query[1], n), []).append(query)
    rows = [curve(name, {**built, 'queries': [q for q in qs if q[2] is not None],
                         'outside': [q for q in qs if q[2] is None]}, [v], ways, out_dir)[0]
            for v, qs in sorted(groups.items())]
    seen = {way: [x for r in rows for x in r['per_query'][way]] for way in ways}
    return {'map': name, 'voxel': float(np.median([v for v, qs in groups.items()
                                                   for _ in qs])),
            'per_scan': [n, min(groups), max(groups)], 'queries': len(built['queries']),
            'outside': len(built['outside']),
            **{key: float(np.median([r[key] for r in rows]))
               for key in ('scan_voxels', 'map_points', 'prepare_s')},
            'load': [rows[0]['load'][0], rows[-1]['load'][1]],
            **{way: summary(seen[way]) for way in ways}, 'per_query': seen}


def occupied(points: np.ndarray, voxel: float) -> int:
    """Return how many voxels of size ``voxel`` (metres) hold ``points``."""
    return len(np.unique(np.floor(points / voxel).astype(np.int64), axis=0))


def summary(seen: list[dict]) -> dict:
    """Return the counts and times of one way's queries, and the found ones' median errors."""
    found = [(x['re'], x['te']) for x in seen if x['outcome'] == 'found']
    return {**tally([(x['outcome'], x['s'], x['outside']) for x in seen]),
            'found_re': float(np.median([e[0] for e in found])) if found else float('nan'),
            'found_te': float(np.median([e[1] for e in found])) if found else float('nan')}


def scan_voxels(built: dict, counts: list[int]) -> dict[int, list[float]]:
    """
    Return, for each N of ``counts``, the voxel leaving each query scan about N voxels.

    An N that some scan has no more points than is left out: the rule cannot hold there.
    """
    return {n: [voxel_size_for(scan, n) for _, scan, _ in built['queries']]
            for n in counts if all(len(scan) > n for _, scan, _ in built['queries'])}


def rule_voxels(voxels: dict[int, list[float]]) -> list[float]:
    """Return the median voxel of each N, rounded as ``voxel_size_for`` rounds."""
    return [float(f'{np.median(v):.2g}') for v in voxels.values()]


def table(rows: list[dict], rules: dict[str, dict[int, list[float]]]) -> str:
    """Return the Markdown tables: the curves, then the voxel each rule gives each map."""
    lines = ['| map | voxel m | scan voxels | map points | found / wrong / refused: places · '
             'whole | median / p90 s (x own voxel) | prepare s (x own) | found: RE° / TE m '
             '| load |', '|---|---|---|---|---|---|---|---|---|']
    for r in rows:
        ways = [w for w in ('places', 'whole') if w in r]
        own = next((o for o in rows if o['map'] == r['map'] and 'per_scan' not in o
                    and o['voxel'] == OWN_VOXEL[r['map']]), r)
        counts = ' · '.join(f"{r[w]['found']} / {r[w]['wrong']} / {r[w]['refused']}"
                            + (f" ({r[w]['outside_refused']} of {r['outside']} outside refused)"
                               if r['outside'] else '') for w in ways)
        voxel = (f"{r['voxel']:g}" if 'per_scan' not in r else
                 f"each scan's, N = {r['per_scan'][0]:,}: {r['per_scan'][1]:g}–"
                 f"{r['per_scan'][2]:g}")
        lines.append(
            f"| {r['map']} | {voxel} | {r['scan_voxels']:,.0f} | {r['map_points']:,.0f} "
            f"| {counts} | {r['places']['median_s']:.2f} / {r['places']['p90_s']:.2f} "
            f"(x{r['places']['median_s'] / own['places']['median_s']:.2f}) "
            f"| {r['prepare_s']:.1f} (x{r['prepare_s'] / own['prepare_s']:.2f}) "
            f"| {r['places']['found_re']:.2f} / {r['places']['found_te']:.3f} "
            f"| {r['load'][0]:.1f}–{r['load'][1]:.1f} |")
    lines += ['', '| scan voxels N | ' + ' | '.join(f'{m}: median (range) m' for m in rules)
              + ' |', '|---|' + '---|' * len(rules)]
    for n in sorted({n for v in rules.values() for n in v}):
        cells = [f'{np.median(v[n]):.3g} ({min(v[n]):.3g}–{max(v[n]):.3g})'
                 if n in v else 'fewer points' for v in rules.values()]
        lines.append(f'| {n:,} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser('bench.maps_voxel', __doc__)
    parser.add_argument('--maps', nargs='+', default=['street', 'floor', 'lidar'],
                        choices=list(VOXELS))
    for name, voxels in VOXELS.items():
        parser.add_argument(f'--{name}', nargs='*', type=float, default=list(voxels),
                            metavar='V', help=f'voxel sizes of the {name} map (metres)')
    parser.add_argument('--counts', nargs='*', type=int, default=list(COUNTS), metavar='N',
                        help='scan voxels of the rule; their voxels are measured too')
    parser.add_argument('--per-scan', nargs='*', type=int, default=[], metavar='N',
                        help="also register each query at its own scan's voxel for N")
    parser.add_argument('--per-room', type=int, default=5, help='queries a room of the floor')
    parser.add_argument('--output', type=Path, default=Path('out/bench/maps_voxel'))
    args = parser.parse_args(argv)
    args.output.mkdir(parents=True, exist_ok=True)
    data = shared_data_dir()
    rows, rules = [], {}
    for name in args.maps:
        built = (street(data) if name == 'street' else
                 floor(data, args.per_room, four_rooms(data)) if name == 'floor' else
                 floor(data, args.per_room, *growth_rooms(data, 12)) if name == 'rooms' else
                 lidar(data, args.per_room))
        if name != 'street':
            built = map_truth.with_settled(built)
        rules[name] = scan_voxels(built, args.counts)
        voxels = sorted(set(getattr(args, name)) | set(rule_voxels(rules[name])))
        ways = ('places',) if name in ('street', 'rooms') else ('places', 'whole')
        rows += curve(name, built, voxels, ways, args.output)
        rows += [per_scan(name, built, n, ways, args.output) for n in args.per_scan]
        # Kept after each map: a long run that fails later loses nothing.
        write_text(args.output / 'maps_voxel.json',
                   json.dumps({'rows': rows, 'rules': {m: {str(n): v for n, v in r.items()}
                                                       for m, r in rules.items()}},
                              indent=1) + '\n')
    text = table(rows, rules)
    print(text)
    write_text(args.output / 'maps_voxel.md', text + '\n')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
