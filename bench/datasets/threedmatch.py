"""
The 3DMatch / 3DLoMatch test benchmark: fragments, ground truth and its official metrics.

Layout (as in ``<shared data>/3dmatch_benchmark``)::

    fragments/<scene>.npz                       key cloud_bin_<k>: (N, 3) points, metres
    benchmarks/{3DMatch,3DLoMatch}/<scene>/gt.log, gt.info, gt_overlap.log
    fragment_poses/<scene>/cloud_bin_<k>.info.txt

Conventions: in ``gt.log`` a block headed ``i j n`` (``n``: fragments in the scene) is
followed by the 4x4 transform of fragment ``j`` (the source) into fragment ``i``'s frame
(the target): ``p_i = T p_j``. ``gt.info`` holds, per block, the 6x6 information matrix
the official RMSE metric uses. ``info.txt`` lines 2-5 are the fragment pose ``P_k`` with
``p_world = P_k p_fragment``, so ``T = inv(P_i) P_j``. Registration pairs are those with
``j - i > 1`` (consecutive fragments are excluded by the protocol).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from cgags_ros.errors import InvalidInputError
from cgags_ros.geometry import apply_transform, rotation_error_deg, translation_error
import numpy as np


BENCHMARKS = ('3DMatch', '3DLoMatch')
RMSE_THRESHOLD = 0.2  # metres: the official RMSE recall counts pairs below it
MAX_RE_DEG, MAX_TE_M = 15.0, 0.3  # registration recall: an estimate right within both


@dataclasses.dataclass
class GtPair:
    """
    One ground-truth pair of a benchmark list.

    :ivar scene: scene folder name.
    :ivar target, source: fragment indices ``i`` and ``j`` (``p_i = transform p_j``).
    :ivar transform: 4x4 source->target, metres.
    :ivar info: 6x6 information matrix from ``gt.info`` (None when absent).
    :ivar overlap: overlap ratio from ``gt_overlap.log`` (NaN when absent).
    """

    scene: str
    target: int
    source: int
    transform: np.ndarray
    info: np.ndarray | None = None
    overlap: float = float('nan')

    @property
    def key(self) -> str:
        """Return ``'<scene>/<target>_<source>'``, unique within a benchmark list."""
        return f'{self.scene}/{self.target}_{self.source}'


def _blocks(path: Path, rows: int) -> list[tuple[int, int, np.ndarray]]:
    """Parse ``i j n`` headed blocks of ``rows`` matrix rows each."""
    try:
        lines = [ln.split() for ln in path.read_text(encoding='utf-8').splitlines()
                 if ln.strip()]
    except OSError as exc:
        raise InvalidInputError(f'cannot read {path}: {exc}') from exc
    if len(lines) % (rows + 1):
        raise InvalidInputError(f'{path}: {len(lines)} lines is not a whole number of '
                                f'{rows + 1}-line blocks')
    out = []
    for b in range(0, len(lines), rows + 1):
        try:
            i, j = int(lines[b][0]), int(lines[b][1])
            matrix = np.array([[float(v) for v in row] for row in lines[b + 1:b + 1 + rows]])
        except (ValueError, IndexError) as exc:
            raise InvalidInputError(f'{path}: bad block at line {b + 1}: {exc}') from exc
        if matrix.shape[0] != rows or matrix.shape[1] != (4 if rows == 4 else 6):
            raise InvalidInputError(f'{path}: block at line {b + 1} is {matrix.shape}')
        out.append((i, j, matrix))
    return out


def read_gt_log(path: str | Path) -> dict[tuple[int, int], np.ndarray]:
    """Return ``{(i, j): 4x4 T}`` of a ``gt.log`` (``p_i = T p_j``, metres)."""
    return {(i, j): m for i, j, m in _blocks(Path(path), 4)}


def read_gt_info(path: str | Path) -> dict[tuple[int, int], np.ndarray]:
    """Return ``{(i, j): 6x6 information matrix}`` of a ``gt.info``."""
    return {(i, j): m for i, j, m in _blocks(Path(path), 6)}


def read_overlaps(path: str | Path) -> dict[tuple[int, int], float]:
    """Return ``{(i, j): overlap ratio}`` of a ``gt_overlap.log`` (``i,j,ratio`` lines)."""
    out = {}
    for line in Path(path).read_text(encoding='utf-8').split():
        i, j, r = line.split(',')
        out[(int(i), int(j))] = float(r)
    return out


def read_fragment_pose(path: str | Path) -> np.ndarray:
    """Return the 4x4 pose ``P`` of an ``info.txt`` (``p_world = P p_fragment``)."""
    lines = [ln.split() for ln in Path(path).read_text(encoding='utf-8').splitlines()
             if ln.strip()]
    try:
        return np.array([[float(v) for v in row] for row in lines[1:5]])
    except ValueError as exc:
        raise InvalidInputError(f'{path}: not a pose: {exc}') from exc


def scenes(root: str | Path, benchmark: str = '3DMatch') -> list[str]:
    """Return the scene folders of ``benchmark`` under ``root`` that have fragments, sorted."""
    base = Path(root) / 'benchmarks' / benchmark
    if not base.is_dir():
        raise InvalidInputError(f'no benchmark folder {base}')
    fragments = Path(root) / 'fragments'
    return sorted(d.name for d in base.iterdir()
                  if (d / 'gt.log').exists() and (fragments / f'{d.name}.npz').exists())


def registration_pairs(root: str | Path, benchmark: str, scene: str,
                       min_gap: int = 2) -> list[GtPair]:
    """
    Return the registration pairs (``j - i >= min_gap``) of one scene, in ``gt.log`` order.

    ``info`` and ``overlap`` are filled where ``gt.info`` / ``gt_overlap.log`` have them.
    """
    folder = Path(root) / 'benchmarks' / benchmark / scene
    log = read_gt_log(folder / 'gt.log')
    info = read_gt_info(folder / 'gt.info') if (folder / 'gt.info').exists() else {}
    overlap = read_overlaps(folder / 'gt_overlap.log') \
        if (folder / 'gt_overlap.log').exists() else {}
    return [GtPair(scene, i, j, T, info.get((i, j)), overlap.get((i, j), float('nan')))
            for (i, j), T in log.items() if j - i >= min_gap]


def benchmark_scenes(root: str | Path, benchmarks: tuple[str, ...] | list[str] = BENCHMARKS):
    """Yield ``(benchmark, scene, Fragments, registration pairs)`` of each list's scenes."""
    for benchmark in benchmarks:
        for scene in scenes(root, benchmark):
            yield (benchmark, scene, Fragments(root, scene),
                   registration_pairs(root, benchmark, scene))


