"""``tfi-quat deform``, run in-process through ``main``."""

from __future__ import annotations

import io
import shutil
from pathlib import Path

import numpy as np
import pytest

import tfi_quat as tq
from tfi_quat.case import load_case
from tfi_quat.cli import _deform, main
from tfi_quat.deform import METHODS, Deformer, rigid_motion

GRIDS = Path(__file__).resolve().parents[1] / "grids"


def run_cli(capsys, *argv):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture
def cgrid(tmp_path):
    """The shipped C-grid and its case file, copied into a scratch folder."""
    for f in ("naca0012_c_257x65.x", "naca0012_c_257x65.toml"):
        shutil.copy(GRIDS / f, tmp_path / f)
    return tmp_path / "naca0012_c_257x65.x", tmp_path / "naca0012_c_257x65.toml"


def _api(grid_path, case_path, move, **kw):
    case = load_case(case_path)
    grid = tq.read(grid_path)
    return Deformer(grid, walls=case.walls, symmetry=case.symmetry, fixed=case.fixed, **kw).deform(move)


def test_case_file_motion_end_to_end(capsys, cgrid):
    grid_path, case_path = cgrid
    out = grid_path.parent / "moved.x"
    rc, so, se = run_cli(capsys, "deform", "--case", case_path, "-o", out)
    assert rc == 0, se
    lines = so.strip().splitlines()
    assert "case file's motion" in lines[0] and lines[0].endswith("; method two-level")
    assert lines[1].startswith("set-up") and "M points/s" in lines[1]
    assert lines[-1].startswith(f"wrote {out}: 0 negative cells, smallest volume ratio")
    got = tq.read(out)
    assert got.source_format == tq.read(grid_path).source_format          # the input's variant
    ref = _api(grid_path, case_path, load_case(case_path).motion.apply)
    assert [b.xyz.tobytes() for b in got] == [b.xyz.tobytes() for b in ref]


@pytest.mark.parametrize("extra,kw", [
    ([], {}),
    (["--method", "tfi"], {"method": "tfi"}),
    (["--method", "samareh"], {"method": "samareh"}),
    (["--method", "two-level"], {}),
    (["--rotation-length", "0.05"], {"rotation_length": 0.05}),
])
def test_rigid_motion_options(capsys, cgrid, extra, kw):
    grid_path, case_path = cgrid
    out = grid_path.parent / "r.x"
    rc, so, se = run_cli(capsys, "deform", grid_path, "--case", case_path, "--rotate", "-15",
                         "--about", "0.25,0,0", "--translate", "0,0.05,0", "-o", out, *extra)
    assert rc == 0, se
    assert "rotated -15 deg about axis (0.0, 0.0, 1.0) through (0.25, 0.0, 0.0)" in so
    ref = _api(grid_path, case_path, rigid_motion(-15.0, (0, 0, 1), (0.25, 0, 0), (0, 0.05, 0)), **kw)
    assert [b.xyz.tobytes() for b in tq.read(out)] == [b.xyz.tobytes() for b in ref]


def test_patches_on_the_command_line_and_a_moved_grid(capsys, cgrid):
    grid_path, case_path = cgrid
    grid = tq.read(grid_path)
    move = rigid_motion(7.0, (0, 0, 1), (0.3, 0.0, 0.0))
    moved = tq.Grid([tq.Block(move(b.xyz.reshape(-1, 3, order="F")).reshape(b.xyz.shape, order="F"))
                     for b in grid], ndim=2)
    mpath = grid_path.parent / "walls.x"
    tq.write(mpath, moved, like=grid)
    out = grid_path.parent / "m.x"
    rc, so, se = run_cli(capsys, "deform", grid_path, "--wall", "1:jmin:65-193", "--fixed", "1:jmax",
                         "--fixed", "1:imin", "--fixed", "1:imax", "--moved", mpath, "-o", out)
    assert rc == 0, se
    assert f"walls from {mpath}" in so
    ref = _api(grid_path, case_path, move)
    np.testing.assert_allclose(tq.read(out)[0].xyz, ref[0].xyz, rtol=0, atol=1e-12)


def test_existing_output_and_the_input_are_not_overwritten(capsys, cgrid):
    grid_path, case_path = cgrid
    out = grid_path.parent / "o.x"
    out.write_bytes(b"keep me")
    rc, so, se = run_cli(capsys, "deform", "--case", case_path, "-o", out)
    assert rc == 2 and so == "" and "exists" in se and out.read_bytes() == b"keep me"
    rc, so, se = run_cli(capsys, "deform", "--case", case_path, "-o", out, "--force")
    assert rc == 0 and out.read_bytes() != b"keep me"
    before = grid_path.read_bytes()
    rc, so, se = run_cli(capsys, "deform", "--case", case_path, "-o", grid_path)
    assert rc == 2 and "input" in se and grid_path.read_bytes() == before   # --force would allow it


