"""The one place that imports numba.

Every kernel in the package is compiled through :data:`jit` (serial) or
:data:`pjit` (parallel, use :data:`prange` for the outer loop).  Settings:

``TFI_QUAT_CACHE=0``
    do not cache compiled kernels on disk (default: cache, so a warm CLI
    start-up skips compilation).
``NUMBA_DISABLE_JIT=1``
    numba's own switch: every kernel runs as plain Python (slow; tests use
    ``kernel.py_func`` instead to run one kernel uncompiled).
"""

from __future__ import annotations

import functools
import os

import numba

__all__ = ["jit", "pjit", "prange", "CACHE", "numba"]

CACHE = os.environ.get("TFI_QUAT_CACHE", "1").strip().lower() not in ("0", "false", "no", "off")

#: serial kernel: ``@jit`` or ``@jit(inline="always")``
jit = functools.partial(numba.njit, cache=CACHE, error_model="numpy", nogil=True)
#: parallel kernel; its outer loop uses :data:`prange`
pjit = functools.partial(numba.njit, cache=CACHE, error_model="numpy", nogil=True, parallel=True)
prange = numba.prange
