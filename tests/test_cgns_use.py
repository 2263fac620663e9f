"""Using a grid's own connectivity (CGNS boundary conditions and 1-to-1 interfaces):
``Grid.connectivity``, the Deformer's default, and the commands that read grids."""

from __future__ import annotations

import dataclasses
import json
import tempfile
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import tfi_quat as tq
from tfi_quat import topology
from tfi_quat.case import load_case
from tfi_quat.cli import main
from tfi_quat.deform import Deformer, rigid_motion
from tfi_quat.errors import CaseError, ConnectivityError, GridFormatError, GridValueError, TfiQuatError
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


# ------------------------------------------------------------------------ CGNS files
DATA = Path(__file__).resolve().parent / "data" / "cgns"


def float32(grid):
    """The grid as a float32 CGNS file stores it."""
    return grid.with_blocks([tq.Block(b.xyz.astype(np.float32), name=b.name) for b in grid])


def tree(path) -> dict:
    """Every node of an HDF5 file: path -> (attributes, data bytes or None)."""
    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            attrs = {k: np.asarray(v).tobytes() for k, v in obj.attrs.items()}
            out[name] = (attrs, obj[()].tobytes() if isinstance(obj, h5py.Dataset) else None)
        f.visititems(visit)
    return out


def assert_kept_but_coordinates(src, out) -> None:
    a, b = tree(src), tree(out)
    assert a.keys() == b.keys()
    changed = [k for k in a if a[k] != b[k]]
    assert changed and all("/GridCoordinates/Coordinate" in k for k in changed), changed


@pytest.mark.parametrize("builder", [box_pair, two_block_o])
def test_cgns_grid_deforms_bit_for_bit_as_plot3d_with_flags(builder, tmp_path, capsys):
    """The issue's property, through the CLI: ``convert --connect --wall``, then ``deform`` with no
    flags gives the grid ``deform`` gives from Plot3D with the walls as flags; the interfaces of
    the deformed file are bit-identical across zones."""
    grid, walls, sym, fixed = builder()
    x, cg = tmp_path / "g.x", tmp_path / "g.cgns"
    tq.write(x, grid)
    flags = [a for k, specs in (("--wall", walls), ("--symmetry", sym), ("--fixed", fixed))
             for s in specs for a in (k, s)]
    rc, out, err = run_cli(capsys, "convert", x, cg, "--connect", *flags)
    assert rc == 0 and "cgns: CGNS/HDF5" in out and "1-to-1 record(s)" in out, err
    motion = ["--rotate", "5", "--about", "0.5,0,0"]
    rc, out, err = run_cli(capsys, "deform", x, *flags, *motion, "-o", tmp_path / "p.x")
    assert rc == 0, err
    rc, out, err = run_cli(capsys, "deform", cg, *motion, "-o", tmp_path / "c.cgns")
    assert rc == 0, err
    want, got = tq.read(tmp_path / "p.x"), tq.read(tmp_path / "c.cgns")
    assert same_bits(got, want) and not same_bits(got, grid)
    assert got.connectivity == tq.read(cg).connectivity
    interfaces_identical(got, got.connectivity)
    assert_kept_but_coordinates(cg, tmp_path / "c.cgns")
    # and back to Plot3D: the same coordinates
    rc, out, err = run_cli(capsys, "convert", tmp_path / "c.cgns", tmp_path / "c.x")
    assert rc == 0 and "note: the boundary conditions and interfaces" in out, err
    assert same_bits(tq.read(tmp_path / "c.x"), want)


def test_cgns_library_cgrid_deforms_as_plot3d_with_its_walls_as_flags(tmp_path, capsys):
    """The CGNS library's C-grid (wake cut as a self 1-to-1 record): no flags needed."""
    src = DATA / "cgrid2d.cgns"
    grid = tq.read(src)
    x = tmp_path / "c.x"
    rc, out, err = run_cli(capsys, "convert", src, x, "--double")
    assert rc == 0, err
    flags = ["--wall", "1:jmin:4-12", "--fixed", "1:jmax", "--fixed", "1:imin", "--fixed", "1:imax"]
    motion = ["--rotate", "3", "--about", "0.25,0,0"]
    assert run_cli(capsys, "deform", x, *flags, *motion, "-o", tmp_path / "p.x")[0] == 0
    rc, out, err = run_cli(capsys, "deform", src, *motion, "-o", tmp_path / "o.cgns")
    assert rc == 0, err
    got = tq.read(tmp_path / "o.cgns")
    assert got.source_format.single                         # the input's float32, kept
    want = Deformer(tq.read(x), walls=flags[1:2], fixed=flags[3::2]).deform(
        rigid_motion(3.0, (0, 0, 1), (0.25, 0, 0)))
    assert same_bits(got, float32(want))
    interfaces_identical(got, got.connectivity)
    assert_kept_but_coordinates(src, tmp_path / "o.cgns")
    # the API the same way: the grid's own walls, output keeps the connectivity and variant
    out = Deformer(grid).deform(rigid_motion(3.0, (0, 0, 1), (0.25, 0, 0)))
    assert out.connectivity is grid.connectivity and out.source_format == grid.source_format
    tq.write(tmp_path / "api.cgns", out, like=grid)
    assert same_bits(tq.read(tmp_path / "api.cgns"), got)


