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
import time
from dataclasses import dataclass
from pathlib import Path

_JOBS: dict = {}
_STARTED: dict = {}

# Under pytest-xdist (the default run: ``-n auto`` in pyproject.toml) every worker
# collects every test, but a job must run once: the first worker (gw0), or the session
# itself without xdist, starts it in a folder named after the test run, and the test,
# on whichever worker it runs, waits for the job's exit status to appear there.
_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
_RUN = os.environ.get("PYTEST_XDIST_TESTRUNUID")


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


def _folder(name: str) -> Path:
    """The job's folder: a new one, or under xdist the one named after the test run."""
    if _RUN is None:
        return Path(tempfile.mkdtemp(prefix=f"tfi_quat_{name}_"))
    return Path(tempfile.gettempdir()) / f"tfi_quat_{name}_{_RUN}"


class _Job:
    """A job this process started (``start``) or one another worker started (``watch``)."""

    def __init__(self, name: str, folder: Path, proc=None):
        self.name, self.folder, self.proc = name, folder, proc

    @classmethod
    def start(cls, name: str) -> "_Job":
        folder = _folder(name)
        folder.mkdir(exist_ok=True)
        argv, cwd, env = _JOBS[name](folder)
        env = {k: v for k, v in (os.environ if env is None else env).items()
               if not k.startswith("PYTEST_XDIST_")}   # the job is no xdist worker
        if shutil.which("nice"):   # it yields to the session, whose tests come first while it runs
            argv = ["nice", "-n", "10", *argv]
        # the exit status is written to ``rc`` (renamed into place) when the job ends, for
        # whichever process waits for it; a session of its own: ending the job ends the
        # programs it started
        script = '"$@" >"$0/log" 2>&1 </dev/null; echo $? >"$0/rc.tmp"; mv "$0/rc.tmp" "$0/rc"'
        proc = subprocess.Popen(["sh", "-c", script, str(folder), *argv], cwd=cwd, env=env,
                                stdin=subprocess.DEVNULL, start_new_session=True)
        return cls(name, folder, proc)

    def wait(self, timeout: float) -> EarlyRun:
        rc = self.folder / "rc"
        deadline = time.monotonic() + timeout
        while not rc.exists():
            if self.proc is not None and self.proc.poll() is not None and not rc.exists():
                pytest.fail(f"early job {self.name!r} ended without an exit status:\n{self._output()[-3000:]}")
            if time.monotonic() > deadline:
                self.kill()
                pytest.fail(f"early job {self.name!r} did not end within {timeout:.0f} s:\n"
                            f"{self._output()[-3000:]}")
            time.sleep(0.2)
        return EarlyRun(int(rc.read_text().strip()), self._output(), self.folder)

    def _output(self) -> str:
        try:
            return (self.folder / "log").read_bytes().decode(errors="replace")
        except FileNotFoundError:
            return ""

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            import signal
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except ProcessLookupError:  # pragma: no cover
                pass
            self.proc.wait()

    def close(self, interrupted: bool) -> None:
        """End of the session of the process that started the job: end it, remove its folder."""
        if self.proc is None:
            return
        if not interrupted and _RUN is not None:
            # under xdist the test may run on another worker: wait until it has
            # looked at the job (``consumed``), then remove the folder
            deadline = time.monotonic() + 1800
            while not (self.folder / "consumed").exists() and time.monotonic() < deadline:
                if self.proc.poll() is not None:
                    deadline = min(deadline, time.monotonic() + 600)
                time.sleep(0.2)
        self.kill()
        shutil.rmtree(self.folder, ignore_errors=True)


def pytest_collection_finish(session):
    if session.config.option.collectonly or _WORKER not in (None, "gw0"):
        return
    for item in session.items:
        mark = item.get_closest_marker("early")
        if mark is not None and mark.args[0] not in _STARTED:
            _STARTED[mark.args[0]] = _Job.start(mark.args[0])


def pytest_sessionfinish(session, exitstatus):
    interrupted = exitstatus == pytest.ExitCode.INTERRUPTED or bool(session.shouldstop)
    while _STARTED:
        _STARTED.popitem()[1].close(interrupted)


@pytest.fixture(scope="session")
def early():
    """``early(name, timeout=...)``: wait for the early job ``name``; an :class:`EarlyRun`.

    A job no process started (no selected test was marked for it) starts now.
    """
    watched = []

    def wait(name: str, timeout: float = 1800.0) -> EarlyRun:
        if name not in _STARTED:
            folder = _folder(name) if _RUN is not None and _WORKER != "gw0" else None
            deadline = time.monotonic() + 60
            while folder is not None and not folder.exists() and time.monotonic() < deadline:
                time.sleep(0.2)   # gw0 starts it when its collection ends
            if folder is not None and folder.exists():
                _STARTED[name] = _Job(name, folder)
            else:
                _STARTED[name] = _Job.start(name)
        watched.append(_STARTED[name].folder)
        return _STARTED[name].wait(timeout)

    yield wait
    for folder in watched:
        if folder.exists():
            (folder / "consumed").touch()
