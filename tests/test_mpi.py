"""Collective writes under MPI (tfi_quat.io.mpi): one file from the blocks of every rank.

Each job runs ``mpiexec -n N python tests/_mpi_job.py SPEC`` (the MPICH of the
``mpi`` extra; 3 ranks on 2 cores is oversubscribed, which MPICH allows) with
a timeout, and the files it writes are compared byte for byte with a serial
``tfi_quat.write`` of the whole grid.  HDF5 files carry their creation time:
both writes take it from ``SOURCE_DATE_EPOCH``.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from _mpi_job import make_grid
from _mpi_run import EPOCH, ROOT, launch, mpiexec

import tfi_quat as tq
from tfi_quat.errors import ParallelError

JOB = Path(__file__).with_name("_mpi_job.py")
TIMEOUT = 240           # seconds for one job: a hang fails the test instead of the suite

VARIANTS = {
    "bin64.x": {},
    "bin32be.x": {"precision": 4, "endian": ">"},
    "fort64.x": {"encoding": "fortran"},
    "fortcoord.x": {"encoding": "fortran", "records": "coordinate", "int_size": 8, "marker_size": 8},
    "fort32ib.x": {"encoding": "fortran", "precision": 4, "iblank": True},
    "grid.h5": {},
    "gzip.h5": {"compression": "gzip", "compression_level": 3},
}


def run_job(tmp_path, nranks: int, spec: dict) -> dict[int, list[str]]:
    """Run one job; for each write, the outcome on each rank ("OK" or "ERROR Type: message")."""
    spec_path = tmp_path / "spec.json"
    spec_path.write_text(json.dumps(spec), encoding="utf-8")
    reports = launch(JOB, spec_path, nranks, tmp_path, TIMEOUT)
    return {i: [rep[i] for rep in reports] for i in range(len(spec["writes"]))}


def serial(path, kind: str, options: dict, monkeypatch) -> bytes:
    monkeypatch.setenv("SOURCE_DATE_EPOCH", EPOCH)
    tq.write(path, make_grid(kind), **options)
    return Path(path).read_bytes()


@pytest.mark.parametrize("partition", ["default", "given"])
@pytest.mark.parametrize("nranks", [1, 2, 3])
def test_collective_write_equals_serial(tmp_path, monkeypatch, nranks, partition):
    out = tmp_path / "mpi"
    out.mkdir()
    writes = [{"path": str(out / name), "options": opts} for name, opts in VARIANTS.items()]
    result = run_job(tmp_path, nranks, {"grid": "3d", "partition": partition, "writes": writes})
    assert all(lines == ["OK"] * nranks for lines in result.values()), result
    for name, opts in VARIANTS.items():
        ref = serial(tmp_path / f"serial_{name}", "3d", opts, monkeypatch)
        assert (out / name).read_bytes() == ref, name
    assert sorted(p.name for p in out.iterdir()) == sorted(VARIANTS)    # no temporary file left


def test_collective_write_2d_and_idle_rank(tmp_path, monkeypatch):
    """A 2-D grid as 2-D Plot3D (ranks disagreeing on ndim or on the variant: refused on
    every rank); then 3 ranks for 2 blocks: rank 2 holds none (grid None);
    a single-block file (no block count) from 2 ranks."""
    writes = [{"path": str(tmp_path / "g2.x"), "options": {"encoding": "fortran"}},
              {"path": str(tmp_path / "g2.h5")},
              {"path": str(tmp_path / "bad.h5"), "fail": "ndim3_on_rank1"},
              {"path": str(tmp_path / "bad.x"), "fail": "float32_variant_on_rank1"}]
    result = run_job(tmp_path, 3, {"grid": "2d", "partition": "given", "writes": writes})
    assert result[0] == result[1] == ["OK"] * 3, result
    assert len(set(result[2])) == 1 and re.match(
        r"ERROR ParallelError: .*bad\.h5: the ranks' grids disagree on ndim \(rank 0: 2-D, rank 1: 3-D, "
        r"rank 2: 2-D\)", result[2][0]), result[2]
    assert len(set(result[3])) == 1 and re.match(
        r"ERROR ParallelError: .*bad\.x: the ranks would write different variants "
        r"\(rank 0: C binary.*float64.*; rank 1: C binary.*float32", result[3][0]), result[3]
    assert not (tmp_path / "bad.h5").exists() and not (tmp_path / "bad.x").exists()
    assert Path(writes[0]["path"]).read_bytes() == serial(tmp_path / "s.x", "2d", {"encoding": "fortran"},
                                                          monkeypatch)
    assert Path(writes[1]["path"]).read_bytes() == serial(tmp_path / "s.h5", "2d", {}, monkeypatch)

    (tmp_path / "pair").mkdir()
    writes = [{"path": str(tmp_path / "pair" / "p.x")}, {"path": str(tmp_path / "pair" / "p.h5")}]
    result = run_job(tmp_path, 3, {"grid": "pair", "partition": "default", "writes": writes})
    assert all(lines == ["OK"] * 3 for lines in result.values()), result
    assert Path(writes[0]["path"]).read_bytes() == serial(tmp_path / "p.x", "pair", {}, monkeypatch)
    assert Path(writes[1]["path"]).read_bytes() == serial(tmp_path / "p.h5", "pair", {}, monkeypatch)

    (tmp_path / "one").mkdir()
    single = {"multiblock": False, "encoding": "fortran", "endian": ">"}
    writes = [{"path": str(tmp_path / "one" / "o.x"), "options": single}]
    result = run_job(tmp_path, 2, {"grid": "one", "partition": "default", "writes": writes})
    assert result[0] == ["OK"] * 2, result
    assert Path(writes[0]["path"]).read_bytes() == serial(tmp_path / "o.x", "one", single, monkeypatch)


def test_error_on_one_rank_reaches_every_rank(tmp_path, monkeypatch):
    """Each failing write ends on every rank with the same message and leaves no file;
    the ranks stay in step: the write after each failure succeeds."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "folder.h5").mkdir()
    writes = [
        # rank 1's block overflows float32 while every rank is writing its blocks
        {"path": str(out / "f32.x"), "options": {"precision": 4}, "fail": "float32_on_rank1"},
        {"path": str(out / "ok1.x")},
        # rank 1 passes no Grid: refused before any file is made
        {"path": str(out / "bad.h5"), "fail": "not_a_grid_on_rank1"},
        # ranks 0 and 1 both claim block 0
        {"path": str(out / "dup.x"), "fail": "duplicate_block0"},
        # rank 0 cannot create the target (a folder): HDF5 path
        {"path": str(out / "folder.h5")},
        # a 3-D grid as 2-D Plot3D: the first rank whose blocks are 3-D says so
        {"path": str(out / "flat.x"), "options": {"ndim": 2}},
        {"path": str(out / "ok2.h5")},
    ]
    result = run_job(tmp_path, 3, {"grid": "3d", "partition": "given", "writes": writes})
    expect = {
        0: r"ERROR GridFormatError: .*f32\.x: block \d of 5: coordinate 1e\+300 is beyond the float32 range",
        2: r"ERROR GridValueError: write needs a Grid \(or None on a rank without blocks\), got dict",
        3: r"ERROR GridValueError: .*dup\.x: block 0 \(0-based\) is given by rank 0 and rank 1",
        4: r"ERROR OverwriteError: .*folder\.h5: is a directory",
        5: r"ERROR GridFormatError: .*flat\.x: block \d is 3-D",
    }
    for i, pattern in expect.items():
        lines = result[i]
        assert len(set(lines)) == 1, f"write {i}: the ranks disagree: {lines}"
        assert re.match(pattern, lines[0]), (i, lines[0])
    assert result[1] == ["OK"] * 3 and result[6] == ["OK"] * 3
    assert (out / "ok1.x").read_bytes() == serial(tmp_path / "s.x", "3d", {}, monkeypatch)
    assert (out / "ok2.h5").read_bytes() == serial(tmp_path / "s.h5", "3d", {}, monkeypatch)
    assert sorted(p.name for p in out.iterdir()) == ["folder.h5", "ok1.x", "ok2.h5"]