def test_flags_override_the_file_face_by_face(tmp_path, capsys):
    """multiblock.cgns names two non-planar faces BCSymmetryPlane: a clear error, and --fixed on
    those faces (nothing else) makes it deformable; the output keeps every other node."""
    src = DATA / "multiblock.cgns"
    out = tmp_path / "o.cgns"
    rc, so, err = run_cli(capsys, "deform", src, "--rotate", "2", "-o", out)
    assert rc == 2 and "symmetry patch 1:kmin" in err and "not planar" in err and not out.exists()
    rc, so, err = run_cli(capsys, "deform", src, "--rotate", "2", "--fixed", "1:kmin", "--fixed", "2:kmin",
                          "-o", out)
    assert rc == 0, err
    grid = tq.read(src)
    d = Deformer(grid, fixed=["1:kmin", "2:kmin"])
    kinds = {(p.spec.block, p.spec.face, p.spec.range): p.kind for p in d.connectivity.patches}
    assert kinds[(0, "kmin", ((0, 4), (0, 3)))] == "fixed"
    assert kinds[(0, "jmin", ((2, 4), (0, 2)))] == "symmetry"            # the file's, kept
    assert kinds[(0, "jmin", ((0, 2), (0, 2)))] == "wall"
    assert same_bits(tq.read(out), d.deform(rigid_motion(2.0)))
    assert_kept_but_coordinates(src, out)
    # the second base has no boundary conditions: walls by flag
    rc, so, err = run_cli(capsys, "deform", src, "--base", "coarse", "--rotate", "2", "-o", tmp_path / "c.cgns")
    assert rc == 2 and "no wall points" in err
    rc, so, err = run_cli(capsys, "deform", src, "--base", "coarse", "--wall", "1:imin", "--rotate", "2",
                          "-o", tmp_path / "c.cgns")
    assert rc == 0, err
    assert tq.read(tmp_path / "c.cgns", base="coarse").nblocks == 1
    rc, so, err = run_cli(capsys, "deform", src, "--base", "nope", "--rotate", "2", "-o", tmp_path / "n.cgns")
    assert rc == 2 and "nope" in err and len(err.strip().splitlines()) == 1


def test_case_file_with_a_cgns_grid_takes_the_file_walls(tmp_path, capsys):
    src = DATA / "cgrid2d.cgns"
    case = tmp_path / "c.toml"
    case.write_text(f'grid = "{src}"\noutput = "o.cgns"\n\n[motion]\nrotate = 3.0\nabout = [0.25, 0.0, 0.0]\n')
    rc, out, err = run_cli(capsys, "deform", "--case", case)
    assert rc == 0, err
    want = Deformer(tq.read(src)).deform(rigid_motion(3.0, (0, 0, 1), (0.25, 0, 0)))
    assert same_bits(tq.read(tmp_path / "o.cgns"), float32(want))
    assert same_bits(tq.deformer_from_case(load_case(case)).deform(rigid_motion(3.0, (0, 0, 1), (0.25, 0, 0))),
                     want)
    # walls in the case file override the file's face by face
    case.write_text(f'grid = "{src}"\noutput = "w.cgns"\nfixed = ["1:jmin"]\nwalls = ["1:jmax"]\n')
    assert run_cli(capsys, "deform", "--case", case, "--rotate", "1")[0] == 0
    moved, ref = tq.read(tmp_path / "w.cgns"), tq.read(src)
    assert np.array_equal(moved[0].face("jmin"), ref[0].face("jmin"))


def test_quality_and_plot_take_the_file_walls(tmp_path, capsys):
    src = DATA / "cgrid2d.cgns"
    rc, out, err = run_cli(capsys, "quality", src, "--json")
    assert rc == 0, err
    assert [w["patch"] for w in json.loads(out)["walls"]] == ["1:jmin:4-12,1-1"]
    rc, out, err = run_cli(capsys, "quality", src, "--json", "--walls", "1:jmax")
    assert [w["patch"] for w in json.loads(out)["walls"]] == ["1:jmax:1-15,1-1"]
    rc, out, err = run_cli(capsys, "plot", src, "-o", tmp_path / "f.png", "--color", "orthogonality")
    assert rc == 0 and (tmp_path / "f.png").stat().st_size > 0, err
    x = tmp_path / "c.x"
    tq.write(x, tq.read(src))
    rc, out, err = run_cli(capsys, "plot", x, "-o", tmp_path / "g.png", "--color", "orthogonality")
    assert rc == 2 and "needs wall patches" in err                     # a Plot3D file has none


