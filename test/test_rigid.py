from cgags_ros.geometry import make_transform
from cgags_ros.registration.rigid import kabsch, kabsch_batch, residuals
import numpy as np
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
