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
from pathlib import Path

import pytest

from conftest import early_job

ROOT = Path(__file__).resolve().parents[1]


def _run(args, jit: str, timeout: float = 600.0):
    env = dict(os.environ, TFI_QUAT_JIT=jit)
    return subprocess.run([sys.executable, *args], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=timeout)


def test_switch_off_gives_plain_python_kernels():
    code = (
        "import numba, numpy as np\n"
        "from tfi_quat import _jit, quaternion as Q, boundary as B, tfi as T\n"
        "assert not _jit.ENABLED and _jit.prange is range\n"
        "for k in (Q.kmul, Q.kblend, B._motion_kernel(False), B._interior_quaternion, T._volume_kernel(True, True, False), T._ARC_DIR[1]):\n"
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
    import numba
    from tfi_quat._jit import ENABLED, SERIAL_BELOW, serial_below
    assert ENABLED           # the suite runs compiled (test_kernel_tests_pass_uncompiled: a subprocess)
    before = numba.get_num_threads()
    with serial_below(SERIAL_BELOW - 1):
        assert numba.get_num_threads() == 1
    assert numba.get_num_threads() == before
    with serial_below(SERIAL_BELOW):
        assert numba.get_num_threads() == before
