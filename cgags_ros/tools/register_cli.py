"""
``cgags-register``: register two point cloud files with no initial guess.

Thin edge tool: reads the files, calls :func:`cgags_ros.pipeline.register_clouds`, prints or
writes the result. Errors the user can fix (unreadable file, bad option value) are one line
on stderr and exit status 2; no traceback.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys
from typing import Sequence

import numpy as np

from .cli import EXIT_ERROR, Parser, run_cli
from ..config import fields
from ..config.node import pipeline_from_keys
from ..config.pipeline import load_yaml, PipelineConfig
from ..errors import InvalidInputError
from ..geometry import apply_transform, rotation_error_deg
from ..io.clouds import read_cloud, SUFFIXES, write_cloud

PROG = 'cgags-register'
EXIT_INVALID = 1  # registration ran but the estimate failed a validity gate

EPILOG = f"""\
point cloud formats: {', '.join(SUFFIXES)} (x, y, z in metres).
The transform maps SOURCE into the TARGET frame: p_target = R p_source + t.
Exit status: 0 valid estimate, {EXIT_INVALID} estimate marked invalid (see 'refusal': code and
message, docs/refusals.md),
{EXIT_ERROR} unreadable input or bad option.
example: cgags-register bun045.ply bun000.ply --voxel-size 0.003 --set refine.method=gicp
levelled LiDAR scans (yaw + translation only): cgags-register a.ply b.ply --voxel-size 0.3 --4dof
A scan in a prior map file (a map fused from many views, its normals, a feature cache):
use cgags-relocalize MAP SCAN [SCAN ...], which prepares the map as the node does.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog=PROG, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
        description='Globally register SOURCE onto TARGET (FPFH correspondences + CGAGS, '
                    'then optional ICP/GICP refinement).')
    parser.add_argument('source', type=Path, help='cloud to move (SOURCE frame)')
    parser.add_argument('target', type=Path, help='fixed cloud (TARGET frame)')
    add_config_options(parser)
    parser.add_argument('--no-refine', action='store_true',
                        help='skip ICP/GICP refinement (same as --set refine.method=none)')
    parser.add_argument('--4dof', action='store_true', dest='yaw_only',
                        help='levelled clouds: solve yaw about the gravity axis + translation '
                             'only (same as --set core.motion_model=4dof)')
    parser.add_argument('--gravity', type=float, nargs=3, metavar=('X', 'Y', 'Z'),
                        help="with --4dof: the up axis in both clouds' frames (default 0 0 1; "
                             'any nonzero length)')
    parser.add_argument('--json', action='store_true',
                        help='print the full result as JSON on stdout instead of text')
    parser.add_argument('--output', type=Path, metavar='ALIGNED',
                        help='write the source moved into the target frame (any format above)')
    parser.add_argument('--plot', type=Path, metavar='PNG',
                        help='save before/after overlay views (PNG, matplotlib)')
    return parser


