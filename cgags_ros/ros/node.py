"""ROS 2 node: registers each source cloud onto a target cloud and publishes the pose.

Topics (relative names; remap them):
    source_cloud (sensor_msgs/PointCloud2, in): the cloud to align, in its sensor frame.
        Sensor-data QoS by default (``source_qos``).
    target_cloud (sensor_msgs/PointCloud2, in): the reference (map or previous scan).
        Reliable; durability ``target_durability`` ('transient_local' receives a latched
        map published before the node started, but then only matches transient-local
        publishers; 'volatile', the default, matches every publisher).
    ~/pose (geometry_msgs/PoseStamped, out): pose of the source frame in the target frame
        (``T``: ``p_target = R p_source + t``, metres), stamped with the source's stamp,
        frame_id = target frame (or ``pose_frame_id``).
    ~/pose_with_covariance (geometry_msgs/PoseWithCovarianceStamped, out): the same with
        the covariance of :func:`pose_covariance`.
    ~/aligned_cloud (sensor_msgs/PointCloud2, out, ``publish_aligned_cloud``): the source
        transformed into the target frame, for RViz.
    /diagnostics (diagnostic_msgs/DiagnosticArray, out): status, counts of received,
        published, rejected (per reason) and dropped (per reason) clouds, last inliers,
        timings and latency.
    /tf (``broadcast_tf``, when tf2_ros is importable): target frame -> source frame.

Parameters: every key of PipelineConfig (``voxel_size``, ``core.*``, ``frontend.*``,
``refine.*``, ``seed``) and of NodeConfig (``pairing_mode``, ``sync_slop``...), declared
with descriptions and ranges generated from the dataclasses. Changes at run time are
validated and apply to the next pair. Note ROS parameters are typed: write ``1.0``, not
``1``, for a float.

Threading: subscription callbacks only decode the cloud (vectorized numpy) and hand it to
the :class:`~cgags_ros.pairing.Pairer`; registration runs on one worker thread, so a slow
registration never blocks reception (the pairer's bounded queue drops the oldest pair).
"""

from __future__ import annotations

import collections
import threading
import time
import traceback
from typing import Any, Callable

from ..features import thread_env  # noqa: F401  (before numpy loads OpenBLAS)

import numpy as np  # noqa: E402
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.node import Node
from scipy.spatial import cKDTree
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from ..config import PipelineConfig
from ..errors import CgagsError, EmptyCloudError, InvalidConfigError, InvalidInputError
from ..node_config import NodeConfig, configs_from_parameters, parameter_descriptions
from ..pairing import Pair, Pairer
from .conversions import (pointcloud2_to_xyz, stamp_to_ns, transform_to_pose,
                          transform_to_transform_stamped, xyz_to_pointcloud2)

RegisterFn = Callable[..., Any]  # register_clouds(source, target, *, config) -> PipelineResult

_INT64_MAX = 2**63 - 1
_FLOAT_MAX = 1.7976931348623157e308
_LOG_REPEAT_S = 30.0  # a cause already logged is logged again at most this often
_WARM_UP_LIMIT_S = 120.0  # starting a registration process (imports Open3D) may take this