def fragment_poses(root: str | Path, scene: str) -> dict[int, np.ndarray]:
    """Return ``{k: P_k}`` for every ``fragment_poses/<scene>/cloud_bin_<k>.info.txt``."""
    folder = Path(root) / 'fragment_poses' / scene
    if not folder.is_dir():
        raise InvalidInputError(f'no fragment poses folder {folder}')
    poses = {}
    for path in folder.glob('cloud_bin_*.info.txt'):
        k = path.name[len('cloud_bin_'):-len('.info.txt')]
        if k.isdigit():
            poses[int(k)] = read_fragment_pose(path)
    return dict(sorted(poses.items()))


def scene_map(fragments: Fragments, poses: dict[int, np.ndarray],
              left_out: int | None = None) -> np.ndarray:
    """
    Return the scene's prior map: every fragment but ``left_out`` in the world frame.

    ``p_world = P_k p_fragment`` for each fragment ``k`` of ``poses``; (M, 3) float64 metres,
    the fragments stacked as they are (their overlaps not merged: a map file as a fusion of
    scans is).
    """
    return np.vstack([apply_transform(P, fragments[k]) for k, P in poses.items()
                      if k != left_out])


class Fragments:
    """The fragments of one scene (``fragments/<scene>.npz``), loaded lazily and kept."""

    def __init__(self, root: str | Path, scene: str):
        """Open ``<root>/fragments/<scene>.npz``; a missing file is an InvalidInputError."""
        path = Path(root) / 'fragments' / f'{scene}.npz'
        try:
            self._npz = np.load(path)
        except OSError as exc:
            raise InvalidInputError(f'cannot read fragments {path}: {exc}') from exc
        self._loaded: dict[int, np.ndarray] = {}

    def __getitem__(self, k: int) -> np.ndarray:
        """Return fragment ``k`` as (N, 3) float64 points (its own frame, metres)."""
        if k not in self._loaded:
            self._loaded[k] = np.asarray(self._npz[f'cloud_bin_{k}'], dtype=np.float64)
        return self._loaded[k]


def nearest_rigid(transform: np.ndarray) -> np.ndarray:
    """
    Return ``transform`` with its 3x3 block projected onto the nearest rotation (SVD).

    Some logged rotations are not quite orthonormal (7-Scenes poses): the rotation error
    ``arccos((tr(R_gt^T R) - 1) / 2)`` of an exact estimate would then read up to degrees.
    """
    U, _, Vt = np.linalg.svd(transform[:3, :3])
    out = np.array(transform, dtype=np.float64)
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return out


def registered(estimate: np.ndarray, truth: np.ndarray) -> bool:
    """Return whether ``estimate`` is right: within MAX_RE_DEG and MAX_TE_M of ``truth``."""
    return bool(rotation_error_deg(estimate, truth) < MAX_RE_DEG
                and translation_error(estimate, truth) < MAX_TE_M)


def rmse_error(estimate: np.ndarray, gt: np.ndarray, info: np.ndarray) -> float:
    """
    Return the official RMSE (metres) of ``estimate`` against ``gt`` under ``info``.

    The 3DMatch protocol: the error transform ``E = inv(gt) estimate`` as
    ``x = [t, q_xyz]`` (unit quaternion with ``q_w >= 0``); ``RMSE^2 = x^T info x /
    info[0, 0]`` approximates the mean squared point displacement over the overlap.
    """
    from scipy.spatial.transform import Rotation

    E = np.linalg.inv(gt) @ estimate
    q = Rotation.from_matrix(E[:3, :3]).as_quat()  # x, y, z, w
    if q[3] < 0:
        q = -q
    x = np.concatenate([E[:3, 3], q[:3]])
    return float(np.sqrt(max(x @ info @ x / info[0, 0], 0.0)))
