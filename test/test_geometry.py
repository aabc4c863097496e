"""cgags_ros.geometry: the voxel size that leaves a cloud about N voxels, grid cell codes."""

from cgags_ros.errors import InvalidInputError
from cgags_ros.geometry import grid_cells, voxel_size_for
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


@pytest.mark.parametrize('spread', [3.0, 1e5])
def test_grid_cells_group_and_order_points_as_their_cells_rows_do(spread):
    rng = np.random.default_rng(4)
    points = rng.normal(size=(5000, 3)) * spread
    points[:, 2] *= 1e-3  # flat: one axis spans few cells
    for size, origin in ((spread / 10, None), (spread / 7, np.zeros(3))):
        low = points.min(axis=0) if origin is None else origin
        ijk = np.floor((points - low) / size).astype(np.int64)
        expected = np.unique(ijk, axis=0, return_index=True, return_inverse=True)
        got = np.unique(grid_cells(points, size, origin), return_index=True,
                        return_inverse=True)
        assert np.array_equal(got[1], expected[1])
        assert np.array_equal(got[2], expected[2].reshape(-1))
    # Cells too many for one integer code are still grouped the same.
    far = np.array([[0.0, 0.0, 0.0], [1e7, 1e7, 1e7], [0.0, 0.0, 0.0], [1e7, 0.0, 1e7]])
    codes = grid_cells(far, 1e-5)
    assert codes[0] == codes[2] and len(np.unique(codes)) == 3
    assert list(np.argsort(codes, kind='stable')) == [0, 2, 3, 1]
