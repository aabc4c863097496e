"""cgags_ros.pipeline.confidence: P(right) from the measurements, and the operating point."""

from __future__ import annotations

import math

from cgags_ros import fitted
from cgags_ros.config import GatesConfig, PipelineConfig
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.pipeline import confidence, covariance, register_clouds
from cgags_ros.pipeline.result import Candidate, PipelineResult
import numpy as np
import pytest


def _measured(**values) -> PipelineResult:
    """Return a result as the gates leave a clearly supported estimate, ``values`` changed."""
    result = PipelineResult(voxel_size=0.05, fitness=0.7, overlap=0.6, inlier_rmse=0.025,
                            observability=0.1, chance_inliers=2.0, free_space_violation=0.05,
                            num_hypotheses=1000, num_correspondences=2000,
                            inliers=np.arange(300), covariance=np.diag([0.03 ** 2] * 6))
    result.candidates = [Candidate(np.eye(4), 300, 0.7), Candidate(np.eye(4), 20, 0.2)]
    result.runner_up_ratio = 15.0
    for name, value in values.items():
        setattr(result, name, value)
    return result


def test_confidence_is_a_probability_that_falls_with_the_evidence():
    strong = confidence.probability(confidence.features(_measured(), 0.01))
    assert 0.0 <= strong <= 1.0 and strong > 0.9
    # Fewer inliers, closer to chance; an overlap loose along a wall; a surface stacked in
    # free space: each alone makes it less sure.
    loose = np.diag([0.03 ** 2] * 6)
    loose[0, 0] = 1.0
    for result in (_measured(inliers=np.arange(12)), _measured(covariance=loose),
                   _measured(free_space_violation=0.3)):
        p = confidence.probability(confidence.features(result, 0.01))
        assert 0.0 <= p < strong
    # No estimate: nothing to be confident about.
    assert confidence.features(PipelineResult(voxel_size=0.05), 0.01) is None
    assert confidence.probability(None) == 0.0


def test_each_input_moves_the_confidence_one_way():
    """Monotone: a weight's sign is its input's meaning, whatever the fit."""
    assert set(confidence.SIGNS) == set(confidence.FEATURES)
    for name, sign in confidence.SIGNS.items():
        assert fitted.CONFIDENCE_WEIGHTS[name] * sign > 0


def test_every_feature_has_a_weight_and_the_weights_are_finite():
    assert set(fitted.CONFIDENCE_WEIGHTS) == set(confidence.FEATURES)
    assert all(math.isfinite(w) for w in fitted.CONFIDENCE_WEIGHTS.values())
    assert math.isfinite(fitted.CONFIDENCE_INTERCEPT)


def test_a_result_without_an_estimate_has_zero_confidence():
    rng = np.random.default_rng(0)
    result = register_clouds(rng.normal(size=(5, 3)), rng.normal(size=(500, 3)),
                             voxel_size=0.05)
    assert not result.valid and result.confidence == 0.0
    assert result.summary()['confidence'] == 0.0


def test_real_pairs_right_is_confident_and_the_threshold_refuses_below_it(redkitchen_pair):
    src, tgt, gt = redkitchen_pair(0, 2)
    result = register_clouds(src, tgt, voxel_size=0.05)
    assert rotation_error_deg(result.transform, gt) < 15 and translation_error(
        result.transform, gt) < 0.3
    assert result.valid and result.confidence >= PipelineConfig().gates.min_confidence
    assert result.confidence > 0.9
    assert result.summary()['confidence'] == pytest.approx(result.confidence)
    # The same estimate under a stricter operating point than its confidence: refused.
    strict = min(1.0, result.confidence + 1e-6)
    refused = register_clouds(src, tgt, voxel_size=0.05,
                              config=PipelineConfig(gates=GatesConfig(min_confidence=strict)))
    np.testing.assert_allclose(refused.transform, result.transform)
    assert not refused.valid and refused.refusal.code.value == 'low_confidence'


def test_a_pose_too_loose_to_use_is_refused_with_its_covariance_kept(redkitchen_pair):
    """
    A near miss whose covariance says it may be metres off is no usable pose.

    A 3DLoMatch pair 36 cm off whose every gate passes: its covariance, opened by the doubt
    its confidence leaves, is far looser than any robot can act on.
    """
    src, tgt, gt = redkitchen_pair(22, 38)
    result = register_clouds(src, tgt, voxel_size=0.05)
    assert translation_error(result.transform, gt) > 0.3  # wrong, if only just
    assert not result.valid and result.refusal.code.value == 'uncertain'
    sigma = covariance.loosest_sigma(result.covariance)
    assert sigma > PipelineConfig().gates.max_position_sigma * 0.05
    assert result.confidence >= PipelineConfig().gates.min_confidence  # not that refusal
    # The bound off: the same pose, called valid.
    loose = register_clouds(src, tgt, voxel_size=0.05, config=PipelineConfig(
        gates=GatesConfig(max_position_sigma=0.0)))
    np.testing.assert_allclose(loose.transform, result.transform)
    assert loose.valid


def test_a_refused_estimate_says_no_more_than_its_refusals_are_right(benchmark_pair,
                                                                     monkeypatch):
    """
    The model rates the pose, never the refusal: a refused estimate is capped by its kind.

    A 3DLoMatch pair the model rates as near certain, refused as ambiguous (a distinct pose
    fits as well) and wrong: its confidence is the share of right ambiguous refusals at most.
    """
    src, tgt, gt = benchmark_pair('sun3d-mit_lab_hj-lab_hj_tea_nov_2_2012_scan1_erika', 21, 24)
    result = register_clouds(src, tgt, voxel_size=0.05)
    assert not result.valid and result.refusal.code.value == 'ambiguous'
    assert rotation_error_deg(result.transform, gt) > 15  # wrong
    assert result.confidence == pytest.approx(fitted.REFUSED_RIGHT['ambiguous'])
    monkeypatch.setattr(fitted, 'REFUSED_RIGHT', {})
    monkeypatch.setattr(fitted, 'REFUSED_RIGHT_OTHER', 1.0)
    uncapped = register_clouds(src, tgt, voxel_size=0.05)
    np.testing.assert_allclose(uncapped.transform, result.transform)
    assert uncapped.confidence > 0.9  # what the model says of the pose alone
    assert confidence.refused_at_most('no_estimate') == fitted.REFUSED_RIGHT_OTHER
