"""PointCloud2 <-> numpy and pose <-> 4x4 conversions, without sensor_msgs_py or tf2.

Decoding is duck-typed: it reads only the attributes every PointCloud2 has (``height``,
``width``, ``fields[name, offset, datatype, count]``, ``is_bigendian``, ``point_step``,
``row_step``, ``data``), so rclpy messages and rosbags-deserialized messages both work and
the decode path imports no ROS package. Builders (``xyz_to_pointcloud2``,
``transform_to_pose``...) import the ROS message types lazily, inside the function.

Conventions: points in metres, in the frame of the message header (REP-103). A 4x4 transform
``T`` maps source-frame points into the target frame, ``p_target = T[:3,:3] @ p_source +
T[:3,3]``; as a pose it is the pose of the source frame expressed in the target frame.
Quaternions are ``(x, y, z, w)`` as in geometry_msgs.
"""

from __future__ import annotations

import array
from typing import Any

import numpy as np

from ..errors import EmptyCloudError, InvalidInputError, MalformedCloudError

# sensor_msgs/PointField datatype constants -> (name, size in bytes)
POINT_FIELD_TYPES = {
    1: ("INT8", 1), 2: ("UINT8", 1), 3: ("INT16", 2), 4: ("UINT16", 2),
    5: ("INT32", 4), 6: ("UINT32", 4), 7: ("FLOAT32", 4), 8: ("FLOAT64", 8),
}
_XYZ_DTYPES = {7: "f4", 8: "f8"}
FLOAT32 = 7

# Sanity limits: a cloud beyond these is a corrupt header, not a real sensor frame.
MAX_POINTS = 50_000_000
MAX_POINT_STEP = 65_536


# --------------------------------------------------------------------------- PointCloud2


def _int_attr(msg: Any, name: str) -> int:
    try:
        value = getattr(msg, name)
    except AttributeError as exc:
        raise MalformedCloudError(f"not a PointCloud2: no attribute {name!r}") from exc
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise MalformedCloudError(f"{name} must be an integer, got {value!r}")
    if value < 0:
        raise MalformedCloudError(f"{name} = {value} is negative")
    return int(value)


def _data_bytes(data: Any) -> np.ndarray:
    """The message's data field as a flat uint8 array, without copying where possible."""
    if isinstance(data, np.ndarray):
        return data.view(np.uint8).reshape(-1) if data.dtype.itemsize == 1 else \
            np.frombuffer(data.tobytes(), np.uint8)
    try:
        # bytes, bytearray, memoryview and rclpy's array.array('B') all expose a buffer
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        return np.asarray(list(data), dtype=np.uint8)


def cloud_field_names(msg: Any) -> list[str]:
    return [str(f.name) for f in getattr(msg, "fields", [])]


