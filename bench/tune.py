r"""
``cgags-tune`` on the bundled bags, started from a voxel size ten times too large and too small.

Run by hand from the repository root, nothing else running (minutes a start)::

    .venv/bin/python -m bench.tune [--bags bunny lidar redkitchen] [--trials 30] \
        [--factors 10 0.1] [--moved [--sensors]] [--consistency] [--live] \
        [--output out/bench/tune]

For every bag and start (the documented voxel size of the bag, the one ``cgags-demo``
chooses, times each factor) it runs ``cgags-tune`` in a fresh study (seed 0, hold-out 0.3,
at most ``--trials`` trials; success as ``cgags-demo`` counts it), then replays the bag
with the written ``params.yaml`` (``cgags-replay --config``) and prints the best settings,
the pairs right and valid and valid but wrong on the whole bag, and the trial that first
reached the best tuned-on score.

``--moved`` tunes, beside each bag, a copy whose clouds are moved out of their sensor frame
(:func:`moved_bag`, written to ``<output>/bags``): the free-space gate then refuses right
poses on the defaults, and the tuning must find the documented fix. For every bag the
defaults (the documented voxel, nothing else) are replayed too, with their free-space
refusals counted. ``--sensors`` tunes the moved copies alone, with the sensors' positions
fixed (``cgags-tune --set frontend.source_sensor=... --set frontend.target_sensor=...``: the
motion's translation, where the sensor sits in every moved cloud's frame); their defaults
are then the documented voxel with those positions. The unmoved bags need no position: their
sensors sit at their clouds' origins, the default.

``--consistency`` tunes without the ground truth (``--ignore-ground-truth``: pairs judged
by consistency), the replay still judging against it. ``--live`` also replays the bag
through a register_node started with ``params.yaml`` over DDS (``cgags-replay --live``,
ROS domain 43, localhost), as a user would after tuning.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys
from typing import Sequence

from bench.common import argument_parser, LIMITS, markdown_table
from cgags_ros.io.shared_data import shared_data_dir
import numpy as np

DOCUMENTED = {'bunny': 0.0024, 'redkitchen': 0.05, 'lidar': 0.3}  # metres, README's table


def motion(bag: str) -> np.ndarray:
    """
    Return the rigid 4x4 transform :func:`moved_bag` moves ``bag``'s clouds by.

    The translation is a hundred documented voxels, so that it is far on every bag's scale;
    it is where the sensor sits in every moved cloud's frame.
    """
    from scipy.spatial.transform import Rotation

    from cgags_ros.geometry import make_transform

    return make_transform(Rotation.from_euler('xyz', [70, -40, 120], degrees=True).as_matrix(),
                          100 * DOCUMENTED[bag] * np.array([1.6, -1.2, 1.0]))


def sensor_settings(bag: str) -> list[str]:
    """Return the ``--set`` items that fix both sensors' positions in ``bag``'s moved copy."""
    position = [float(c) for c in motion(bag)[:3, 3]]
    return [f'frontend.{role}_sensor={position}' for role in ('source', 'target')]


def moved_bag(bag: str, path: Path) -> Path:
    """
    Write ``bag`` with every cloud moved by :func:`motion` (its ground truth moved with it).

    As a tool that re-centres clouds would: the sensor is no longer at the clouds' origin.
    """
    from cgags_ros.geometry import apply_transform
    from cgags_ros.io.bag import read_messages, write_bag
    from cgags_ros.io.pointcloud2 import pointcloud2_to_xyz, pose_to_transform

    if path.exists():
        return path
    moved = motion(bag)
    messages = []
    for rec in read_messages(shared_data_dir() / 'bags' / bag,
                             ['/source_cloud', '/target_cloud', '/ground_truth']):
        if rec.error:
            continue
        if rec.topic == '/ground_truth':
            truth = pose_to_transform(rec.msg)
            messages.append((rec.topic, rec.stamp_ns, 'moved',
                             moved @ truth @ np.linalg.inv(moved)))
        else:
            messages.append((rec.topic, rec.stamp_ns, rec.frame_id,
                             apply_transform(moved, pointcloud2_to_xyz(rec.msg))))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_bag(path, messages)
    return path


def run_start(bag: Path, voxel: float, trials: int, out: Path, consistency: bool,
              fixed: Sequence[str] = ()) -> dict:
    """Run ``cgags-tune`` on ``bag`` from ``voxel`` in a fresh study; return its summary."""
    max_re, max_te = LIMITS[_kind(bag)]
    (out / 'study.db').unlink(missing_ok=True)
    subprocess.run([sys.executable, '-m', 'cgags_ros.tools.tune', str(bag),
                    '--voxel-size', f'{voxel:g}', '--trials', str(trials), '--output', str(out),
                    '--quiet', '--max-re-deg', str(max_re), '--max-te', str(max_te)]
                   + (['--ignore-ground-truth'] if consistency else [])
                   + [arg for item in fixed for arg in ('--set', item)], check=True)
    return json.loads((out / 'summary.json').read_text(encoding='utf-8'))


def _kind(bag: Path) -> str:
    """Return the bundled bag a bag is (or is moved from)."""
    return bag.name.removesuffix('_moved')


def replay_params(bag: Path, settings: list[str], out: Path, live: bool
                  ) -> tuple[int, int, int, int]:
    """Replay ``bag`` with ``settings`` (offline or live): right, wrong, pairs, free space."""
    max_re, max_te = LIMITS[_kind(bag)]
    subprocess.run([sys.executable, '-m', 'cgags_ros.tools.replay', str(bag), *settings,
                    '--output', str(out), '--quiet', '--max-re-deg', str(max_re),
                    '--max-te', str(max_te)] + ['--live'] * live, check=True)
    rows = json.loads((out / 'results.json').read_text(encoding='utf-8'))['pairs']
    return (sum(bool(r['success']) for r in rows),
            sum(bool(r['valid'] and not r['success']) for r in rows), len(rows),
            sum((r.get('refusal') or {}).get('code') == 'free_space' for r in rows))


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('--bags', nargs='+', default=sorted(DOCUMENTED))
    parser.add_argument('--trials', type=int, default=30)
    parser.add_argument('--factors', type=float, nargs='+', default=[10.0, 0.1])
    parser.add_argument('--moved', action='store_true',
                        help="also each bag's clouds moved out of their sensor frame")
    parser.add_argument('--sensors', action='store_true',
                        help="only the moved copies, the sensors' positions fixed (cgags-tune "
                        '--set frontend.source_sensor/target_sensor)')
    parser.add_argument('--consistency', action='store_true',
                        help='tune without the ground truth (judged by consistency)')
    parser.add_argument('--live', action='store_true',
                        help='also replay params.yaml through a register_node over DDS')
    parser.add_argument('--output', type=Path, default=Path('out/bench/tune'))
    args = parser.parse_args(argv)
    if args.live:
        os.environ.update(ROS_DOMAIN_ID='43', ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    bags = [shared_data_dir() / 'bags' / bag for bag in args.bags]
    if args.moved or args.sensors:  # first: they need the fix the defaults lack
        bags = [moved_bag(bag, args.output / 'bags' / f'{bag}_moved')
                for bag in args.bags] + ([] if args.sensors else bags)
    suffix = '_consistency' * args.consistency + '_sensors' * args.sensors
    rows = []
    for bag in bags:
        voxel = DOCUMENTED[_kind(bag)]
        fixed = sensor_settings(_kind(bag)) if args.sensors else []
        right, wrong, pairs, free = replay_params(
            bag, ['--voxel-size', f'{voxel:g}'] + [a for s in fixed for a in ('--set', s)],
            args.output / f'{bag.name}_defaults{suffix}', False)
        defaults = f'{right}/{pairs}, {wrong} wrong, {free} free space'
        for factor in args.factors:
            out = args.output / f'{bag.name}_x{factor:g}{suffix}'
            summary = run_start(bag, voxel * factor, args.trials, out, args.consistency, fixed)
            params = ['--config', str(out / 'params.yaml')]
            right, wrong, pairs, free = replay_params(bag, params, out / 'replay', live=False)
            live = (replay_params(bag, params, out / 'replay_live', live=True)
                    if args.live else None)
            scored = [t for t in summary['trials'] if 'right' in t and 'repeat_of' not in t]
            top = max(t['right'] - 1000 * t['wrong'] for t in scored)
            rows.append((bag.name, f'{voxel * factor:g}', f'{voxel:g}', defaults,
                         ', '.join(f'{k}={v}' for k, v in summary['written'].items()),
                         f'{right}/{pairs}', wrong, free,
                         f'{live[0]}/{live[2]}, {live[1]} wrong' if live else '-',
                         next(t['number'] for t in scored
                              if t['right'] - 1000 * t['wrong'] == top),
                         f"{len(scored)} (+{len(summary['trials']) - len(scored)} repeats)",
                         '; '.join(f"{s['trial']}: {', '.join(s['opened'])}"
                                   for s in summary['stages']) or '-',
                         summary['warning'] or summary['guard'] or '-'))
            print(rows[-1], flush=True)
    print(markdown_table(('bag', 'start voxel', 'documented voxel', 'defaults (whole bag)',
                          'written settings', 'right and valid (whole bag)', 'valid but wrong',
                          'free space refusals', 'live over DDS',
                          'first trial at the best tuned-on score', 'trials',
                          'stages (trial: opened)', 'warning'), rows))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
