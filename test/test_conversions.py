"""
PointCloud2 layouts, malformed clouds, poses and quaternions.

Tests of cgags_ros.io.pointcloud2 and the message builders of ros/outputs.py and transforms.py.
"""

from __future__ import annotations

import types

from cgags_ros import geometry
from cgags_ros.errors import EmptyCloudError, InvalidInputError, MalformedCloudError
from cgags_ros.io import pointcloud2 as pc2
from cgags_ros.io.bag import read_messages
from cgags_ros.ros import outputs as conv
from cgags_ros.ros.transforms import transform_to_transform_stamped
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

RNG = np.random.default_rng(7)


def field(name, offset, datatype, count=1):
    return types.SimpleNamespace(name=name, offset=offset, datatype=datatype, count=count)


def make_cloud(points, *, layout=(('x', 7), ('y', 7), ('z', 7)), pad_point=0, pad_row=0,
               height=1, bigendian=False, extra=()):
    """Build a duck-typed PointCloud2 with arbitrary field order/types/padding/endianness."""
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    width = n // height
    order = '>' if bigendian else '<'
    names, formats, offsets, fields, offset = [], [], [], [], 0
    for name, datatype in list(layout) + list(extra):
        fmt = {7: 'f4', 8: 'f8', 2: 'u1', 4: 'u2'}[datatype]
        names.append(name)
        formats.append(order + fmt)
        offsets.append(offset)
        fields.append(field(name, offset, datatype))
        offset += np.dtype(fmt).itemsize
    point_step = offset + pad_point
    dtype = np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                      'itemsize': point_step})
    arr = np.zeros(n, dtype=dtype)
    for i, axis in enumerate('xyz'):
        if axis in names:
            arr[axis] = points[:, i]
    row_bytes = width * point_step
    rows = np.zeros((height, row_bytes + pad_row), dtype=np.uint8)
    rows[:, :row_bytes] = arr.view(np.uint8).reshape(height, row_bytes)
    return types.SimpleNamespace(
        height=height, width=width, fields=fields, is_bigendian=bigendian,
        point_step=point_step, row_step=row_bytes + pad_row, data=rows.tobytes(),
        is_dense=bool(np.isfinite(points).all()))


POINTS = RNG.normal(size=(60, 3)) * 10.0


@pytest.mark.parametrize('kwargs', [
    {},
    {'layout': (('z', 7), ('x', 7), ('y', 7))},
    {'layout': (('x', 8), ('y', 8), ('z', 8))},
    {'layout': (('x', 7), ('y', 7), ('z', 7)), 'extra': (('intensity', 7), ('ring', 4)),
     'pad_point': 2},
    {'bigendian': True},
    {'bigendian': True, 'layout': (('y', 8), ('z', 8), ('x', 8))},
    {'height': 6, 'pad_row': 5},
])
def test_layouts_decode_exactly(kwargs):
    msg = make_cloud(POINTS, **kwargs)
    xyz = pc2.pointcloud2_to_xyz(msg)
    assert xyz.dtype == np.float64 and xyz.shape == (60, 3)
    tol = 0 if kwargs.get('layout', (('x', 7),))[0][1] == 8 else 1e-5
    np.testing.assert_allclose(xyz, POINTS, rtol=tol, atol=tol)


def test_organized_cloud_with_nans_drops_non_finite_points():
    pts = POINTS.copy()
    pts[::4] = np.nan
    pts[1, 2] = np.inf
    xyz = pc2.pointcloud2_to_xyz(make_cloud(pts, height=6))
    keep = np.isfinite(pts).all(axis=1)
    np.testing.assert_allclose(xyz, pts[keep], atol=1e-5)


@pytest.mark.parametrize('mutate, match', [
    (lambda m: setattr(m, 'fields', m.fields[:2]), 'no z field'),
    (lambda m: setattr(m, 'data', m.data[:-12]), 'truncated'),
    (lambda m: setattr(m, 'row_step', m.row_step - 1), 'row_step'),
    (lambda m: setattr(m, 'width', 10**9), 'above the limit'),
    (lambda m: setattr(m, 'point_step', 8), 'does not fit'),
    (lambda m: setattr(m, 'point_step', 10**6), 'absurd'),
    (lambda m: setattr(m.fields[0], 'datatype', 2), 'UINT8'),
    (lambda m: setattr(m.fields[1], 'datatype', 42), 'unknown'),
    (lambda m: setattr(m, 'height', -1), 'negative'),
])
def test_malformed_clouds_raise_with_reason(mutate, match):
    msg = make_cloud(POINTS)
    mutate(msg)
    with pytest.raises(MalformedCloudError, match=match):
        pc2.pointcloud2_to_xyz(msg)


