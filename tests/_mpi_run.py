"""Launching an MPI test job: ``mpiexec -n N python JOB SPEC`` under a timeout, each rank
writing its report to ``SPEC.rank<r>`` (JSON); shared by tests/test_mpi.py and
tests/test_mpi_deform.py."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).parent.parent
#: HDF5 files carry their creation time: the serial and the MPI writes take it from here
EPOCH = "1700000000"


def mpiexec() -> str:
    """The ``mpiexec`` of the installed ``mpi`` extra: next to this Python, else on PATH."""
    here = Path(sysconfig.get_path("scripts")) / "mpiexec"
    found = str(here) if here.exists() else shutil.which("mpiexec")
    assert found, 'mpiexec not found: install the mpi extra (pip install "tfi_quat[mpi]")'
    return found


def launch(job: Path, spec_path: Path, nranks: int, cwd: Path, timeout: float) -> list:
    """Run ``job`` on ``nranks`` ranks with the spec file ``spec_path``; a hang (past
    ``timeout`` seconds) or a failed launch fails the test; returns each rank's report (the
    reports are removed)."""
    env = dict(os.environ, SOURCE_DATE_EPOCH=EPOCH, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1",
               NUMBA_NUM_THREADS="1")
    proc = subprocess.Popen([mpiexec(), "-n", str(nranks), sys.executable, str(job), str(spec_path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            cwd=cwd, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"MPI job hung (killed after {timeout} s):\n{out}\n{err}")
    assert proc.returncode == 0, f"mpiexec failed ({proc.returncode}):\n{out}\n{err}"
    reports = []
    for r in range(nranks):
        report = Path(f"{spec_path}.rank{r}")
        assert report.exists(), f"rank {r} did not finish:\n{out}\n{err}"
        reports.append(json.loads(report.read_text(encoding="utf-8")))
        report.unlink()
    return reports
