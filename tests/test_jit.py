"""The JIT settings (tfi_quat._jit): one switch turns compilation off for the whole package.

With ``TFI_QUAT_JIT=0`` every kernel is the plain Python function, so the
kernel tests below run the algebra, boundary and TFI kernels uncompiled, end
to end (a kernel's ``py_func`` inside a compiled session still calls the
compiled kernels it uses).
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from conftest import early_job
from tfi_quat import _jit

ROOT = Path(__file__).resolve().parents[1]


def _run(args, jit: str, timeout: float = 600.0):
    env = dict(os.environ, TFI_QUAT_JIT=jit)
    return subprocess.run([sys.executable, *args], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=timeout)


def test_switch_off_gives_plain_python_kernels():
    code = (
        "import numba, numpy as np\n"
        "from tfi_quat import _jit, quaternion as Q, boundary as B, tfi as T, blending as L\n"
        "assert not _jit.ENABLED and _jit.threads() == 1\n"
        "for k in (Q.kmul, Q.kblend, B._motion_rows, B._interior_quaternion, T._volume_kernel(True, True, False), L._arc_layer_jk):\n"
        "    assert not isinstance(k, numba.core.dispatcher.Dispatcher), k\n"
        "    assert k.py_func is k\n"
        "out = np.empty(4)\n"
        "Q.kmul(np.array([0.0, 1, 0, 0]), np.array([0.0, 0, 1, 0]), out)\n"
        "assert list(out) == [0, 0, 0, 1]\n"
        "print('plain')\n"
    )
    res = _run(["-c", code], "0", timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "plain"
    res = _run(["-c", "import numba; from tfi_quat import _jit, quaternion as Q; "
                      "assert _jit.ENABLED; assert isinstance(Q.kmul, numba.core.dispatcher.Dispatcher); "
                      "print('compiled')"], "1", timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "compiled"


UNCOMPILED = ["tests/test_quaternion.py", "tests/test_boundary.py", "tests/test_tfi.py"]


@early_job("uncompiled")
def _uncompiled_job(folder):
    # the memory test needs a 128^3 block (minutes in plain Python) and measures numpy
    # allocations, which are the same compiled or not
    argv = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "0", "-k",
            "not allocates_only_surface_tables", *UNCOMPILED]
    return argv, ROOT, dict(os.environ, TFI_QUAT_JIT="0")


@pytest.mark.slow
@pytest.mark.early("uncompiled")
def test_kernel_tests_pass_uncompiled(early):
    """The quaternion, boundary and TFI test files, run with every kernel as plain Python
    (an early job: started when collection ends, beside the rest of the session)."""
    res = early("uncompiled")
    tail = res.output[-3000:]
    assert res.returncode == 0, tail
    assert " passed" in res.output and "failed" not in res.output and "skipped" not in res.output, tail


def test_serial_below_runs_small_work_on_one_thread():
    from tfi_quat._jit import ENABLED, SERIAL_BELOW, THREADS, serial_below, threads
    assert ENABLED           # the suite runs compiled (test_kernel_tests_pass_uncompiled: a subprocess)
    assert threads() == THREADS
    with serial_below(SERIAL_BELOW - 1):
        assert threads() == 1
    assert threads() == THREADS
    with serial_below(SERIAL_BELOW):
        assert threads() == THREADS


def _record(lo, hi, log, fail_at=-1):
    """A 'kernel' in Python: logs its range and thread; raises on task ``fail_at``."""
    log.append((lo, hi, threading.get_ident(), _jit.threads()))
    if lo <= fail_at < hi:
        raise ArithmeticError(f"task {fail_at}")


@pytest.mark.parametrize("ntasks", [0, 1, 2, 3, 7, 1000])
@pytest.mark.parametrize("cap", [1, 2, 3, None])
def test_parallel_for_splits_tasks_into_one_contiguous_chunk_per_thread(ntasks, cap):
    log = []
    with _jit.use_threads(cap):
        want = min(_jit.threads(), max(ntasks, 1))
        _jit.parallel_for(_record, ntasks, log)
    chunks = sorted(log)
    if ntasks == 0:
        assert chunks == []
        return
    assert len(chunks) == want
    assert chunks[0][0] == 0 and chunks[-1][1] == ntasks
    assert all(a[1] == b[0] for a, b in zip(chunks, chunks[1:]))       # contiguous, no overlap
    sizes = [hi - lo for lo, hi, _, _ in chunks]
    assert max(sizes) - min(sizes) <= 1
    me = threading.get_ident()
    assert [c[2] == me for c in chunks].count(True) == 1              # the caller took one
    assert (0, sizes[0], me, want) in log or want == 1                 # ... the first
    assert all(c[3] == 1 for c in chunks if c[2] != me)               # nested calls: serial
    assert len({c[2] for c in chunks}) == want


def test_use_threads_is_per_calling_thread_and_nests():
    assert _jit.threads() == _jit.THREADS
    seen = {}
    with _jit.use_threads(1):
        assert _jit.threads() == 1
        with _jit.use_threads(5):                  # an inner context never raises the cap
            assert _jit.threads() == 1
        t = threading.Thread(target=lambda: seen.setdefault("other", _jit.threads()))
        t.start()
        t.join()
    assert seen["other"] == _jit.THREADS
    assert _jit.threads() == _jit.THREADS
    with _jit.use_threads(10 ** 6):
        assert _jit.threads() == _jit.THREADS
    with pytest.raises(ValueError, match="threads must be >= 1"):
        _jit.use_threads(0)


@pytest.mark.parametrize("fail_at", [0, 999])
def test_parallel_for_raises_a_chunks_error_after_every_chunk_is_done(fail_at):
    log = []
    with pytest.raises(ArithmeticError, match=f"task {fail_at}"):
        _jit.parallel_for(_record, 1000, log, fail_at)
    assert sum(hi - lo for lo, hi, _, _ in log) == 1000


def test_results_do_not_depend_on_the_threads():
    """Task kernels on 1, 2 and 3 threads (at most THREADS: the caller and the pool), bit for bit."""
    from tfi_quat import blending, tfi
    rng = np.random.default_rng(5)
    xyz = np.asfortranarray(np.cumsum(rng.uniform(0.1, 1.0, (37, 29, 11, 3)), axis=0))
    lam = [rng.uniform(0.0, 2.0, shape) for shape in ((29, 11), (29, 11), (37, 11), (37, 11),
                                                      (37, 29), (37, 29))]
    got = []
    for n in (1, 2, 3):
        with _jit.use_threads(n), _jit.serial_below(0):
            got.append((tfi.arclength(xyz), blending.wall_layer_arclength(xyz, lam)))
    for s, w in got[1:]:
        assert np.array_equal(s.view(np.int64), got[0][0].view(np.int64))
        assert np.array_equal(w.view(np.int64), got[0][1].view(np.int64))


_SIGNATURES = r"""
import io, contextlib, sys, tempfile
import numba
from tfi_quat.cli import main
with contextlib.redirect_stdout(io.StringIO()):
    rc = main(["demo", "-o", tempfile.mkdtemp(), "--force", "--no-figure"])