def test_memory_is_the_ranks_own_blocks(tmp_path, monkeypatch):
    """Plot3D: a rank allocates next to nothing while writing (its blocks go to the file
    as they are); HDF5: rank 0 holds one other rank's block at a time, the others nothing."""
    block = 40 ** 3 * 3 * 8
    writes = [{"path": str(tmp_path / "big.x")}, {"path": str(tmp_path / "big.h5")}]
    result = run_job(tmp_path, 3, {"grid": "big", "partition": "given", "trace": True, "writes": writes})
    peaks = {i: [int(line.split()[1]) for line in lines] for i, lines in result.items()}
    assert all(p < block // 4 for p in peaks[0]), peaks            # Plot3D, every rank
    assert block <= peaks[1][0] < 1.5 * block, peaks                # HDF5 rank 0: one block
    assert all(p < block // 4 for p in peaks[1][1:]), peaks        # HDF5 other ranks
    assert Path(writes[0]["path"]).read_bytes() == serial(tmp_path / "s.x", "big", {}, monkeypatch)
    assert Path(writes[1]["path"]).read_bytes() == serial(tmp_path / "s.h5", "big", {}, monkeypatch)


def test_ascii_refused_on_every_rank(tmp_path):
    writes = [{"path": str(tmp_path / "a.fmt"), "options": {"encoding": "ascii"}}]
    result = run_job(tmp_path, 2, {"grid": "3d", "partition": "default", "writes": writes})
    assert len(set(result[0])) == 1
    assert "ERROR GridFormatError" in result[0][0] and "no fixed block offsets" in result[0][0]
    assert not (tmp_path / "a.fmt").exists()


def test_comm_without_mpi4py_names_the_extra(tmp_path, monkeypatch):
    grid = make_grid("3d")
    monkeypatch.setitem(sys.modules, "mpi4py", None)       # import mpi4py raises ImportError
    monkeypatch.setitem(sys.modules, "mpi4py.MPI", None)
    with pytest.raises(ParallelError, match=re.escape('pip install "tfi_quat[mpi]"')):
        tq.write(tmp_path / "g.x", grid, comm=object())
    assert not list(tmp_path.iterdir())


def test_blocks_without_comm(tmp_path):
    with pytest.raises(ParallelError, match="give comm= too"):
        tq.write(tmp_path / "g.x", make_grid("3d"), blocks=[0, 1, 2, 3, 4])


def test_serial_use_does_not_import_mpi4py(tmp_path):
    """The package imports and writes without touching mpi4py; comm= must be a communicator."""
    code = ("import sys, tfi_quat as tq\n"
            "from _mpi_job import make_grid\n"
            f"tq.write({str(tmp_path / 'g.x')!r}, make_grid('3d'))\n"
            f"tq.write({str(tmp_path / 'g.h5')!r}, make_grid('3d'))\n"
            "assert 'mpi4py' not in sys.modules, 'mpi4py imported by a serial write'\n"
            "try:\n"
            f"    tq.write({str(tmp_path / 'h.x')!r}, make_grid('3d'), comm='world')\n"
            "except tq.ParallelError as exc:\n"
            "    print(exc)\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(JOB.parent)]))
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         timeout=TIMEOUT)
    assert run.returncode == 0, run.stderr
    assert "comm= must be an mpi4py intracommunicator" in run.stdout and "got str" in run.stdout


def test_mpi4py_runs_under_mpiexec(tmp_path):
    """The extra's launcher and library: two ranks see a world of two."""
    code = ("from mpi4py import MPI; c = MPI.COMM_WORLD; s = c.allreduce(c.rank + 1)\n"
            "if c.rank == 0: print(s, c.size)")      # one rank prints: the ranks' lines interleave
    run = subprocess.run([mpiexec(), "-n", "2", sys.executable, "-c", code], capture_output=True,
                         text=True, timeout=TIMEOUT, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["3", "2"]
