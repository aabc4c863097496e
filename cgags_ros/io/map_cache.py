"""
On-disk cache of a map's features: one directory of ``.npy`` arrays per key, memory-mapped.

ROS-free and Open3D-free: arrays in, arrays out. The key (:func:`cache_key`) is a hash of
the map file's bytes and of every setting that changes the features. An entry is a directory
``map_features_<key>/`` of one ``.npy`` file per array and a ``meta.json`` of scalars (the
map file, its digest, the settings), written into a temporary directory and renamed, so a
crash never leaves a half-written entry that would be read back.

Entries load by memory mapping (copy on write): every process that loads one map shares the
page cache's one copy of its arrays instead of holding its own, and a restart reads only the
pages a registration touches.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
import shutil
import tempfile
from typing import Any, Mapping

import numpy as np

from ..errors import InvalidInputError

# Bump when the stored arrays change meaning or how they are computed: 2 = FPFH from our
# compiled code (equal to Open3D's to rounding, not to the bit), not Open3D's; 3 = one
# directory of memory-mapped arrays an entry, the descriptor index and local origin with them;
# 4 = the map's places (pipeline/places.py) with them; 5 = the cells of the places' submaps.
CACHE_FORMAT = 5
PREFIX = 'map_features_'
META = 'meta.json'
_CHUNK = 1 << 20


def file_digest(path: str | Path) -> str:
    """Return the blake2b hex digest of the file's bytes (read in 1 MB chunks)."""
    h = hashlib.blake2b(digest_size=16)
    try:
        with open(path, 'rb') as f:
            for chunk in iter(lambda: f.read(_CHUNK), b''):
                h.update(chunk)
    except OSError as exc:
        raise InvalidInputError(f'cannot read map file {path}: {exc}') from exc
    return h.hexdigest()


def cache_key(content_digest: str, settings: Mapping[str, Any]) -> str:
    """Return the cache key of a map file's digest and the feature settings (hex)."""
    text = json.dumps({'format': CACHE_FORMAT, 'content': content_digest,
                       'settings': dict(settings)}, sort_keys=True)
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


def entry_path(cache_dir: str | Path, key: str) -> Path:
    """Return the path of the cache entry (a directory) of ``key`` in ``cache_dir``."""
    return Path(cache_dir) / f'{PREFIX}{key}'


def load_entry(cache_dir: str | Path, key: str
               ) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
    """
    Return the arrays (memory-mapped, copy on write) and the meta stored under ``key``.

    None when there is no readable entry: a damaged one is recomputed and replaced, never
    trusted.
    """
    path = entry_path(cache_dir, key)
    try:
        meta = json.loads((path / META).read_text(encoding='utf-8'))
        arrays = {name: np.asarray(np.load(path / f'{name}.npy', mmap_mode='c',
                                           allow_pickle=False))
                  for name in meta['arrays']}
    except (OSError, ValueError, KeyError, TypeError, EOFError):
        return None
    return arrays, meta


def save_entry(cache_dir: str | Path, key: str, arrays: Mapping[str, np.ndarray],
               meta: Mapping[str, Any]) -> Path:
    """
    Store ``arrays`` and the JSON-able ``meta`` under ``key`` atomically; return the entry.

    An entry another process stored first is kept (it holds the same arrays).

    :raises InvalidInputError: when the cache directory cannot be created or written.
    """
    path = entry_path(cache_dir, key)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=path.parent, suffix='.tmp'))
        for name, array in arrays.items():
            _write(tmp / f'{name}.npy', lambda f, a=array: np.save(
                f, np.ascontiguousarray(a), allow_pickle=False))
        text = json.dumps({**meta, 'arrays': sorted(arrays)}, indent=1).encode()
        _write(tmp / META, lambda f: f.write(text))
        try:
            os.replace(tmp, path)
        except OSError:
            if not (path / META).is_file():
                raise
            shutil.rmtree(tmp, ignore_errors=True)  # stored meanwhile by another process
    except OSError as exc:
        raise InvalidInputError(f'cannot write the map cache in {cache_dir}: {exc}') from exc
    return path


def _write(path: Path, write) -> None:
    """
    Write a file through ``write(f)`` and flush it to disk before the entry is renamed.

    Flushed, the entry survives a crash whole; and its pages are clean, which every process
    that maps them then shares (pages still dirty are mapped privately).
    """
    with open(path, 'wb') as f:
        write(f)
        f.flush()
        os.fsync(f.fileno())


def entries(cache_dir: str | Path) -> list[tuple[Path, dict[str, Any]]]:
    """Return every readable entry of ``cache_dir`` with its meta, oldest first."""
    found = []
    for path in sorted(Path(cache_dir).glob(f'{PREFIX}*')):
        try:
            found.append((path, json.loads((path / META).read_text(encoding='utf-8'))))
        except (OSError, ValueError):
            continue
    return sorted(found, key=lambda e: e[0].stat().st_mtime)
