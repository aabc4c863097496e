"""cgags_ros.io.clouds and bench.datasets.gt_pairs on the shared real data."""

from bench.datasets.gt_pairs import find_pair, parse_gt_pairs, read_gt_pairs
from cgags_ros.errors import InvalidInputError
from cgags_ros.io.clouds import read_cloud, read_cloud_and_normals, write_cloud
from cgags_ros.io.pcd import read_fields as read_pcd_fields
import numpy as np
import pytest


@pytest.mark.parametrize('relpath, count', [
    ('objects/stanford_bunny_scans/bun000.ply', 40256),  # ascii PLY + range_grid element
    ('indoor_3dmatch/7-scenes-redkitchen/cloud_bin_0.ply', 258342),  # binary PLY
    ('lidar/small_gicp/source.ply', 69792),  # binary PLY with intensity
    ('objects/pcl/bun0.pcd', 397),  # ascii PCD
    ('indoor_3dmatch/geotransformer_demo/src.npy', 15953),
])
def test_read_real_clouds(data_dir, relpath, count):
    points = read_cloud(data_dir / relpath)
    assert points.shape == (count, 3) and points.dtype == np.float64
    assert np.isfinite(points).all()


@pytest.mark.parametrize('suffix', ['.ply', '.pcd', '.npy', '.csv', '.xyz', '.txt'])
def test_write_read_round_trip(tmp_path, suffix):
    points = np.random.default_rng(0).normal(size=(50, 3))
    write_cloud(tmp_path / f'c{suffix}', points)
    atol = 0 if suffix in ('.ply', '.pcd', '.npy') else 1e-7
    np.testing.assert_allclose(read_cloud(tmp_path / f'c{suffix}'), points, atol=atol, rtol=0)


