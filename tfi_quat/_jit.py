"""The one place that imports numba, and the package's thread pool.

Every kernel in the package is compiled through :data:`jit` (serial,
``nogil``) or, when it is a *task kernel* run on several threads,
:data:`task_jit`.  Settings, read once when this module is first imported:

``TFI_QUAT_JIT=0``
    do not compile at all: :data:`jit` and :data:`task_jit` return the plain
    Python function (with ``py_func`` pointing at itself, as a compiled
    kernel has), and :func:`parallel_for` runs every task on the calling
    thread.  Every kernel then runs as ordinary Python (slow: for tests and
    debugging with pdb/coverage).
``TFI_QUAT_CACHE=0``
    do not cache compiled kernels on disk (default: cache, so a warm CLI
    start-up skips compilation).
``NUMBA_NUM_THREADS``
    the most threads :func:`parallel_for` uses (numba's own setting, which
    defaults to the number of CPUs): :data:`THREADS`.

Threads
-------
No kernel uses numba's parallel loops (``parallel=True``/``prange``).  A
task kernel is serial over a range of independent tasks (rows, planes,
tiles of lines) given as its first two arguments ``lo, hi``;
:func:`parallel_for` splits ``[0, ntasks)`` into one contiguous chunk per
thread and runs the chunks at once, the calling thread taking the first and
a persistent pool of ``THREADS - 1`` Python threads the others.  The kernels
release the GIL (``nogil``), so the chunks run truly in parallel; a waiting
pool thread blocks on a lock and takes no CPU (numba's OpenMP layer spun
between parallel regions: on a loaded machine a step took ~4x the CPU of a
one-thread step).  A serial kernel also compiles seconds faster than the
same loop as a numba parallel one (no parfor passes, no gufunc): with every
kernel serial, the demo's cold start fell from 65.6 s to 49.9 s.  Tasks
write disjoint parts of the output, and any reduction is combined after the
chunks in a fixed order, so results are bit for bit the same with any number
of threads.  The threads a call may use are a per-thread setting:
:func:`use_threads` caps them (``Deformer(threads=N)``), :func:`serial_below`
drops to one for small work; :func:`threads` reads it.  A task kernel called
from a pool thread (a nested call) runs on that thread alone.

Task kernels are compiled with numba's ``noalias`` flag, as numba compiled the
bodies of its parallel loops: the volume loops vectorise only with it.  Their
array arguments must therefore not overlap except to read, or, for an
in-place update, point for point (each point read before it is written).

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

import concurrent.futures
import contextlib
import functools
import os
import threading

import numba
from numba.core import compiler as _compiler

__all__ = ["jit", "task_jit", "CACHE", "ENABLED", "THREADS", "numba", "parallel_for",
           "serial_below", "SERIAL_BELOW", "threads", "use_threads", "warm_up_in_background"]


def _flag(name: str, default: str) -> bool:
    return os.environ.get(name, default).strip().lower() not in ("0", "false", "no", "off")


#: kernels are compiled (``TFI_QUAT_JIT``, default on)
ENABLED = _flag("TFI_QUAT_JIT", "1")
#: compiled kernels are cached on disk (``TFI_QUAT_CACHE``, default on)
CACHE = _flag("TFI_QUAT_CACHE", "1")
#: the most threads a :func:`parallel_for` uses (``NUMBA_NUM_THREADS``, default: the CPUs)
THREADS = max(1, int(numba.config.NUMBA_NUM_THREADS))


def _plain(*args, **options):
    """Stand-in for ``numba.njit`` when compilation is off: ``@_plain`` or ``@_plain(...)``."""
    def wrap(fn):
        fn.py_func = fn
        return fn
    if len(args) == 1 and callable(args[0]) and not options:
        return wrap(args[0])
    return wrap


class _NoAliasCompiler(_compiler.Compiler):
    """numba's default pipeline with the ``noalias`` flag set (array arguments do not
    overlap), which numba otherwise sets only on the bodies of its parallel loops."""

    def define_pipelines(self):
        self.state.flags.noalias = True
        return super().define_pipelines()


if ENABLED:
    #: serial kernel: ``@jit`` or ``@jit(inline="always")``
    jit = functools.partial(numba.njit, cache=CACHE, error_model="numpy", nogil=True)
    #: task kernel for :func:`parallel_for`: ``kernel(lo, hi, *args)`` runs tasks
    #: ``lo <= t < hi``; compiled as :data:`jit` with ``noalias`` (module docstring)
    task_jit = functools.partial(numba.njit, cache=CACHE, error_model="numpy", nogil=True,
                                 pipeline_class=_NoAliasCompiler)
else:
    jit = _plain
    task_jit = _plain


#: parallel kernels on less work than this (points) run on one thread: on a
#: shared 2-core machine a parallel call whose second thread is descheduled
#: waits for it (a 16 705-point C-grid step took 28-40 ms with 2 threads under
#: load, 0.3-0.7 ms on one), while below this size the second thread saves
#: less than a millisecond when the machine is idle
SERIAL_BELOW = 200_000

_local = threading.local()          # .cap: threads for this thread's calls; .worker: a pool thread


def threads() -> int:
    """The threads a :func:`parallel_for` called now by this thread may use (1 in a pool
    thread, and when compilation is off)."""
    if not ENABLED or getattr(_local, "worker", False):
        return 1
    return getattr(_local, "cap", THREADS)


@contextlib.contextmanager
def _capped(n: int):
    prev = getattr(_local, "cap", THREADS)
    _local.cap = max(1, min(n, prev))
    try:
        yield
    finally:
        _local.cap = prev


def serial_below(work: int, limit: int = SERIAL_BELOW):
    """Context: the task kernels called inside (by this thread) run on one thread when
    ``work < limit``.  Other threads are not affected; outside the context the previous
    setting is restored."""
    if not ENABLED or work >= limit:
        return contextlib.nullcontext()
    return _capped(1)


def use_threads(n: int | None):
    """Context: the task kernels called inside (by this thread) use at most ``n`` threads
    (and at most :data:`THREADS`); ``None``: leave the setting as it is.  The previous
    setting is restored on exit."""
    if n is None:
        return contextlib.nullcontext()
    n = int(n)
    if n < 1:
        raise ValueError(f"threads must be >= 1, got {n}")
    return _capped(n)


_pool = None
_pool_lock = threading.Lock()


def _mark_worker():
    _local.worker = True


def _get_pool():
    global _pool
    pool = _pool
    if pool is None:
        with _pool_lock:
            pool = _pool
            if pool is None:
                pool = _pool = concurrent.futures.ThreadPoolExecutor(
                    max_workers=THREADS - 1, thread_name_prefix="tfi_quat",
                    initializer=_mark_worker)
    return pool


def _forget_pool():
    """In a forked child the pool's threads do not exist: start a new pool on demand."""
    global _pool, _pool_lock
    _pool = None
    _pool_lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def parallel_for(kernel, ntasks: int, *args) -> None:
    """Run the task kernel ``kernel(lo, hi, *args)`` over the tasks ``0 <= t < ntasks``.

    The tasks are split into :func:`threads` contiguous chunks of (nearly) equal
    counts, one per thread, run at once: the first by the calling thread, the others by
    the pool.  Returns when every chunk is done; an exception raised by a chunk is
    raised here (after the other chunks have finished).  The tasks must be
    independent: each writes its own part of the output.
    """
    ntasks = int(ntasks)
    if ntasks <= 0:
        return
    nt = min(threads(), ntasks)
    if nt == 1:
        kernel(0, ntasks, *args)
        return
    edge = [ntasks * p // nt for p in range(nt + 1)]
    pool = _get_pool()
    futures = [pool.submit(kernel, edge[p], edge[p + 1], *args) for p in range(1, nt)]
    err = None
    try:
        kernel(edge[0], edge[1], *args)
    except BaseException as exc:      # noqa: BLE001 -- re-raised once the others are done
        err = exc
    for f in futures:
        exc = f.exception()
        if err is None and exc is not None:
            err = exc
    if err is not None:
        raise err


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
