"""Using a grid's own connectivity (CGNS boundary conditions and 1-to-1 interfaces):
``Grid.connectivity``, the Deformer's default, and the commands that read grids."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import tfi_quat as tq
from tfi_quat import topology
from tfi_quat.cli import main
from tfi_quat.deform import Deformer, rigid_motion
from tfi_quat.errors import CaseError, ConnectivityError, GridFormatError, GridValueError
from tfi_quat.topology import Connectivity

from _deform_grids import box_pair, two_block_o

MOTION = rigid_motion(5.0, (0.0, 0.0, 1.0), (0.5, 0.0, 0.0))


def run_cli(capsys, *argv):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def as_file(conn: Connectivity, *, reverse: bool = False) -> Connectivity:
    """The connectivity as a file reader gives it: every patch ``origin="file"`` with no plane,
    in the file's order (``reverse``: backwards)."""
    patches = [dataclasses.replace(p, origin="file", plane=None) for p in conn.patches]
    if reverse:
        patches = patches[::-1]
    return Connectivity(conn.interfaces, patches, conn.ndim, conn.dims)


def with_own(builder, **kw):
    """``(plain grid, the same grid carrying connect()'s map as a file's, walls, symmetry, fixed)``."""
    grid, walls, sym, fixed = builder()
    conn = as_file(topology.connect(grid, walls=walls, symmetry=sym, fixed=fixed), **kw)
    return grid, tq.Grid(grid.blocks, grid.ndim, connectivity=conn), walls, sym, fixed


def same_bits(a, b) -> bool:
    return len(a) == len(b) and all(x.xyz.tobytes() == y.xyz.tobytes() for x, y in zip(a, b))


def interfaces_identical(grid, conn) -> None:
    """Every interface's master and slave points are the same bits after deformation."""
    for itf in conn.interfaces:
        ijk = tq.grid.face_ijk(grid[itf.master.block].dims, itf.master.face, itf.master.range).reshape(-1, 3)
        sl = itf.slave_index(ijk)
        a = grid[itf.master.block].xyz[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
        b = grid[itf.slave.block].xyz[sl[:, 0], sl[:, 1], sl[:, 2]]
        assert a.tobytes() == b.tobytes(), str(itf)


# ------------------------------------------------------------------------ Grid.connectivity
def test_grid_carries_a_checked_connectivity():
    grid, own, *_ = with_own(box_pair)
    assert grid.connectivity is None
    assert own.connectivity is not None and len(own.connectivity.interfaces) == 1
    # copy and with_blocks share it; with other dimensions it is dropped
    assert own.copy().connectivity is own.connectivity
    assert own.with_blocks([b.copy() for b in own]).connectivity is own.connectivity
    assert own.with_blocks([own[0].copy()]).connectivity is None
    assert own.with_blocks([own[0], own[1].xyz[:-1]]).connectivity is None
    # equality ignores it
    assert own == grid and grid == own
    # checked against the blocks
    with pytest.raises(ConnectivityError, match="block 2: connectivity is for 7 x 7 x 7"):
        tq.Grid([own[0], own[1].xyz[:-1]], connectivity=own.connectivity)
    with pytest.raises(ConnectivityError, match=r"for 2 block\(s\), the grid has 1"):
        tq.Grid([own[0]], connectivity=own.connectivity)
    with pytest.raises(GridValueError, match="Connectivity"):
        tq.Grid(grid.blocks, connectivity={"walls": []})


# ------------------------------------------------------------------------ the Deformer's default
@pytest.mark.parametrize("builder", [box_pair, two_block_o])
@pytest.mark.parametrize("reverse", [False, True])
def test_own_connectivity_deforms_as_the_same_walls_by_flags(builder, reverse):
    grid, own, walls, sym, fixed = with_own(builder, reverse=reverse)
    want = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed).deform(MOTION)
    d = Deformer(own)
    got = d.deform(MOTION)
    assert same_bits(got, want)
    interfaces_identical(got, d.connectivity)
    # the result keeps the reference's connectivity and file variant
    assert got.connectivity is own.connectivity and got.source_format is own.source_format
    assert d.connectivity.interfaces == own.connectivity.interfaces


def test_own_connectivity_with_gaps_is_completed_as_connect_does():
    """Boundary parts the file leaves out get connect()'s kinds (fixed, symmetry by a wall)."""
    grid, walls, sym, fixed = box_pair()
    conn = topology.connect(grid, walls=walls)
    kept = [dataclasses.replace(p, origin="file") for p in conn.patches if p.kind == "wall"]
    own = tq.Grid(grid.blocks, connectivity=Connectivity(conn.interfaces, kept, 3, conn.dims))
    d = Deformer(own)
    assert [(p.spec, p.kind) for p in d.connectivity.patches] == [(p.spec, p.kind) for p in conn.patches]
    assert same_bits(d.deform(MOTION), Deformer(grid, walls=walls).deform(MOTION))


