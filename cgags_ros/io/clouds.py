"""
Read and write point clouds as (N, 3) float64 arrays (metres, the file's own frame).

Formats, chosen by file extension:

- ``.ply``: ascii and binary; only the ``vertex`` element's x, y, z are read, so Stanford
  scans with their extra ``range_grid`` element load fine.
- ``.pcd``: ascii, binary and binary_compressed (PCL).
- ``.npy``: an (N, >=3) numeric array; the first three columns are x, y, z.
- ``.csv``, ``.xyz``, ``.txt``: one point per row, the first three columns x, y, z; the
  delimiter (comma, semicolon, tab or spaces) is detected from the first data row, so a
  whitespace-separated ``.csv`` (as some public datasets ship their scans) reads too; a
  non-numeric header row and ``#`` comments are skipped.

Every failure raises :class:`~cgags_ros.errors.InvalidInputError` naming the file and the
problem; nothing is printed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import pcd, ply
from ..errors import InvalidInputError

TEXT_SUFFIXES = ('.csv', '.xyz', '.txt')
SUFFIXES = ('.ply', '.pcd', '.npy') + TEXT_SUFFIXES


def read_cloud(path: str | Path) -> np.ndarray:
    """
    Points of the cloud stored at ``path`` as a (N, 3) float64 array.

    Non-finite points are kept (the pipeline drops them); N may be 0 only when the file
    itself declares no points.
    """
    return read_cloud_and_normals(path)[0]


def read_cloud_and_normals(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """
    Return :func:`read_cloud`'s points and the normals stored with them, from one read.

    Normals, (N, 3) float64 with rows matching the points, come from PLY vertex properties
    ``nx ny nz`` (or ``normal_x normal_y normal_z``) and PCD fields ``normal_x normal_y
    normal_z``; other formats carry none (None). A map's normals say which side of each
    surface its sensors saw.
    """
    path = Path(path)
    suffix = _suffix(path)
    if not path.is_file():
        raise InvalidInputError(f'cannot read {path}: no such file')
    normals = None
    try:
        if suffix in ('.ply', '.pcd'):
            columns = ply.read_vertex_columns(path) if suffix == '.ply' \
                else pcd.read_columns(path)
            if columns is None:  # binary_compressed PCD
                points, normals = pcd.read_open3d(path, pcd.count(path))
            else:
                points, normals = _named(columns, ('x', 'y', 'z')), _normals(columns)
        elif suffix == '.npy':
            points = _read_npy(path)
        else:
            points = _read_text(path)
    except InvalidInputError:
        raise
    except (OSError, ValueError) as exc:
        raise InvalidInputError(f'cannot read {path}: {exc}') from exc
    return _as_xyz(points, path), normals


def write_cloud(path: str | Path, points: np.ndarray,
                normals: np.ndarray | None = None) -> None:
    """
    Write (N, 3) points to ``path`` in the format of its extension.

    PLY is binary little-endian with double x, y, z (lossless) and, when ``normals`` (N, 3)
    are given, double nx, ny, nz (only PLY stores them); PCD is ascii; NPY float64; text
    formats get 9 significant digits.
    """
    path = Path(path)
    suffix = _suffix(path)
    pts = _as_xyz(np.asarray(points), path)
    if normals is not None and (suffix != '.ply' or np.shape(normals) != pts.shape):
        raise InvalidInputError(f'{path}: normals are written to PLY only, one (3,) a point')
    try:
        if suffix == '.ply':
            ply.write(path, pts, normals)
        elif suffix == '.pcd':
            pcd.write(path, pts)
        elif suffix == '.npy':
            np.save(path, pts)
        else:
            np.savetxt(path, pts, fmt='%.9g', delimiter=',' if suffix == '.csv' else ' ')
    except OSError as exc:
        raise InvalidInputError(f'cannot write {path}: {exc}') from exc


NORMAL_NAMES = (('nx', 'ny', 'nz'), ('normal_x', 'normal_y', 'normal_z'))


def _normals(columns: dict[str, np.ndarray]) -> np.ndarray | None:
    for names in NORMAL_NAMES:
        if set(names) <= set(columns):
            return _named(columns, names)
    return None


def _suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise InvalidInputError(
            f"unsupported point cloud format {suffix or '(no extension)'!r} for {path}; "
            f"use one of {', '.join(SUFFIXES)}")
    return suffix


def _as_xyz(points: np.ndarray, path: Path) -> np.ndarray:
    if points.ndim != 2 or points.shape[1] < 3:
        raise InvalidInputError(
            f'{path}: expected an (N, 3) array of x, y, z, got shape {points.shape}')
    try:
        return np.ascontiguousarray(points[:, :3], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f'{path}: point coordinates are not numeric ({exc})') from exc


def _named(columns: dict[str, np.ndarray], names: tuple[str, ...]) -> np.ndarray:
    return np.stack([columns[c] for c in names], axis=1).astype(np.float64)


def _read_npy(path: Path) -> np.ndarray:
    array = np.load(path, allow_pickle=False)  # never unpickle user files
    if not np.issubdtype(array.dtype, np.number):
        raise InvalidInputError(f'{path}: array dtype {array.dtype} is not numeric')
    return array


def _read_text(path: Path) -> np.ndarray:
    with open(path, 'r', encoding='utf-8', errors='replace') as f:
        lines = [ln for ln in f if ln.strip() and not ln.lstrip().startswith('#')]
    delimiter = _sniff_delimiter(lines[1] if len(lines) > 1 else lines[0]) if lines else None
    if lines and not _is_numeric_row(lines[0], delimiter):
        lines = lines[1:]  # a header such as "x,y,z"
    if not lines:
        return np.zeros((0, 3))
    return np.loadtxt(lines, delimiter=delimiter, ndmin=2)


def _sniff_delimiter(line: str) -> str | None:
    """
    Return the delimiter of a data row.

    That is the first of , ; tab that splits it into numbers, else None (runs of
    whitespace).
    """
    for delimiter in (',', ';', '\t'):
        if delimiter in line and _is_numeric_row(line, delimiter):
            return delimiter
    return None


def _is_numeric_row(line: str, delimiter: str | None) -> bool:
    try:
        [float(tok) for tok in line.split(delimiter)]
    except ValueError:
        return False
    return True
