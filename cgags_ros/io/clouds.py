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

from ..errors import InvalidInputError

TEXT_SUFFIXES = ('.csv', '.xyz', '.txt')
SUFFIXES = ('.ply', '.pcd', '.npy') + TEXT_SUFFIXES


def read_cloud(path: str | Path) -> np.ndarray:
    """
    Points of the cloud stored at ``path`` as a (N, 3) float64 array.

    Non-finite points are kept (the pipeline drops them); N may be 0 only when the file
    itself declares no points.
    """
    path = Path(path)
    suffix = _suffix(path)
    if not path.is_file():
        raise InvalidInputError(f'cannot read {path}: no such file')
    try:
        if suffix == '.ply':
            points = _read_ply(path)
        elif suffix == '.pcd':
            points = _read_pcd(path)
        elif suffix == '.npy':
            points = _read_npy(path)
        else:
            points = _read_text(path)
    except InvalidInputError:
        raise
    except (OSError, ValueError) as exc:
        raise InvalidInputError(f'cannot read {path}: {exc}') from exc
    return _as_xyz(points, path)


def write_cloud(path: str | Path, points: np.ndarray) -> None:
    """
    Write (N, 3) points to ``path`` in the format of its extension.

    PLY is binary little-endian with double x, y, z (lossless); PCD is ascii; NPY float64;
    text formats get 9 significant digits.
    """
    path = Path(path)
    suffix = _suffix(path)
    pts = _as_xyz(np.asarray(points), path)
    try:
        if suffix == '.ply':
            _write_ply(path, pts)
        elif suffix == '.pcd':
            _write_pcd(path, pts)
        elif suffix == '.npy':
            np.save(path, pts)
        else:
            np.savetxt(path, pts, fmt='%.9g', delimiter=',' if suffix == '.csv' else ' ')
    except OSError as exc:
        raise InvalidInputError(f'cannot write {path}: {exc}') from exc


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


PLY_TYPES = {'char': 'i1', 'int8': 'i1', 'uchar': 'u1', 'uint8': 'u1', 'short': 'i2',
             'int16': 'i2', 'ushort': 'u2', 'uint16': 'u2', 'int': 'i4', 'int32': 'i4',
             'uint': 'u4', 'uint32': 'u4', 'float': 'f4', 'float32': 'f4', 'double': 'f8',
             'float64': 'f8'}


def _read_ply(path: Path) -> np.ndarray:
    """
    Read x, y, z of the ``vertex`` element of a PLY file.

    Our own reader rather than Open3D's, because Open3D fills a truncated binary file with
    zeros instead of failing.
    """
    with open(path, 'rb') as f:
        fmt, elements = _ply_header(f, path)
        names = [e[0] for e in elements]
        if 'vertex' not in names:
            raise InvalidInputError(f'{path}: PLY file has no vertex element')
        for name, count, props in elements[:names.index('vertex')]:
            _skip_ply_element(f, path, fmt, name, count, props)
        _, count, props = elements[names.index('vertex')]
        if not {'x', 'y', 'z'} <= {p for p, _ in props}:
            raise InvalidInputError(f'{path}: PLY vertex element lacks x, y, z properties')
        if any(t is None for _, t in props):
            raise InvalidInputError(f'{path}: PLY vertex element has list properties')
        if fmt == 'ascii':
            rows = [f.readline() for _ in range(count)]
            data = np.loadtxt(rows, ndmin=2, usecols=range(len(props))) if count else \
                np.zeros((0, len(props)))
            columns = [p for p, _ in props]
            return data[:, [columns.index(c) for c in 'xyz']]
        endian = '<' if fmt == 'binary_little_endian' else '>'
        dtype = np.dtype([(p, endian + t) for p, t in props])
        raw = f.read(count * dtype.itemsize)
    if len(raw) < count * dtype.itemsize:
        raise InvalidInputError(f'{path}: PLY file is truncated ({len(raw) // dtype.itemsize} '
                                f'of {count} vertices present)')
    data = np.frombuffer(raw, dtype=dtype)
    return np.stack([data['x'], data['y'], data['z']], axis=1).astype(np.float64)


def _ply_header(f, path: Path) -> tuple[str, list]:
    """(format, [(element name, count, [(property, numpy type or None for lists)])])."""
    if f.readline().strip() != b'ply':
        raise InvalidInputError(f"{path} is not a PLY file (first line is not 'ply')")
    fmt, elements = None, []
    for raw in f:
        tok = raw.decode('ascii', errors='replace').split()
        if not tok:
            continue
        if tok[0] == 'format':
            fmt = tok[1]
        elif tok[0] == 'element':
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == 'property' and elements:
            is_list = tok[1] == 'list'
            if not is_list and tok[1] not in PLY_TYPES:
                raise InvalidInputError(f'{path}: unknown PLY property type {tok[1]!r}')
            elements[-1][2].append((tok[-1], None if is_list else PLY_TYPES[tok[1]]))
        elif tok[0] == 'end_header':
            break
    else:
        raise InvalidInputError(f'{path}: PLY header has no end_header line')
    if fmt not in ('ascii', 'binary_little_endian', 'binary_big_endian'):
        raise InvalidInputError(f'{path}: unknown PLY format {fmt!r}')
    return fmt, elements