def pointcloud2_to_xyz(msg: Any, *, max_points: int = MAX_POINTS) -> np.ndarray:
    """x, y, z of every finite point of a PointCloud2, as an (N, 3) float64 array (metres).

    Handles any field order, float32 or float64 coordinates, padding inside a point and at
    the end of each row (``row_step > width * point_step``), organized clouds
    (``height > 1``), big-endian data and non-finite points (dropped, whatever
    ``is_dense`` claims).

    Raises:
        MalformedCloudError: a missing x/y/z field, an unsupported coordinate datatype, a
            field that does not fit in ``point_step``, ``data`` whose length disagrees with
            ``height * row_step``, or absurd sizes (more than ``max_points`` points).
        EmptyCloudError: no points, or no finite point.
    """
    height = _int_attr(msg, "height")
    width = _int_attr(msg, "width")
    point_step = _int_attr(msg, "point_step")
    row_step = _int_attr(msg, "row_step")
    fields = {str(f.name): f for f in getattr(msg, "fields", [])}
    missing = [axis for axis in "xyz" if axis not in fields]
    if missing:
        raise MalformedCloudError(
            f"PointCloud2 has no {'/'.join(missing)} field (fields: "
            f"{', '.join(fields) or 'none'}); an x, y, z cloud is required")
    n = height * width
    if n > max_points:
        raise MalformedCloudError(
            f"PointCloud2 claims {height} x {width} = {n} points, above the limit {max_points}")
    if point_step > MAX_POINT_STEP:
        raise MalformedCloudError(f"point_step = {point_step} bytes is absurd (> {MAX_POINT_STEP})")

    dtype_fields = {}
    for axis in "xyz":
        f = fields[axis]
        datatype = int(f.datatype)
        if datatype not in _XYZ_DTYPES:
            type_name = POINT_FIELD_TYPES.get(datatype, (f"unknown ({datatype})",))[0]
            raise MalformedCloudError(
                f"field {axis!r} has datatype {type_name}; only FLOAT32 and FLOAT64 "
                "coordinates are supported")
        if int(getattr(f, "count", 1)) < 1:
            raise MalformedCloudError(f"field {axis!r} has count {f.count}; expected >= 1")
        size = 8 if datatype == 8 else 4
        offset = int(f.offset)
        if offset < 0 or offset + size > point_step:
            raise MalformedCloudError(
                f"field {axis!r} (offset {offset}, {size} bytes) does not fit in "
                f"point_step = {point_step}")
        dtype_fields[axis] = (_XYZ_DTYPES[datatype], offset)

    data = _data_bytes(msg.data)
    if n == 0:
        raise EmptyCloudError(
            f"PointCloud2 has no points (height {height}, width {width}, {data.size} data bytes)")
    if row_step < width * point_step:
        raise MalformedCloudError(
            f"row_step = {row_step} is smaller than width * point_step = {width} * "
            f"{point_step} = {width * point_step}")
    if data.size != height * row_step:
        raise MalformedCloudError(
            f"data has {data.size} bytes but height * row_step = {height} * {row_step} = "
            f"{height * row_step}; the message is truncated or its header is wrong")

    order = ">" if bool(getattr(msg, "is_bigendian", False)) else "<"
    dtype = np.dtype({"names": list(dtype_fields),
                      "formats": [order + fmt for fmt, _ in dtype_fields.values()],
                      "offsets": [off for _, off in dtype_fields.values()],
                      "itemsize": point_step})
    if row_step == width * point_step:
        rows = data
    else:  # drop the padding at the end of every row
        rows = np.ascontiguousarray(data.reshape(height, row_step)[:, :width * point_step])
    structured = rows.view(dtype).reshape(-1)
    xyz = np.empty((n, 3), dtype=np.float64)
    for i, axis in enumerate("xyz"):
        xyz[:, i] = structured[axis]
    finite = np.isfinite(xyz).all(axis=1)
    if not finite.all():
        xyz = xyz[finite]
        if xyz.shape[0] == 0:
            raise EmptyCloudError(f"PointCloud2 has {n} points but none is finite")
    return xyz


def xyz_to_pointcloud2(points: np.ndarray, header: Any = None) -> Any:
    """A dense, unorganized ``sensor_msgs/PointCloud2`` (float32 x, y, z; 12-byte points).

    ``header`` is a std_msgs/Header (or None for an empty one); points are in its frame.
    Raises InvalidInputError for anything but an (N, 3) array.
    """
    from sensor_msgs.msg import PointCloud2, PointField  # lazy: decode path needs no ROS

    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidInputError(f"points must have shape (N, 3), got {pts.shape}")
    pts32 = np.ascontiguousarray(pts, dtype="<f4")
    msg = PointCloud2()
    if header is not None:
        msg.header = header
    msg.height = 1
    msg.width = int(pts32.shape[0])
    msg.fields = [PointField(name=name, offset=4 * i, datatype=FLOAT32, count=1)
                  for i, name in enumerate("xyz")]
    msg.is_bigendian = False
    msg.point_step = 12
    msg.row_step = 12 * msg.width
    msg.is_dense = bool(np.isfinite(pts32).all())
    # array.array('B') takes rclpy's fast path; a bytes/list value is checked byte by byte.
    buf = array.array("B")
    buf.frombytes(pts32.tobytes())
    msg.data = buf
    return msg


def to_rclpy_pointcloud2(msg: Any) -> Any:
    """Copy any PointCloud2-like message (e.g. from rosbags) into an rclpy
    ``sensor_msgs/PointCloud2``, byte for byte: layout, header and even malformed sizes are
    kept, so a bag can be republished exactly as recorded."""
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import PointCloud2, PointField
    from std_msgs.msg import Header

    out = PointCloud2()
    out.header = Header(stamp=Time(sec=int(msg.header.stamp.sec),
                                   nanosec=int(msg.header.stamp.nanosec)),
                        frame_id=str(msg.header.frame_id))
    out.height, out.width = int(msg.height), int(msg.width)
    out.fields = [PointField(name=str(f.name), offset=int(f.offset), datatype=int(f.datatype),
                             count=int(f.count)) for f in msg.fields]
    out.is_bigendian, out.is_dense = bool(msg.is_bigendian), bool(msg.is_dense)
    out.point_step, out.row_step = int(msg.point_step), int(msg.row_step)
    buf = array.array("B")
    buf.frombytes(_data_bytes(msg.data).tobytes())
    out.data = buf
    return out