def add_config_options(parser: argparse.ArgumentParser, voxel_default: str = '') -> None:
    """
    Add the options that make the pipeline's configuration (shared by the tools).

    ``voxel_default``: how the tool chooses the voxel size when none is given, if not the
    config's default.
    """
    default = voxel_default or f"the config's, {PipelineConfig().voxel_size:g}"
    parser.add_argument('--voxel-size', type=float, metavar='V',
                        help='voxel size in metres; every radius and threshold derives from '
                             f'it (default: {default})')
    parser.add_argument('--config', type=Path, metavar='YAML',
                        help="YAML of configuration keys, the node's format (flat or nested "
                             "keys, or a ROS 'node: {ros__parameters: ...}' file; the node's "
                             'own keys are checked and ignored)')
    parser.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                        dest='overrides',
                        help='override one parameter, e.g. core.max_iterations=20000 or '
                             'frontend.max_correspondences=3000 (repeatable; YAML values)')
    parser.add_argument('--seed', type=int, metavar='N', help='random seed of the sampler')
    parser.add_argument('--candidates', type=int, metavar='K',
                        help='report the K best distinct candidate poses (same as --set '
                             'num_candidates=K; default 5)')


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgags-register``."""
    args = build_parser().parse_args(argv)
    return run_cli(PROG, lambda: _register(args))


def _register(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    source, target = read_cloud(args.source), read_cloud(args.target)
    from ..pipeline import register_clouds  # after the cheap checks: imports Open3D

    result = register_clouds(source, target, config=config)
    if args.output:
        write_cloud(args.output, apply_transform(result.transform, source))
    if args.plot:
        plot_overlay(args.plot, source, target, result.transform)
    print(json.dumps(result.summary(), indent=2) if args.json else format_result(result))
    return 0 if result.valid else EXIT_INVALID


def config_from_args(args: argparse.Namespace) -> PipelineConfig:
    """Return the pipeline configuration the options ask for (YAML, then --set, then flags)."""
    return pipeline_from_keys(option_keys(args))


def option_keys(args: argparse.Namespace) -> dict:
    """Return the flat configuration keys the options set (YAML, then --set, then flags)."""
    values: dict = load_yaml(args.config) if args.config else {}
    values.update(fields.parse_key_values(args.overrides))
    if args.voxel_size is not None:
        values['voxel_size'] = args.voxel_size
    if getattr(args, 'no_refine', False):
        values['refine.method'] = 'none'
    if getattr(args, 'yaw_only', False):
        values['core.motion_model'] = '4dof'
    if getattr(args, 'gravity', None) is not None:
        values['core.gravity'] = list(args.gravity)
    if args.seed is not None:
        values['seed'] = args.seed
    if args.candidates is not None:
        values['num_candidates'] = args.candidates
    return fields.flatten_mapping(values)


def format_result(result) -> str:
    """Format a human-readable report: transform, validity, inliers, quality, stage times."""
    lines = ['transform (source -> target, metres):']
    lines += ['  ' + ' '.join(f'{x: .6f}' for x in row) for row in result.transform]
    lines.append(f"valid: {'yes' if result.valid else 'no'}"
                 + (f' ({result.refusal})' if result.refusal else ''))
    lines.append(f'inliers: {result.num_inliers} / {result.num_correspondences} correspondences '
                 f'({100 * result.inlier_ratio:.1f} %), {result.num_hypotheses} hypotheses')
    lines.append(f'fitness: {result.fitness:.3f}, inlier RMSE: {result.inlier_rmse:.4g} m, '
                 f"overlap: {result.overlap:.3f}, refined: {'yes' if result.refined else 'no'}")
    lines.append(f'points after {result.voxel_size:g} m voxels: {result.num_source_points} '
                 f'source, {result.num_target_points} target; '
                 f'resolution {result.resolution:.4g} m')
    stages = ('downsample', 'normals', 'fpfh', 'matching', 'registration', 'refinement',
              'candidates', 'total')
    lines.append(f"ambiguous: {'yes' if result.ambiguous else 'no'}, best/runner-up inliers "
                 f'{result.runner_up_ratio:.2f}')
    lines += [f'candidate {i}: inliers {c.num_inliers}, fitness {c.fitness:.3f}, ratio '
              f"{c.ratio:.3f}, t [{' '.join(f'{v:.3f}' for v in c.transform[:3, 3])}] m, "
              f'rotation {rotation_angle_deg(c.transform):.1f} deg'
              for i, c in enumerate(result.candidates)]
    lines.append('time [s]: ' + ', '.join(f'{k} {result.timings[k]:.3f}'
                                          for k in stages if k in result.timings))
    return '\n'.join(lines)


def rotation_angle_deg(T: np.ndarray) -> float:
    """Return the rotation angle of the 4x4 transform ``T`` (degrees)."""
    return rotation_error_deg(T, np.eye(4))


def plot_overlay(path: Path, source: np.ndarray, target: np.ndarray,
                 transform: np.ndarray, max_points: int = 20000) -> None:
    """Plot top (x-y) and side (x-z) views of target + source before and after alignment."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(0)
    pick = lambda p: p[rng.choice(len(p), min(len(p), max_points), replace=False)]  # noqa: E731
    src, dst = pick(source), pick(target)
    fig, axes = plt.subplots(2, 2, figsize=(10, 9))
    for col, (title, moved) in enumerate((('before (identity)', src),
                                          ('after (estimate)', apply_transform(transform, src)))):
        for row, (a, b, label) in enumerate(((0, 1, 'x-y'), (0, 2, 'x-z'))):
            ax = axes[row, col]
            ax.scatter(dst[:, a], dst[:, b], s=0.3, c='tab:blue', label='target')
            ax.scatter(moved[:, a], moved[:, b], s=0.3, c='tab:orange', label='source')
            ax.set_title(f'{title}, {label} view', fontsize=9)
            ax.set_aspect('equal', adjustable='datalim')
            ax.legend(loc='upper right', markerscale=10, fontsize=7)
    fig.tight_layout()
    try:
        fig.savefig(path, dpi=100)
    except OSError as exc:
        raise InvalidInputError(f'cannot write plot {path}: {exc}') from exc
    finally:
        plt.close(fig)


if __name__ == '__main__':
    sys.exit(main())
