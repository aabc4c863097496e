"""PLY files: the ``vertex`` element's scalar properties, read and written (binary, ascii)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InvalidInputError

PLY_TYPES = {'char': 'i1', 'int8': 'i1', 'uchar': 'u1', 'uint8': 'u1', 'short': 'i2',
             'int16': 'i2', 'ushort': 'u2', 'uint16': 'u2', 'int': 'i4', 'int32': 'i4',
             'uint': 'u4', 'uint32': 'u4', 'float': 'f4', 'float32': 'f4', 'double': 'f8',
             'float64': 'f8'}


def read_vertex_columns(path: Path) -> dict[str, np.ndarray]:
    """
    Return every scalar property of the ``vertex`` element by name (x, y, z required).

    Our own reader rather than Open3D's, because Open3D fills a truncated binary file with
    zeros instead of failing; other elements (a Stanford scan's ``range_grid``) are skipped.
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
            return {p: data[:, i] for i, (p, _) in enumerate(props)}
        endian = '<' if fmt == 'binary_little_endian' else '>'
        dtype = np.dtype([(p, endian + t) for p, t in props])
        raw = f.read(count * dtype.itemsize)
    if len(raw) < count * dtype.itemsize:
        raise InvalidInputError(f'{path}: PLY file is truncated ({len(raw) // dtype.itemsize} '
                                f'of {count} vertices present)')
    data = np.frombuffer(raw, dtype=dtype)
    return {p: data[p] for p, _ in props}


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


def write(path: Path, points: np.ndarray, normals: np.ndarray | None = None) -> None:
    """Write binary little-endian double x, y, z (and nx, ny, nz with ``normals``)."""
    names = 'xyz' if normals is None else ('x', 'y', 'z', 'nx', 'ny', 'nz')
    table = points if normals is None else np.hstack([points, normals])
    header = ('ply\nformat binary_little_endian 1.0\ncomment written by cgags_ros\n'
              f'element vertex {len(points)}\n'
              + ''.join(f'property double {n}\n' for n in names) + 'end_header\n')
    with open(path, 'wb') as f:
        f.write(header.encode('ascii'))
        f.write(np.ascontiguousarray(table, dtype='<f8').tobytes())
