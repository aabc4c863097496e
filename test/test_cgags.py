"""End-to-end tests of the core on correspondences built from the real Stanford bunny model."""

import tracemalloc

from bench.datasets.synthetic import load_bunny, make_correspondences
from cgags_ros.errors import DegenerateCorrespondencesError, InvalidInputError
from cgags_ros.geometry import point_resolution
from cgags_ros.refusal import RefusalCode as Code
from cgags_ros.registration import (
    CoreConfig,
    register_correspondences,
    rotation_error_deg,
    translation_error,
)
import numpy as np
import pytest

TAU = 0.05  # inlier threshold on the unit-scaled bunny, ~3 sigma of the 0.01 noise
MAX_RE_DEG, MAX_TE = 3.0, 0.05  # noise sigma 0.01 on a unit-sized model


@pytest.fixture(scope='module')
def bunny(data_dir):
    return load_bunny(data_dir)


def _check_recovery(prob, res):
    re = rotation_error_deg(res.transform, prob.transform)
    te = translation_error(res.transform, prob.transform)
    assert res.valid, res.reason
    assert re < MAX_RE_DEG and te < MAX_TE, f'RE {re:.2f} deg, TE {te:.3f}'
    true_inliers = np.flatnonzero(prob.inlier_mask)
    recall = np.isin(true_inliers, res.inliers).mean()
    assert recall > 0.9, f'only {recall:.0%} of the true inliers recovered'


@pytest.mark.parametrize('n,ratio,seeds', [
    (1000, 0.5, [0]), (1000, 0.9, [0, 1]), (1000, 0.95, [0, 1]), (1000, 0.99, [0, 1, 2]),
    (5000, 0.9, [0]), (5000, 0.99, [0, 1]), (5000, 0.995, [0]),
])
def test_recovers_any_rotation_under_heavy_outliers(bunny, n, ratio, seeds):
    for seed in seeds:
        prob = make_correspondences(bunny, n, ratio, noise_sigma=0.01, rng=100 + seed)
        res = register_correspondences(prob.src, prob.dst, inlier_threshold=TAU, seed=seed)
        _check_recovery(prob, res)


def test_structured_surface_outliers(bunny):
    prob = make_correspondences(bunny, 2000, 0.98, noise_sigma=0.005, rng=7, outliers='surface')
    res = register_correspondences(prob.src, prob.dst, inlier_threshold=0.025, seed=0)
    _check_recovery(prob, res)


def test_paper_thresholds_from_resolution(bunny):
    pr = point_resolution(bunny)
    prob = make_correspondences(bunny, 1000, 0.9, noise_sigma=pr / 2, rng=3)
    res = register_correspondences(prob.src, prob.dst, resolution=pr, seed=0)
    assert res.inlier_threshold == pytest.approx(6 * pr)
    assert res.compatibility_threshold == pytest.approx(10 * pr)
    _check_recovery(prob, res)


def test_deterministic_for_a_seed(bunny):
    prob = make_correspondences(bunny, 1000, 0.97, rng=5)
    a = register_correspondences(prob.src, prob.dst, inlier_threshold=TAU, seed=11)
    b = register_correspondences(prob.src, prob.dst, inlier_threshold=TAU, seed=11)
    assert np.array_equal(a.transform, b.transform)
    assert np.array_equal(a.inliers, b.inliers)
    assert a.num_hypotheses == b.num_hypotheses


def test_result_reports_stages(bunny):
    prob = make_correspondences(bunny, 1000, 0.95, rng=9)
    res = register_correspondences(prob.src, prob.dst, inlier_threshold=TAU)
    for stage in ('compatibility_graph', 'compatible_sampling', 'guided_sampling', 'refit',
                  'total'):
        assert stage in res.timings
    drawn = res.stats['compatible_samples'] + res.stats['guided_samples']
    assert 0 < res.num_hypotheses <= drawn  # triples rejected before fitting are not hypotheses
    assert res.stats['graph_edges'] > 0
    assert res.stats['stopped_by'] in ('p1_bound', 'p2_bound')
    assert 0 < res.inlier_ratio <= 1
    summary = res.summary()
    assert summary['valid'] and len(summary['transform']) == 4


@pytest.mark.parametrize('config,constants', [
    ({'edge_tournament': 1, 'vertex_tournament': 1}, {}),
    ({'guided_sampling': False}, {}),
    ({'futility_stop': True},
     {'cgags.REFIT_ITERATIONS': 1, 'cgags.MIN_PAIR_DISTANCE_FACTOR': 1.0}),
    ({'max_iterations': 3000}, {'search.STOPPING': 'fixed'}),
])
def test_every_variant_still_registers(bunny, monkeypatch, config, constants):
    from cgags_ros.registration import cgags, search

    modules = {'cgags': cgags, 'search': search}
    for name, value in constants.items():
        module, constant = name.split('.')
        monkeypatch.setattr(modules[module], constant, value)
    prob = make_correspondences(bunny, 1000, 0.95, rng=21)
    res = register_correspondences(prob.src, prob.dst, inlier_threshold=TAU,
                                   config=CoreConfig(**config), seed=1)
    _check_recovery(prob, res)


