"""Distributed deformation under MPI (tfi_quat.deform.distributed): the result files of
``mpiexec -n 1/2/3`` are byte-identical to a serial run's.

Each job runs ``mpiexec -n N python tests/_mpi_deform_job.py SPEC`` (the MPICH of the
``mpi`` extra; 3 ranks on 2 cores is oversubscribed, which MPICH allows) with a
timeout, several cases per job (each start of a job costs seconds).  The grids: the
501 k-point wing (4 blocks), the two-block 2-D grid, and a 3-D ring split into four
blocks (one reversed) so that its interfaces cross ranks.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from _mpi_deform_job import motion
from _mpi_run import EPOCH, ROOT, launch

import tfi_quat as tq
from tfi_quat import Block, Grid
from tfi_quat.case import load_case
from tfi_quat.deform import Deformer

JOB = Path(__file__).with_name("_mpi_deform_job.py")
GRIDS = ROOT / "grids"
TIMEOUT = 300           # seconds for one job: a hang fails the test instead of the suite


def run_job(tmp_path, nranks: int, cases: list) -> list[list[dict]]:
    """Run one job; per case, the result dict of each rank."""
    spec_path = tmp_path / f"spec{nranks}.json"
    spec_path.write_text(json.dumps({"cases": cases}), encoding="utf-8")
    reports = launch(JOB, spec_path, nranks, tmp_path, TIMEOUT)
    return [[rep[i] for rep in reports] for i in range(len(cases))]


def split_ring8() -> tuple[Grid, list, list, list]:
    """The ring of :func:`split_ring` cut in eight blocks, four around i times two in j, with
    symmetry planes at both k ends: the four points where four blocks meet, on the two
    planes, are free vertices (the inverse-distance blend, split by rows over the ranks)."""
    from _deform_grids import extrude, o_grid
    ring = extrude(o_grid(65, 17)[0], nk=5, dz=0.1)[0].xyz
    parts = [ring[a:a + 17, c:c + 9] for a in (0, 16, 32, 48) for c in (0, 8)]
    blocks = [Block(np.asfortranarray(p), name=f"ring8_{n}") for n, p in enumerate(parts)]
    return (Grid(blocks, ndim=3), [f"{b}:jmin" for b in range(1, 9, 2)],
            [f"{b}:{f}" for b in range(1, 9) for f in ("kmin", "kmax")],
            [f"{b}:jmax" for b in range(2, 9, 2)])


def split_ring() -> tuple[Grid, list, list, list]:
    """A 3-D O-grid ring (65 x 17 x 5) cut in four blocks around i, the third reversed in i:
    point-matched interfaces (one of them the ring's seam) between every pair of neighbours."""
    from _deform_grids import extrude, o_grid
    ring = extrude(o_grid(65, 17)[0], nk=5, dz=0.1)[0].xyz
    parts = [ring[0:17], ring[16:33], ring[32:49][::-1], ring[48:65]]
    blocks = [Block(np.asfortranarray(p), name=f"ring{n}") for n, p in enumerate(parts)]
    n = range(1, 5)
    return (Grid(blocks, ndim=3), [f"{b}:jmin" for b in n],
            [f"{b}:{f}" for b in n for f in ("kmin", "kmax")], [f"{b}:jmax" for b in n])


@pytest.fixture(scope="module")
def grids(tmp_path_factory):
    """The three grids as files with their cases, and the serial results written per output."""
    root = tmp_path_factory.mktemp("mpi_deform")
    wing = load_case(GRIDS / "wing_ch_501k.toml", check_grid=False)
    two = load_case(GRIDS / "two_block_65x33.toml", check_grid=False)
    ring, rw, rs, rf = split_ring()
    tq.write(root / "ring.h5", ring)
    ring8, r8w, r8s, r8f = split_ring8()
    tq.write(root / "ring8.x", ring8)
    spec = {
        "wing": dict(grid=str(GRIDS / "wing_ch_501k.x"), walls=[str(s) for s in wing.walls],
                     symmetry=[str(s) for s in wing.symmetry], fixed=[str(s) for s in wing.fixed]),
        "two": dict(grid=str(GRIDS / "two_block_65x33.x"), walls=[str(s) for s in two.walls],
                    fixed=[str(s) for s in two.fixed]),
        "ring": dict(grid=str(root / "ring.h5"), walls=rw, symmetry=rs, fixed=rf),
        "ring8": dict(grid=str(root / "ring8.x"), walls=r8w, symmetry=r8s, fixed=r8f),
        # the file's own boundary conditions (walls) and 1-to-1 interfaces, some faces fixed
        "cgns": dict(grid=str(ROOT / "tests" / "data" / "cgns" / "multiblock.cgns"), walls=[],
                     fixed=[f"{b}:{f}" for b in (1, 2, 3) for f in ("kmin", "kmax", "jmin", "jmax")]),
    }
    return root, spec


def serial_bytes(root, case: dict, name: str, monkeypatch) -> bytes:
    """The file a serial Deformer writes for ``case`` (cached per case)."""
    path = root / f"serial_{case['_key']}_{name}"
    if not path.exists():
        monkeypatch.setenv("SOURCE_DATE_EPOCH", EPOCH)
        grid = tq.read(case["grid"])
        d = Deformer(grid, walls=case["walls"], symmetry=case.get("symmetry", ()),
                     fixed=case.get("fixed", ()), method=case.get("method", "two-level"))
        same = Path(case["grid"]).suffix == Path(name).suffix
        tq.write(path, d.deform(motion(case["motion"])), like=grid if same else None)
    return path.read_bytes()


def case(spec, grid: str, mot: str, outputs=(), **kw) -> dict:
    c = dict(spec[grid], motion=mot, outputs=list(outputs), **kw)
    c["_key"] = f"{grid}_{mot}_{kw.get('method', 'two-level')}"
    return c


def check_outputs(root, tmp_path, cases, results, monkeypatch):
    for c, per_rank in zip(cases, results):
        for r in per_rank:
            assert r.get("ok"), f"{c['_key']}: {r}"
        assert len({r["quality"] for r in per_rank}) == 1        # the merged check, everywhere
        for out in c["outputs"]:
            ext = Path(out).suffix
            got = (tmp_path / out).read_bytes()
            assert got == serial_bytes(root, c, f"out{ext}", monkeypatch), f"{c['_key']} {out}"


def test_two_ranks_all_grids_errors_and_cli(grids, tmp_path, monkeypatch):
    """2 ranks: the wing (balanced partition, the array form in a shuffled order with global
    ids), the two-block grid (a given partition, reversed), the split ring (interfaces across
    the ranks; samareh and tfi too); then errors on one rank, and the CLI."""
    root, spec = grids
    cases = [
        case(spec, "two", "rigid", ["t.x"], blocks=[[1], [0]]),
        case(spec, "ring", "bend", ["r.h5"]),
        case(spec, "wing", "bend", ["w.x", "w.h5"], array=True, trace=True),
        case(spec, "ring", "rigid", ["rs.h5"], method="samareh"),
        case(spec, "ring", "rigid", ["rt.h5"], method="tfi", blocks=[[3, 0], [2, 1]], out=True),
        # errors: each must reach every rank, the same, and end the case without a hang
        case(spec, "ring", "rigid", fail="shape_on_rank1"),
        case(spec, "ring", "rigid", fail="differ_on_rank1"),
        case(spec, "wing", "fold", check="raise"),
        case(spec, "ring", "rigid", blocks=[[0, 1], [1, 2, 3]]),
        dict(cli=["deform", "--case", str(root / "wing.toml"), "-o", "cli.h5"], _key="cli"),
        # --moved: the wall faces of a moved grid (the serial bend of the wing)
        dict(cli=["deform", "--case", str(root / "wing.toml"), "--moved",
                  str(root / "serial_wing_bend_two-level_out.x"), "-o", "moved.x",
                  "--allow-negative"], _key="moved"),
        # errors in the CLI: reported once (rank 0), the same exit status everywhere
        dict(cli=["deform", "--case", str(root / "wing.toml"), "--rotate", "40", "-o", "neg.h5"],
             _key="negative"),
        dict(cli=["deform", str(GRIDS / "wing_ch_501k.x"), "--wall", "9:jmin", "-o", "bad.h5",
                  "--rotate", "1"], _key="bad"),
    ]
    serial_bytes(root, cases[2], "out.x", monkeypatch)      # the moved grid of the last case
    case_file = root / "wing.toml"
    text = (GRIDS / "wing_ch_501k.toml").read_text(encoding="utf-8")
    case_file.write_text(text.replace('"wing_ch_501k.x"', json.dumps(str(GRIDS / "wing_ch_501k.x"))),
                         encoding="utf-8")
    results = run_job(tmp_path, 2, cases)
    check_outputs(root, tmp_path, cases[:5], results[:5], monkeypatch)
    # one rank's bad input, motions that differ, a folded grid with check="raise", a block
    # owned twice: the same error on every rank
    for c, per_rank, kind, words in zip(cases[5:9], results[5:9],
                                        ["DeformationError", "ParallelError", "DeformationError",
                                         "GridValueError"],
                                        ["xs has 3 rows", "differs between rank 0 and rank 1", "invalid cells",
                                         "block 1 (0-based) is owned by rank 0 and rank 1"]):
        errors = {r.get("error") for r in per_rank}
        assert len(errors) == 1, per_rank
        err = errors.pop()
        assert err is not None and err.startswith(kind) and words in err, err
    # the CLI: the same file as a serial tfi-quat deform, the summary line printed once
    cli = results[9]
    assert [r["rc"] for r in cli] == [0, 0]
    assert cli[0]["stdout"].count("wrote cli.h5: 0 negative cells") == 1, cli[0]["stdout"]
    assert "2 MPI ranks" in cli[0]["stdout"]
    from tfi_quat.cli import main
    monkeypatch.setenv("SOURCE_DATE_EPOCH", EPOCH)
    monkeypatch.chdir(root)
    assert main(["deform", "--case", str(case_file), "-o", "serial_cli.h5"]) == 0
    assert (tmp_path / "cli.h5").read_bytes() == (root / "serial_cli.h5").read_bytes()
    assert [r["rc"] for r in results[10]] == [0, 0]
    assert "walls from" in results[10][0]["stdout"], results[10][0]["stdout"]
    assert main(["deform", "--case", str(case_file), "--moved",
                 str(root / "serial_wing_bend_two-level_out.x"), "-o", "serial_moved.x",
                 "--allow-negative"]) == 0
    assert (tmp_path / "moved.x").read_bytes() == (root / "serial_moved.x").read_bytes()
    for per_rank, status, words in ((results[11], 1, "negative cells"), (results[12], 2, "9:jmin")):
        assert [r["rc"] for r in per_rank] == [status, status], per_rank
        assert per_rank[0]["stderr"].count("tfi-quat deform") == 1 and words in per_rank[0]["stderr"]
        assert per_rank[1]["stderr"] == per_rank[1]["stdout"] == ""
    assert not (tmp_path / "neg.h5").exists() and not (tmp_path / "bad.h5").exists()
    # memory (measured after the other cases compiled every kernel): a rank holds its blocks
    # plus O(surface) arrays, not the whole grid.  Fitted over the two ranks' shares, the peak
    # is about 50 B per own point plus 500-600 B per boundary point copy (the replicated
    # skeleton: the step's boundary fields, the plans' tables) on this machine
    per_rank = results[2]
    (p0, n0, g), (p1, n1, _) = [(r["peak"], r["own_points"], r["surface_points"]) for r in per_rank]
    assert n0 != n1
    per_point = (p0 - p1) / (n0 - n1)
    fixed_part = p0 - per_point * n0
    assert 0 < per_point < 150, (per_point, per_rank)
    assert fixed_part < 800 * g, (fixed_part, g, per_rank)
    for r in per_rank:
        assert r["peak"] < 150 * r["own_points"] + 800 * r["surface_points"], r


def test_one_and_three_ranks(grids, tmp_path, monkeypatch):
    """1 rank (comm=COMM_WORLD of one) and 3 ranks (4 blocks: one rank holds two; a given
    round-robin partition of the ring; a CGNS grid with its own boundary conditions and
    interfaces, 3 blocks): the same files as the serial run."""
    root, spec = grids
    three = [
        case(spec, "wing", "bend", ["w.x"]),
        case(spec, "ring", "bend", ["r.h5", "r.x"], blocks=[[3, 0], [1], [2]]),
        case(spec, "two", "rigid", ["t.h5"], blocks=[[0], [1], []]),
        case(spec, "cgns", "rigid", ["c.h5"]),
        case(spec, "ring8", "bend", ["r8.x"]),
        case(spec, "ring8", "bend", ["r8s.x"], method="samareh", blocks=[[0, 1], [2, 3, 4, 5], [6, 7]]),
    ]
    results = run_job(tmp_path, 3, three)
    check_outputs(root, tmp_path, three[:2] + three[3:], results[:2] + results[3:], monkeypatch)
    # the free vertices' blend is split: each rank computes the rows its blocks read (ranks 0
    # and 2 hold one side of the ring: the four vertices at its two junctions)
    rows = [r["free_rows"] for r in results[5]]
    assert [full for _, full in rows] == [8, 8, 8] and rows[0][0] < 8 and rows[2][0] < 8, rows
    errors = {r.get("error") for r in results[2]}
    assert len(errors) == 1 and "blocks= is empty" in errors.pop()
    one = [case(spec, "ring", "bend", ["r1.h5"]), case(spec, "two", "rigid", ["t1.x"], jvp=True)]
    results = run_job(tmp_path, 1, one)
    check_outputs(root, tmp_path, one, results, monkeypatch)
    # the derivatives are not distributed yet: refused with a clear error, not wrong numbers
    err = results[1][0]["jvp_error"]
    assert err.startswith("ParallelError") and "not available on a distributed Deformer" in err


def test_deformer_comm_without_mpi4py_names_the_extra(monkeypatch):
    """Without mpi4py the package deforms serially; comm= raises naming the extra, and a comm
    that is no communicator is refused; blocks= needs comm=; a serial Deformer takes a path."""
    from tfi_quat.errors import CaseError, ParallelError
    from _deform_grids import two_block_o
    grid, walls, _, fixed = two_block_o(17, 9)
    with pytest.raises(ParallelError, match="not a comm|intracommunicator"):
        Deformer(grid, walls=walls, fixed=fixed, comm="world")
    with pytest.raises(CaseError, match="blocks= goes with comm="):
        Deformer(grid, walls=walls, fixed=fixed, blocks=[0])
    monkeypatch.setitem(sys.modules, "mpi4py", None)       # import mpi4py raises ImportError
    monkeypatch.setitem(sys.modules, "mpi4py.MPI", None)
    with pytest.raises(ParallelError, match=r'pip install "tfi_quat\[mpi\]"'):
        Deformer(grid, walls=walls, fixed=fixed, comm=object())
    d = Deformer(grid, walls=walls, fixed=fixed)
    assert d.deform(motion("rigid")).dims == grid.dims


def test_serial_deformer_reads_a_path(tmp_path):
    """Deformer(path) reads the grid whole: the same bits as Deformer(read(path))."""
    case = load_case(GRIDS / "two_block_65x33.toml", check_grid=False)
    path = GRIDS / "two_block_65x33.x"
    a = Deformer(str(path), walls=case.walls, fixed=case.fixed).deform(motion("rigid"))
    b = Deformer(tq.read(path), walls=case.walls, fixed=case.fixed).deform(motion("rigid"))
    assert a == b and a.blocks[0].xyz.tobytes() == b.blocks[0].xyz.tobytes()


def test_fingerprint_sees_one_bit_and_row_order():
    """The ranks' wall input is compared by fingerprint: one bit changed anywhere, or two rows
    swapped, changes it; the rows gathered from a larger array give the contiguous rows'."""
    from tfi_quat.deform.distributed import fingerprint
    rng = np.random.default_rng(3)
    X = rng.standard_normal((500, 3))

    def fp(A, rows=None):
        out = np.zeros(2, dtype=np.uint64)
        fingerprint(A.view(np.uint64), np.arange(A.shape[0]) if rows is None else rows, out)
        return out.tobytes()

    base = fp(X)
    for r, c in ((0, 0), (257, 1), (499, 2)):
        Y = X.copy()
        Y[r, c] = np.nextafter(Y[r, c], np.inf)
        assert fp(Y) != base
    assert fp(X[[1, 0] + list(range(2, 500))]) != base
    big = np.zeros((900, 3))
    rows = np.sort(rng.choice(900, 500, replace=False))
    big[rows] = X
    assert fp(big, rows) == base
