"""PCD files (PCL): fields read from ascii, binary and binary_compressed, x, y, z written."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InvalidInputError

PCD_TYPES = {('F', '4'): 'f4', ('F', '8'): 'f8', ('I', '1'): 'i1', ('I', '2'): 'i2',
             ('I', '4'): 'i4', ('I', '8'): 'i8', ('U', '1'): 'u1', ('U', '2'): 'u2',
             ('U', '4'): 'u4', ('U', '8'): 'u8'}


def read_columns(path: Path) -> dict[str, np.ndarray] | None:
    """
    Return the scalar fields of an ascii or binary PCD by name (x, y, z required).

    Parsed here, as Open3D silently pads a truncated file with zeros; None for
    binary_compressed, which :func:`read_open3d` reads.
    """
    with open(path, 'rb') as f:
        header = _header(f, path)
        fields, count, data = header['FIELDS'], int(header['POINTS'][0]), header['DATA'][0]
        if not {'x', 'y', 'z'} <= set(fields):
            raise InvalidInputError(f'{path}: PCD FIELDS lack x, y, z')
        if data == 'ascii':
            rows = [ln for ln in f.read().decode('ascii', errors='replace').splitlines()
                    if ln.strip()]
            if len(rows) < count:
                raise InvalidInputError(f'{path}: PCD file is truncated ({len(rows)} of '
                                        f'{count} points present)')
            columns = _columns(header)
            table = np.loadtxt(rows[:count], ndmin=2) if count else np.zeros((0, len(columns)))
            return {c: table[:, columns.index(c)] for c in fields}
        if data == 'binary':
            table = _binary_table(f, header, path)
            return {c: table[c][:, 0] for c in fields}
    return None


def count(path: Path) -> int:
    """Return the number of points the header declares."""
    with open(path, 'rb') as f:
        return int(_header(f, path)['POINTS'][0])


def read_fields(path: str | Path) -> np.ndarray:
    """
    Every field of a binary PCD file as a structured array (one record per point).

    Field names, types and order are the file's (e.g. x, y, z, intensity, normals); fields
    with COUNT 1 are scalars. Units are the file's (metres for x, y, z).
    """
    path = Path(path)
    with open(path, 'rb') as f:
        header = _header(f, path)
        if header['DATA'][0] != 'binary':
            kind = header['DATA'][0]
            raise InvalidInputError(f'{path}: read_fields reads DATA binary, not {kind}')
        table = _binary_table(f, header, path)
    dtype = np.dtype([(name, table.dtype[name].base) if table.dtype[name].shape == (1,)
                      else (name, table.dtype[name]) for name in table.dtype.names])
    return table.view(dtype) if dtype.itemsize == table.dtype.itemsize else table


def _binary_table(f, header: dict[str, list[str]], path: Path) -> np.ndarray:
    """Read the points of a binary PCD after its header (one record per point)."""
    count = int(header['POINTS'][0])
    dtype = np.dtype([(name, '<' + PCD_TYPES[(t, s)], (int(c),))
                      for name, s, t, c in zip(header['FIELDS'], header['SIZE'],
                                               header['TYPE'], header['COUNT'])])
    raw = f.read(count * dtype.itemsize)
    if len(raw) < count * dtype.itemsize:
        raise InvalidInputError(f'{path}: PCD file is truncated')
    return np.frombuffer(raw, dtype=dtype)


def _header(f, path: Path) -> dict[str, list[str]]:
    header: dict[str, list[str]] = {}
    for raw in f:
        tok = raw.decode('ascii', errors='replace').split()
        if tok and not tok[0].startswith('#'):
            header[tok[0].upper()] = tok[1:]
        if tok[:1] == ['DATA']:
            break
    needed = ('FIELDS', 'SIZE', 'TYPE', 'POINTS', 'DATA')
    if any(not header.get(k) for k in needed):
        raise InvalidInputError(f"{path}: not a PCD file (header needs {', '.join(needed)})")
    header.setdefault('COUNT', ['1'] * len(header['FIELDS']))
    try:
        [PCD_TYPES[(t, s)] for t, s in zip(header['TYPE'], header['SIZE'])]
    except KeyError as exc:
        raise InvalidInputError(f'{path}: unsupported PCD TYPE/SIZE {exc}') from exc
    return header


def _columns(header: dict[str, list[str]]) -> list[str]:
    """Column names of an ascii PCD row (fields with COUNT > 1 span several columns)."""
    return [name for name, c in zip(header['FIELDS'], header['COUNT']) for _ in range(int(c))]


def read_open3d(path: Path, declared: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Return the points and (when the file has them) the normals, through Open3D."""
    from ..open3d_import import open3d as o3d

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.io.read_point_cloud(str(path), format='pcd')
    points = np.asarray(cloud.points)
    if len(points) != declared:
        raise InvalidInputError(
            f'{path}: header declares {declared} points but {len(points)} could be read; '
            'the file is truncated or corrupt')
    return points, np.asarray(cloud.normals) if cloud.has_normals() else None


def write(path: Path, points: np.ndarray) -> None:
    """Write ascii x, y, z with 17 significant digits."""
    n = len(points)
    header = ('# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n'
              f'SIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n'
              f'VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA ascii\n')
    with open(path, 'w', encoding='ascii') as f:
        f.write(header)
        np.savetxt(f, points, fmt='%.17g')
