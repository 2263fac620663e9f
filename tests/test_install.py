"""Installed, not only checked out: the wheel holds the package and its sample grids, and
``tfi-quat demo`` runs from an empty folder in a fresh virtual environment.

The wheel is built the way ``pip install .`` builds it (isolated build, so it needs the
package index that installed the project).  The fresh environment has no system site
packages; the running interpreter's site folders are appended to its path by a ``.pth``
file so it finds numpy, numba, h5py, scipy and matplotlib without downloading them, and
the test checks that ``tfi_quat`` is imported from the wheel, not from this checkout or
from any other install.  The demo's first run compiles every numba kernel (the installed
package has its own, empty, cache): minutes of CPU time, so the whole sequence (build,
install, demo) is one early job (``tests/conftest.py``): this file run as a script, started
when collection ends and running beside the rest of the suite; the tests below check what
it left in its folder.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

from conftest import early_job

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = sorted(p.name for p in (ROOT / "grids").iterdir() if p.suffix in (".x", ".toml"))
DEMO_FILES = ("naca0012_tfi.x", "naca0012_samareh.x", "naca0012_quaternion.x", "demo.png", "demo.md",
              "demo.json")


def _run(cmd, cwd, env=None, timeout=900):
    print("$", *cmd, flush=True)
    res = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    print(res.stdout, res.stderr, sep="\n", flush=True)
    if res.returncode != 0:
        raise SystemExit(f"{cmd} failed ({res.returncode})")
    return res


def build_install_and_run_demo(folder: Path) -> None:
    """The job, all inside ``folder``: the wheel in ``wheel``, the environment ``env`` with
    it installed, the demo's output in ``out`` of the empty folder ``work`` it ran in;
    the files ``where`` and ``demo`` hold what the installed package printed."""
    # built from a copy of the sources: setuptools' build/ folder in the checkout may hold
    # modules since removed, which an in-place build would ship
    src = folder / "src" / "tfi_quat"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        ".git", ".venv", "build", "dist", "*.egg-info", "__pycache__", ".pytest_cache", ".hypothesis",
        "demo_out", "out"))
    out = folder / "wheel"
    out.mkdir()
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(out), str(src)], cwd=out)
    (wheel,) = out.glob("tfi_quat-*.whl")

    env_dir = folder / "env"
    venv.create(env_dir, with_pip=False, symlinks=os.name != "nt")
    bindir = env_dir / ("Scripts" if os.name == "nt" else "bin")
    python = bindir / ("python.exe" if os.name == "nt" else "python")
    site = _run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                cwd=folder).stdout.strip()
    (folder / "site").write_text(site)
    # the running interpreter's site folders, after the fresh environment's own (numpy & co.,
    # and pip to install the wheel with); .pth files inside them are not run, so an
    # editable install of this checkout there stays invisible; a regular install there (as CI
    # makes) is ignored by pip, so the wheel lands in the fresh environment, which comes first
    here = [p for p in sys.path if p.endswith(("site-packages", "dist-packages")) and Path(p).is_dir()]
    (Path(site) / "_tfi_quat_test_deps.pth").write_text("\n".join(here) + "\n")
    _run([str(python), "-m", "pip", "install", "-q", "--no-deps", "--ignore-installed", str(wheel)],
         cwd=folder)

    work = folder / "work"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "NUMBA_CACHE_DIR")}
    where = _run([str(python), "-c", "import tfi_quat, tfi_quat.demo as d; "
                  "print(tfi_quat.__file__); print(d.default_grid_path())"], cwd=work, env=env).stdout
    (folder / "where").write_text(where)
    demo = _run([str(bindir / "tfi-quat"), "demo", "-o", "out"], cwd=work, env=env).stdout
    (folder / "demo").write_text(demo)


@early_job("install")
def _install_job(folder: Path):
    return [sys.executable, __file__, str(folder)], folder, dict(os.environ)


@pytest.fixture(scope="module")
def installed(early):
    """The early job's folder, once it has ended (whatever its outcome)."""
    return early("install")


@pytest.mark.early("install")
def test_wheel_holds_every_package_and_sample_grid(installed):
    wheels = list((installed.folder / "wheel").glob("tfi_quat-*.whl"))
    assert len(wheels) == 1, installed.output[-5000:]
    names = set(zipfile.ZipFile(wheels[0]).namelist())
    packages = sorted(str(p.parent.relative_to(ROOT)).replace(os.sep, "/")
                      for p in (ROOT / "tfi_quat").rglob("__init__.py"))
    for pkg in packages:
        assert f"{pkg}/__init__.py" in names, f"{pkg} missing from the wheel (pyproject.toml packages)"
    for name in SAMPLES:
        assert f"tfi_quat/grids/{name}" in names, f"sample {name} missing from the wheel"
    assert not any(n.startswith(("tests/", "grids/", "benchmarks/")) for n in names)


@pytest.mark.slow
@pytest.mark.early("install")
def test_demo_runs_from_an_empty_folder_in_a_fresh_venv(installed):
    assert installed.returncode == 0, installed.output[-5000:]
    folder = installed.folder
    site = Path((folder / "site").read_text())
    where = (folder / "where").read_text().split()
    assert Path(where[0]).is_relative_to(site), where
    assert Path(where[1]).is_relative_to(site / "tfi_quat" / "grids"), where
    assert "quaternion TFI" in (folder / "demo").read_text()
    work = folder / "work"
    for name in DEMO_FILES:
        assert (work / "out" / name).stat().st_size > 0, name
    assert sorted(p.name for p in work.iterdir()) == ["out"]


if __name__ == "__main__":
    build_install_and_run_demo(Path(sys.argv[1]))