assert rc == 0, rc
seen = set()
for name, mod in list(sys.modules.items()):
    if not name.startswith("tfi_quat"):
        continue
    for attr, v in vars(mod).items():
        if isinstance(v, numba.core.registry.CPUDispatcher) and id(v) not in seen:
            seen.add(id(v))
            if v.signatures:
                print(f"{name}.{attr} {len(v.signatures)}")
"""


def test_demo_compiles_one_specialisation_per_kernel(tmp_path):
    """A first run compiles what it uses once (docs/performance.md, *Cold start*): in the demo
    (2-D, three methods) every module-level kernel and helper has one compiled signature (no
    int32/int64, layout or literal-argument duplicates), but the volume row and point, one per
    kind (baseline, quaternion, based); its point sets are small, so no point search is compiled.
    Run cold (an empty numba cache: a kernel loaded from the cache does not load its helpers)."""
    env = dict(os.environ, TFI_QUAT_JIT="1", NUMBA_CACHE_DIR=str(tmp_path))
    out = subprocess.run([sys.executable, "-c", _SIGNATURES], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    counts = dict(line.rsplit(" ", 1) for line in out.stdout.splitlines() if line.strip())
    counts = {k: int(v) for k, v in counts.items()}
    per_kind = ("tfi_quat.tfi._point", "tfi_quat.tfi._row")
    assert all(counts.get(k) == 3 for k in per_kind), counts
    many = {k: n for k, n in counts.items() if n > 1 and k not in per_kind}
    assert not many, f"compiled more than once: {many}"
    searches = {k for k in counts if k.startswith("tfi_quat._points.")}
    assert not searches, f"point searches compiled for the demo's small sets: {searches}"
