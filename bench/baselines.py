"""
Baseline robust registration solvers for the benchmarks, on the same putative correspondences.

Every baseline is a function ``(src, dst, tau) -> 4x4`` (row ``i`` of ``src`` corresponds to row
``i`` of ``dst``; the returned transform maps ``src`` onto ``dst``, ``dst ≈ R @ src + t``), so the
core benchmark (:mod:`bench.core`) and the pipeline benchmark can call them the same way.
``*_detailed`` variants return a :class:`BaselineResult` with the baseline's own validity flag and
diagnostics. ``tau`` is the inlier threshold (metres / model units) also given to our solver.
On clouds (the pipeline benchmarks), :func:`open3d_fpfh_ransac` and
:func:`kiss_matcher_estimate` take ``(source, target, voxel)`` instead.

Open3D (``open3d`` 0.19)
    ``o3d.pipelines.registration.registration_ransac_based_on_correspondence(
    source, target, corres, max_correspondence_distance=tau,
    estimation_method=TransformationEstimationPointToPoint(with_scaling=False), ransac_n=3,
    checkers=[], criteria=RANSACConvergenceCriteria(max_iteration=100000, confidence=0.999))``
    with ``source``/``target`` = point clouds of the ``src``/``dst`` rows and
    ``corres = [[i, i] for i in range(N)]``. ``o3d.utility.random.seed(seed)`` is set before each
    call, but the RANSAC runs in parallel (TBB), so results are not bit-reproducible.

    Caveat (Open3D source, ``Registration.cpp``): a hypothesis is *scored* by
    ``GetRegistrationResultAndCorrespondences``, i.e. by the **nearest-neighbour** overlap of the
    transformed source cloud with the target cloud (``fitness`` = fraction of source points with
    *any* target point within ``tau``), not by the residuals of the given correspondences. Only the
    early-stop bound uses the correspondence inlier ratio. With dense outlier-contaminated ``dst``
    clouds (N = 5000 uniform outliers fill the model's bounding box at ~tau spacing) the NN fitness
    barely separates right from wrong poses. Each hypothesis costs an N-point KD-tree query, so at
    high outlier ratios (the stop bound never fires) a call runs all 1e5 iterations.
    Validity: Open3D reports none; ``valid`` here is ``fitness > 0``.

KISS-Matcher (PyPI ``kiss-matcher`` 1.0.2, pybind11 module ``_kiss_matcher``)
    ``cfg = KISSMatcherConfig(voxel_size=tau, use_voxel_sampling=True, use_quatro=False,
    thr_linearity=1.0, num_max_corr=5000, normal_r_gain=3.0, fpfh_r_gain=5.0,
    robin_noise_bound_gain=1.0, solver_noise_bound_gain=1.0, enable_noise_bound_clamping=True)``
    then ``KISSMatcher(cfg).prune_and_solve(src_f32, dst_f32)``.

    * The config has no direct noise-bound argument: ``robin_noise_bound = voxel_size *
      robin_noise_bound_gain`` and ``solver_noise_bound = voxel_size * solver_noise_bound_gain``
      (computed in the constructor; the matcher copies them when it is built). With
      ``voxel_size = tau`` and both gains 1.0, both bounds equal ``tau`` (the library defaults are
      robin 1.0 and solver 0.75). Clamping only acts on bounds > 1.0. Voxel size, FPFH radii,
      ``thr_linearity``, ``num_max_corr`` and ``use_voxel_sampling`` are used only by the
      feature-matching path (``match``/``estimate``), not by ``prune_and_solve``.
    * ``prune_and_solve`` = ROBIN pruning (pairwise-invariant graph: edge when
      ``| |s_i - s_j| - |d_i - d_j| | <= robin_noise_bound``, then the graph's max k-core) on the
      given pairs, then ``solve`` = TEASER-style GNC-TLS rotation on a chain of TIMs (noise bound
      internally doubled for TIMs) + component-wise adaptive-voting (COTE) translation with
      ``solver_noise_bound``. Deterministic (no random sampling on this path).
    * Inputs are ``Sequence[float32 [3,1]]``: an (N, 3) ndarray is accepted (pybind11 converts it
      row by row into ``std::vector<Eigen::Vector3f>``), so the measured time includes that
      conversion, float32 -> float64 copies, the O(N^2) ROBIN graph build and max-core, and the
      GNC solve. See :func:`kiss_prune_and_solve_breakdown` for the split.
    * Output: ``RegistrationSolution`` with ``rotation`` (3x3), ``translation`` (3,) and ``valid``.
      ``valid`` is only "at least 2 rotation-inlier TIMs and at least 1 translation inlier" (and
      False with < 2 pruned pairs); it is *not* a quality gate (wrong poses are reported valid).
      ``get_num_rotation_inliers()`` / ``get_num_final_inliers()`` give the inlier counts.
      ``get_rejection_time()`` is NOT updated by ``prune_and_solve`` (stale/uninitialised value);
      ``get_solver_time()`` is (the GNC + COTE part only).
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import queue
import time
from typing import Any, Callable

import numpy as np

OPEN3D_MAX_ITERATIONS = 100_000
OPEN3D_CONFIDENCE = 0.999
OPEN3D_RANSAC_N = 3


@dataclasses.dataclass
class BaselineResult:
    transform: np.ndarray
    valid: bool
    info: dict[str, Any] = dataclasses.field(default_factory=dict)


def _as_points(a: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f'{name} must be (N, 3), got {a.shape}')
    return a


def _check(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    src, dst = _as_points(src, 'src'), _as_points(dst, 'dst')
    if len(src) != len(dst):
        raise ValueError(f'src and dst need the same number of rows ({len(src)} != {len(dst)})')
    return src, dst


# --------------------------------------------------------------------------------- Open3D


def open3d_ransac_detailed(src: np.ndarray, dst: np.ndarray, tau: float, *,
                           max_iterations: int = OPEN3D_MAX_ITERATIONS,
                           confidence: float = OPEN3D_CONFIDENCE,
                           seed: int | None = None) -> BaselineResult:
    """Open3D correspondence RANSAC with the benchmark's settings (see module docstring)."""
    import open3d as o3d

    src, dst = _check(src, dst)
    reg = o3d.pipelines.registration
    if seed is not None:
        o3d.utility.random.seed(int(seed) % (2**31 - 1))  # binding takes an int32
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(dst))
    idx = np.arange(len(src), dtype=np.int32)
    corres = o3d.utility.Vector2iVector(np.stack([idx, idx], axis=1))
    result = reg.registration_ransac_based_on_correspondence(
        source, target, corres, float(tau),
        reg.TransformationEstimationPointToPoint(False),
        OPEN3D_RANSAC_N,
        [],
        reg.RANSACConvergenceCriteria(int(max_iterations), float(confidence)))
    T = np.array(result.transformation, dtype=np.float64)
    return BaselineResult(T, bool(result.fitness > 0.0), {
        'fitness_nn': float(result.fitness),
        'inlier_rmse_nn': float(result.inlier_rmse),
        'num_nn_correspondences': int(len(result.correspondence_set)),
    })


