"""cgags_ros.pipeline.regenerate: poses proposed by local re-matching, on real RGB-D pairs."""

from __future__ import annotations

import dataclasses

from cgags_ros.config import PipelineConfig
from cgags_ros.config.fields import update_from_flat
from cgags_ros.frontend.keypoints import match_keypoints
from cgags_ros.geometry import apply_transform, rotation_error_deg, translation_error
from cgags_ros.pipeline import clear_feature_cache, register_clouds
from cgags_ros.pipeline import regenerate
from cgags_ros.pipeline.cache import cached_features
from cgags_ros.refusal import Refusal, RefusalCode as Code
from cgags_ros.registration import register_correspondences, RegistrationResult
import numpy as np
import pytest

MIT_LAB = 'sun3d-mit_lab_hj-lab_hj_tea_nov_2_2012_scan1_erika'


def _config(**values) -> PipelineConfig:
    return update_from_flat(PipelineConfig(), values)


def _right(transform: np.ndarray, truth: np.ndarray) -> bool:
    return rotation_error_deg(transform, truth) < 15 and translation_error(transform, truth) < 0.3


def _prepared(src: np.ndarray, tgt: np.ndarray, cfg: PipelineConfig):
    """Return the pair's features, correspondences and core result, as the pipeline has them."""
    fs = cached_features(src, cfg.voxel_size, cfg.frontend, 'source')
    ft = cached_features(tgt, cfg.voxel_size, cfg.frontend, 'target')
    corr = match_keypoints(fs.points, fs.descriptors, ft.descriptors, cfg.voxel_size,
                           cfg.frontend, 1, ft.descriptor_index(1))
    core = register_correspondences(
        fs.points[corr.source_index], ft.points[corr.target_index],
        resolution=0.5 * (fs.resolution + ft.resolution), config=cfg.core, seed=cfg.seed)
    return fs, ft, corr, core


@pytest.mark.slow
def test_local_re_matching_finds_more_right_matches_than_the_single_pass(benchmark_pair):
    """Around the right seeds, the spheres hold several times the right matches of the cloud."""
    src, tgt, truth = benchmark_pair(MIT_LAB, 15, 18)
    cfg = PipelineConfig()
    fs, ft, corr, core = _prepared(src, tgt, cfg)
    tau, delta = core.inlier_threshold, core.compatibility_threshold
    ps, pt = fs.points[corr.source_index], ft.points[corr.target_index]
    right = np.linalg.norm(apply_transform(truth, ps) - pt, axis=1) < tau
    seeds = regenerate.seed_rows(ps, pt, delta, 0.0, cfg)
    assert 0 < len(seeds) <= regenerate.SEEDS
    radius = regenerate.RADIUS * cfg.voxel_size
    found = set()
    for s in seeds[right[seeds]]:
        i, j = regenerate.local_matches(fs, ft, ps[s], pt[s], radius, delta)
        ok = np.linalg.norm(apply_transform(truth, fs.points[i]) - ft.points[j], axis=1) < tau
        found |= set(zip(i[ok].tolist(), j[ok].tolist()))
    assert right[seeds].sum() >= 2
    assert len(found) > 2 * right.sum()


@pytest.mark.slow
@pytest.mark.parametrize('scene, target, source', [(MIT_LAB, 15, 18),
                                                   ('7-scenes-redkitchen', 4, 53)])
def test_a_wrong_estimate_is_replaced_by_the_right_proposal(benchmark_pair, scene, target,
                                                            source):
    """Low-overlap pairs whose core estimate is wrong: the stage puts the right pose in."""
    src, tgt, truth = benchmark_pair(scene, target, source)
    clear_feature_cache()
    off = register_clouds(src, tgt, config=_config(**{'regenerate.enabled': False}))
    on = register_clouds(src, tgt, config=_config(**{'regenerate.enabled': True}))
    assert not _right(off.transform, truth)
    assert _right(on.transform, truth)
    assert 'regeneration' in on.timings and 'regeneration' not in off.timings


