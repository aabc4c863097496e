#!/usr/bin/env python3
"""
Render the README's picture: a real pair of LiDAR scans before and after registration.

    python scripts/render_figure.py                 # writes docs/images/registration_pair.png
    python scripts/render_figure.py --output /tmp/pair.png

The pair is the committed fixture test/fixtures/small_gicp (two consecutive scans of a
spinning LiDAR, with ground truth), so the picture renders from a bare clone. Those scans
are only half a metre apart; to show that no initial guess is used, the source is first
moved by a known motion (``--yaw-deg``, ``--shift``), which the ground truth then includes.
``register_clouds`` registers the moved source onto the target; the left panel draws the
source as given (the identity), the right one the source under the estimate, both from
above. The caption gives the rotation and translation error against the ground truth.
Other clouds (any format ``cgags_ros.io`` reads) with ``--source``, ``--target`` and
``--gt`` (4x4 text, p_target = T p_source; optional).

Prints one JSON line: the errors, whether the result is valid, and the output path.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import sys

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FIXTURE = REPO / 'test' / 'fixtures' / 'small_gicp'
DEFAULT_OUTPUT = REPO / 'docs' / 'images' / 'registration_pair.png'
SOURCE_COLOUR, TARGET_COLOUR = '#e8710a', '#1a73e8'


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser."""
    p = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0])
    p.add_argument('--output', type=Path, default=DEFAULT_OUTPUT, help='PNG to write')
    p.add_argument('--source', type=Path, default=FIXTURE / 'source.npy')
    p.add_argument('--target', type=Path, default=FIXTURE / 'target.npy')
    p.add_argument('--gt', type=Path, default=FIXTURE / 'T_target_source.txt',
                   help="4x4 ground truth (p_target = T p_source); 'none' for no errors")
    p.add_argument('--voxel-size', type=float, default=0.4, help='metres (LiDAR: 0.3-0.5)')
    p.add_argument('--yaw-deg', type=float, default=135.0,
                   help='rotation about z applied to the source before registering')
    p.add_argument('--shift', type=float, nargs=2, default=(12.0, -8.0), metavar=('X', 'Y'),
                   help='translation (metres) applied to the source with that rotation')
    p.add_argument('--view-radius', type=float, default=30.0,
                   help='metres around the target origin that are drawn')
    p.add_argument('--max-points', type=int, default=12000,
                   help='points drawn per cloud (a random subset; keeps the PNG small)')
    return p


def known_motion(yaw_deg: float, shift: tuple[float, float]) -> np.ndarray:
    """Return the 4x4 motion applied to the source: a yaw and a shift in x, y."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    X = np.eye(4)
    X[:2, :2] = [[c, -s], [s, c]]
    X[:2, 3] = shift
    return X


def subset(points: np.ndarray, centre: np.ndarray, radius: float, count: int,
           rng: np.random.Generator) -> np.ndarray:
    """Return at most ``count`` of the points within ``radius`` (x-y) of ``centre``."""
    near = points[np.hypot(*(points[:, :2] - centre[:2]).T) <= radius]
    if len(near) > count:
        near = near[np.sort(rng.choice(len(near), count, replace=False))]
    return near


def render(output: Path, source: np.ndarray, target: np.ndarray, transform: np.ndarray,
           caption: str, view_radius: float, max_points: int) -> None:
    """Draw the before/after panels (top-down) and write them to ``output``."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from cgags_ros.geometry import apply_transform

    rng = np.random.default_rng(0)
    centre = np.zeros(3)
    target_drawn = subset(target, centre, view_radius, max_points, rng)
    before = subset(source, centre, view_radius, max_points, rng)
    after = subset(apply_transform(transform, source), centre, view_radius, max_points, rng)
    panels = (('before: the source as given', before),
              ('after: the source under the estimate', after))
    fig, axes = plt.subplots(1, 2, figsize=(9.0, 5.0), sharex=True, sharey=True)
    for ax, (title, drawn) in zip(axes, panels):
        ax.scatter(target_drawn[:, 0], target_drawn[:, 1], s=0.4, c=TARGET_COLOUR,
                   linewidths=0, rasterized=True, label='target')
        # Half transparent, so that the target shows through where the two overlap.
        ax.scatter(drawn[:, 0], drawn[:, 1], s=0.4, c=SOURCE_COLOUR, alpha=0.5,
                   linewidths=0, rasterized=True, label='source')
        ax.set_title(title, fontsize=10)
        ax.set_aspect('equal')
        ax.set_xlim(-view_radius, view_radius)
        ax.set_ylim(-view_radius, view_radius)
        ax.set_xlabel('x [m]', fontsize=8)
        ax.tick_params(labelsize=7)
        legend = ax.legend(loc='upper right', markerscale=8, fontsize=7, frameon=True)
        # legend_handles since matplotlib 3.7; Jazzy's apt matplotlib (3.6) has legendHandles.
        handles = getattr(legend, 'legend_handles', None) or legend.legendHandles
        for handle in handles:
            handle.set_alpha(1.0)
    axes[0].set_ylabel('y [m] (target frame, from above)', fontsize=8)
    fig.text(0.5, 0.012, caption, ha='center', va='bottom', fontsize=8, wrap=True)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    output.parent.mkdir(parents=True, exist_ok=True)
    # No software/date metadata: the same inputs give the same file.
    fig.savefig(output, dpi=110, metadata={'Software': None})
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """Register the pair, render the figure and print the summary line."""
    args = build_parser().parse_args(argv)
    sys.path.insert(0, str(REPO))  # the repository's package when run from a clone
    from cgags_ros.pipeline import register_clouds
    from cgags_ros.geometry import apply_transform, rotation_error_deg, translation_error
    from cgags_ros.io.clouds import read_cloud

    source, target = read_cloud(args.source), read_cloud(args.target)
    motion = known_motion(args.yaw_deg, tuple(args.shift))
    moved = apply_transform(motion, source)
    result = register_clouds(moved, target, voxel_size=args.voxel_size)
    summary = {'valid': bool(result.valid), 'reason': result.reason,
               'voxel_size': args.voxel_size, 'output': str(args.output)}
    caption = (f'Two LiDAR scans ({len(source)} / {len(target)} points), voxel '
               f'{args.voxel_size:g} m; the source was first turned {args.yaw_deg:g} deg and '
               f'shifted {math.hypot(*args.shift):.1f} m (no initial guess is used).')
    if str(args.gt).lower() != 'none':
        # The ground truth maps the original source; the moved one is undone first.
        T_gt = np.loadtxt(args.gt).reshape(4, 4) @ np.linalg.inv(motion)
        re, te = rotation_error_deg(result.transform, T_gt), translation_error(
            result.transform, T_gt)
        summary.update(re_deg=re, te_m=te)
        caption += (f'\nError against the ground truth: rotation {re:.2f} deg, translation '
                    f'{te:.2f} m.')
    if not result.valid:
        caption += f' The result was rejected: {result.reason}.'
    render(args.output, moved, target, result.transform, caption, args.view_radius,
           args.max_points)
    print(json.dumps(summary))
    return 0


if __name__ == '__main__':
    sys.exit(main())