def test_empty_and_all_nan_clouds():
    empty = make_cloud(np.zeros((0, 3)))
    with pytest.raises(EmptyCloudError, match='no points'):
        pc2.pointcloud2_to_xyz(empty)
    with pytest.raises(EmptyCloudError, match='none is finite'):
        pc2.pointcloud2_to_xyz(make_cloud(np.full((8, 3), np.nan)))


def test_round_trip_through_rclpy_message():
    from std_msgs.msg import Header

    header = Header(frame_id='velodyne')
    msg = conv.xyz_to_pointcloud2(POINTS, header)
    assert (msg.width, msg.height, msg.point_step, msg.row_step) == (60, 1, 12, 720)
    assert msg.header.frame_id == 'velodyne' and msg.is_dense
    np.testing.assert_allclose(pc2.pointcloud2_to_xyz(msg), POINTS, rtol=1e-6, atol=1e-5)


def test_bag_messages_decode_and_faulty_bag_reasons(data_dir):
    bags = data_dir / 'bags'
    rec = next(read_messages(bags / 'lidar', ['/source_cloud']))
    xyz = pc2.pointcloud2_to_xyz(rec.msg)  # rosbags message, intensity field skipped
    assert xyz.shape == (rec.msg.width, 3) and np.abs(xyz).max() < 200.0
    outcomes = []
    for rec in read_messages(bags / 'faulty', ['/source_cloud']):
        try:
            outcomes.append(len(pc2.pointcloud2_to_xyz(rec.msg)))
        except (EmptyCloudError, MalformedCloudError) as exc:
            outcomes.append(type(exc).__name__)
    assert outcomes.count('EmptyCloudError') == 2 and outcomes.count('MalformedCloudError') == 2
    assert outcomes[-1] == 40097  # the good cloud at the end


def test_quaternion_matrix_round_trip_including_near_180_degrees():
    rots = list(Rotation.random(50, random_state=3)) + [
        Rotation.from_rotvec([np.pi, 0, 0]), Rotation.from_rotvec([0, np.pi - 1e-9, 0]),
        Rotation.from_rotvec([0.0, 0.0, 0.0])]
    for rot in rots:
        R = rot.as_matrix()
        q = geometry.matrix_to_quaternion(R)
        assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(geometry.quaternion_to_matrix(q), R, atol=1e-9)
        q_ref = rot.as_quat()  # scipy also uses (x, y, z, w)
        assert min(np.abs(q - q_ref).max(), np.abs(q + q_ref).max()) < 1e-9


def test_pose_round_trip_rclpy_and_duck_typed():
    T = geometry.make_transform(
        Rotation.from_euler('xyz', [10, -20, 170], degrees=True).as_matrix(), [1.0, -2.0, 0.5])
    pose = conv.transform_to_pose(T)
    np.testing.assert_allclose(pc2.pose_to_transform(pose), T, atol=1e-12)
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import PoseStamped
    from std_msgs.msg import Header

    stamped = PoseStamped(header=Header(frame_id='map'), pose=pose)  # as ~/pose carries it
    np.testing.assert_allclose(pc2.pose_to_transform(stamped), T, atol=1e-12)
    tf = transform_to_transform_stamped(T, Header(frame_id='map'), 'base')
    np.testing.assert_allclose(pc2.pose_to_transform(tf), T, atol=1e-12)
    ns = types.SimpleNamespace
    duck = ns(header=None, pose=ns(
        position=ns(x=1.0, y=-2.0, z=0.5),
        orientation=ns(**dict(zip('xyzw', geometry.matrix_to_quaternion(T[:3, :3]))))))
    np.testing.assert_allclose(pc2.pose_to_transform(duck), T, atol=1e-12)
    assert (pc2.stamp_to_ns(Time(sec=1_700_000_000, nanosec=500_000_001))
            == 1_700_000_000_500_000_001)


def test_fields_to_pointcloud2_carries_every_field_and_decodes_to_xyz():
    table = np.zeros(50, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'),
                                ('intensity', '<f4'), ('ring', '<u2'), ('t', '<f8')])
    xyz = RNG.uniform(-10, 10, (50, 3))
    for i, c in enumerate('xyz'):
        table[c] = xyz[:, i]
    table['ring'] = np.arange(50)
    msg = conv.fields_to_pointcloud2(table)
    assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [
        ('x', 0, 7), ('y', 4, 7), ('z', 8, 7), ('intensity', 12, 7), ('ring', 16, 4),
        ('t', 18, 8)]
    assert msg.point_step == 26 and msg.row_step == 26 * 50 and msg.is_dense
    assert bytes(msg.data) == table.tobytes()
    np.testing.assert_allclose(pc2.pointcloud2_to_xyz(msg), xyz.astype(np.float32))
    with pytest.raises(InvalidInputError, match='PointField'):
        conv.fields_to_pointcloud2(np.zeros(3, dtype=[('x', '<f4'), ('v', '<f4', (3,))]))
