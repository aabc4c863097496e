r"""
Where each benchmark pair's surfaces settle, started from its truth: evidence for the truth check.

:mod:`bench.truth_check` doubts a fragment's benchmark pose when the poses its partners'
trusted estimates imply agree with each other and not with it. Where our estimates are
refused or wrong, a fragment has too few trusted partners to be checked (fragments of the
hardest scenes' wrong valid pairs among them). This module gathers evidence that does not
depend on our estimator: for every pair of both lists, point-to-plane ICP on the raw
fragments, started from the benchmark's relative pose ``inv(P_i) P_j``. If fragment j's
pose is off, each partner's ICP pulls the pair towards the true relative pose, and the
implied poses ``P_i T_ij`` agree with each other away from ``P_j``; if it is right, they stay
on it. A pair whose ICP slides (a low-overlap or degenerate view) implies a pose off on its
own and joins no agreeing group. The records are written in the format the truth check
reads (every settled pose counts as trusted evidence), so the same thresholds decide::

    .venv/bin/python -m bench.truth_settle [--root <shared data>/3dmatch_benchmark] \
        [--output out/truth_check/settled.jsonl]
    .venv/bin/python -m bench.truth_check out/truth_check/settled.jsonl \
        --output out/truth_check/settled

The ICP's settings are fixed, not fitted: the fragments at half the benchmark's 5-cm voxel
(VOXEL), normals from NORMAL_NEIGHBOURS points within four voxels, correspondences within
three voxels (DISTANCE), at most ITERATIONS. Each record also holds how far the ICP moved
the truth and the overlap (fitness within DISTANCE) before and after. A few minutes on two
cores; the records are appended as they are made and a rerun skips the pairs it has.
"""

from __future__ import annotations

import json
from pathlib import Path

from bench.common import argument_parser
from bench.datasets import threedmatch as tdm
from bench.truth_check import read_records
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.shared_data import shared_data_dir
import numpy as np
import open3d as o3d

VOXEL = 0.025
DISTANCE = 3 * VOXEL
NORMAL_NEIGHBOURS = 30
ITERATIONS = 60


def surface(points: np.ndarray) -> o3d.geometry.PointCloud:
    """Return a fragment at VOXEL with normals, as the ICP below takes it."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(VOXEL)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(4 * VOXEL, NORMAL_NEIGHBOURS))
    return cloud


def settle(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud,
           start: np.ndarray) -> dict:
    """Return where point-to-plane ICP from ``start`` settles, and the overlap before and after."""
    reg = o3d.pipelines.registration
    before = reg.evaluate_registration(source, target, DISTANCE, start)
    result = reg.registration_icp(source, target, DISTANCE, start,
                                  reg.TransformationEstimationPointToPlane(),
                                  reg.ICPConvergenceCriteria(max_iteration=ITERATIONS))
    T = result.transformation
    return {'transform': T.tolist(), 'moved_deg': rotation_error_deg(T, start),
            'moved_m': translation_error(T, start), 'fitness_before': before.fitness,
            'fitness_after': result.fitness}


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark')
    parser.add_argument('--output', type=Path, default=Path('out/truth_check/settled.jsonl'))
    args = parser.parse_args(argv)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    done = ({(r['benchmark'], r['scene'], r['target'], r['source'])
             for r in read_records([args.output])} if args.output.exists() else set())
    with args.output.open('a', encoding='utf-8') as out:
        for scene in tdm.scenes(args.root):
            fragments = tdm.Fragments(args.root, scene)
            poses = tdm.fragment_poses(args.root, scene)
            surfaces: dict[int, o3d.geometry.PointCloud] = {}
            for benchmark in tdm.BENCHMARKS:
                for p in tdm.registration_pairs(args.root, benchmark, scene):
                    if (benchmark, scene, p.target, p.source) in done:
                        continue
                    for k in (p.source, p.target):
                        if k not in surfaces:
                            surfaces[k] = surface(fragments[k])
                    start = tdm.nearest_rigid(np.linalg.inv(poses[p.target]) @ poses[p.source])
                    row = settle(surfaces[p.source], surfaces[p.target], start)
                    out.write(json.dumps({'benchmark': benchmark, 'scene': scene,
                                          'target': p.target, 'source': p.source,
                                          'valid': True, **row}) + '\n')
                    out.flush()
            print(f'{scene}: settled', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