def test_convert_writes_maps_into_cgns(tmp_path, capsys):
    grid, walls, *_ = box_pair()
    x = tmp_path / "g.x"
    tq.write(x, grid)
    conn = topology.connect(grid, walls=walls)
    conn.to_json(tmp_path / "m.json")
    conn.to_nmf(tmp_path / "m.nmf")
    for opt, path in (("--connectivity", tmp_path / "m.json"), ("--nmf", tmp_path / "m.nmf")):
        out = tmp_path / f"{path.suffix[1:]}.cgns"
        rc, so, err = run_cli(capsys, "convert", x, out, opt, path)
        assert rc == 0 and "10 boundary condition(s), 2 1-to-1 record(s)" in so, err
        got = tq.read(out)
        assert same_bits(got, grid)
        assert [(p.spec, p.kind) for p in got.connectivity.patches] == [(p.spec, p.kind) for p in conn.patches]
        assert got.connectivity.interfaces == conn.interfaces
    # a map with --wall over it; --single
    rc, so, err = run_cli(capsys, "convert", x, tmp_path / "s.cgns", "--connectivity", tmp_path / "m.json",
                          "--fixed", "2:imin", "--single")
    assert rc == 0 and "float32" in so, err
    got = tq.read(tmp_path / "s.cgns")
    assert {p.spec.face: p.kind for p in got.connectivity.patches if p.spec.block == 1}["imin"] == "fixed"
    # CGNS to CGNS with a new search replaces the boundary conditions, keeps the rest
    src = DATA / "multiblock.cgns"
    rc, so, err = run_cli(capsys, "convert", src, tmp_path / "n.cgns", "--connect", "--wall", "1:imin")
    assert rc == 0, err
    got = tq.read(tmp_path / "n.cgns")
    assert [p.spec for p in got.connectivity.patches if p.kind == "wall"] == \
        [p.spec for p in topology.connect(got, walls=["1:imin"]).patches if p.kind == "wall"]
    assert "FlowSolution" in "".join(tree(tmp_path / "n.cgns"))
    rc, so, err = run_cli(capsys, "convert", src, tmp_path / "n.x", "--in-base", "coarse")
    assert rc == 0 and tq.read(tmp_path / "n.x").nblocks == 1, err


def test_convert_refuses_other_format_options_for_cgns(tmp_path, capsys):
    grid, *_ = box_pair()
    x = tmp_path / "g.x"
    tq.write(x, grid)
    rc, out, err = run_cli(capsys, "convert", x, tmp_path / "o.cgns", "--fortran", "--compress")
    assert rc == 2 and "--ascii/--binary/--fortran, --compress/--no-compress/--compression-level do not " \
        "apply to CGNS output" in err, err
    assert not (tmp_path / "o.cgns").exists()


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(walls=st.lists(st.sampled_from(["1:jmin", "2:imin", "1:kmin", "2:kmax", "1:jmin:1-4,1-7"]),
                      min_size=1, max_size=3, unique=True),
       angle=st.floats(-4.0, 4.0), axis=st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(
           lambda v: sum(x * x for x in v) > 0.1),
       shift=st.tuples(*[st.floats(-0.02, 0.02)] * 3))
def test_any_walls_written_to_cgns_deform_as_given_by_flags(walls, angle, axis, shift):
    """Whatever walls a CGNS file names, deforming it is bit for bit deforming the Plot3D grid with
    those walls as flags (or both refuse the case with the same error)."""
    if "1:jmin" in walls and "1:jmin:1-4,1-7" in walls:
        walls = [w for w in walls if w != "1:jmin:1-4,1-7"]
    grid, *_ = box_pair()
    motion = rigid_motion(angle, axis, (0.5, 0.0, 0.5), shift)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "g.cgns"
        tq.write(path, grid, connectivity=topology.connect(grid, walls=walls))
        own = tq.read(path)
        assert own == grid
        try:
            want = Deformer(grid, walls=walls).deform(motion)
        except TfiQuatError as exc:
            with pytest.raises(type(exc)):
                Deformer(own).deform(motion)
            return
        got = Deformer(own).deform(motion)
        assert same_bits(got, want)
        interfaces_identical(got, own.connectivity)
        tq.write(Path(tmp) / "o.cgns", got, like=own)
        assert same_bits(tq.read(Path(tmp) / "o.cgns"), want)


def test_deform_a_plot3d_grid_into_cgns_writes_the_boundaries_used(tmp_path, capsys):
    grid, walls, *_ = box_pair()
    x = tmp_path / "g.x"
    tq.write(x, grid)
    rc, out, err = run_cli(capsys, "deform", x, "--wall", "1:jmin", "--wall", "2:imin", "--rotate", "5",
                           "--about", "0.5,0,0", "-o", tmp_path / "o.cgns")
    assert rc == 0, err
    got = tq.read(tmp_path / "o.cgns")
    d = Deformer(grid, walls=walls)
    assert same_bits(got, d.deform(MOTION))
    assert [(p.spec, p.kind) for p in got.connectivity.patches] == [(p.spec, p.kind) for p in d.connectivity.patches]
    assert got.connectivity.interfaces == d.connectivity.interfaces