@pytest.mark.parametrize("argv,fragment", [
    (["--rotate", "5", "--moved", "X.x"], "not both"),
    (["--method", "tfi", "--rotation-length", "0.1"], "--rotation-length"),
    (["--method", "samareh", "--rotation-length", "0.1"], "--rotation-length"),
    (["--method", "samareh", "--formulation", "two-level"], "disagree"),
    (["--rotation-length", "-2"], "rotation_length"),
])
def test_bad_options_are_one_line_errors(capsys, cgrid, argv, fragment):
    grid_path, case_path = cgrid
    rc, so, se = run_cli(capsys, "deform", "--case", case_path, "-o", grid_path.parent / "z.x", *argv)
    assert rc == 2 and so == ""
    assert len(se.strip().splitlines()) == 1 and fragment in se, se


def test_no_motion_and_no_grid(capsys, cgrid, tmp_path):
    grid_path, _ = cgrid
    rc, so, se = run_cli(capsys, "deform", grid_path, "--wall", "1:jmin", "-o", tmp_path / "a.x")
    assert rc == 2 and "no wall motion" in se
    rc, so, se = run_cli(capsys, "deform", "--rotate", "3", "-o", tmp_path / "a.x")
    assert rc == 2 and "no grid" in se


def test_progress_bar_draws_on_a_terminal(monkeypatch):
    buf = io.StringIO()
    buf.isatty = lambda: True
    monkeypatch.setattr("sys.stderr", buf)
    bar = _deform._Progress(True)
    for k in range(1, 9):
        bar(k, 8)
    text = buf.getvalue()
    assert text.count("\r") == 8 and text.endswith("8/8\n") and "#" * 30 in text
    quiet = io.StringIO()
    monkeypatch.setattr("sys.stderr", quiet)
    _deform._Progress(True)(1, 8)                       # not a terminal: nothing
    assert quiet.getvalue() == ""


def test_method_names_match_the_library():
    assert _deform.METHODS == METHODS


@pytest.mark.parametrize("old,new", [
    (["--method", "quaternion"], "two-level"),
    (["--method", "quaternion", "--formulation", "samareh"], "samareh"),
    (["--formulation", "samareh"], "samareh"),
    (["--formulation", "two-level"], "two-level"),
    (["--method", "tfi", "--formulation", "samareh"], "tfi"),
])
def test_old_method_spellings_are_accepted_with_a_note(capsys, cgrid, old, new):
    grid_path, case_path = cgrid
    out = grid_path.parent / "old.x"
    rc, so, se = run_cli(capsys, "deform", "--case", case_path, "-o", out, *old)
    assert rc == 0, se
    assert "deprecated" in se and f"use --method {new}" in se and len(se.strip().splitlines()) == 1
    assert so.splitlines()[0].endswith(f"; method {new}")
    ref = _api(grid_path, case_path, load_case(case_path).motion.apply, method=new)
    assert [b.xyz.tobytes() for b in tq.read(out)] == [b.xyz.tobytes() for b in ref]


def test_connectivity_and_nmf_files(capsys, cgrid):
    """A map written by 'tfi-quat connect' gives the same grid as the search; it is checked
    against the grid it is used with."""
    grid_path, case_path = cgrid
    folder = grid_path.parent
    argv = ["--wall", "1:jmin:65-193", "--fixed", "1:jmax", "--fixed", "1:imin", "--fixed", "1:imax"]
    rc, so, se = run_cli(capsys, "deform", grid_path, *argv, "--rotate", "8", "-o", folder / "a.x")
    assert rc == 0, se
    for ext, opt in (("json", "--connectivity"), ("nmf", "--nmf")):
        m = folder / f"map.{ext}"
        rc, so, se = run_cli(capsys, "connect", grid_path, *argv, "-o", m)
        assert rc == 0, se
        rc, so, se = run_cli(capsys, "deform", grid_path, opt, m, "--rotate", "8", "-o", folder / f"b.{ext}.x")
        assert rc == 0, se
        assert tq.read(folder / f"b.{ext}.x") == tq.read(folder / "a.x")
    other = folder / "other.x"
    tq.write(other, tq.Grid([tq.Block(tq.read(grid_path)[0].xyz[::2].copy(order="F"))], ndim=2))
    rc, so, se = run_cli(capsys, "deform", other, "--connectivity", folder / "map.json", "--rotate", "8",
                         "-o", folder / "c.x")
    assert rc == 2 and len(se.strip().splitlines()) == 1, se
