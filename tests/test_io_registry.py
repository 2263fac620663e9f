"""The format registry (tfi_quat.io): choosing a format, atomic writes."""

import os
import subprocess
import sys

import numpy as np
import pytest

import tfi_quat as tq
from tfi_quat.io import _atomic, format_for

from conftest import sheared_box


@pytest.fixture
def grid():
    return tq.Grid([sheared_box(4, 3, 2)])


def test_extension_picks_the_format(tmp_path, grid):
    assert format_for(tmp_path / "a.x").name == "plot3d"
    assert format_for(tmp_path / "a.H5").name == "hdf5"
    assert format_for(tmp_path / "a.dat", format="hdf5").name == "hdf5"


def test_unknown_extension_hdf5_by_signature_else_error(tmp_path, grid):
    p = tmp_path / "grid.dat"
    tq.write(p, grid, format="hdf5")
    assert tq.read(p) == grid
    q = tmp_path / "other.dat"
    q.write_bytes(b"not a grid")
    with pytest.raises(tq.GridFormatError, match="other.dat: unknown file extension"):
        tq.read(q)
    with pytest.raises(tq.GridFormatError, match="unknown format 'tecplot'"):
        tq.read(p, format="tecplot")


def test_write_with_unknown_extension_or_format_is_an_error_and_writes_nothing(tmp_path, grid):
    with pytest.raises(tq.GridFormatError, match=r"grid\.dat: unknown file extension; give format="):
        tq.write(tmp_path / "grid.dat", grid)
    with pytest.raises(tq.GridFormatError, match=r"unknown format 'vtk': expected one of cgns, hdf5, plot3d"):
        tq.write(tmp_path / "grid.x", grid, format="vtk")
    assert os.listdir(tmp_path) == []
    tq.write(tmp_path / "grid.dat", grid, format="plot3d")
    assert tq.read(tmp_path / "grid.dat", format="plot3d") == grid


def test_read_of_a_folder_or_missing_file(tmp_path):
    with pytest.raises(IsADirectoryError, match="Is a directory"):
        tq.read(tmp_path)
    with pytest.raises(FileNotFoundError, match="No such file"):
        tq.read(tmp_path / "none.x")


def test_importing_one_format_module_does_not_hide_the_other(tmp_path, grid):
    code = ("import tfi_quat.io.hdf5, tfi_quat as tq, numpy as np;"
            "g = tq.Grid([np.zeros((2, 2, 2, 3))]);"
            f"tq.write({str(tmp_path / 'a.x')!r}, g); print(tq.read({str(tmp_path / 'a.x')!r}).dims)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "(2, 2, 2)" in out.stdout


@pytest.mark.parametrize("mode", ["wb", "path"])
def test_atomic_output_replaces_only_on_success(tmp_path, mode):
    target = tmp_path / "t.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with _atomic.atomic_output(target, mode) as fh:
            if mode == "path":
                with open(fh, "wb") as f:
                    f.write(b"half")
            else:
                fh.write(b"half")
            raise RuntimeError("writer failed")
    assert target.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["t.bin"]
    with _atomic.atomic_output(target, mode) as fh:
        if mode == "path":
            with open(fh, "wb") as f:
                f.write(b"new")
        else:
            fh.write(b"new")
    assert target.read_bytes() == b"new"
    assert os.listdir(tmp_path) == ["t.bin"]


def test_python_dash_m_runs_the_cli(tmp_path, grid):
    p = tmp_path / "g.x"
    tq.write(p, grid)
    out = subprocess.run([sys.executable, "-m", "tfi_quat.cli", "info", str(p)], capture_output=True,
                         text=True)
    assert out.returncode == 0 and "4 x 3 x 2" in out.stdout
    bad = subprocess.run([sys.executable, "-m", "tfi_quat.cli", "info", str(tmp_path / "none.x")],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1
    assert np.all(np.isfinite(grid[0].xyz))
