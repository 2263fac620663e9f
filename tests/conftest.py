"""Shared fixtures: small canonical grids and helpers."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import settings

settings.register_profile("ci", max_examples=40, deadline=None, derandomize=True)
settings.register_profile("dev", max_examples=40, deadline=None)
settings.load_profile(os.environ.get("TFI_QUAT_HYPOTHESIS", "ci"))


def sheared_box(ni=5, nj=4, nk=3, seed=0):
    """A sheared, slightly warped 3-D box, float64 Fortran order ``(ni, nj, nk, 3)``."""
    i, j, k = np.meshgrid(np.linspace(0, 1, ni), np.linspace(0, 1, nj), np.linspace(0, 1, nk),
                          indexing="ij")
    x = 2.0 * i + 0.3 * j + 0.05 * np.sin(3 * k)
    y = 1.5 * j + 0.2 * k + 0.02 * i * i
    z = 1.0 * k + 0.1 * i * j
    return np.asfortranarray(np.stack([x, y, z], axis=-1))


def annulus(ni=9, nj=5, r0=1.0, r1=3.0, theta=np.pi / 2):
    """A 2-D annulus sector ``(ni, nj, 1, 3)``: i around, j outwards, z = 0."""
    t = np.linspace(0.0, theta, ni)[:, None]
    r = np.geomspace(r0, r1, nj)[None, :]
    xyz = np.zeros((ni, nj, 1, 3), order="F")
    xyz[:, :, 0, 0] = r * np.cos(t)
    xyz[:, :, 0, 1] = r * np.sin(t)
    return xyz


@pytest.fixture
def box_xyz():
    return sheared_box()


@pytest.fixture
def annulus_xyz():
    return annulus()


# ---------------------------------------------------------------- work started early
#
# A few tests check a whole program run in another process (the wheel installed into a
# fresh virtual environment and its demo; the kernel tests run uncompiled).  Each such run
# is mostly one CPU busy for minutes, so it is started when collection ends, as soon as a
# selected test is marked ``@pytest.mark.early(NAME)``, and runs beside the rest of the
# session; the test waits for it with the ``early`` fixture and checks its outcome.
# A job is a function ``(folder) -> (argv, cwd, env)`` registered with :func:`early_job`;
# the process gets an empty ``folder`` of its own and writes its output to ``folder/log``.

import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

_JOBS: dict = {}
_STARTED: dict = {}


def early_job(name: str):
    """Register ``fn(folder) -> (argv, cwd, env)`` as the early job ``name``."""
    def register(fn):
        _JOBS[name] = fn
        return fn
    return register


@dataclass
class EarlyRun:
    """The outcome of an early job: its exit status, output (stdout and stderr) and folder."""

    returncode: int
    output: str
    folder: Path


class _Job:
    def __init__(self, name: str):
        self.name = name
        self.folder = Path(tempfile.mkdtemp(prefix=f"tfi_quat_{name}_"))
        argv, cwd, env = _JOBS[name](self.folder)
        if shutil.which("nice"):   # it yields to the session, whose tests come first while it runs
            argv = ["nice", "-n", "10", *argv]
        self.log = open(self.folder / "log", "w+b")
        # a session of its own: ending the job ends the programs it started
        self.proc = subprocess.Popen(argv, cwd=cwd, env=env, stdin=subprocess.DEVNULL, stdout=self.log,
                                     stderr=subprocess.STDOUT, start_new_session=True)

    def wait(self, timeout: float) -> EarlyRun:
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            pytest.fail(f"early job {self.name!r} did not end within {timeout:.0f} s:\n{self._output()[-3000:]}")
        return EarlyRun(self.proc.returncode, self._output(), self.folder)

    def _output(self) -> str:
        self.log.flush()
        self.log.seek(0)
        return self.log.read().decode(errors="replace")

    def kill(self) -> None:
        if self.proc.poll() is None:
            import signal
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except ProcessLookupError:  # pragma: no cover
                pass
            self.proc.wait()

    def close(self) -> None:
        self.kill()
        self.log.close()
        shutil.rmtree(self.folder, ignore_errors=True)


def pytest_collection_finish(session):
    if session.config.option.collectonly:
        return
    for item in session.items:
        mark = item.get_closest_marker("early")
        if mark is not None and mark.args[0] not in _STARTED:
            _STARTED[mark.args[0]] = _Job(mark.args[0])


def pytest_sessionfinish(session):
    while _STARTED:
        _STARTED.popitem()[1].close()


@pytest.fixture(scope="session")
def early():
    """``early(name, timeout=...)``: wait for the early job ``name``; an :class:`EarlyRun`.

    A job no selected test was marked for (so not started yet) starts now.
    """
    def wait(name: str, timeout: float = 1800.0) -> EarlyRun:
        if name not in _STARTED:
            _STARTED[name] = _Job(name)
        return _STARTED[name].wait(timeout)
    return wait
