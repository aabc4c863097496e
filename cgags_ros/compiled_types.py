"""
The numba types every compiled function's signature is built from, declared once.

The core (:mod:`.registration.compiled`) and the front end (:mod:`.frontend.compiled`)
decorate each compiled function with its signature built from these aliases
(``@njit(signature, cache=True, nogil=True)``): numba compiles it, or loads it from its
on-disk cache, when the module is imported, and refuses any other argument types with a
``TypeError`` instead of compiling a new specialization on a later call. Arrays are
C-contiguous and writable; :func:`c_array` gives any array that form (copying only when it
must). Each package's ``types`` module adds the named tuples its functions take.
"""

from __future__ import annotations

from numba import types
import numpy as np


def _array(dtype, ndim: int) -> types.Array:
    return types.Array(dtype, ndim, 'C')


RNG = types.NumPyRandomGeneratorType('NumPyRandomGeneratorType')  # numpy.random.Generator
INT = types.int64
FLOAT = types.float64
BOOL = types.boolean
F64_1D, F64_2D = _array(types.float64, 1), _array(types.float64, 2)
F64_3D = _array(types.float64, 3)
F32_1D, F32_2D = _array(types.float32, 1), _array(types.float32, 2)
I64_1D, I64_2D = _array(types.int64, 1), _array(types.int64, 2)
I32_1D, I32_2D = _array(types.int32, 1), _array(types.int32, 2)
U64_1D, U64_2D = _array(types.uint64, 1), _array(types.uint64, 2)
BOOL_1D, BOOL_2D = _array(types.boolean, 1), _array(types.boolean, 2)


def c_array(a, dtype) -> np.ndarray:
    """Return ``a`` as a C-contiguous, aligned, writable ``dtype`` array (copied if it is not)."""
    if type(a) is np.ndarray and a.dtype == dtype:  # the usual case, without np.require's cost
        flags = a.flags
        if flags.c_contiguous and flags.aligned and flags.writeable:
            return a
    return np.require(a, dtype, 'CAW')