def test_given_kinds_override_the_own_connectivity_face_by_face():
    grid, own, *_ = with_own(box_pair)
    d = Deformer(own, fixed=["2:imin"])
    kinds = {(p.spec.block, p.spec.face): p.kind for p in d.connectivity.patches}
    assert kinds[(1, "imin")] == "fixed" and kinds[(0, "jmin")] == "wall"
    assert kinds[(0, "kmin")] == "symmetry"                 # the file's kind, kept
    out = d.deform(MOTION)
    off = grid[1].face("imin")[..., 0] > 1.0          # not on the edge it shares with 1:jmin
    assert np.array_equal(out[1].face("imin")[off], grid[1].face("imin")[off])   # no longer moves
    assert not np.array_equal(out[0].face("jmin"), grid[0].face("jmin"))


def test_given_connectivity_wins_over_the_own_one():
    grid, own, walls, *_ = with_own(box_pair)
    other = topology.connect(grid, walls=["1:jmin"])
    d = Deformer(own, connectivity=other)
    assert d.connectivity is other
    assert same_bits(d.deform(MOTION), Deformer(grid, walls=["1:jmin"]).deform(MOTION))


def test_own_connectivity_without_a_wall_is_a_case_error():
    grid, walls, sym, fixed = box_pair()
    own = tq.Grid(grid.blocks, connectivity=as_file(topology.connect(grid)))
    with pytest.raises(CaseError, match="name no wall.*give at least one wall"):
        Deformer(own)


# ------------------------------------------------------------------------ CLI without CGNS files
def test_base_applies_to_cgns_inputs_only(tmp_path, capsys):
    grid, walls, *_ = box_pair()
    path = tmp_path / "g.x"
    tq.write(path, grid)
    for argv in (["deform", path, "--wall", "1:jmin", "--rotate", "1", "-o", tmp_path / "o.x"],
                 ["quality", path], ["plot", path, "-o", tmp_path / "f.png"]):
        rc, out, err = run_cli(capsys, *argv, "--base", "Base")
        assert rc == 2 and f"{path}: --base Base:" in err and "CGNS" in err, err
        assert len(err.strip().splitlines()) == 1


def test_deform_output_format_follows_the_output_extension(tmp_path, capsys):
    """``-o OUT.h5`` of a Plot3D grid is an HDF5 file (the input's variant only for the same format)."""
    grid, walls, *_ = box_pair()
    path = tmp_path / "g.x"
    tq.write(path, grid)
    for name, fmt in (("o.h5", "hdf5"), ("o.xyz", "plot3d"), ("o.dat", "plot3d")):
        rc, out, err = run_cli(capsys, "deform", path, "--wall", "1:jmin", "--wall", "2:imin",
                               "--rotate", "5", "--about", "0.5,0,0", "-o", tmp_path / name)
        assert rc == 0, err
        got = tq.read(tmp_path / name, format=fmt if name.endswith(".dat") else None)
        assert tq.io.format_for(like=got).name == fmt
        assert same_bits(got, Deformer(grid, walls=walls).deform(MOTION))


def test_convert_connectivity_options_need_a_cgns_target(tmp_path, capsys):
    grid, *_ = box_pair()
    path = tmp_path / "g.x"
    tq.write(path, grid)
    topology.connect(grid).to_json(tmp_path / "m.json")
    for extra in (["--connect"], ["--connectivity", tmp_path / "m.json"], ["--connect", "--wall", "1:jmin"]):
        rc, out, err = run_cli(capsys, "convert", path, tmp_path / "o.h5", *extra)
        assert rc == 2 and "hdf5 file cannot hold boundary conditions" in err, err
        assert not (tmp_path / "o.h5").exists()
    rc, out, err = run_cli(capsys, "convert", path, tmp_path / "o.h5", "--wall", "1:jmin")
    assert rc == 2 and "--wall need --connect, --connectivity or --nmf" in err
    with pytest.raises(SystemExit) as exc:       # a usage error
        run_cli(capsys, "convert", path, tmp_path / "o.h5", "--connect", "--connectivity", tmp_path / "m.json")
    assert exc.value.code == 2 and "not allowed with" in capsys.readouterr().err