def test_text_with_header_and_extra_columns(tmp_path):
    (tmp_path / 'c.csv').write_text('x,y,z,intensity\n1,2,3,9\n4,5,6,9\n')
    np.testing.assert_array_equal(read_cloud(tmp_path / 'c.csv'), [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize('text', [
    '# x y z\n1 2 3\n4\t5   6\n',  # whitespace-separated .csv, as some datasets ship
    'x;y;z\n1;2;3\n4;5;6\n',
    'x\ty\tz\n1\t2\t3\n4\t5\t6\n',
    '1, 2, 3\n4, 5, 6\n',
])
def test_text_delimiter_is_detected(tmp_path, text):
    (tmp_path / 'c.csv').write_text(text)
    np.testing.assert_array_equal(read_cloud(tmp_path / 'c.csv'), [[1, 2, 3], [4, 5, 6]])


def test_truncated_binary_files_fail_loudly(tmp_path, data_dir):
    # Open3D would return zero-padded points here; we must not.
    raw = (data_dir / 'lidar/small_gicp/source.ply').read_bytes()
    (tmp_path / 't.ply').write_bytes(raw[:5000])
    with pytest.raises(InvalidInputError, match='truncated'):
        read_cloud(tmp_path / 't.ply')
    text = (data_dir / 'objects/pcl/bun0.pcd').read_text()
    (tmp_path / 't.pcd').write_text(text[:3000])
    with pytest.raises(InvalidInputError, match='truncated'):
        read_cloud(tmp_path / 't.pcd')


@pytest.mark.parametrize('name, content, match', [
    ('missing.ply', None, 'no such file'),
    ('cloud.obj', b'v 1 2 3\n', 'unsupported point cloud format'),
    ('garbage.ply', b'hello\n', 'not a PLY file'),
    ('garbage.pcd', b'hello\n', 'not a PCD file'),
    ('bad.csv', b'1,2,3\n4,five,6\n', 'cannot read'),
    ('flat.npy', None, 'expected an \\(N, 3\\) array'),
])
def test_unreadable_files_raise_invalid_input(tmp_path, name, content, match):
    path = tmp_path / name
    if name == 'flat.npy':
        np.save(path, np.zeros(5))
    elif content is not None:
        path.write_bytes(content)
    with pytest.raises(InvalidInputError, match=match):
        read_cloud(path)


def test_gt_pairs_of_every_folder(data_dir):
    pairs = {(s.name, t.name): T for f in sorted(data_dir.glob('**/gt_pairs.txt'))
             for s, t, T in read_gt_pairs(f)}
    assert {('bun045.ply', 'bun000.ply'), ('cloud_bin_4.ply', 'cloud_bin_0.ply'),
            ('src.npy', 'ref.npy'), ('source.ply', 'target.ply')} <= set(pairs)
    # The demo's gt.npy and the parsed block agree (same source -> target convention).
    gt = np.load(data_dir / 'indoor_3dmatch/geotransformer_demo/gt.npy')
    np.testing.assert_allclose(pairs[('src.npy', 'ref.npy')], gt, atol=1e-8)
    s, _, _ = find_pair(data_dir / 'indoor_3dmatch/gt_pairs.txt', 'src.npy', 'ref.npy')
    assert s.exists()


def test_gt_pairs_format_errors():
    good = '# c\npair a b\n' + '1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n'
    assert parse_gt_pairs(good)[0][:2] == ('a', 'b')
    with pytest.raises(InvalidInputError, match='4 rows of 4'):
        parse_gt_pairs('pair a b\n1 0 0 0\n')
    with pytest.raises(InvalidInputError, match="before any 'pair'"):
        parse_gt_pairs('1 0 0 0\n')
    with pytest.raises(InvalidInputError, match='not a rigid'):
        parse_gt_pairs(good.replace('0 1 0 0', '0 2 0 0'))


def test_read_pcd_fields_keeps_every_field_of_a_kitti_scan(data_dir):
    path = data_dir / 'kitti/seq00_16scans/pcd/000000.pcd'
    table = read_pcd_fields(path)
    assert table.dtype.names == ('x', 'y', 'z', 'intensity', 'normal_x', 'normal_y',
                                 'normal_z', 'curvature')
    assert table.dtype.itemsize == 32 and table.shape == (124668,)
    np.testing.assert_array_equal(np.stack([table[c] for c in 'xyz'], axis=1),
                                  read_cloud(path).astype(np.float32))
    with pytest.raises(InvalidInputError, match='binary'):
        read_pcd_fields(data_dir / 'objects/pcl/bun0.pcd')  # an ascii PCD


def test_normals_round_trip_and_are_read_from_ply_and_pcd(tmp_path, data_dir):
    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 3))
    normals = rng.normal(size=(50, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    write_cloud(tmp_path / 'map.ply', points, normals)
    assert np.array_equal(read_cloud(tmp_path / 'map.ply'), points)
    assert np.array_equal(read_cloud_and_normals(tmp_path / 'map.ply')[1], normals)
    # ascii PLY with the properties in another order, and an ascii PCD with normal_x...
    rows = '\n'.join(' '.join(f'{v:.17g}' for v in (*n, *p)) for p, n in zip(points, normals))
    (tmp_path / 'ascii.ply').write_text(
        'ply\nformat ascii 1.0\nelement vertex 50\nproperty float nx\nproperty float ny\n'
        'property float nz\nproperty double x\nproperty double y\nproperty double z\n'
        'end_header\n' + rows + '\n')
    assert np.allclose(read_cloud_and_normals(tmp_path / 'ascii.ply')[1], normals)
    assert np.allclose(read_cloud(tmp_path / 'ascii.ply'), points)
    (tmp_path / 'a.pcd').write_text(
        'VERSION 0.7\nFIELDS normal_x normal_y normal_z x y z\nSIZE 4 4 4 8 8 8\n'
        'TYPE F F F F F F\nCOUNT 1 1 1 1 1 1\nWIDTH 50\nHEIGHT 1\nPOINTS 50\nDATA ascii\n'
        + rows + '\n')
    assert np.allclose(read_cloud_and_normals(tmp_path / 'a.pcd')[1], normals)
    # A binary PCD with normals (a KITTI scan as shipped): as many rows as points.
    scan = data_dir / 'kitti' / 'seq00_16scans' / 'pcd' / '000002.pcd'
    if scan.exists():
        fields = read_pcd_fields(scan)
        normals_x = read_cloud_and_normals(scan)[1][:, 0]
        assert np.array_equal(normals_x, fields['normal_x'].astype(np.float64))
    # No normals: None; they are written to PLY only.
    write_cloud(tmp_path / 'plain.ply', points)
    for name in ('plain.ply', 'plain.npy'):
        if name.endswith('.npy'):
            np.save(tmp_path / name, np.hstack([points, normals]))
        assert read_cloud_and_normals(tmp_path / name)[1] is None
    with pytest.raises(InvalidInputError, match='PLY only'):
        write_cloud(tmp_path / 'map.pcd', points, normals)
