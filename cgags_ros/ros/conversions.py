"""
Message builders: numpy arrays and 4x4 transforms to rclpy messages.

The reverse direction (decoding PointCloud2, reading poses and stamps) is ROS-free and
lives in :mod:`cgags_ros.io.pointcloud2`. Conventions as there: metres, the header's
frame, ``T`` maps source-frame points into the target frame (the pose of the source frame
in the target frame), quaternions ``(x, y, z, w)``.
"""

from __future__ import annotations

import array
from typing import Any

from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose, TransformStamped
import numpy as np
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from ..errors import InvalidInputError
from ..geometry import matrix_to_quaternion
from ..io.pointcloud2 import data_bytes, POINT_FIELD_TYPES


def xyz_to_pointcloud2(points: np.ndarray, header: Any = None) -> Any:
    """
    Build a dense, unorganized ``sensor_msgs/PointCloud2`` (float32 x, y, z; 12-byte points).

    ``header`` is a std_msgs/Header (or None for an empty one); points are in its frame.

    :raises InvalidInputError: for anything but an (N, 3) array.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidInputError(f'points must have shape (N, 3), got {pts.shape}')
    xyz = np.dtype([(name, '<f4') for name in 'xyz'])
    return fields_to_pointcloud2(np.ascontiguousarray(pts, dtype='<f4').view(xyz).reshape(-1),
                                 header)


def fields_to_pointcloud2(table: np.ndarray, header: Any = None) -> Any:
    """
    Build a dense, unorganized ``sensor_msgs/PointCloud2`` carrying every field of ``table``.

    ``table`` is a structured array, one record per point, of numeric scalar fields (e.g.
    :func:`cgags_ros.io.pcd.read_fields`: x, y, z in metres, intensity, normals...);
    the layout is the array's, little-endian. ``header`` as in :func:`xyz_to_pointcloud2`.

    :raises InvalidInputError: for a field that is not a numeric scalar of a PointField type.
    """
    table = np.ascontiguousarray(table)
    names = table.dtype.names or ()
    datatypes = {np.dtype(name.lower()): code for code, (name, _) in POINT_FIELD_TYPES.items()}
    fields = []
    for name in names:
        kind, offset = table.dtype.fields[name][:2]
        if kind.shape or kind.newbyteorder('<') not in datatypes:
            raise InvalidInputError(f'field {name!r} of type {kind} has no PointField type')
        if kind.byteorder == '>':
            raise InvalidInputError(f'field {name!r} is big-endian')
        fields.append(PointField(name=name, offset=int(offset),
                                 datatype=datatypes[kind.newbyteorder('<')], count=1))
    msg = PointCloud2()
    if header is not None:
        msg.header = header
    msg.height, msg.width = 1, int(table.shape[0])
    msg.fields = fields
    msg.is_bigendian = False
    msg.point_step = table.dtype.itemsize
    msg.row_step = msg.point_step * msg.width
    msg.is_dense = all(np.isfinite(table[c]).all() for c in 'xyz' if c in names)
    # array.array('B') takes rclpy's fast path; a bytes/list value is checked byte by byte.
    buf = array.array('B')
    buf.frombytes(table.tobytes())
    msg.data = buf
    return msg


def to_rclpy_pointcloud2(msg: Any) -> Any:
    """
    Copy any PointCloud2-like message (e.g. from rosbags) into an rclpy PointCloud2.

    The copy is byte for byte: layout, header and even malformed sizes are kept, so a bag
    can be republished exactly as recorded.
    """
    out = PointCloud2()
    out.header = Header(stamp=Time(sec=int(msg.header.stamp.sec),
                                   nanosec=int(msg.header.stamp.nanosec)),
                        frame_id=str(msg.header.frame_id))
    out.height, out.width = int(msg.height), int(msg.width)
    out.fields = [PointField(name=str(f.name), offset=int(f.offset), datatype=int(f.datatype),
                             count=int(f.count)) for f in msg.fields]
    out.is_bigendian, out.is_dense = bool(msg.is_bigendian), bool(msg.is_dense)
    out.point_step, out.row_step = int(msg.point_step), int(msg.row_step)
    buf = array.array('B')
    buf.frombytes(data_bytes(msg.data).tobytes())
    out.data = buf
    return out


def _check_transform(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InvalidInputError(f'transform must be a finite 4x4 array, got shape {T.shape}')
    return T


def transform_to_pose(T: np.ndarray) -> Any:
    """4x4 transform -> geometry_msgs/Pose."""
    T = _check_transform(T)
    qx, qy, qz, qw = matrix_to_quaternion(T[:3, :3])
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in T[:3, 3])
    pose.orientation.x, pose.orientation.y = float(qx), float(qy)
    pose.orientation.z, pose.orientation.w = float(qz), float(qw)
    return pose


def transform_to_transform_stamped(T: np.ndarray, header: Any, child_frame_id: str) -> Any:
    """4x4 transform -> geometry_msgs/TransformStamped (parent = header.frame_id)."""
    T = _check_transform(T)
    msg = TransformStamped(header=header, child_frame_id=child_frame_id)
    tr, rot = msg.transform.translation, msg.transform.rotation
    tr.x, tr.y, tr.z = (float(v) for v in T[:3, 3])
    rot.x, rot.y, rot.z, rot.w = (float(v) for v in matrix_to_quaternion(T[:3, :3]))
    return msg
