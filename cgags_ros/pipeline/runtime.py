"""
Thread settings of one registration.

BLAS is held to one thread and descriptor matching runs on its own threads. Own matching
threads are faster than BLAS's (the argmins run in parallel too), and idle BLAS workers
cannot then spin into Open3D's time. The environment defaults that make OpenMP and
OpenBLAS wait passively are set when ``cgags_ros`` is imported (see its ``__init__``),
before numpy and Open3D load.
"""

from __future__ import annotations

import contextlib

from ..parallel import DEFAULT_WORKERS
from ..registration import blas_controller, single_blas_thread


def blas_guard() -> tuple[contextlib.AbstractContextManager, int]:
    """
    Return (context keeping BLAS to one thread, descriptor-matching threads).

    With threadpoolctl: one BLAS thread and ``DEFAULT_WORKERS`` matching threads; without
    it nothing and 1 (BLAS's own threads then match).
    """
    if blas_controller() is None:
        return contextlib.nullcontext(), 1
    return single_blas_thread(), DEFAULT_WORKERS