@pytest.mark.slow
def test_the_replacement_is_judged_on_the_original_correspondences(benchmark_pair):
    """Its inliers index the putative matches and its chance level is the core's own."""
    src, tgt, truth = benchmark_pair(MIT_LAB, 15, 18)
    cfg = _config(**{'regenerate.enabled': True})
    fs, ft, corr, core = _prepared(src, tgt, cfg)
    replaced = regenerate.regenerated_estimate(fs, ft, corr, core, cfg)
    assert replaced is not None and _right(replaced.transform, truth)
    assert replaced.chance_level == core.chance_level
    assert replaced.num_correspondences == len(corr)
    assert replaced.inliers.max() < len(corr)
    residual = np.linalg.norm(
        apply_transform(replaced.transform, fs.points[corr.source_index[replaced.inliers]])
        - ft.points[corr.target_index[replaced.inliers]], axis=1)
    assert (residual <= core.inlier_threshold).all()
    # The pose it displaced counts against it, measured the same way.
    assert replaced.runner_up > 0
    # A stricter free-space limit than any pose meets: nothing replaces the estimate.
    strict = dataclasses.replace(
        cfg, gates=dataclasses.replace(cfg.gates, max_free_space_violation=0.0))
    assert regenerate.regenerated_estimate(fs, ft, corr, core, strict) is None


@pytest.mark.slow
def test_an_estimate_the_core_trusts_is_left_as_it_is(redkitchen_pair):
    """By default the stage runs only on refused estimates: a valid pair's result is unchanged."""
    src, tgt, _ = redkitchen_pair(0, 2)
    clear_feature_cache()
    off = register_clouds(src, tgt, config=_config(**{'regenerate.enabled': False}))
    on = register_clouds(src, tgt, config=_config(**{'regenerate.enabled': True}))
    assert off.valid and on.valid
    np.testing.assert_allclose(on.transform, off.transform, atol=1e-9)
    assert 'regeneration' not in on.timings


def test_the_stage_runs_on_refused_estimates_of_six_dof_pairs_only():
    refused = RegistrationResult(refusal=Refusal(Code.CHANCE_LEVEL, 'chance level'))
    collinear = RegistrationResult(refusal=Refusal(Code.COLLINEAR, 'on a line'),
                                   inliers=np.arange(40))
    trusted = RegistrationResult(refusal=None)
    on = _config(**{'regenerate.enabled': True})
    runs = regenerate.regenerates
    assert runs(refused, on, map_target=False)
    assert not runs(trusted, on, map_target=False)
    assert runs(collinear, on, map_target=False)
    assert runs(trusted, _config(**{'regenerate.enabled': True,
                                    'regenerate.when': 'always'}), map_target=False)
    assert not runs(refused, on, map_target=True)
    for other in ({'core.motion_model': '4dof'}, {'refine.method': 'none'},
                  {'regenerate.enabled': False}):
        assert not runs(refused, _config(**{'regenerate.enabled': True, **other}),
                        map_target=False)


def test_a_sphere_pose_needs_consistent_matches():
    rng = np.random.default_rng(0)
    a = rng.uniform(-0.3, 0.3, (40, 3))
    c, s = np.cos(0.4), np.sin(0.4)
    T = np.array([[c, -s, 0, 0.5], [s, c, 0, -0.2], [0, 0, 1, 0.1], [0, 0, 0, 1.0]])
    b = apply_transform(T, a)
    b[:10] += rng.uniform(-0.15, 0.15, (10, 3))  # a quarter of the sphere's matches wrong
    fitted = regenerate.local_pose(a, b, 0.05)
    assert rotation_error_deg(fitted, T) < 1e-6 and translation_error(fitted, T) < 1e-9
    # Nothing consistent to fit: no pose.
    assert regenerate.local_pose(a[:4], rng.uniform(-5, 5, (4, 3)), 0.01) is None


def test_the_judged_proposals_are_those_the_most_correspondences_support():
    rng = np.random.default_rng(1)
    src = rng.uniform(-2, 2, (60, 3))
    poses = [np.eye(4) for _ in range(4)]
    for k, T in enumerate(poses):
        T[:3, 3] = [0.5 * k, 0.0, 0.0]
    # Correspondences that agree with pose 2 (30), pose 0 (20) and pose 3 (10).
    dst = np.vstack([src[:30] + poses[2][:3, 3], src[30:50], src[50:] + poses[3][:3, 3]])
    kept = regenerate.best_supported(poses, src, dst, 0.1, 2)
    assert [T[0, 3] for T in kept] == [1.0, 0.0]
    assert regenerate.best_supported(poses, src, dst, 0.1, 0) == poses  # 0 keeps every pose
    assert regenerate.best_supported(poses, src, dst, 0.1, 9) == poses