# --------------------------------------------------------------------------- stamps


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time (``sec``, ``nanosec``) -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Any:
    """Integer nanoseconds -> builtin_interfaces/Time (lazy import)."""
    from builtin_interfaces.msg import Time

    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


# --------------------------------------------------------------------------- quaternions


def quaternion_to_matrix(q: Any) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` -> 3x3 rotation matrix. Normalizes the input."""
    x, y, z, w = np.asarray(q, dtype=np.float64).reshape(4)
    norm = np.sqrt(x * x + y * y + z * z + w * w)
    if not np.isfinite(norm) or norm < 1e-12:
        raise InvalidInputError(f"quaternion {tuple(q)} has zero or non-finite norm")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix -> unit quaternion ``(x, y, z, w)`` with ``w >= 0``.

    Shepperd's method picks the largest diagonal term, so it is stable near 180 degrees.
    """
    R = np.asarray(R, dtype=np.float64)[:3, :3]
    trace = np.trace(R)
    diag = np.array([R[0, 0], R[1, 1], R[2, 2], trace])
    k = int(np.argmax(diag))
    if k == 3:
        w = 0.5 * np.sqrt(max(1.0 + trace, 0.0))
        q = np.array([(R[2, 1] - R[1, 2]), (R[0, 2] - R[2, 0]), (R[1, 0] - R[0, 1]), 0.0])
        q /= 4.0 * w
        q[3] = w
    else:
        i, j, l = k, (k + 1) % 3, (k + 2) % 3
        s = 0.5 * np.sqrt(max(1.0 + R[i, i] - R[j, j] - R[l, l], 0.0))
        q = np.zeros(4)
        q[i] = s
        q[j] = (R[j, i] + R[i, j]) / (4.0 * s)
        q[l] = (R[l, i] + R[i, l]) / (4.0 * s)
        q[3] = (R[l, j] - R[j, l]) / (4.0 * s)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


# --------------------------------------------------------------------------- poses


def pose_to_transform(pose: Any) -> np.ndarray:
    """geometry_msgs Pose, PoseStamped, PoseWithCovariance(Stamped) or Transform(Stamped)
    (rclpy or rosbags) -> 4x4 float64 transform. Duck-typed."""
    while hasattr(pose, "pose") or hasattr(pose, "transform"):  # unwrap *Stamped / WithCovariance
        pose = pose.pose if hasattr(pose, "pose") else pose.transform
    if hasattr(pose, "position"):
        p, q = pose.position, pose.orientation
    else:  # geometry_msgs/Transform
        p, q = pose.translation, pose.rotation
    R = quaternion_to_matrix((q.x, q.y, q.z, q.w))
    return make_transform(R, (p.x, p.y, p.z))


def _check_transform(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InvalidInputError(f"transform must be a finite 4x4 array, got shape {T.shape}")
    return T


def transform_to_pose(T: np.ndarray) -> Any:
    """4x4 transform -> geometry_msgs/Pose (lazy import)."""
    from geometry_msgs.msg import Pose

    T = _check_transform(T)
    qx, qy, qz, qw = matrix_to_quaternion(T[:3, :3])
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in T[:3, 3])
    pose.orientation.x, pose.orientation.y = float(qx), float(qy)
    pose.orientation.z, pose.orientation.w = float(qz), float(qw)
    return pose


def transform_to_pose_stamped(T: np.ndarray, header: Any) -> Any:
    """4x4 transform -> geometry_msgs/PoseStamped with the given header (lazy import)."""
    from geometry_msgs.msg import PoseStamped

    return PoseStamped(header=header, pose=transform_to_pose(T))


def transform_to_transform_stamped(T: np.ndarray, header: Any, child_frame_id: str) -> Any:
    """4x4 transform -> geometry_msgs/TransformStamped (parent = header.frame_id)."""
    from geometry_msgs.msg import TransformStamped

    T = _check_transform(T)
    msg = TransformStamped(header=header, child_frame_id=child_frame_id)
    tr, rot = msg.transform.translation, msg.transform.rotation
    tr.x, tr.y, tr.z = (float(v) for v in T[:3, 3])
    rot.x, rot.y, rot.z, rot.w = (float(v) for v in matrix_to_quaternion(T[:3, :3]))
    return msg
