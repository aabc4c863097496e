"""
PointCloud2 decoding and pose/stamp reading, duck-typed and ROS-free.

Decoding reads only the attributes every PointCloud2 has (``height``, ``width``,
``fields[name, offset, datatype, count]``, ``is_bigendian``, ``point_step``, ``row_step``,
``data``), so rclpy messages and rosbags-deserialized messages both work, and the offline
tools need no ROS installation. Building messages is :mod:`cgags_ros.ros.outputs`.

Conventions: points in metres, in the frame of the message header (REP-103). A pose is the
4x4 transform ``T`` of the source frame in the target frame (``p_target = T[:3,:3] @
p_source + T[:3,3]``); quaternions ``(x, y, z, w)`` as in geometry_msgs.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import EmptyCloudError, MalformedCloudError
from ..geometry import make_transform, quaternion_to_matrix

# sensor_msgs/PointField datatype constants -> (name, size in bytes)
POINT_FIELD_TYPES = {
    1: ('INT8', 1), 2: ('UINT8', 1), 3: ('INT16', 2), 4: ('UINT16', 2),
    5: ('INT32', 4), 6: ('UINT32', 4), 7: ('FLOAT32', 4), 8: ('FLOAT64', 8),
}
_XYZ_DTYPES = {7: 'f4', 8: 'f8'}
FLOAT32 = 7

# Sanity limits: a cloud beyond these is a corrupt header, not a real sensor frame.
MAX_POINTS = 50_000_000
MAX_POINT_STEP = 65_536


# --------------------------------------------------------------------------- PointCloud2


def _int_attr(msg: Any, name: str) -> int:
    try:
        value = getattr(msg, name)
    except AttributeError as exc:
        raise MalformedCloudError(f'not a PointCloud2: no attribute {name!r}') from exc
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise MalformedCloudError(f'{name} must be an integer, got {value!r}')
    if value < 0:
        raise MalformedCloudError(f'{name} = {value} is negative')
    return int(value)


def data_bytes(data: Any) -> np.ndarray:
    """Return the message's data field as a flat uint8 array, without copying where possible."""
    if isinstance(data, np.ndarray):
        return data.view(np.uint8).reshape(-1) if data.dtype.itemsize == 1 else \
            np.frombuffer(data.tobytes(), np.uint8)
    try:
        # bytes, bytearray, memoryview and rclpy's array.array('B') all expose a buffer
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        return np.asarray(list(data), dtype=np.uint8)


def pointcloud2_to_xyz(msg: Any, *, max_points: int = MAX_POINTS) -> np.ndarray:
    """
    Decode x, y, z of every finite point of a PointCloud2 (an (N, 3) float64 array, metres).

    Handles any field order, float32 or float64 coordinates, padding inside a point and at
    the end of each row (``row_step > width * point_step``), organized clouds
    (``height > 1``), big-endian data and non-finite points (dropped, whatever
    ``is_dense`` claims).

    :raises MalformedCloudError: for a missing x/y/z field, an unsupported coordinate
        datatype, a field that does not fit in ``point_step``, ``data`` whose length
        disagrees with ``height * row_step``, or absurd sizes (more than ``max_points``
        points).
    :raises EmptyCloudError: for no points, or no finite point.
    """
    height = _int_attr(msg, 'height')
    width = _int_attr(msg, 'width')
    point_step = _int_attr(msg, 'point_step')
    row_step = _int_attr(msg, 'row_step')
    fields = {str(f.name): f for f in getattr(msg, 'fields', [])}
    missing = [axis for axis in 'xyz' if axis not in fields]
    if missing:
        raise MalformedCloudError(
            f"PointCloud2 has no {'/'.join(missing)} field (fields: "
            f"{', '.join(fields) or 'none'}); an x, y, z cloud is required")
    n = height * width
    if n > max_points:
        raise MalformedCloudError(
            f'PointCloud2 claims {height} x {width} = {n} points, above the limit {max_points}')
    if point_step > MAX_POINT_STEP:
        raise MalformedCloudError(
            f'point_step = {point_step} bytes is absurd (> {MAX_POINT_STEP})')

    dtype_fields = {}
    for axis in 'xyz':
        f = fields[axis]
        datatype = int(f.datatype)
        if datatype not in _XYZ_DTYPES:
            type_name = POINT_FIELD_TYPES.get(datatype, (f'unknown ({datatype})',))[0]
            raise MalformedCloudError(
                f'field {axis!r} has datatype {type_name}; only FLOAT32 and FLOAT64 '
                'coordinates are supported')
        if int(getattr(f, 'count', 1)) < 1:
            raise MalformedCloudError(f'field {axis!r} has count {f.count}; expected >= 1')
        size = 8 if datatype == 8 else 4
        offset = int(f.offset)
        if offset < 0 or offset + size > point_step:
            raise MalformedCloudError(
                f'field {axis!r} (offset {offset}, {size} bytes) does not fit in '
                f'point_step = {point_step}')
        dtype_fields[axis] = (_XYZ_DTYPES[datatype], offset)

    data = data_bytes(msg.data)
    if n == 0:
        raise EmptyCloudError(
            f'PointCloud2 has no points (height {height}, width {width}, {data.size} data bytes)')
    if row_step < width * point_step:
        raise MalformedCloudError(
            f'row_step = {row_step} is smaller than width * point_step = {width} * '
            f'{point_step} = {width * point_step}')
    if data.size != height * row_step:
        raise MalformedCloudError(
            f'data has {data.size} bytes but height * row_step = {height} * {row_step} = '
            f'{height * row_step}; the message is truncated or its header is wrong')

    order = '>' if bool(getattr(msg, 'is_bigendian', False)) else '<'
    dtype = np.dtype({'names': list(dtype_fields),
                      'formats': [order + fmt for fmt, _ in dtype_fields.values()],
                      'offsets': [off for _, off in dtype_fields.values()],
                      'itemsize': point_step})
    if row_step == width * point_step:
        rows = data
    else:  # drop the padding at the end of every row
        rows = np.ascontiguousarray(data.reshape(height, row_step)[:, :width * point_step])
    structured = rows.view(dtype).reshape(-1)
    xyz = np.empty((n, 3), dtype=np.float64)
    with np.errstate(invalid='ignore'):  # signalling NaNs in the data: dropped just below
        for i, axis in enumerate('xyz'):
            xyz[:, i] = structured[axis]
    finite = np.isfinite(xyz).all(axis=1)
    if not finite.all():
        xyz = xyz[finite]
        if xyz.shape[0] == 0:
            raise EmptyCloudError(f'PointCloud2 has {n} points but none is finite')
    return xyz


# --------------------------------------------------------------------------- stamps


def stamp_to_ns(stamp: Any) -> int:
    """Convert a builtin_interfaces/Time (``sec``, ``nanosec``) to integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


# --------------------------------------------------------------------------- poses


def pose_to_transform(pose: Any) -> np.ndarray:
    """
    Convert a pose to a 4x4 float64 transform.

    Accepts a geometry_msgs Pose, PoseStamped, PoseWithCovariance(Stamped) or
    Transform(Stamped), from rclpy or rosbags (duck-typed).
    """
    while hasattr(pose, 'pose') or hasattr(pose, 'transform'):  # unwrap *Stamped / WithCovariance
        pose = pose.pose if hasattr(pose, 'pose') else pose.transform
    if hasattr(pose, 'position'):
        p, q = pose.position, pose.orientation
    else:  # geometry_msgs/Transform
        p, q = pose.translation, pose.rotation
    R = quaternion_to_matrix((q.x, q.y, q.z, q.w))
    return make_transform(R, (p.x, p.y, p.z))
