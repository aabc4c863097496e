"""
On-disk cache of a map's features: content hash of the map file, one ``.npz`` per key.

ROS-free and Open3D-free: arrays in, arrays out. The key (:func:`cache_key`) is a hash of
the map file's bytes and of every setting that changes the features; an entry is written to
a temporary file and renamed, so a crash never leaves a half-written entry that would be
read back.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
import tempfile
from typing import Any, Mapping

import numpy as np

from ..errors import InvalidInputError

# Bump when the stored arrays change meaning or how they are computed: 2 = FPFH from our
# compiled code (equal to Open3D's to rounding, not to the bit), not Open3D's.
CACHE_FORMAT = 2
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
    """Return the path of the cache entry of ``key`` in ``cache_dir``."""
    return Path(cache_dir) / f'map_features_{key}.npz'


def load_entry(cache_dir: str | Path, key: str) -> dict[str, np.ndarray] | None:
    """Return the arrays stored under ``key``, or None when there is no readable entry."""
    path = entry_path(cache_dir, key)
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            return {name: data[name] for name in data.files}
    except (OSError, ValueError, EOFError):
        return None  # a damaged entry is recomputed (and overwritten), never trusted


def save_entry(cache_dir: str | Path, key: str, arrays: Mapping[str, np.ndarray]) -> Path:
    """
    Store ``arrays`` under ``key`` atomically; return the entry's path.

    :raises InvalidInputError: when the cache directory cannot be created or written.
    """
    path = entry_path(cache_dir, key)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix='.tmp')
        with os.fdopen(fd, 'wb') as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)
    except OSError as exc:
        raise InvalidInputError(f'cannot write the map cache in {cache_dir}: {exc}') from exc
    return path