def test_pure_outliers_are_not_reported_valid(bunny):
    rng = np.random.default_rng(0)
    src = bunny[rng.integers(0, len(bunny), 1000)]
    dst = rng.uniform(-0.5, 0.5, (1000, 3))
    res = register_correspondences(src, dst, inlier_threshold=TAU, seed=0)
    assert not res.valid
    # no consensus is large enough, or stands out from what random pairs reach
    assert res.refusal.code in {Code.FEW_INLIERS, Code.CHANCE_LEVEL, Code.NO_ESTIMATE}, res.refusal


def test_incompatible_correspondences_give_a_reason():
    rng = np.random.default_rng(1)
    src = rng.uniform(0, 1, (50, 3))
    dst = rng.uniform(0, 1000, (50, 3))  # nothing length-consistent at this threshold
    res = register_correspondences(src, dst, inlier_threshold=1e-4)
    assert not res.valid and res.refusal.code is Code.NO_ESTIMATE
    assert 'length-consistent' in res.reason
    assert np.array_equal(res.transform, np.eye(4))


@pytest.mark.parametrize('src,dst,error,match', [
    (np.zeros((2, 3)), np.zeros((2, 3)), DegenerateCorrespondencesError, 'at least 3'),
    (np.ones((10, 3)), np.random.default_rng(0).normal(size=(10, 3)),
     DegenerateCorrespondencesError, 'identical'),
    (np.outer(np.arange(10.0), [1, 2, 3]), np.random.default_rng(0).normal(size=(10, 3)),
     DegenerateCorrespondencesError, 'collinear'),
    (np.zeros((10, 2)), np.zeros((10, 2)), InvalidInputError, 'shape'),
    (np.zeros((10, 3)), np.zeros((9, 3)), InvalidInputError, 'same number of rows'),
    (np.array([[np.nan, 0, 0]] + [[i, i * i, 1.0] for i in range(9)]),
     np.random.default_rng(0).normal(size=(10, 3)), InvalidInputError, 'NaN'),
    ([['a', 'b', 'c']] * 5, np.zeros((5, 3)), InvalidInputError, 'numeric'),
])
def test_bad_input_raises_typed_errors(src, dst, error, match):
    with pytest.raises(error, match=match):
        register_correspondences(src, dst, inlier_threshold=0.1)


def test_thresholds_are_required_and_positive(bunny):
    prob = make_correspondences(bunny, 100, 0.5, rng=0)
    with pytest.raises(InvalidInputError, match='inlier_threshold'):
        register_correspondences(prob.src, prob.dst)
    with pytest.raises(InvalidInputError, match='positive'):
        register_correspondences(prob.src, prob.dst, inlier_threshold=-1.0)
    with pytest.raises(InvalidInputError, match='positive'):
        register_correspondences(prob.src, prob.dst, resolution=float('nan'))


def test_invalid_config_is_rejected(bunny):
    from cgags_ros.errors import InvalidConfigError

    prob = make_correspondences(bunny, 100, 0.5, rng=0)
    with pytest.raises(InvalidConfigError, match='p1'):
        register_correspondences(prob.src, prob.dst, inlier_threshold=TAU,
                                 config=CoreConfig(p1=1.5))
    with pytest.raises(InvalidConfigError, match='motion_model'):
        register_correspondences(prob.src, prob.dst, inlier_threshold=TAU,
                                 config=CoreConfig(motion_model='magic'))


def test_twenty_thousand_correspondences_stay_under_1gb(bunny):
    prob = make_correspondences(bunny, 20000, 0.95, rng=4)
    tracemalloc.start()
    res = register_correspondences(prob.src, prob.dst, inlier_threshold=TAU, seed=0)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 1 << 30, f'peak {peak / 2**20:.0f} MiB'
    _check_recovery(prob, res)


def test_nearly_collinear_correspondences_end_quickly_and_invalid():
    rng = np.random.default_rng(3)
    line = np.outer(rng.uniform(0, 1, 2000), [1.0, 0.5, 0.2]) + rng.normal(0, 1e-4, (2000, 3))
    res = register_correspondences(line, line + [0.1, 0, 0], inlier_threshold=0.01, seed=0)
    assert not res.valid and res.refusal.code is Code.COLLINEAR
    assert 'collinear' in res.reason
    # Quickly in draws, not seconds: a fresh clone's first call also compiles the numba code.
    # The sampling bound stops it, far from the iteration cap.
    assert res.stats['stopped_by'] not in ('max_iterations', 'time_budget'), res.stats
    draws = res.stats['compatible_samples'] + res.stats['guided_samples']
    assert draws < CoreConfig().max_iterations // 100, res.stats


def test_blas_runs_single_threaded_during_the_core_and_is_restored(bunny, monkeypatch):
    threadpoolctl = pytest.importorskip('threadpoolctl')
    from cgags_ros.registration import motion

    def blas_threads():
        return [lib['num_threads'] for lib in threadpoolctl.threadpool_info()
                if lib['user_api'] == 'blas']

    before = blas_threads()
    with threadpoolctl.threadpool_limits(limits=2, user_api='blas'):
        outer = blas_threads()
        seen = []
        build = motion.build_compatibility_graph

        def spy(*args, **kwargs):
            seen.append(blas_threads())
            return build(*args, **kwargs)

        monkeypatch.setattr(motion, 'build_compatibility_graph', spy)
        prob = make_correspondences(bunny, 300, 0.5, rng=3)
        _check_recovery(prob, register_correspondences(prob.src, prob.dst, inlier_threshold=TAU))
        assert seen and all(n == 1 for n in seen[0])
        assert blas_threads() == outer  # the caller's limits come back
    assert blas_threads() == before
