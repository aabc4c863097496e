"""cgags_ros.geometry.voxel_size_for: the voxel size that leaves a cloud about N voxels."""

from cgags_ros.errors import InvalidInputError
from cgags_ros.geometry import voxel_size_for
import numpy as np
import pytest


def test_voxel_size_for_a_lattice_and_its_scale():
    # 20^3 points 0.1 m apart: 10^3 voxels of 0.2 m hold them.
    lattice = np.stack(np.meshgrid(*[np.arange(20) * 0.1] * 3), axis=-1).reshape(-1, 3)
    lattice += 0.01  # off the voxel edges
    voxel = voxel_size_for(lattice, 1000)
    assert 0.18 <= voxel <= 0.22
    assert voxel == float(f'{voxel:.2g}')  # two significant digits
    assert voxel_size_for(100.0 * lattice, 1000) == pytest.approx(100.0 * voxel, rel=0.05)
    assert voxel_size_for(lattice, 8) > voxel > voxel_size_for(lattice, 4000)


def test_voxel_size_for_too_few_points():
    with pytest.raises(InvalidInputError, match='only 10 points'):
        voxel_size_for(np.zeros((10, 3)), 5000)
