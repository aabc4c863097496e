"""
rosbag2 (MCAP) input and output without ROS, through ``rosbags``.

A thin adapter: it turns a bag into small records in log-time order and stops there; the
conversion to numpy is :mod:`cgags_ros.io.pointcloud2` (duck-typed, so it accepts the
rosbags messages yielded here).

Accepted paths: a rosbag2 directory (with ``metadata.yaml``) or a single ``.mcap`` file.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from ..errors import BagError, BagTopicError, InvalidInputError
from ..geometry import matrix_to_quaternion

POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'


@dataclasses.dataclass(frozen=True)
class BagRecord:
    """
    One message of a bag.

    :ivar topic: topic name as recorded (e.g. ``/source_cloud``).
    :ivar msgtype: ROS type name (``sensor_msgs/msg/PointCloud2``).
    :ivar log_time_ns: time the message was recorded, integer nanoseconds.
    :ivar stamp_ns: ``header.stamp`` in nanoseconds, or None when the message has no header
        or could not be deserialized.
    :ivar frame_id: ``header.frame_id`` ('' when unknown).
    :ivar msg: the deserialized rosbags message, or None for a broken message.
    :ivar error: '' for a good message; otherwise why it could not be deserialized.
    """

    topic: str
    msgtype: str
    log_time_ns: int
    stamp_ns: int | None
    frame_id: str
    msg: Any
    error: str = ''

    @property
    def ok(self) -> bool:
        return not self.error


@dataclasses.dataclass(frozen=True)
class TopicInfo:
    name: str
    msgtype: str
    count: int


def _check_path(path: str | Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise BagError(f'bag {path} does not exist')
    if path.is_dir():
        if not (path / 'metadata.yaml').exists():
            raise BagError(f'{path} is a directory without metadata.yaml, so not a rosbag2 bag; '
                           'pass the bag directory or its .mcap file')
    elif path.suffix not in ('.mcap', '.db3'):
        raise BagError(f'{path} is not a rosbag2 bag (expected a bag directory or a .mcap file)')
    return path


class BagReader:
    """
    Reads a rosbag2 bag; use as a context manager.

    ``messages()`` yields :class:`BagRecord` in log-time order. A message that fails to
    deserialize is yielded as a record with ``msg=None`` and ``error`` set, and counted in
    ``num_errors``, so one corrupt message never ends a replay.
    """

    def __init__(self, path: str | Path):
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import get_typestore, Stores

        self.path = _check_path(path)
        self.num_errors = 0
        try:
            # Jazzy types back up bags (e.g. sqlite3) that carry no message definitions.
            self._reader = AnyReader([self.path],
                                     default_typestore=get_typestore(Stores.ROS2_JAZZY))
        except Exception as exc:
            raise BagError(f'cannot read bag {self.path}: {exc}') from exc

    def __enter__(self) -> 'BagReader':
        self.open()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def open(self) -> None:  # noqa: A003 - public API of BagReader, like file objects
        try:
            self._reader.open()
        except Exception as exc:  # rosbags raises several unrelated types for bad files
            raise BagError(f'cannot read bag {self.path}: {exc}') from exc

    def close(self) -> None:
        if self._reader.stack is not None:
            self._reader.close()

    @property
    def topics(self) -> dict[str, TopicInfo]:
        out: dict[str, TopicInfo] = {}
        for c in self._reader.connections:
            prev = out.get(c.topic)
            count = c.msgcount + (prev.count if prev else 0)
            out[c.topic] = TopicInfo(c.topic, c.msgtype, count)
        return out

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[BagRecord]:
        """
        Iterate over the records of the given topics (all when None), in log-time order.

        Topic names may be given with or without the leading '/'.

        :raises BagTopicError: when a requested topic is not in the bag.
        """
        available = self.topics
        connections = self._reader.connections
        if topics is not None:
            wanted = set()
            for name in topics:
                key = name if name in available else '/' + name.lstrip('/')
                if key not in available:
                    raise BagTopicError(
                        f'topic {name!r} is not in {self.path}; it has: '
                        f"{', '.join(f'{t} ({i.msgtype})' for t, i in sorted(available.items()))}")
                wanted.add(key)
            connections = [c for c in connections if c.topic in wanted]
        return self._iterate(connections)  # not a generator itself: topic errors raise now

    def _iterate(self, connections: list) -> Iterator[BagRecord]:
        try:
            for conn, log_time, raw in self._reader.messages(connections=connections):
                yield self._record(conn, int(log_time), raw)
        except Exception as exc:  # storage-level corruption: stop with a typed error
            raise BagError(f'cannot read messages from {self.path}: {exc}') from exc

    def _record(self, conn: Any, log_time: int, raw: Any) -> BagRecord:
        try:
            msg = self._reader.deserialize(raw, conn.msgtype)
        except Exception as exc:  # noqa: BLE001 - a broken message becomes an error record
            self.num_errors += 1
            return BagRecord(conn.topic, conn.msgtype, log_time, None, '', None,
                             f'cannot deserialize {conn.msgtype} ({len(raw)} bytes): '
                             f'{type(exc).__name__}: {exc}')
        header = getattr(msg, 'header', None)
        stamp_ns = None
        frame_id = ''
        if header is not None:
            stamp_ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
            frame_id = str(header.frame_id)
        return BagRecord(conn.topic, conn.msgtype, log_time, stamp_ns, frame_id, msg)


def read_messages(path: str | Path, topics: Iterable[str] | None = None) -> Iterator[BagRecord]:
    """
    Iterate over the records of a bag in log-time order (see :meth:`BagReader.messages`).

    Path and topic errors raise here, not at the first ``next()``; the bag is closed when
    the iterator is exhausted or garbage-collected.
    """
    reader = BagReader(path)
    reader.open()
    try:
        records = reader.messages(topics)
    except BaseException:
        reader.close()
        raise

    def _closing() -> Iterator[BagRecord]:
        try:
            yield from records
        finally:
            reader.close()

    return _closing()


def write_poses_mcap(path: str | Path, records: Iterable[tuple[int, str, np.ndarray]], *,
                     topic: str = '/pose') -> int:
    """
    Write ``geometry_msgs/msg/PoseStamped`` messages to a new rosbag2 MCAP bag directory.

    The bag is readable by rosbags and playable with ``ros2 bag play`` (rosbag2 version 9
    metadata, CDR, MCAP storage).

    :param path: bag directory to create (must not exist; rosbags never overwrites).
    :param records: ``(stamp_ns, frame_id, T)`` with ``T`` a 4x4 transform whose pose is
        written (the pose of the source frame in ``frame_id``); the stamp is used as both
        header stamp and log time.
    :param topic: output topic.
    :returns: the number of messages written.
    """
    poses = [(topic, stamp, frame, np.asarray(T, dtype=np.float64))
             for stamp, frame, T in records]
    for _, stamp, _, T in poses:
        if T.shape != (4, 4):
            raise InvalidInputError(f'pose at {stamp} ns is not a finite 4x4 transform')
    return write_bag(path, poses)


def write_bag(path: str | Path, messages: Iterable[tuple[str, int, str, np.ndarray]]) -> int:
    """
    Write clouds and poses to a new rosbag2 MCAP bag directory, in log-time order.

    :param messages: ``(topic, stamp_ns, frame_id, array)``: an (N, 3) array is written as
        a ``sensor_msgs/msg/PointCloud2`` (float32 x, y, z), a 4x4 one as a
        ``geometry_msgs/msg/PoseStamped`` (its pose); the stamp is the header stamp and the
        log time.
    :returns: the number of messages written.
    """
    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.enums import StoragePlugin
    from rosbags.typesys import get_typestore, Stores

    path = Path(path)
    if path.exists():
        raise BagError(f'{path} exists already; rosbags writes new bags only')
    store = get_typestore(Stores.ROS2_JAZZY)
    count = 0
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections: dict[str, Any] = {}
        for topic, stamp_ns, frame_id, array in sorted(messages, key=lambda m: m[1]):
            array = np.asarray(array, dtype=np.float64)
            sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
            header = store.types['std_msgs/msg/Header'](
                stamp=store.types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec),
                frame_id=str(frame_id))
            if array.shape == (4, 4):
                msgtype, msg = POSE_STAMPED, _pose_stamped(store, header, array, stamp_ns)
            elif array.ndim == 2 and array.shape[1] == 3:
                msgtype, msg = POINTCLOUD2, _pointcloud2(store, header, array)
            else:
                raise InvalidInputError(f'{topic} at {stamp_ns} ns: neither a 4x4 pose nor '
                                        f'(N, 3) points, shape {array.shape}')
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic], int(stamp_ns), store.serialize_cdr(msg, msgtype))
            count += 1
    return count


def _pose_stamped(store: Any, header: Any, T: np.ndarray, stamp_ns: int) -> Any:
    if not np.isfinite(T).all():
        raise InvalidInputError(f'pose at {stamp_ns} ns is not a finite 4x4 transform')
    types = store.types
    qx, qy, qz, qw = (float(v) for v in matrix_to_quaternion(T[:3, :3]))
    x, y, z = (float(v) for v in T[:3, 3])
    position = types['geometry_msgs/msg/Point'](x=x, y=y, z=z)
    orientation = types['geometry_msgs/msg/Quaternion'](x=qx, y=qy, z=qz, w=qw)
    return types[POSE_STAMPED](header=header, pose=types['geometry_msgs/msg/Pose'](
        position=position, orientation=orientation))


def _pointcloud2(store: Any, header: Any, points: np.ndarray) -> Any:
    types = store.types
    data = np.ascontiguousarray(points, dtype=np.float32)
    fields = [types['sensor_msgs/msg/PointField'](name=n, offset=4 * i, datatype=7, count=1)
              for i, n in enumerate('xyz')]
    return types[POINTCLOUD2](header=header, height=1, width=len(data), fields=fields,
                              is_bigendian=False, point_step=12, row_step=12 * len(data),
                              data=data.view(np.uint8).ravel(), is_dense=True)
