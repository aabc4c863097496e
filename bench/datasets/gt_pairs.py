"""
Ground-truth pairs of the shared test data (``gt_pairs.txt``).

Format: blocks headed ``pair SOURCE TARGET`` followed by four rows of a 4x4 transform T with
``p_target = T[:3, :3] @ p_source + T[:3, 3]`` (metres); ``#`` starts a comment. File names
are relative to the folder holding ``gt_pairs.txt`` or one of its sub-folders.
"""

from __future__ import annotations

from pathlib import Path

from cgags_ros.errors import InvalidInputError
import numpy as np


def parse_gt_pairs(text: str, origin: str = 'gt_pairs.txt') -> list[tuple[str, str, np.ndarray]]:
    """Parse ``text`` into [(source name, target name, 4x4 source->target T)], file order."""
    pairs: list[tuple[str, str, np.ndarray]] = []
    names: tuple[str, str] | None = None
    rows: list[list[float]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split('#', 1)[0].strip()
        if not line:
            continue
        tok = line.split()
        if tok[0] == 'pair':
            _finish(pairs, names, rows, origin, lineno)
            if len(tok) != 3:
                raise InvalidInputError(f"{origin}:{lineno}: expected 'pair SOURCE TARGET'")
            names, rows = (tok[1], tok[2]), []
            continue
        if names is None:
            raise InvalidInputError(f"{origin}:{lineno}: matrix row before any 'pair' line")
        try:
            rows.append([float(v) for v in tok])
        except ValueError as exc:
            raise InvalidInputError(f'{origin}:{lineno}: not a matrix row: {raw!r}') from exc
    _finish(pairs, names, rows, origin, len(text.splitlines()))
    return pairs


def read_gt_pairs(path: str | Path) -> list[tuple[Path, Path, np.ndarray]]:
    """Parse ``path`` and resolve each file name to an existing path (below its folder)."""
    path = Path(path)
    try:
        text = path.read_text(encoding='utf-8')
    except OSError as exc:
        raise InvalidInputError(f'cannot read ground truth {path}: {exc}') from exc
    return [(_resolve(path.parent, s), _resolve(path.parent, t), T)
            for s, t, T in parse_gt_pairs(text, str(path))]


def find_pair(path: str | Path, source: str, target: str) -> tuple[Path, Path, np.ndarray]:
    """Return the pair of ``path`` whose source and target file names are given."""
    for s, t, T in read_gt_pairs(path):
        if s.name == source and t.name == target:
            return s, t, T
    raise InvalidInputError(f'{path} has no pair {source} -> {target}')


def _finish(pairs: list, names: tuple[str, str] | None, rows: list[list[float]],
            origin: str, lineno: int) -> None:
    if names is None:
        return
    T = np.asarray(rows, dtype=np.float64)
    if T.shape != (4, 4):
        raise InvalidInputError(f'{origin}: pair {names[0]} -> {names[1]} (before line '
                                f'{lineno}) needs 4 rows of 4 numbers, got shape {T.shape}')
    # 1e-3: published ground truth (3DMatch logs) is orthonormal only to ~5e-5.
    rotation_ok = np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-3)
    if not np.allclose(T[3], [0, 0, 0, 1]) or not rotation_ok:
        raise InvalidInputError(f'{origin}: pair {names[0]} -> {names[1]} is not a rigid '
                                'transform (rotation not orthonormal or last row not 0 0 0 1)')
    pairs.append((names[0], names[1], T))


def _resolve(folder: Path, name: str) -> Path:
    direct = folder / name
    if direct.exists():
        return direct
    found = sorted(folder.rglob(name))
    if not found:
        raise InvalidInputError(f"{name} (listed in {folder / 'gt_pairs.txt'}) not found "
                                f'under {folder}')
    return found[0]
