"""
Keep BLAS to one thread while the core runs (optional ``threadpoolctl``).

The core's matrix products are small (3x3 fits, 5-deep graph blocks) or memory bound, so a
second OpenBLAS thread does not shorten them; it only spins and takes CPU time that, on a
robot, belongs to the other nodes (docs/design.md). ``threadpoolctl`` is not a
dependency of the core (numpy/scipy only): without it this is a no-op.
"""

from __future__ import annotations

import contextlib
import functools
from typing import Any

_controller: Any = None


def blas_controller() -> Any:
    """
    Return the shared ``threadpoolctl.ThreadpoolController``, or None without threadpoolctl.

    The controller is made once, on first use, after numpy and scipy have loaded their BLAS.
    """
    global _controller
    if _controller is None:
        try:
            from threadpoolctl import ThreadpoolController
        except ImportError:
            _controller = False
        else:
            _controller = ThreadpoolController()
    return None if _controller is False else _controller


def single_blas_thread() -> contextlib.AbstractContextManager:
    """Context in which BLAS uses one thread (nests; restores the previous limits)."""
    controller = blas_controller()
    if controller is None:
        return contextlib.nullcontext()
    return controller.limit(limits=1, user_api='blas')


def with_single_blas_thread(fn):
    """Wrap ``fn`` so that it runs under :func:`single_blas_thread` (a decorator)."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with single_blas_thread():
            return fn(*args, **kwargs)
    return wrapper
