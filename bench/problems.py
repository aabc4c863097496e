"""
The core benchmark's problems: one seed, ground truth and correspondence set a cell and trial.

A problem depends only on (seed, outlier ratio, N, trial), never on which cells or solvers
a run has, so ``bench.core``, ``bench.ab_core`` (the core against an earlier revision's)
and ``bench.studies.chance_sample`` see the same problems for the same cell.
"""

from __future__ import annotations

from bench.datasets.synthetic import make_correspondences, SyntheticProblem
import numpy as np
from scipy.spatial.transform import Rotation


def problem_seed(seed: int, ratio: float, n: int, trial: int) -> int:
    """Per-problem seed that depends only on (seed, ratio, N, trial), not on the cells run."""
    ss = np.random.SeedSequence([int(seed), int(round(ratio * 10000)), int(n), int(trial)])
    return int(ss.generate_state(1, dtype=np.uint32)[0])


def problem_transform(motion: str, seed: int, tilt_noise: float = 0.0) -> np.ndarray | None:
    """
    Return the ground truth of a 4-DoF problem (None for 6-DoF: a random one).

    Yaw uniform about +z, translation uniform in [-1, 1]^3, then a tilt of ``tilt_noise``
    degrees about a random horizontal axis. Drawn from its own stream of the problem seed,
    so the correspondences are drawn as for 6-DoF.
    """
    if motion != '4dof':
        return None
    rng = np.random.default_rng([seed, 4])
    T = np.eye(4)
    axis = np.r_[rng.normal(size=2), 0.0]
    tilt = Rotation.from_rotvec(np.radians(tilt_noise) * axis / np.linalg.norm(axis))
    T[:3, :3] = (tilt * Rotation.from_euler('z', rng.uniform(-np.pi, np.pi))).as_matrix()
    T[:3, 3] = rng.uniform(-1.0, 1.0, 3)
    return T


def problem(model: np.ndarray, n: int, ratio: float, trial: int, *, seed: int = 0,
            motion: str = '6dof', outliers: str = 'uniform', noise: float = 0.01,
            tilt_noise: float = 0.0) -> tuple[int, SyntheticProblem]:
    """Return the problem seed and the correspondences of one cell's trial."""
    s = problem_seed(seed, ratio, n, trial)
    return s, make_correspondences(model, n, ratio, noise_sigma=noise, rng=s, outliers=outliers,
                                   transform=problem_transform(motion, s, tilt_noise))
