from cgags_ros.geometry import make_transform
from cgags_ros.registration.rigid import kabsch, kabsch_batch, residuals
import numpy as np
import pytest
from scipy.spatial.transform import Rotation


def test_kabsch_batch_recovers_random_rigid_motions():
    rng = np.random.default_rng(0)
    R_true = Rotation.random(200, random_state=1).as_matrix()
    t_true = rng.normal(size=(200, 3))
    P = rng.normal(size=(200, 3, 3))
    Q = np.einsum('bij,bkj->bki', R_true, P) + t_true[:, None]
    R, t = kabsch_batch(P, Q)
    assert np.allclose(R, R_true, atol=1e-9)
    assert np.allclose(t, t_true, atol=1e-9)


def test_kabsch_never_returns_a_reflection():
    rng = np.random.default_rng(1)
    P = rng.normal(size=(50, 4, 3))
    Q = P * np.array([-1.0, 1.0, 1.0])  # a mirror image: best proper rotation, not a reflection
    R, _ = kabsch_batch(P, Q)
    assert np.allclose(np.linalg.det(R), 1.0)


def test_kabsch_least_squares_on_noisy_points_and_residuals():
    rng = np.random.default_rng(2)
    T = make_transform(Rotation.from_euler('xyz', [10, -20, 30], degrees=True).as_matrix(),
                       [1, 2, 3])
    src = rng.uniform(-1, 1, (500, 3))
    dst = src @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.001, (500, 3))
    est = kabsch(src, dst)
    assert np.allclose(est, T, atol=5e-4)
    assert residuals(est, src, dst).mean() < 0.003


def test_weighted_kabsch_equals_the_batch_svd_and_residuals_equal_numpy():
    """The compiled Horn fit (kabsch) gives the SVD's optimum, weighted or not, mirrors too."""
    rng = np.random.default_rng(3)
    for trial in range(40):
        k = int(rng.integers(3, 60))
        src = rng.normal(size=(k, 3)) * rng.uniform(0.01, 50)
        R = Rotation.random(random_state=trial).as_matrix()
        dst = src @ R.T + rng.normal(size=3) + rng.normal(0, rng.choice([0, 0.01, 1]), (k, 3))
        if trial % 4 == 0:
            dst = dst * np.array([-1.0, 1.0, 1.0])  # a mirror image
        weights = rng.random(k) if trial % 2 else None
        T = kabsch(src, dst, weights)
        R_ref, t_ref = kabsch_batch(src[None], dst[None], None if weights is None
                                    else weights[None])
        np.testing.assert_allclose(T[:3, :3], R_ref[0], atol=1e-9)
        np.testing.assert_allclose(T[:3, 3], t_ref[0], atol=1e-9 * max(1.0, np.abs(src).max()))
        assert np.allclose(T[3], [0, 0, 0, 1]) and np.isclose(np.linalg.det(T[:3, :3]), 1.0)
        ref = np.linalg.norm(src @ T[:3, :3].T + T[:3, 3] - dst, axis=1)
        np.testing.assert_allclose(residuals(T, src, dst), ref, rtol=1e-12, atol=1e-12)


def test_kabsch_without_weight_is_a_clear_error():
    with pytest.raises(ValueError, match='positive total weight'):
        kabsch(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError, match='positive total weight'):
        kabsch(np.eye(3), np.eye(3), np.zeros(3))
