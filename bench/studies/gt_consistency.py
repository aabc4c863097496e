"""
Distance of a pair's ground truth from the best alignment its own geometry supports.

Can the reference confirm RE <= 1 deg and TE <= 3 cm after refinement on the 3DMatch
redkitchen pairs? This script measures it: it refines each pair of
``../shared/data/indoor_3dmatch/gt_pairs.txt`` starting *at the ground truth* with two
local refiners of different libraries and costs on the full-resolution fragments (the
pipeline's own ``features.refine``, at finer voxels and a wider matching distance),

- Open3D point-to-plane ICP, and
- small_gicp GICP,

and reports how far each converged pose lies from the ground truth (RE/TE, the literature's
metrics). If both refiners move the same way, the geometric optimum is that far from the
reference and no estimate can be verified closer to it than that. It then runs our pipeline
(``register_clouds``, default settings, voxel 5 cm) and reports its distance to the ground
truth and to each refiner's optimum.

Run by hand (~20 s)::

    .venv/bin/python -m bench.studies.gt_consistency [--voxels 0.01 0.025]
"""

from __future__ import annotations

from unittest import mock

from bench.common import argument_parser
from bench.datasets.gt_pairs import read_gt_pairs
from cgags_ros.config.frontend import RefineConfig
from cgags_ros.frontend import refine
from cgags_ros.frontend.features import downsample
from cgags_ros.frontend.refine import refine_transform
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.clouds import read_cloud
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import register_clouds
import numpy as np


def refine_from(source: np.ndarray, target: np.ndarray, init: np.ndarray, voxel: float,
                method: str) -> np.ndarray:
    """
    Refine ``init`` with the pipeline's own refinement (``features.refine``).

    It runs on ``voxel``-downsampled clouds, matches within 3 voxels and stops after at most
    100 iterations a stage (this study's own setting of ``refine.MAX_ITERATIONS``).
    """
    config = RefineConfig(method=method, max_correspondence_distance_factor=3.0)
    with mock.patch.object(refine, 'MAX_ITERATIONS', 100):
        return refine_transform(downsample(source, voxel, 3), downsample(target, voxel, 3),
                                init, voxel_size=voxel, config=config)


def errors(T: np.ndarray, ref: np.ndarray) -> str:
    return f'{rotation_error_deg(T, ref):5.2f} deg {100 * translation_error(T, ref):5.1f} cm'


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('--voxels', type=float, nargs='+', default=[0.01, 0.025],
                        help='refiner voxel sizes in metres (correspondence distance 3 voxels)')
    parser.add_argument('--pipeline-voxel', type=float, default=0.05)
    args = parser.parse_args(argv)
    pairs = read_gt_pairs(shared_data_dir() / 'indoor_3dmatch' / 'gt_pairs.txt')
    for src_path, tgt_path, gt in pairs:
        source, target = read_cloud(src_path), read_cloud(tgt_path)
        ours = register_clouds(source, target, voxel_size=args.pipeline_voxel).transform
        print(f'{src_path.name} -> {tgt_path.name}: ours (voxel {args.pipeline_voxel} m) '
              f'vs ground truth: {errors(ours, gt)}')
        for voxel in args.voxels:
            for name, method in (('Open3D point-to-plane ICP', 'point_to_plane'),
                                 ('small_gicp GICP', 'gicp')):
                optimum = refine_from(source, target, gt, voxel, method)
                print(f'  {name:26s} from GT, voxel {voxel:5.3f}: '
                      f'optimum vs GT {errors(optimum, gt)};'
                      f' ours vs optimum {errors(ours, optimum)}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
