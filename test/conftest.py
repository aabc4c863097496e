"""
Shared fixtures.

Real data comes from ../shared/data (read-only, never copied here); a bare clone has no
../shared, so the tests that need it skip with the reason. CI sets CGAGS_REQUIRE_DATA=1,
which makes them fail instead, so that CI still runs every one. What a bare clone runs on
lives in test/fixtures/ (small, committed, each with its licence).
"""

import os
from pathlib import Path

from cgags_ros.parallel import quiet_idle_threads

# The suite runs the pipeline in its own process, as the tools do: set up before numpy loads.
quiet_idle_threads()

from cgags_ros.io.shared_data import shared_data_dir  # noqa: E402, I100
import pytest  # noqa: E402

REQUIRE_DATA = 'CGAGS_REQUIRE_DATA'
FIXTURES = Path(__file__).resolve().parent / 'fixtures'


def require_shared(path: Path, what: str, marker: str = 'README.md', hint: str = '') -> Path:
    """
    Return ``path`` if ``path / marker`` exists; else skip the test (CGAGS_REQUIRE_DATA=1: fail).

    Call it from a fixture or a test, never at module level (a bare clone must collect).
    """
    if (path / marker).exists():
        return path
    reason = f'{what} not found at {path}'
    if os.environ.get(REQUIRE_DATA) == '1':
        pytest.fail(f'{reason}, and {REQUIRE_DATA}=1 requires it', pytrace=False)
    pytest.skip(f'{reason} (no ../shared beside this clone{hint})')


@pytest.fixture(scope='session', name='require_shared')
def require_shared_fixture():
    """Provide :func:`require_shared` to test modules (conftest is not importable by name)."""
    return require_shared


@pytest.fixture(scope='session')
def data_dir() -> Path:
    """Return the shared test data folder (../shared/data or CGAGS_DATA_DIR)."""
    return require_shared(shared_data_dir(), 'shared test data',
                          hint='; CGAGS_DATA_DIR names another copy')


@pytest.fixture(scope='session')
def benchmark_pair(data_dir):
    """
    Return ``pair(scene, target, source)`` -> (source points, target points, 4x4 truth).

    A pair of the 3DMatch or 3DLoMatch list of one of the benchmark's scenes (fragments
    ``source`` into ``target``, the truth projected onto a rotation).
    """
    from bench.datasets import threedmatch as tdm

    root = require_shared(data_dir / '3dmatch_benchmark', '3dmatch_benchmark',
                          marker='benchmarks')
    scenes: dict[str, tuple[dict, tdm.Fragments]] = {}

    def pair(scene: str, target: int, source: int):
        if scene not in scenes:
            scenes[scene] = ({(p.target, p.source): p for benchmark in tdm.BENCHMARKS
                              for p in tdm.registration_pairs(root, benchmark, scene)},
                             tdm.Fragments(root, scene))
        pairs, fragments = scenes[scene]
        p = pairs[(target, source)]
        return fragments[source], fragments[target], tdm.nearest_rigid(p.transform)
    return pair


@pytest.fixture(scope='session')
def redkitchen_pair(benchmark_pair):
    """Return ``pair(target, source)``: :func:`benchmark_pair` of the redkitchen scene."""
    return lambda target, source: benchmark_pair('7-scenes-redkitchen', target, source)


@pytest.fixture(scope='module')
def kitti(data_dir):
    """Return the 16 KITTI scans (Velodyne frame, metres) and (16, 4, 4): scan k -> scan 0."""
    from bench.datasets.rigs import KITTI_SCANS, kitti_scans
    import numpy as np

    scans = kitti_scans(data_dir, list(range(16)))
    truth = np.loadtxt((data_dir / KITTI_SCANS).parent / 'pseudo_gt.txt').reshape(-1, 4, 4)
    return scans, truth