def _skip_ply_element(f, path: Path, fmt: str, name: str, count: int, props: list) -> None:
    if fmt == 'ascii':
        for _ in range(count):
            f.readline()
    elif any(t is None for _, t in props):
        raise InvalidInputError(
            f'{path}: cannot skip binary PLY element {name!r} (list properties) stored '
            'before the vertex element')
    else:
        f.seek(count * sum(np.dtype(t).itemsize for _, t in props), 1)


PCD_TYPES = {('F', '4'): 'f4', ('F', '8'): 'f8', ('I', '1'): 'i1', ('I', '2'): 'i2',
             ('I', '4'): 'i4', ('I', '8'): 'i8', ('U', '1'): 'u1', ('U', '2'): 'u2',
             ('U', '4'): 'u4', ('U', '8'): 'u8'}


def _read_pcd(path: Path) -> np.ndarray:
    """
    Read x, y, z of a PCD file.

    ascii and binary are parsed here (Open3D silently pads a truncated file with zeros);
    binary_compressed goes to Open3D with a count check.
    """
    with open(path, 'rb') as f:
        header = _pcd_header(f, path)
        fields, count, data = header['FIELDS'], int(header['POINTS'][0]), header['DATA'][0]
        if not {'x', 'y', 'z'} <= set(fields):
            raise InvalidInputError(f'{path}: PCD FIELDS lack x, y, z')
        if data == 'ascii':
            rows = [ln for ln in f.read().decode('ascii', errors='replace').splitlines()
                    if ln.strip()]
            if len(rows) < count:
                raise InvalidInputError(f'{path}: PCD file is truncated ({len(rows)} of '
                                        f'{count} points present)')
            columns = _pcd_columns(header)
            table = np.loadtxt(rows[:count], ndmin=2) if count else np.zeros((0, len(columns)))
            return table[:, [columns.index(c) for c in 'xyz']]
        if data == 'binary':
            table = _pcd_binary_table(f, header, path)
            return np.stack([table[c][:, 0] for c in 'xyz'], axis=1).astype(np.float64)
    return _read_pcd_open3d(path, count)


def read_pcd_fields(path: str | Path) -> np.ndarray:
    """
    Every field of a binary PCD file as a structured array (one record per point).

    Field names, types and order are the file's (e.g. x, y, z, intensity, normals); fields
    with COUNT 1 are scalars. Units are the file's (metres for x, y, z).
    """
    path = Path(path)
    with open(path, 'rb') as f:
        header = _pcd_header(f, path)
        if header['DATA'][0] != 'binary':
            kind = header['DATA'][0]
            raise InvalidInputError(f'{path}: read_pcd_fields reads DATA binary, not {kind}')
        table = _pcd_binary_table(f, header, path)
    dtype = np.dtype([(name, table.dtype[name].base) if table.dtype[name].shape == (1,)
                      else (name, table.dtype[name]) for name in table.dtype.names])
    return table.view(dtype) if dtype.itemsize == table.dtype.itemsize else table


def _pcd_binary_table(f, header: dict[str, list[str]], path: Path) -> np.ndarray:
    """Read the points of a binary PCD after its header (one record per point)."""
    count = int(header['POINTS'][0])
    dtype = np.dtype([(name, '<' + PCD_TYPES[(t, s)], (int(c),))
                      for name, s, t, c in zip(header['FIELDS'], header['SIZE'],
                                               header['TYPE'], header['COUNT'])])
    raw = f.read(count * dtype.itemsize)
    if len(raw) < count * dtype.itemsize:
        raise InvalidInputError(f'{path}: PCD file is truncated')
    return np.frombuffer(raw, dtype=dtype)


def _pcd_header(f, path: Path) -> dict[str, list[str]]:
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


def _pcd_columns(header: dict[str, list[str]]) -> list[str]:
    """Column names of an ascii PCD row (fields with COUNT > 1 span several columns)."""
    return [name for name, c in zip(header['FIELDS'], header['COUNT']) for _ in range(int(c))]


def _read_pcd_open3d(path: Path, declared: int) -> np.ndarray:
    import open3d as o3d

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.io.read_point_cloud(str(path), format='pcd')
    points = np.asarray(cloud.points)
    if len(points) != declared:
        raise InvalidInputError(
            f'{path}: header declares {declared} points but {len(points)} could be read; '
            'the file is truncated or corrupt')
    return points


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


def _write_ply(path: Path, points: np.ndarray) -> None:
    header = ('ply\nformat binary_little_endian 1.0\ncomment written by cgags_ros\n'
              f'element vertex {len(points)}\nproperty double x\nproperty double y\n'
              'property double z\nend_header\n')
    with open(path, 'wb') as f:
        f.write(header.encode('ascii'))
        f.write(points.astype('<f8').tobytes())


def _write_pcd(path: Path, points: np.ndarray) -> None:
    n = len(points)
    header = ('# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n'
              f'SIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n'
              f'VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA ascii\n')
    with open(path, 'w', encoding='ascii') as f:
        f.write(header)
        np.savetxt(f, points, fmt='%.17g')
