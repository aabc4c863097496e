r"""
Pipeline benchmark on the bundled bags.

Run by hand::

    .venv/bin/python -m bench.pipeline [--bags bunny lidar] \
        [--set frontend.max_keypoints=5000] [--output out/bench/pipeline.json]

For every bag in ``<shared data>/bags`` (or ``--bags-dir``) and every source cloud with
ground truth, paired with its target exactly as ``cgags-replay`` pairs them (the node's
:class:`~cgags_ros.engine.pairing.Pairer`), it runs:

``cgags``
    :func:`cgags_ros.pipeline.register_clouds` with default parameters, or those changed by
    ``--set KEY=VALUE`` (includes its point-to-plane ICP refinement).
``open3d_fpfh_ransac``
    Open3D 0.19 ``registration_ransac_based_on_feature_matching`` on the *same* front end
    (:func:`bench.baselines.open3d_fpfh_ransac`: voxel size, normal and FPFH radii and
    neighbour caps of ``PipelineConfig().frontend``), ``mutual_filter=True``,
    ``max_correspondence_distance = 1.5 v`` (Open3D's tutorial), point-to-point
    estimation, ``ransac_n = 3``, checkers ``EdgeLength(0.9)`` and ``Distance(1.5 v)``,
    ``RANSACConvergenceCriteria(100000, 0.999)``; no refinement.
``kiss_matcher``
    ``kiss_matcher.KISSMatcher(KISSMatcherConfig(voxel_size=v)).estimate(src, tgt)``
    (kiss-matcher 1.0.2; its own voxelization, FasterPFH, ROBIN and GNC; float32 input;
    no refinement). Its config refuses ``voxel_size < 5e-3`` ("Too small voxel size"),
    so object-scale data fails as is.
``cgags_4dof``
    The same with ``core.motion_model='4dof'`` (yaw about +z + translation).
``kiss_matcher_quatro``
    ``KISSMatcherConfig(voxel_size=v, use_quatro=True)`` (its 4-DoF mode), otherwise as
    ``kiss_matcher``.
``kiss_matcher_rescaled``
    The same with both clouds and the voxel multiplied by ``s = 0.3 / v`` (KISS-Matcher's
    default 0.3 m voxel), the translation divided by ``s`` afterwards. Only run where
    ``s != 1``. Measures whether KISS-Matcher needs rescaling (its noise bounds are
    multiples of the voxel size, so apart from the 5 mm floor and the 1.0 clamps it is
    scale-invariant).

Metrics per method and bag: registration recall (RE and TE below the bag's thresholds,
:data:`bench.common.LIMITS`; other bags: 5 deg and 3 voxel sizes), mean RE/TE over the
successes, median wall time per pair (seconds, everything from the raw (N, 3) clouds to
the 4x4 transform, single process). Prints a markdown table and writes it with every trial
as JSON to ``--output`` (default ``out/bench/pipeline.json``).
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
import time
from typing import Callable

from bench.baselines import kiss_matcher_estimate, open3d_fpfh_ransac
from bench.common import (add_set_option, argument_parser, cell, LIMITS, machine, markdown_table,
                          output_path, parse_overrides, write_json)
from cgags_ros.config import PipelineConfig
from cgags_ros.config.fields import update_from_flat
from cgags_ros.config.node import NodeConfig
from cgags_ros.engine.pairing import Pairer
from cgags_ros.errors import CgagsError, InvalidInputError
from cgags_ros.geometry import rotation_error_deg, translation_error, voxel_size_for
from cgags_ros.io.bag import read_messages
from cgags_ros.io.pointcloud2 import pointcloud2_to_xyz, pose_to_transform
from cgags_ros.io.shared_data import shared_data_dir
import numpy as np

KISS_DEFAULT_VOXEL = 0.3
AUTO_VOXEL_POINTS = 5000  # the target points by which cgags-replay chooses a voxel size
DEFAULT_MAX_RE_DEG, DEFAULT_MAX_TE_VOXELS = 5.0, 3.0  # a bag without limits of its own
TOPICS = {'/source_cloud': 'source', '/target_cloud': 'target'}
GROUND_TRUTH = '/ground_truth'

Method = Callable[[np.ndarray, np.ndarray, float], np.ndarray]


# --- methods: (source (N,3), target (M,3), voxel metres) -> 4x4 source->target ----------------

def run_cgags(src: np.ndarray, tgt: np.ndarray, voxel: float, motion: str = '6dof',
              overrides: dict | None = None) -> np.ndarray:
    from cgags_ros.pipeline import clear_feature_cache, register_clouds

    # Cold: the baselines featurise both clouds every pair, so ours does too (the node,
    # with a latched target, would reuse the target's features and be faster).
    clear_feature_cache()
    config = update_from_flat(PipelineConfig(), {'core.motion_model': motion,
                                                 **(overrides or {})})
    result = register_clouds(src, tgt, voxel_size=voxel, config=config)
    if not result.valid:
        raise CgagsError(f'invalid: {result.reason}')
    return result.transform


def run_cgags_4dof(src: np.ndarray, tgt: np.ndarray, voxel: float) -> np.ndarray:
    return run_cgags(src, tgt, voxel, '4dof')


def run_kiss(src: np.ndarray, tgt: np.ndarray, voxel: float, scale: float = 1.0,
             quatro: bool = False) -> np.ndarray:
    """KISS-Matcher on clouds (and voxel) multiplied by ``scale``; returns the unscaled T."""
    out = kiss_matcher_estimate(src, tgt, voxel, scale=scale, quatro=quatro)
    if not out.valid:
        raise CgagsError('KISS-Matcher reported valid=False')
    return out.transform


def run_kiss_rescaled(src: np.ndarray, tgt: np.ndarray, voxel: float) -> np.ndarray:
    return run_kiss(src, tgt, voxel, KISS_DEFAULT_VOXEL / voxel)


def run_kiss_quatro(src: np.ndarray, tgt: np.ndarray, voxel: float) -> np.ndarray:
    return run_kiss(src, tgt, voxel, quatro=True)


METHODS: dict[str, Method] = {
    'cgags': run_cgags,
    'cgags_4dof': run_cgags_4dof,
    'open3d_fpfh_ransac': open3d_fpfh_ransac,
    'kiss_matcher': run_kiss,
    'kiss_matcher_rescaled': run_kiss_rescaled,
    'kiss_matcher_quatro': run_kiss_quatro,
}


# --- benchmark ----------------------------------------------------------------------------

@dataclasses.dataclass
class Trial:
    bag: str
    method: str
    source_stamp_ns: int
    time_s: float
    re_deg: float | None
    te_m: float | None
    success: bool
    error: str = ''


def load_pairs(
        bag_dir: Path) -> tuple[list[tuple[int, np.ndarray, np.ndarray, np.ndarray]], float]:
    """
    Return a bag's pairs with ground truth and the voxel size cgags-replay would choose.

    One pair (stamp, source, target, ground truth) per source cloud with ground truth, in
    the order the node's pairing forms them; messages that cannot be read or decoded are
    skipped, as the node rejects them.
    """
    clouds, truth = [], {}
    for rec in read_messages(bag_dir, [*TOPICS, GROUND_TRUTH]):
        if rec.error:
            continue
        try:
            if rec.topic == GROUND_TRUTH:
                truth[int(rec.stamp_ns)] = pose_to_transform(rec.msg)
            else:
                clouds.append((TOPICS[rec.topic], rec, pointcloud2_to_xyz(rec.msg)))
        except (AttributeError, TypeError, InvalidInputError):
            continue
    pairer = Pairer.from_config(NodeConfig().pairing)
    pairs = []
    for role, rec, xyz in clouds:
        add = pairer.add_source if role == 'source' else pairer.add_target
        add(rec.stamp_ns, rec.frame_id, xyz)
        while (pair := pairer.pop()) is not None:
            stamp = pair.source.stamp_ns
            if stamp in truth:
                pairs.append((stamp, pair.source.payload, pair.target.payload, truth[stamp]))
    target = next(xyz for role, _, xyz in clouds if role == 'target')
    return pairs, voxel_size_for(target, AUTO_VOXEL_POINTS)


def thresholds(bag: str, voxel: float) -> tuple[float, float]:
    return LIMITS.get(bag, (DEFAULT_MAX_RE_DEG, DEFAULT_MAX_TE_VOXELS * voxel))


def run_trial(bag: str, method: str, fn: Method, stamp: int, src: np.ndarray,
              tgt: np.ndarray, gt: np.ndarray, voxel: float,
              limits: tuple[float, float]) -> Trial:
    t0 = time.perf_counter()
    try:
        T = fn(src, tgt, voxel)
    except Exception as exc:  # noqa: BLE001 - a failing baseline is a data point
        return Trial(bag, method, stamp, time.perf_counter() - t0, None, None, False,
                     ' '.join(f'{type(exc).__name__}: {exc}'.split()))
    dt = time.perf_counter() - t0
    re, te = rotation_error_deg(T, gt), translation_error(T, gt)
    return Trial(bag, method, stamp, dt, re, te, bool(re <= limits[0] and te <= limits[1]))


def summarize(trials: list[Trial]) -> dict:
    ok = [t for t in trials if t.success]
    return {
        'pairs': len(trials), 'successes': len(ok),
        'recall': len(ok) / len(trials) if trials else None,
        'mean_re_deg': float(np.mean([t.re_deg for t in ok])) if ok else None,
        'mean_te_m': float(np.mean([t.te_m for t in ok])) if ok else None,
        'median_time_s': float(np.median([t.time_s for t in trials])) if trials else None,
        'errors': sorted({t.error for t in trials if t.error}),
    }


def main(argv: list[str] | None = None) -> int:
    p = argument_parser(__spec__.name, __doc__)
    p.add_argument('--bags-dir', type=Path, default=shared_data_dir() / 'bags')
    p.add_argument('--bags', nargs='+', default=None, help='default: every bag in --bags-dir')
    p.add_argument('--methods', nargs='+', choices=sorted(METHODS), default=list(METHODS))
    add_set_option(p)
    p.add_argument('--output', type=Path, default=output_path('pipeline.json'),
                   help='JSON results path (default: %(default)s)')
    args = p.parse_args(argv)
    methods = dict(METHODS)
    if args.set:
        changed = parse_overrides(args.set)
        methods['cgags'] = functools.partial(run_cgags, overrides=changed)
        methods['cgags_4dof'] = functools.partial(run_cgags, motion='4dof', overrides=changed)
    names = args.bags or sorted(d.name for d in args.bags_dir.iterdir()
                                if (d / 'metadata.yaml').exists())
    trials: list[Trial] = []
    rows, summary = [], {}
    for bag in names:
        pairs, voxel = load_pairs(args.bags_dir / bag)
        limits = thresholds(bag, voxel)
        print(f'{bag}: {len(pairs)} pair(s) with ground truth, voxel {voxel:g} m, success '
              f'RE <= {limits[0]:g} deg, TE <= {limits[1]:g} m', flush=True)
        for method in args.methods:
            if method == 'kiss_matcher_rescaled' and np.isclose(voxel, KISS_DEFAULT_VOXEL):
                continue
            got = [run_trial(bag, method, methods[method], *pair, voxel, limits)
                   for pair in pairs]
            trials += got
            s = summarize(got)
            summary.setdefault(bag, {'voxel_size': voxel, 'max_re_deg': limits[0],
                                     'max_te_m': limits[1], 'methods': {}})['methods'][method] = s
            rows.append((bag, method, f"{s['successes']}/{s['pairs']}", s['mean_re_deg'],
                         s['mean_te_m'], s['median_time_s'], '; '.join(s['errors'])[:70]))
            print(f"  {method}: recall {s['successes']}/{s['pairs']}, median "
                  f"{cell(s['median_time_s'])} s", flush=True)
    table = markdown_table(('bag', 'method', 'recall', 'mean RE [deg]', 'mean TE [m]',
                            'median time [s]', 'errors'), rows)
    print('\n' + table + (f"\n\nours with --set {' '.join(args.set)}" if args.set else ''))
    path = write_json(args.output, {'machine': machine(), 'set': args.set, 'summary': summary,
                                    'table': table,
                                    'trials': [dataclasses.asdict(t) for t in trials]},
                      indent=2)
    print(f'\nwrote {path}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