def pose_covariance(src: np.ndarray, dst: np.ndarray, T: np.ndarray) -> np.ndarray:
    """6x6 covariance of a rigid pose estimated from matched points, ROS order.

    Row-major, ordered (x, y, z, rotation about X, Y, Z) as geometry_msgs/
    PoseWithCovariance wants: a perturbation ``t' = t + dt`` (metres, target frame) and
    ``R' = exp([dphi]x) R`` (radians, about the target frame's axes through the source
    origin).

    Gauss-Newton on the point-to-point residuals ``r_i = R src_i + t - dst_i``: the
    Jacobian of r_i is ``J_i = [I, -[R src_i]x]``, the information is ``sum J_i^T J_i``
    and ``cov = sigma^2 (J^T J)^-1`` with the residual variance ``sigma^2 = sum |r_i|^2 /
    (3K - 6)``. It reflects geometry (a planar scene leaves some directions weak) and fit
    quality; it ignores wrong correspondences and correlation between points, so treat it
    as optimistic. Fewer than 3 pairs or a singular information: variances of 1e6.
    """
    src = np.asarray(src, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(dst, dtype=np.float64).reshape(-1, 3)
    k = min(len(src), len(dst))
    if k < 3:
        return np.diag([1e6] * 6)
    R, t = T[:3, :3], T[:3, 3]
    rotated = src[:k] @ R.T
    residuals = rotated + t - dst[:k]
    sigma2 = max(float(np.sum(residuals**2)) / max(3 * k - 6, 1), 1e-12)
    # J_i^T J_i summed in closed form: [[K I, -S^T], [-S, sum(|p|^2 I - p p^T)]],
    # with S = sum [p]x (p = R src_i); -[p]x^T = [p]x, so the off-diagonal block is [sum p]x.
    p_sum = rotated.sum(axis=0)
    skew = np.array([[0, -p_sum[2], p_sum[1]], [p_sum[2], 0, -p_sum[0]],
                     [-p_sum[1], p_sum[0], 0]])
    info = np.zeros((6, 6))
    info[:3, :3] = k * np.eye(3)
    info[:3, 3:] = skew
    info[3:, :3] = skew.T
    info[3:, 3:] = np.sum(rotated**2) * np.eye(3) - rotated.T @ rotated
    if np.linalg.cond(info) > 1e12:
        return np.diag([1e6] * 6)
    return sigma2 * np.linalg.inv(info)


def inlier_pairs(result: Any, source: np.ndarray, target: np.ndarray,
                 T: np.ndarray, max_distance: float, max_points: int = 2000
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Matched (source, target) points behind the estimate, for :func:`pose_covariance`.

    The pipeline's inlier correspondences when the result carries them (at least 3);
    otherwise nearest neighbours of a subsample of the aligned source within
    ``max_distance`` metres.
    """
    src = getattr(result, "inlier_source_points", None)
    dst = getattr(result, "inlier_target_points", None)
    if src is not None and dst is not None and len(src) >= 3:
        return np.asarray(src), np.asarray(dst)
    rng = np.random.default_rng(0)
    src = source if len(source) <= max_points else source[rng.choice(len(source), max_points, replace=False)]
    aligned = src @ T[:3, :3].T + T[:3, 3]
    # Only the target near the aligned source matters; cropping keeps the tree small.
    lo, hi = aligned.min(axis=0) - max_distance, aligned.max(axis=0) + max_distance
    near = target[np.all((target >= lo) & (target <= hi), axis=1)]
    if len(near) == 0:
        return src[:0], src[:0]
    dist, idx = cKDTree(near).query(aligned, distance_upper_bound=max_distance)
    ok = np.isfinite(dist)
    return src[ok], near[idx[ok]]


class RegistrationTimeout(CgagsError):
    """A registration ran past ``registration_timeout`` and its process was killed."""


_child_target: np.ndarray | None = None  # in the registration process: the last target


class _TargetNotHeld(Exception):
    """The registration process holds no target (it was restarted): send it again."""


def _register_in_child(source: np.ndarray, target: np.ndarray | None, *,
                       config: PipelineConfig) -> Any:
    """``register_clouds`` in the registration process; ``target=None`` reuses the target
    sent last, so an unchanged (latched) target crosses the pipe once, not every pair."""
    global _child_target
    from ..pipeline import register_clouds

    if target is not None:
        _child_target = target
    elif _child_target is None:
        raise _TargetNotHeld()
    return register_clouds(source, _child_target, config=config)


class _IsolatedRegistration:
    """Runs ``register_clouds`` in one spawned child process with a time limit.

    A pathological input that makes the pipeline loop (or crash natively) costs one pair:
    the child is killed and a fresh one started. Spawn, not fork: forking a process that
    runs DDS threads is unsafe. Results and typed errors come back pickled. The child keeps
    the last target: a target that is the same array object as the previous call's is not
    sent again (the node never writes to a decoded cloud).
    """

    def __init__(self, timeout_s: float):
        self.timeout_s = timeout_s
        self._pool: Any = None
        self._closed = False
        self._sent_target: np.ndarray | None = None  # what the child holds (by identity)
        self._start()

    def _start(self) -> None:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        from ..pipeline import warm_up

        self._fn = _register_in_child
        self._sent_target = None
        self._pool = ProcessPoolExecutor(max_workers=1,
                                         mp_context=multiprocessing.get_context("spawn"))
        # Warm-up: the child imports the pipeline (Open3D) and runs every stage once on a
        # small synthetic pair, so no start-up cost is counted against a real pair's limit.
        self._warm = self._pool.submit(warm_up)

    def __call__(self, source: np.ndarray, target: np.ndarray, *, config: PipelineConfig) -> Any:
        from concurrent.futures import TimeoutError as FutureTimeout
        from concurrent.futures.process import BrokenProcessPool

        if self._pool is None:
            raise RegistrationTimeout("the registration process is shut down")
        if self._warm is not None:
            try:
                self._warm.result(timeout=_WARM_UP_LIMIT_S)
            except Exception:  # noqa: BLE001 - a failed warm-up shows again on the real pair
                pass
            self._warm = None
        held = target is self._sent_target
        # Only a completed call proves the child holds this target; after any failure it
        # is sent again.
        self._sent_target = None
        future = self._pool.submit(self._fn, source, None if held else target, config=config)
        try:
            result = future.result(timeout=self.timeout_s)
            self._sent_target = target
            return result
        except _TargetNotHeld:  # not expected (a restart forgets what was sent); resend
            return self(source, target, config=config)
        except FutureTimeout:
            self.restart()
            raise RegistrationTimeout(
                f"registration took longer than registration_timeout = {self.timeout_s:g} s; "
                "its process was restarted") from None
        except BrokenProcessPool:
            self.restart()
            raise RegistrationTimeout("the registration process died; restarted") from None

    def restart(self) -> None:
        self._kill()
        if not self._closed:
            self._start()

    def close(self) -> None:
        self._closed = True
        # Wait for the pool's manager thread: one still running at interpreter exit races
        # concurrent.futures' atexit hook, which then prints "OSError: handle is closed"
        # (CPython 3.11; seen once in ~20 SIGTERM shutdowns). The child is killed first,
        # so this returns at once.
        self._kill(wait=True)

    def _kill(self, wait: bool = False) -> None:
        pool, self._pool = self._pool, None
        if pool is None:
            return
        # ProcessPoolExecutor cannot cancel a running call: stop its process directly.
        for proc in list(getattr(pool, "_processes", {}).values()):
            proc.kill()
        pool.shutdown(wait=wait, cancel_futures=True)


class _Cloud:
    """A decoded cloud: points (N, 3) metres in ``header.frame_id``, receipt time."""

    __slots__ = ("xyz", "header", "receipt_ns")

    def __init__(self, xyz: np.ndarray, header: Any, receipt_ns: int):
        self.xyz, self.header, self.receipt_ns = xyz, header, receipt_ns


class RegisterNode(Node):
    """Wires topics, parameters and diagnostics around ``cgags_ros.pipeline.register_clouds``.

    ``register_fn`` replaces the pipeline; it exists for unit tests of the plumbing only.
    """

    def __init__(self, node_name: str = "register_node", *,
                 register_fn: RegisterFn | None = None, **kwargs: Any):
        super().__init__(node_name, **kwargs)
        self._declare_parameters()
        values = {name: self.get_parameter(name).value for name in self._descriptions}
        # Invalid startup values (e.g. a choice typo) raise InvalidConfigError here.
        self._pipeline_cfg, self._node_cfg = configs_from_parameters(values)
        self._isolated: _IsolatedRegistration | None = None
        if register_fn is not None:  # unit tests of the plumbing only
            self._register = register_fn
        elif self._node_cfg.registration_timeout > 0:
            self._isolated = _IsolatedRegistration(self._node_cfg.registration_timeout)
            self._register = self._isolated
        else:  # import the pipeline (and Open3D) now, so the first pair is not slowed by it
            self._register = _load_pipeline()
        self._lock = threading.Lock()  # guards configs and statistics
        cfg = self._node_cfg
        self._pairer = Pairer.from_config(cfg)
        self._rejected: collections.Counter[str] = collections.Counter()
        self._counts: collections.Counter[str] = collections.Counter()
        self._last: dict[str, Any] = {}
        self._latencies: collections.deque[float] = collections.deque(maxlen=200)
        self._logged: dict[str, float] = {}
        self._tf_broadcaster: Any = None
        self._tf_missing_logged = False

        self.create_subscription(PointCloud2, "source_cloud", self._on_source, self._source_qos())
        self.create_subscription(PointCloud2, "target_cloud", self._on_target, self._target_qos())
        self._pose_pub = self.create_publisher(PoseStamped, "~/pose", 10)
        self._pose_cov_pub = self.create_publisher(PoseWithCovarianceStamped,
                                                   "~/pose_with_covariance", 10)
        self._aligned_pub = self.create_publisher(PointCloud2, "~/aligned_cloud", 1)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(cfg.diagnostics_period, self._publish_diagnostics)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self._stop = threading.Event()
        self._worker = threading.Thread(target=self._work, name="register_worker", daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"registering source_cloud onto target_cloud ({cfg.pairing_mode}, voxel_size "
            f"{self._pipeline_cfg.voxel_size} m, target {cfg.target_durability})")

    # ------------------------------------------------------------------ parameters

    def _declare_parameters(self) -> None:
        self._descriptions = parameter_descriptions()
        for name, meta in self._descriptions.items():
            self.declare_parameter(name, meta["default"], _descriptor(name, meta))

    def _on_set_parameters(self, params: list[rclpy.parameter.Parameter]) -> SetParametersResult:
        changes = {p.name: p.value for p in params if p.name in self._descriptions}
        if not changes:
            return SetParametersResult(successful=True)
        with self._lock:
            try:
                pipe, node = configs_from_parameters(
                    changes, base=(self._pipeline_cfg, self._node_cfg))
            except InvalidConfigError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
            self._pipeline_cfg, self._node_cfg = pipe, node
            self._pairer.slop_ns = int(round(node.sync_slop * 1e9))
        self.get_logger().info(f"parameters changed (next pair): {changes}")
        return SetParametersResult(successful=True)

    @property
    def pipeline_config(self) -> PipelineConfig:
        with self._lock:
            return self._pipeline_cfg

    @property
    def node_config(self) -> NodeConfig:
        with self._lock:
            return self._node_cfg

    # ------------------------------------------------------------------ input

    def _source_qos(self) -> QoSProfile:
        cfg = self._node_cfg
        if cfg.source_qos == "sensor_data":
            qos = QoSProfile(depth=cfg.source_depth)
            qos.reliability = qos_profile_sensor_data.reliability
            qos.durability = qos_profile_sensor_data.durability
            qos.history = HistoryPolicy.KEEP_LAST
            return qos
        return QoSProfile(depth=cfg.source_depth, reliability=ReliabilityPolicy.RELIABLE)

    def _target_qos(self) -> QoSProfile:
        cfg = self._node_cfg
        durability = (DurabilityPolicy.TRANSIENT_LOCAL if cfg.target_durability == "transient_local"
                      else DurabilityPolicy.VOLATILE)
        return QoSProfile(depth=cfg.target_depth, reliability=ReliabilityPolicy.RELIABLE,
                          durability=durability)

    def _decode(self, msg: PointCloud2, role: str) -> _Cloud | None:
        receipt = time.monotonic_ns()
        with self._lock:
            self._counts[f"received_{role}"] += 1
            max_points = self._node_cfg.max_cloud_points
        try:
            xyz = pointcloud2_to_xyz(msg, max_points=max_points)
        except InvalidInputError as exc:
            kind = "empty" if isinstance(exc, EmptyCloudError) else "malformed"
            self._reject(f"{role}_{kind}", f"{role} cloud rejected: {exc}")
            return None
        return _Cloud(xyz, msg.header, receipt)

    def _on_source(self, msg: PointCloud2) -> None:
        cloud = self._decode(msg, "source")
        if cloud is not None:
            self._pairer.add_source(stamp_to_ns(msg.header.stamp), msg.header.frame_id, cloud)

    def _on_target(self, msg: PointCloud2) -> None:
        cloud = self._decode(msg, "target")
        if cloud is not None:
            self._pairer.add_target(stamp_to_ns(msg.header.stamp), msg.header.frame_id, cloud)

    # ------------------------------------------------------------------ worker

    def _work(self) -> None:
        while not self._stop.is_set():
            pair = self._pairer.wait_pop(timeout=0.2)
            if pair is None:
                continue
            try:
                self._process(pair)
            except Exception as exc:  # noqa: BLE001 - the worker must outlive any bad pair
                if not self._stop.is_set() and self.context.ok():
                    self._reject("internal_error", f"pair failed: {exc!r}\n{traceback.format_exc()}")

    def _process(self, pair: Pair) -> None:
        source, target = pair.source.payload, pair.target.payload
        with self._lock:
            pipe_cfg, cfg = self._pipeline_cfg, self._node_cfg
        try:
            result = self._register(source.xyz, target.xyz, config=pipe_cfg)
        except InvalidInputError as exc:
            self._reject("pipeline_input", f"pair rejected by the pipeline: {exc}")
            return
        except RegistrationTimeout as exc:
            self._reject("timeout", str(exc))
            return
        except CgagsError as exc:
            self._reject("pipeline_error", f"registration failed: {exc}")
            return
        T = np.asarray(result.transform, dtype=np.float64)
        valid = bool(result.valid) and np.isfinite(T).all()
        with self._lock:
            self._last = {"valid": valid, "reason": str(getattr(result, "reason", "")),
                          "inliers": int(result.num_inliers),
                          "fitness": float(getattr(result, "fitness", float("nan"))),
                          "voxel_size": pipe_cfg.voxel_size,
                          "timings": dict(getattr(result, "timings", {}) or {}),
                          "source_stamp_ns": pair.source.stamp_ns}
        if not valid:
            if not cfg.publish_invalid or not np.isfinite(T).all():
                self._reject("invalid_result", f"invalid registration: {result.reason}")
                return
            with self._lock:
                self._counts["published_invalid"] += 1
        self._publish(pair, T, result, pipe_cfg, cfg)

    def _publish(self, pair: Pair, T: np.ndarray, result: Any, pipe_cfg: PipelineConfig,
                 cfg: NodeConfig) -> None:
        source, target = pair.source.payload, pair.target.payload
        header = Header(stamp=source.header.stamp,
                        frame_id=cfg.pose_frame_id or target.header.frame_id)
        pose = transform_to_pose(T)
        self._send(self._pose_pub, PoseStamped(header=header, pose=pose))
        cov_msg = PoseWithCovarianceStamped(header=header)
        cov_msg.pose.pose = pose
        threshold = float(getattr(result, "inlier_threshold", float("nan")))
        if not np.isfinite(threshold) or threshold <= 0:
            threshold = 1.5 * pipe_cfg.voxel_size
        src, dst = inlier_pairs(result, source.xyz, target.xyz, T, threshold)
        cov_msg.pose.covariance = [float(v) for v in pose_covariance(src, dst, T).ravel()]
        self._send(self._pose_cov_pub, cov_msg)
        if cfg.publish_aligned_cloud:
            aligned = source.xyz @ T[:3, :3].T + T[:3, 3]
            self._send(self._aligned_pub, xyz_to_pointcloud2(aligned, header))
        if cfg.broadcast_tf:
            self._broadcast(T, header, cfg.tf_child_frame or source.header.frame_id)
        latency = (time.monotonic_ns() - source.receipt_ns) * 1e-9
        with self._lock:
            self._counts["published"] += 1
            self._latencies.append(latency)

    def _broadcast(self, T: np.ndarray, header: Header, child: str) -> None:
        if self._tf_broadcaster is None:
            try:
                from tf2_ros import TransformBroadcaster
            except ImportError:
                if not self._tf_missing_logged:
                    self._tf_missing_logged = True
                    self.get_logger().warning("broadcast_tf is set but tf2_ros is not "
                                              "importable; no TF is broadcast")
                return
            self._tf_broadcaster = TransformBroadcaster(self)
        self._tf_broadcaster.sendTransform(transform_to_transform_stamped(T, header, child))

    # ------------------------------------------------------------------ health

    def _reject(self, cause: str, message: str) -> None:
        """Count a rejection and log it, once per cause and then at most every 30 s."""
        now = time.monotonic()
        with self._lock:
            self._rejected[cause] += 1
            n = self._rejected[cause]
            last = self._logged.get(cause)
            due = last is None or now - last >= _LOG_REPEAT_S
            if due:
                self._logged[cause] = now
        if due:
            suffix = f" ({n} so far; repeats are logged every {_LOG_REPEAT_S:.0f} s)" if n > 1 else ""
            self.get_logger().warning(message + suffix)

    def statistics(self) -> dict[str, Any]:
        """Flat snapshot of the node's counters (what /diagnostics carries)."""
        with self._lock:
            stats: dict[str, Any] = dict(self._counts)
            stats.update({f"rejected.{k}": v for k, v in sorted(self._rejected.items())})
            stats["rejected"] = sum(self._rejected.values())
            for key, value in self._last.items():
                if key == "timings":
                    stats.update({f"last_timing.{k}": v for k, v in value.items()})
                else:
                    stats[f"last_{key}"] = value
            lat = np.array(self._latencies)
            voxel = self._pipeline_cfg.voxel_size
        stats["voxel_size"] = voxel
        if lat.size:
            stats["latency_p50_s"] = float(np.percentile(lat, 50))
            stats["latency_p95_s"] = float(np.percentile(lat, 95))
        pairing = self._pairer.counters()
        stats.update({f"pairing.{k}": v for k, v in pairing.items()})
        return stats

    def _publish_diagnostics(self) -> None:
        stats = self.statistics()
        status = DiagnosticStatus(name=f"{self.get_name()}: registration",
                                  hardware_id=self.get_fully_qualified_name())
        if not stats.get("received_source") or not stats.get("received_target"):
            status.level, status.message = DiagnosticStatus.STALE, "waiting for source and target clouds"
        elif stats.get("last_valid") is False:
            status.level = DiagnosticStatus.WARN
            status.message = f"last registration invalid: {stats.get('last_reason', '')}"
        elif stats["rejected"] or stats["pairing.dropped"]:
            status.level, status.message = DiagnosticStatus.WARN, "running; some clouds rejected or dropped"
        else:
            status.level, status.message = DiagnosticStatus.OK, "running"
        status.values = [KeyValue(key=str(k), value=str(v)) for k, v in stats.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._send(self._diag_pub, msg)

    def _send(self, publisher: Any, msg: Any) -> None:
        """Publish unless the context has been shut down (Ctrl-C / SIGTERM).

        rclpy's signal handler shuts the context down asynchronously: the executor may
        still dispatch the diagnostics timer, and the worker may still be finishing a
        pair. A publish then raises RCLError ("publisher's context is invalid"), which
        from a timer callback would escape rclpy.spin() and end the node with exit 1.
        Errors while the context is still valid are raised as before.
        """
        if not self.context.ok():
            return
        try:
            publisher.publish(msg)
        except RuntimeError:  # rclpy's RCLError derives from RuntimeError
            if self.context.ok():
                raise

    # ------------------------------------------------------------------ shutdown

    def destroy_node(self) -> None:
        self._stop.set()
        self._pairer.wake()
        if self._isolated is not None:
            self._isolated.close()  # ends a registration in flight at once
        self._worker.join(timeout=5.0)
        super().destroy_node()


def _descriptor(name: str, meta: dict[str, Any]) -> ParameterDescriptor:
    """ParameterDescriptor from configutil metadata (type, description, range, read-only)."""
    default = meta["default"]
    desc = ParameterDescriptor(name=name, description=str(meta["description"]),
                               read_only=bool(meta.get("read_only")))
    if meta.get("choices"):
        desc.additional_constraints = "one of: " + ", ".join(map(str, meta["choices"]))
    low, high = meta.get("low"), meta.get("high")
    if isinstance(default, bool):
        desc.type = ParameterType.PARAMETER_BOOL
    elif isinstance(default, int):
        desc.type = ParameterType.PARAMETER_INTEGER
        if low is not None or high is not None:
            desc.integer_range = [IntegerRange(
                from_value=int(low) if low is not None else -_INT64_MAX,
                to_value=int(high) if high is not None else _INT64_MAX, step=1)]
    elif isinstance(default, float):
        desc.type = ParameterType.PARAMETER_DOUBLE
        if low is not None or high is not None:
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(low) if low is not None else -_FLOAT_MAX,
                to_value=float(high) if high is not None else _FLOAT_MAX, step=0.0)]
    elif isinstance(default, str):
        desc.type = ParameterType.PARAMETER_STRING
    else:  # None default (optional value): let the YAML decide the type
        desc.dynamic_typing = True
    return desc


def _load_pipeline() -> RegisterFn:
    from ..pipeline import register_clouds, warm_up

    warm_up()  # pay Open3D's start-up now rather than on the first pair
    return register_clouds


def main(args: list[str] | None = None) -> None:
    """Entry point of ``ros2 run cgags_ros register_node`` and ``python -m
    cgags_ros.register_node``; exits cleanly on Ctrl-C and SIGTERM."""
    from rclpy.executors import ExternalShutdownException

    rclpy.init(args=args)
    node = None
    try:
        node = RegisterNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except InvalidConfigError as exc:  # e.g. a pairing_mode typo in the YAML
        rclpy.logging.get_logger("register_node").fatal(str(exc))
        raise SystemExit(2) from None
    except RuntimeError:  # an rclpy call racing the signal handler's shutdown
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
