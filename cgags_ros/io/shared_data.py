"""
Where the shared real data lives: ``../shared/data`` beside the repository, or ``CGAGS_DATA_DIR``.

``cgags-demo`` finds its bundled bags there; the tests and the benchmarks read their scans
from it. An installed package has no repository beside it, so there only the environment
variable names the folder.
"""

from __future__ import annotations

import os
from pathlib import Path

DEFAULT_SHARED_DATA = Path(__file__).resolve().parents[2].parent / 'shared' / 'data'


def shared_data_dir() -> Path:
    """Return ``../shared/data`` relative to the repository root (or CGAGS_DATA_DIR)."""
    return Path(os.environ.get('CGAGS_DATA_DIR', DEFAULT_SHARED_DATA))
