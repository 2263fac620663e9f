"""The command line on bad input: one line on stderr, a documented exit status, never a traceback.

Inputs: ``tests/data/robustness/`` (described in ``tests/test_robust_files.py``)
and the shipped grids.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import tfi_quat as tq
import tfi_quat.quality
from tfi_quat.cli import EXIT_CHECK, EXIT_INPUT, EXIT_INTERNAL, EXIT_TERMINATED, main

DATA = Path(__file__).resolve().parent / "data" / "robustness"
GRIDS = Path(__file__).resolve().parents[1] / "grids"
ROOT = Path(__file__).resolve().parents[1]
TWO = "two_block_65x33.x"
FIXED_TWO = ["--fixed", "1:imin", "--fixed", "1:imax", "--fixed", "2:imin", "--fixed", "2:jmin",
             "--fixed", "2:jmax"]


def run_cli(capsys, *argv):
    """``tfi-quat argv`` in-process: (exit status, stdout, stderr); usage errors included."""
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:       # argparse's usage errors
        rc = exc.code
    out, err = capsys.readouterr()
    return rc, out, err


def one_line(rc, out, err, status=EXIT_INPUT, *fragments):
    assert rc == status, (rc, err)
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for f in fragments:
        assert str(f) in lines[0], (f, lines[0])
    return lines[0]


@pytest.fixture
def work(tmp_path, monkeypatch):
    """A scratch folder (the current directory) with the two-block grid and the C-grid case."""
    for f in (TWO, "naca0012_c_257x65.x", "naca0012_c_257x65.toml"):
        shutil.copy(GRIDS / f, tmp_path / f)
    for f in DATA.iterdir():
        shutil.copy(f, tmp_path / f.name)
    monkeypatch.chdir(tmp_path)
    return tmp_path


# ------------------------------------------------------------ 08_cli_tracebacks.sh, 02_nmf_huge_alloc.sh
@pytest.mark.parametrize("opt,name,fragment", [
    ("--connectivity", "bad_utf8.json", "bad_utf8.json:1: not UTF-8 text (byte 0xff at offset 138)"),
    ("--connectivity", "inf.json", "inf.json:1: patch 1: 'block' must be an integer, got inf"),
    ("--connectivity", "huge.json", "huge.json: connectivity is for a 3-D grid, the grid is 2-D"),
    ("--nmf", "huge_25000.nmf", "huge_25000.nmf: connectivity is for a 3-D grid"),
    ("--nmf", "huge_60000.nmf", "huge_60000.nmf: connectivity is for a 3-D grid"),
    ("--nmf", "k.nmf", "k.nmf:6: block 1: sizes must be from 1 to 2147483647"),
])
def test_hostile_maps_are_one_line(capsys, work, opt, name, fragment):
    rc, out, err = run_cli(capsys, "deform", TWO, opt, name, "--rotate", "1", "-o", "o5.x")
    one_line(rc, out, err, EXIT_INPUT, "tfi-quat deform: error:", fragment)
    assert not (work / "o5.x").exists()


# ------------------------------------------------------------ OS errors (item 10)
@pytest.mark.parametrize("argv", [
    ["info", "{p}"], ["convert", "{p}", "out.h5"], ["connect", "{p}"], ["quality", "{p}"],
    ["plot", "{p}", "-o", "a.png"], ["deform", TWO, "--wall", "1:jmin", "--rotate", "1", "--nmf", "{p}", "-o", "o.x"],
    ["deform", TWO, "--wall", "1:jmin", "--rotate", "1", "--connectivity", "{p}", "-o", "o.x"],
    ["deform", "--case", "{p}", "-o", "o.x"], ["quality", "--case", "{p}"],
])
@pytest.mark.parametrize("what", ["missing", "directory"])
def test_missing_file_and_directory_are_one_line_naming_the_path(capsys, work, argv, what):
    path = "nope.x" if what == "missing" else "folder"
    (work / "folder").mkdir()
    rc, out, err = run_cli(capsys, *[a.format(p=path) for a in argv])
    line = one_line(rc, out, err, EXIT_INPUT, f"tfi-quat {argv[0]}: error:", path)
    if argv[0] in ("deform",) or "--case" in argv:       # readers of this module: the standard reason
        assert line.endswith(f"{path}: " + ("No such file or directory" if what == "missing" else "Is a directory"))


def test_no_permission_is_one_line(capsys, work, monkeypatch):
    import tfi_quat.io._atomic as atomic

    def deny(path, *args, **kw):
        raise PermissionError(13, "Permission denied", str(path))
    monkeypatch.setattr(atomic, "open", deny, raising=False)
    rc, out, err = run_cli(capsys, "deform", "--case", "naca0012_c_257x65.toml", "-o", "o.x")
    one_line(rc, out, err, EXIT_INPUT, "naca0012_c_257x65.toml: Permission denied")


# ------------------------------------------------------------ cli_checks.sh: case files
CASE_HEAD = ('grid = "two_block_65x33.x"\nwalls = ["1:jmin"]\n'
             'fixed = ["1:imin", "1:imax", "2:imin", "2:jmin", "2:jmax"]\n')


@pytest.mark.parametrize("body,fragment", [
    ("[motion]\nbend = nan\n", "motion.bend: expected a finite number"),
    ("[motion]\ndeformation = 'bend'\namplitude = nan\n", "motion.amplitude"),
    ('[motion]\nrotate = "ten"\n', "motion.rotate: expected a number"),
    ("[motion]\naxis = [0, 0, 0]\n", "motion.axis: must not be the zero vector"),
    ("[motion]\nspan = 0\n", "motion.span: must be > 0"),
    ("[motion]\nspan = 5e-324\nbend = 0.1\n", "motion.span: 5e-324 is too small"),
    ('[motion]\naxis = "001"\n', "motion.axis: expected 3 numbers"),
    ("[motion]\nspin = 3\n", "unknown key 'motion.spin'"),
    ("walls2 = []\n", "unknown key 'walls2'"),
    ("[motion\n", "TOML syntax error"),
])
def test_bad_case_files_are_one_line_naming_the_key(capsys, work, body, fragment):
    (work / "c.toml").write_text(CASE_HEAD + body)
    rc, out, err = run_cli(capsys, "deform", "--case", "c.toml", "-o", "o.x")
    one_line(rc, out, err, EXIT_INPUT, "c.toml", fragment)


@pytest.mark.parametrize("text,fragment", [
    ('walls = ["1:jmin"]\n', "key 'grid' is missing"),
    ("grid = 5\n", "key 'grid': expected a file name"),
    ('grid = "two_block_65x33.x"\nwalls = "1:jmin"\n', "key 'walls': expected a list"),
    ('grid = "."\n', "key 'grid': grid file "),
])
def test_case_file_grid_and_walls_keys(capsys, work, text, fragment):
    (work / "c.toml").write_text(text)
    rc, out, err = run_cli(capsys, "deform", "--case", "c.toml", "-o", "o.x")
    one_line(rc, out, err, EXIT_INPUT, fragment)


def test_the_overflowing_axis_moves_the_walls_as_about_z(capsys, work):
    """05_motion_axis_overflow.sh: the rotation was dropped and the input written back."""
    (work / "ax.toml").write_text(CASE_HEAD + "[motion]\nrotate = 5\naxis = [0, 0, 1e200]\n")
    (work / "z.toml").write_text(CASE_HEAD + "[motion]\nrotate = 5\naxis = [0, 0, 1]\n")
    # (5 deg about the origin folds a few cells of this grid: the comparison is of the motion)
    rc, out, err = run_cli(capsys, "deform", "--case", "ax.toml", "-o", "ax.x", "--allow-negative")
    assert rc == 0 and err == "", err
    rc, out, err = run_cli(capsys, "deform", "--case", "z.toml", "-o", "z.x", "--allow-negative")
    assert rc == 0, err
    moved, ref, before = tq.read("ax.x"), tq.read("z.x"), tq.read(TWO)
    assert moved == ref and moved != before


@pytest.mark.parametrize("argv,fragment", [
    (["--rotate", "nan"], "argument --rotate: expected a finite number"),
    (["--rotate", "1", "--axis", "0,0,inf"], "argument --axis: expected 3 finite numbers"),
    (["--rotate", "1", "--axis", "0,0,0"], "--axis: must not be the zero vector"),
    (["--translate", "1e999,0,0"], "argument --translate"),
])
def test_bad_motion_options(capsys, work, argv, fragment):
    rc, out, err = run_cli(capsys, "deform", TWO, "--wall", "1:jmin", *FIXED_TWO, *argv, "-o", "o.x")
    assert rc == EXIT_INPUT and fragment in err and "Traceback" not in err


def test_a_huge_but_finite_axis_option_means_its_direction(capsys, work):
    rc, out, err = run_cli(capsys, "deform", TWO, "--wall", "1:jmin", *FIXED_TWO, "--rotate", "3",
                           "--axis", "0,0,1e300", "-o", "huge_axis.x", "--allow-negative")
    assert rc == 0, err
    rc, out, err = run_cli(capsys, "deform", TWO, "--wall", "1:jmin", *FIXED_TWO, "--rotate", "3", "-o", "unit_axis.x", "--allow-negative")
    assert rc == 0, err
    assert tq.read("huge_axis.x") == tq.read("unit_axis.x")


# ------------------------------------------------------------ folded grids (item 12)
def test_a_folded_grid_is_not_written_without_allow_negative(capsys, work):
    argv = ["deform", "--case", "naca0012_c_257x65.toml", "--translate", "0,30,0", "--rotate", "0"]
    rc, out, err = run_cli(capsys, *argv, "-o", "fold.x")
    line = one_line(rc, "", err, EXIT_CHECK, "tfi-quat deform: ", " negative cells (first: block 1 cell (",
                    "fold.x not written (--allow-negative writes it)")
    count = int(line.split("tfi-quat deform: ")[1].split()[0])
    assert count > 1000 and not (work / "fold.x").exists()
    assert "walls rotated 0 deg" in out            # what was attempted is still reported
    rc, out, err = run_cli(capsys, *argv, "-o", "fold.x", "--allow-negative")
    assert rc == 0 and err == ""
    last = out.strip().splitlines()[-1]
    assert last.startswith(f"wrote fold.x: {count} negative cells (first: block 1 cell (")
    grid, ref = tq.read("fold.x"), tq.read("naca0012_c_257x65.x")
    bad = tq.quality.negative_cells(grid, ref)
    assert sum(len(c) for _, c in bad) == count
    b, ijk = bad[0]
    assert f"block {b + 1} cell ({ijk[0][0] + 1}, {ijk[0][1] + 1}, {ijk[0][2] + 1})" in last


# ------------------------------------------------------------ plot --cut on 2-D (item 13)
@pytest.mark.parametrize("argv", [["deform", TWO, "--wall", "1:jmin", "--rotate", "1", "-o", "."],
                                  ["plot", TWO, "-o", "."], ["convert", TWO, "."]])
def test_an_output_that_is_a_directory_says_so(capsys, work, argv):
    rc, out, err = run_cli(capsys, *argv)
    one_line(rc, out, err, EXIT_INPUT, ".: is a directory")
    rc, out, err = run_cli(capsys, *argv, "--force")
    one_line(rc, out, err, EXIT_INPUT, ".: is a directory")


def test_plot_cut_on_a_2d_grid_is_an_error(capsys, work):
    rc, out, err = run_cli(capsys, "plot", TWO, "--cut", "5:k=3", "-o", "a.png")
    one_line(rc, out, err, EXIT_INPUT, "--cut 5:k=3", "2-D")
    assert not (work / "a.png").exists()


# ------------------------------------------------------------ last-resort handlers
def test_memory_error_and_internal_errors_are_one_line(capsys, work, monkeypatch):
    from tfi_quat.cli import _info

    def out_of_memory(args):
        raise MemoryError("Unable to allocate 26.8 GiB")
    monkeypatch.setattr(_info, "run", out_of_memory)
    rc, out, err = run_cli(capsys, "info", TWO)
    one_line(rc, out, err, EXIT_INPUT, "tfi-quat info: error: out of memory (Unable to allocate 26.8 GiB)")

    def bug(args):
        return 1 / 0
    monkeypatch.setattr(_info, "run", bug)
    rc, out, err = run_cli(capsys, "info", TWO)
    one_line(rc, out, err, EXIT_INTERNAL, "internal error: ZeroDivisionError", "--debug")
    with pytest.raises(ZeroDivisionError):
        main(["--debug", "info", TWO])


# ------------------------------------------------------------ SIGTERM (item 11)
def test_sigterm_in_process_removes_the_temporary_file(capsys, work, monkeypatch):
    """The write is interrupted half-way by a real SIGTERM to this process."""
    from tfi_quat.cli import _convert
    from tfi_quat.io._atomic import atomic_output

    def write(path, grid, **kw):
        with atomic_output(path, "wb") as fh:
            fh.write(b"half a grid")
            os.kill(os.getpid(), signal.SIGTERM)
            fh.write(b"never")          # pragma: no cover - the signal handler raised
    monkeypatch.setattr(_convert, "write", write)
    before = signal.getsignal(signal.SIGTERM)
    rc, out, err = run_cli(capsys, "convert", TWO, "sigterm_out.x")
    assert rc == EXIT_TERMINATED and err.strip() == "tfi-quat: terminated"
    assert sorted(p.name for p in work.iterdir() if p.name.startswith(".")) == []
    assert not (work / "sigterm_out.x").exists()
    assert signal.getsignal(signal.SIGTERM) is before      # main restored the handler


def test_sigterm_during_a_real_convert_leaves_no_temporary_file(tmp_path):
    """09_sigterm_tmp.sh: a subprocess converting a 24 MB grid to ASCII is sent SIGTERM mid-write."""
    n = 100
    src = tmp_path / "med.x"
    with open(src, "wb") as f:
        f.write(np.array([1, n, n, n], "<i4").tobytes())
        f.write(np.random.default_rng(0).random(3 * n ** 3).tobytes())
    target = tmp_path / "t2.x"
    target.write_bytes(b"the old target")
    proc = subprocess.Popen([sys.executable, "-m", "tfi_quat.cli", "convert", str(src), str(target),
                             "--ascii", "--force"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 300
    tmp = []
    while not tmp and proc.poll() is None and time.monotonic() < deadline:
        tmp = list(tmp_path.glob(".t2.x.*.tmp"))
        time.sleep(0.02)
    assert tmp, "the conversion ended before its temporary file was seen"
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == EXIT_TERMINATED, err
    assert err.decode().strip().splitlines()[-1] == "tfi-quat: terminated"
    assert list(tmp_path.glob(".t2.x.*")) == []
    assert target.read_bytes() == b"the old target"
