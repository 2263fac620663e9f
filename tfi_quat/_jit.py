"""The one place that imports numba.

Every kernel in the package is compiled through :data:`jit` (serial) or
:data:`pjit` (parallel, use :data:`prange` for the outer loop).  Settings,
read once when this module is first imported:

``TFI_QUAT_JIT=0``
    do not compile at all: :data:`jit` and :data:`pjit` return the plain
    Python function (with ``py_func`` pointing at itself, as a compiled
    kernel has) and :data:`prange` is ``range``.  Every kernel then runs as
    ordinary Python (slow: for tests and debugging with pdb/coverage).
``TFI_QUAT_CACHE=0``
    do not cache compiled kernels on disk (default: cache, so a warm CLI
    start-up skips compilation).

numba's disk cache is invalidated only by changes to a kernel's own source
file: kernels that inline helpers from another module (``tfi``, ``deform``,
``blending`` and ``boundary`` inline the helpers of ``kernels`` and
``quaternion``) keep their cached machine code when only the helper's file
changes.  After
editing such a helper, delete the package's ``__pycache__`` folders (or run
with ``TFI_QUAT_CACHE=0``); a fresh checkout, as in CI, has no cache.

Tests that run one kernel uncompiled inside a compiled session use
``kernel.py_func``; ``tests/test_jit.py`` runs the package with
``TFI_QUAT_JIT=0`` in a subprocess.  (numba's own ``NUMBA_DISABLE_JIT=1``
also works for code that does not use ``py_func``.)
"""

from __future__ import annotations

import contextlib
import functools
import os

import numba

__all__ = ["jit", "pjit", "prange", "CACHE", "ENABLED", "numba", "serial_below", "SERIAL_BELOW",
           "use_threads", "warm_up_in_background"]


def _flag(name: str, default: str) -> bool:
    return os.environ.get(name, default).strip().lower() not in ("0", "false", "no", "off")


#: kernels are compiled (``TFI_QUAT_JIT``, default on)
ENABLED = _flag("TFI_QUAT_JIT", "1")
#: compiled kernels are cached on disk (``TFI_QUAT_CACHE``, default on)
CACHE = _flag("TFI_QUAT_CACHE", "1")


def _plain(*args, **options):
    """Stand-in for ``numba.njit`` when compilation is off: ``@_plain`` or ``@_plain(...)``."""
    def wrap(fn):
        fn.py_func = fn
        return fn
    if len(args) == 1 and callable(args[0]) and not options:
        return wrap(args[0])
    return wrap


if ENABLED:
    #: serial kernel: ``@jit`` or ``@jit(inline="always")``
    jit = functools.partial(numba.njit, cache=CACHE, error_model="numpy", nogil=True)
    #: parallel kernel; its outer loop uses :data:`prange`
    pjit = functools.partial(numba.njit, cache=CACHE, error_model="numpy", nogil=True, parallel=True)
    prange = numba.prange
else:
    jit = _plain
    pjit = _plain
    prange = range


#: parallel kernels on less work than this (points) run on one thread: on a
#: shared 2-core machine a parallel region whose second thread is descheduled
#: waits for it (a 16 705-point C-grid step took 28-40 ms with 2 threads under
#: load, 0.3-0.7 ms on one), while below this size the second thread saves
#: less than a millisecond when the machine is idle
SERIAL_BELOW = 200_000


def serial_below(work: int, limit: int = SERIAL_BELOW):
    """Context: run the parallel kernels called inside on one thread when ``work < limit``.

    ``numba.set_num_threads`` is per calling thread, so other threads are not
    affected; outside the context the previous setting is restored.
    """
    if not ENABLED or work >= limit:
        return contextlib.nullcontext()
    return _one_thread()


@contextlib.contextmanager
def _one_thread():
    prev = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(prev)


def use_threads(n: int | None):
    """Context: the parallel kernels called inside (by this thread) use at most ``n``
    threads; ``None``: leave the setting as it is.  The previous setting is restored
    on exit."""
    if n is None or not ENABLED:
        return contextlib.nullcontext()
    n = int(n)
    if n < 1:
        raise ValueError(f"threads must be >= 1, got {n}")
    return _n_threads(min(n, numba.config.NUMBA_NUM_THREADS))


@contextlib.contextmanager
def _n_threads(n: int):
    prev = numba.get_num_threads()
    numba.set_num_threads(min(n, prev) if prev else n)
    try:
        yield
    finally:
        numba.set_num_threads(prev)


def warm_up_in_background():
    """Start numba's one-time set-up (its typing and lowering tables: about 0.6 s of CPU that
    the first compiled call of a process otherwise waits for) in a background thread, so
    that it overlaps work without kernels, such as reading a grid.  Returns the thread
    (``None`` when compilation is off).  A kernel called meanwhile waits for it (numba's
    compiler lock); if the set-up fails here, the first kernel call does it as usual."""
    if not ENABLED:
        return None

    def work():
        try:
            from numba.core.compiler_lock import global_compiler_lock
            from numba.core.registry import cpu_target
            with global_compiler_lock:
                cpu_target.target_context.refresh()
        except Exception:           # noqa: BLE001 -- an optimisation only
            pass

    import threading
    thread = threading.Thread(target=work, name="tfi_quat-jit-warm-up")
    thread.start()
    return thread