def open3d_ransac(src: np.ndarray, dst: np.ndarray, tau: float) -> np.ndarray:
    """(src, dst, tau) -> 4x4 with Open3D's correspondence RANSAC (1e5 iterations, 0.999)."""
    return open3d_ransac_detailed(src, dst, tau).transform


# --------------------------------------------------------------------------- KISS-Matcher


def kiss_config(tau: float, *, robin_gain: float = 1.0, solver_gain: float = 1.0,
                quatro: bool = False):
    """
    Return a KISSMatcherConfig whose ROBIN and solver noise bounds both equal ``tau``.

    ``quatro=True`` sets ``use_quatro=True``: the 4-DoF (yaw + translation) Quatro solver
    instead of TEASER's 6-DoF GNC-TLS rotation.
    """
    import kiss_matcher as km

    return km.KISSMatcherConfig(
        voxel_size=float(tau), use_voxel_sampling=True, use_quatro=bool(quatro),
        thr_linearity=1.0,
        num_max_corr=5000, normal_r_gain=3.0, fpfh_r_gain=5.0,
        robin_noise_bound_gain=float(robin_gain), solver_noise_bound_gain=float(solver_gain),
        enable_noise_bound_clamping=True)


def kiss_transform(solution, scale: float = 1.0) -> np.ndarray:
    """Return a KISS-Matcher solution as a 4x4 source->target transform, translation / scale."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(solution.rotation, dtype=np.float64).reshape(3, 3)
    T[:3, 3] = np.asarray(solution.translation, dtype=np.float64).reshape(3) / scale
    return T


def kiss_prune_and_solve_detailed(src: np.ndarray, dst: np.ndarray, tau: float, *,
                                  quatro: bool = False) -> BaselineResult:
    """
    KISS-Matcher ROBIN pruning + GNC-TLS/COTE solve with noise bounds = tau.

    ``quatro=True``: ``KISSMatcherConfig(use_quatro=True)``, its 4-DoF mode.
    """
    import kiss_matcher as km

    src, dst = _check(src, dst)
    cfg = kiss_config(tau, quatro=quatro)
    matcher = km.KISSMatcher(cfg)
    src32 = np.ascontiguousarray(src, dtype=np.float32)
    dst32 = np.ascontiguousarray(dst, dtype=np.float32)
    solution = matcher.prune_and_solve(src32, dst32)
    return BaselineResult(kiss_transform(solution), bool(solution.valid), {
        'robin_noise_bound': float(cfg.robin_noise_bound),
        'solver_noise_bound': float(cfg.solver_noise_bound),
        'num_rotation_inliers': int(matcher.get_num_rotation_inliers()),
        'num_final_inliers': int(matcher.get_num_final_inliers()),
        'solver_time_s': float(matcher.get_solver_time()),
    })


def kiss_prune_and_solve(src: np.ndarray, dst: np.ndarray, tau: float) -> np.ndarray:
    """(src, dst, tau) -> 4x4 with KISS-Matcher ``prune_and_solve`` (noise bounds = tau)."""
    return kiss_prune_and_solve_detailed(src, dst, tau).transform


def kiss_quatro_prune_and_solve(src: np.ndarray, dst: np.ndarray, tau: float) -> np.ndarray:
    """(src, dst, tau) -> 4x4 with KISS-Matcher + Quatro (``use_quatro=True``, 4-DoF)."""
    return kiss_prune_and_solve_detailed(src, dst, tau, quatro=True).transform


def kiss_prune_and_solve_breakdown(src: np.ndarray, dst: np.ndarray, tau: float,
                                   repeats: int = 5) -> dict[str, float]:
    """
    Median milliseconds of the parts of one KISS-Matcher ``prune_and_solve`` call.

    ``total``: the Python-timed call; ``solver``: the library's own ``get_solver_time()`` (GNC-TLS
    rotation + COTE translation); ``to_float32``: the numpy float64 -> float32 copy done by the
    wrapper; ``pybind_conversion_upper``: both (N, 3) arrays converted to
    ``std::vector<Eigen::Vector3f>``, measured by letting the binding convert ``src`` and fail on
    the second argument (an upper bound: it includes the binding's two overload passes and the
    TypeError), times two; ``prune_and_rest``: ``total - solver - pybind_conversion_upper``
    (ROBIN graph + max-core + copies), a lower bound on the pruning time.
    """
    import kiss_matcher as km

    src, dst = _check(src, dst)
    matcher = km.KISSMatcher(kiss_config(tau))
    med = lambda xs: float(np.median(xs)) * 1e3  # noqa: E731
    t_f32, t_conv, t_total, t_solver = [], [], [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        src32 = np.ascontiguousarray(src, dtype=np.float32)
        dst32 = np.ascontiguousarray(dst, dtype=np.float32)
        t_f32.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        try:
            matcher.prune_and_solve(src32, None)
        except TypeError:
            pass
        t_conv.append(2.0 * (time.perf_counter() - t0))
        t0 = time.perf_counter()
        matcher.prune_and_solve(src32, dst32)
        t_total.append(time.perf_counter() - t0)
        t_solver.append(matcher.get_solver_time())
    out = {'total': med(t_total), 'solver': med(t_solver), 'to_float32': med(t_f32),
           'pybind_conversion_upper': med(t_conv)}
    out['prune_and_rest'] = out['total'] - out['solver'] - out['pybind_conversion_upper']
    return out


# ------------------------------------------------------------------------------- on clouds

OPEN3D_DISTANCE_FACTOR = 1.5  # Open3D's tutorial: max_correspondence_distance = 1.5 voxels


def open3d_fpfh_ransac(src: np.ndarray, tgt: np.ndarray, voxel: float,
                       seed: int = 0) -> np.ndarray:
    """
    Open3D RANSAC on feature matching over our front end's features; returns the 4x4.

    The features are :func:`cgags_ros.frontend.features.extract_features` with the voxel,
    normal and FPFH radii and neighbour caps of ``PipelineConfig().frontend``;
    ``mutual_filter=True``, ``max_correspondence_distance = 1.5 v``, point-to-point
    estimation, ``ransac_n = 3``, checkers ``EdgeLength(0.9)`` and ``Distance(1.5 v)``,
    ``RANSACConvergenceCriteria(100000, 0.999)``; no refinement.
    """
    from cgags_ros.config import PipelineConfig
    from cgags_ros.frontend.features import extract_features
    import open3d as o3d

    reg = o3d.pipelines.registration
    frontend = PipelineConfig().frontend
    fs = extract_features(src, voxel, frontend, 'source')
    ft = extract_features(tgt, voxel, frontend, 'target')
    clouds, features = [], []
    for f in (fs, ft):
        clouds.append(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(f.points)))
        feature = reg.Feature()
        feature.data = np.ascontiguousarray(f.descriptors.T, dtype=np.float64)
        features.append(feature)
    distance = OPEN3D_DISTANCE_FACTOR * voxel
    o3d.utility.random.seed(seed)
    result = reg.registration_ransac_based_on_feature_matching(
        clouds[0], clouds[1], features[0], features[1], True, distance,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
         reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(100000, 0.999))
    return np.asarray(result.transformation, dtype=np.float64)


def kiss_matcher_estimate(src: np.ndarray, tgt: np.ndarray, voxel: float, *,
                          scale: float = 1.0, quatro: bool = False) -> BaselineResult:
    """
    KISS-Matcher on clouds, its own front end: ``KISSMatcherConfig(voxel).estimate``.

    Both clouds and the voxel are multiplied by ``scale`` (float32 input, as the binding
    takes) and the translation divided by it afterwards; ``quatro=True`` is its 4-DoF
    mode. ``valid`` is the library's own flag; no refinement.
    """
    import kiss_matcher as km

    matcher = km.KISSMatcher(km.KISSMatcherConfig(voxel * scale, use_quatro=quatro))
    solution = matcher.estimate((src * scale).astype(np.float32),
                                (tgt * scale).astype(np.float32))
    return BaselineResult(kiss_transform(solution, scale), bool(solution.valid),
                          {'num_final_inliers': int(matcher.get_num_final_inliers())})


BASELINES: dict[str, Callable[[np.ndarray, np.ndarray, float], np.ndarray]] = {
    'open3d': open3d_ransac,
    'kiss': kiss_prune_and_solve,
    'kiss-quatro': kiss_quatro_prune_and_solve,
}


def kiss_matcher_forked(scan: np.ndarray, target: np.ndarray, voxel: float,
                        timeout: float = 600.0) -> np.ndarray | None:
    """
    Return :func:`kiss_matcher_estimate`'s transform, run in a forked process (or None).

    None when that process died or took longer than ``timeout`` seconds.

    It segfaults on some maps in UTM coordinates (after printing 'voxel coord is out of
    range' for every point, silenced here), which would end the benchmark.
    """
    ctx = multiprocessing.get_context('fork')
    out = ctx.Queue()
    child = ctx.Process(target=_kiss_child, args=(scan, target, voxel, out))
    child.start()
    T, deadline = None, time.monotonic() + timeout
    while T is None and time.monotonic() < deadline:
        try:
            T = out.get(timeout=1.0)
        except queue.Empty:
            if not child.is_alive() and out.empty():
                break  # it died without an answer
    child.join(10)
    if child.is_alive():
        child.kill()
    return T


def _kiss_child(scan, target, voxel, out) -> None:
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)
    out.put(kiss_matcher_estimate(scan, target, voxel).transform)
