"""``tfi-quat info`` and ``tfi-quat convert``, run in-process through ``main``."""

from __future__ import annotations

import gc
import json
import sys

import h5py
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import tfi_quat
from tfi_quat import Block, Grid, GridFormatError
from tfi_quat.cli import GC_THRESHOLDS, _info, console_main, main
from tfi_quat.io import hdf5, plot3d
from tfi_quat.io.hdf5 import HDF5Format
from tfi_quat.io.plot3d import Plot3DFormat

from conftest import annulus, sheared_box


def run_cli(capsys, *argv):
    """Run ``tfi-quat argv``; return (exit status, stdout, stderr)."""
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def edge_oracle(grid):
    """Shortest/longest cell edge, computed plainly over whole blocks."""
    lengths = [np.linalg.norm(np.diff(b.xyz, axis=a), axis=-1).ravel()
               for b in grid for a in range(3) if b.dims[a] > 1]
    allv = np.concatenate(lengths)
    return allv.min(), allv.max()


def two_block_grid():
    b1 = Block(sheared_box(5, 4, 3), name="wing")
    ib = np.ones((6, 2, 7), dtype=np.int32)
    ib[0, 0, 0] = 0
    b2 = Block(sheared_box(6, 2, 7) + [3.0, -1.0, 0.5], iblank=ib, name="wake")
    return Grid([b1, b2])


@pytest.fixture
def h5grid(tmp_path):
    p = tmp_path / "two.h5"
    grid = two_block_grid()
    hdf5.write(p, grid)
    return p, grid


def assert_one_line_error(rc, out, err, *fragments):
    assert rc == 2
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for f in fragments:
        assert str(f) in lines[0], (f, lines[0])


def test_console_main_sets_the_collector_for_a_process_and_main_leaves_it(capsys, monkeypatch, h5grid):
    """The process entry runs the command with the collector set for a short run (and exits
    with its status); ``main`` called from Python changes nothing."""
    before = gc.get_threshold()
    assert run_cli(capsys, "info", h5grid[0])[0] == 0
    assert gc.get_threshold() == before
    monkeypatch.setattr(sys, "argv", ["tfi-quat", "info", str(h5grid[0])])
    try:
        with pytest.raises(SystemExit) as exc:
            console_main()
        assert exc.value.code == 0
        assert gc.get_threshold() == GC_THRESHOLDS and gc.get_freeze_count() > 0
        assert "wing" in capsys.readouterr().out
        monkeypatch.setattr(sys, "argv", ["tfi-quat", "info", str(h5grid[0]) + ".missing"])
        with pytest.raises(SystemExit) as exc:
            console_main()
        assert exc.value.code == 2
    finally:
        gc.unfreeze()
        gc.set_threshold(*before)


# ----------------------------------------------------------------------------- info

def test_info_text(capsys, h5grid):
    p, grid = h5grid
    rc, out, err = run_cli(capsys, "info", p)
    assert rc == 0 and err == ""
    lines = out.splitlines()
    assert lines[0] == str(p)
    assert "format      hdf5: layout v1, uncompressed" in out
    assert "ndim        3" in out and "blocks      2" in out
    assert any(l.split()[:6] == ["1", "wing", "5", "x", "4", "x"] and "60 points" in l for l in lines)
    wake = [l for l in lines if "wake" in l][0]
    assert "6 x 2 x 7" in wake and "84 points" in wake and wake.endswith("iblank")
    assert "points      144" in out
    lo, hi = grid.bbox()
    assert f"x [{lo[0]:.6g}, {hi[0]:.6g}]" in out and f"z [{lo[2]:.6g}, {hi[2]:.6g}]" in out
    emin, emax = edge_oracle(grid)
    assert f"cell edge   min {emin:.6g}  max {emax:.6g}" in out
    assert lines[-1] == "  iblank      yes"


def test_info_json(capsys, h5grid):
    p, grid = h5grid
    rc, out, _ = run_cli(capsys, "info", p, "--json")
    assert rc == 0
    s = json.loads(out)
    assert s["format"] == "hdf5" and s["variant"] == {"compression": None, "compression_level": None,
                                                      "shuffle": False, "version": 1}
    assert s["ndim"] == 3 and s["nblocks"] == 2 and s["points"] == 144 and s["iblank"] is True
    assert s["blocks"] == [{"block": 1, "name": "wing", "dims": [5, 4, 3], "points": 60, "iblank": False},
                           {"block": 2, "name": "wake", "dims": [6, 2, 7], "points": 84, "iblank": True}]
    lo, hi = grid.bbox()
    assert s["bbox"] == {"min": lo.tolist(), "max": hi.tolist()}
    emin, emax = edge_oracle(grid)
    assert s["edge_length"]["min"] == pytest.approx(emin, rel=1e-14)
    assert s["edge_length"]["max"] == pytest.approx(emax, rel=1e-14)


def test_info_2d_grid_without_iblank(capsys, tmp_path):
    p = tmp_path / "ann.hdf5"
    grid = Grid([annulus()])
    hdf5.write(p, grid, compression="gzip", compression_level=2)
    rc, out, _ = run_cli(capsys, "info", p, "--json")
    s = json.loads(out)
    assert rc == 0 and s["ndim"] == 2 and s["iblank"] is False
    assert s["description"] == "hdf5: layout v1, gzip level 2 + shuffle"
    assert s["blocks"][0]["dims"] == [9, 5, 1]
    # annulus: shortest edge is the inner radial spacing or the inner arc chord
    r = np.geomspace(1.0, 3.0, 5)
    chord = 2 * np.sin(np.pi / 2 / 8 / 2)
    assert s["edge_length"]["min"] == pytest.approx(min(r[1] - r[0], chord * r[0]), rel=1e-12)
    assert s["edge_length"]["max"] == pytest.approx(max(r[-1] - r[-2], chord * r[-1]), rel=1e-12)


def test_edge_lengths_of_a_uniform_box():
    x, y, z = np.meshgrid(np.arange(4) * 0.1, np.arange(3) * 0.2, np.arange(5) * 0.5, indexing="ij")
    grid = Grid([np.stack([x, y, z], axis=-1)])
    lo, hi = _info.edge_length_range(grid)
    assert lo == pytest.approx(0.1, rel=1e-15) and hi == pytest.approx(0.5, rel=1e-15)
    assert _info.edge_length_range(Grid([np.zeros((1, 1, 1, 3))], 3)) is None


@pytest.mark.parametrize("compiled", [True, False])
@given(dims=st.lists(st.tuples(st.integers(1, 7), st.integers(1, 6), st.integers(1, 6)),
                     min_size=1, max_size=3),
       seed=st.integers(0, 1000))
def test_edge_lengths_match_the_oracle(compiled, dims, seed):
    rng = np.random.default_rng(seed)
    grid = Grid([rng.normal(size=d + (3,)) for d in dims], 3)
    kernel = None if compiled else _info._edge_range_kernel.py_func
    got = _info.edge_length_range(grid, kernel=kernel)
    if all(d == (1, 1, 1) for d in dims):
        assert got is None
    else:
        assert got == pytest.approx(edge_oracle(grid), rel=1e-14)


def test_edge_lengths_skip_nan_and_see_collapsed_edges():
    xyz = sheared_box(4, 3, 3)
    xyz[1, 1, 1] = xyz[2, 1, 1]  # one collapsed edge
    xyz[0, 0, 0, 0] = np.nan
    grid = Grid([Block(xyz, allow_nonfinite=True)])
    lo, hi = _info.edge_length_range(grid)
    assert lo == 0.0
    ok = Grid([sheared_box(4, 3, 3)])
    assert hi <= 2 * edge_oracle(ok)[1] and np.isfinite(hi)
    nan = Grid([Block(np.full((2, 1, 1, 3), np.nan), allow_nonfinite=True)], 3)
    assert _info.edge_length_range(nan) is None


def test_info_hdf5_with_unknown_extension_is_sniffed(capsys, h5grid, tmp_path):
    p, _ = h5grid
    q = tmp_path / "grid.dat"
    q.write_bytes(p.read_bytes())
    rc, out, _ = run_cli(capsys, "info", q, "--json")
    assert rc == 0 and json.loads(out)["format"] == "hdf5"


def test_info_allow_nonfinite(capsys, tmp_path):
    p = tmp_path / "nan.h5"
    xyz = sheared_box(3, 3, 3)
    xyz[1, 1, 1, 0] = np.nan
    hdf5.write(p, Grid([Block(xyz, allow_nonfinite=True)]))
    rc, out, err = run_cli(capsys, "info", p)
    assert_one_line_error(rc, out, err, "tfi-quat info: error:", p, "block 1", "non-finite")
    rc, out, _ = run_cli(capsys, "info", p, "--allow-nonfinite", "--json")
    s = json.loads(out)
    assert rc == 0 and s["bbox"]["min"][0] is None and s["bbox"]["min"][1] == 0.0


# ----------------------------------------------------------------------------- info: errors

def test_info_missing_file(capsys, tmp_path):
    rc, out, err = run_cli(capsys, "info", tmp_path / "nope.h5")
    assert_one_line_error(rc, out, err, "tfi-quat info: error:", "nope.h5", "no such file")


def test_info_not_an_hdf5_file(capsys, tmp_path):
    p = tmp_path / "bad.h5"
    p.write_text("not a grid\n")
    rc, out, err = run_cli(capsys, "info", p)
    assert_one_line_error(rc, out, err, str(p), "not an HDF5 file")


def test_info_hdf5_without_the_layout(capsys, tmp_path):
    p = tmp_path / "other.h5"
    with h5py.File(p, "w") as f:
        f["data"] = np.zeros(3)
    rc, out, err = run_cli(capsys, "info", p)
    assert_one_line_error(rc, out, err, str(p), "no attribute 'format'")


def test_info_plot3d_options_do_not_apply_to_hdf5(capsys, h5grid):
    p, _ = h5grid
    rc, out, err = run_cli(capsys, "info", p, "--endian", "big", "--single-block")
    assert_one_line_error(rc, out, err, str(p), "HDF5", "--endian", "--single-block")


def test_debug_shows_the_exception(tmp_path):
    p = tmp_path / "bad.h5"
    p.write_text("x")
    with pytest.raises(GridFormatError, match="not an HDF5 file"):
        main(["info", str(p), "--debug"])


def test_usage_errors_exit_2(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["info", "g.h5", "--endian", "middle"])
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


def test_multi_line_errors_are_folded_into_one_line(capsys, h5grid, monkeypatch):
    p, _ = h5grid

    def fails(*a, **k):
        raise GridFormatError(f"{p}: no variant fits; Closest:\n  as A: too short\n  as B: too long\n")

    monkeypatch.setattr(_info, "read", fails)
    rc, out, err = run_cli(capsys, "info", p)
    assert_one_line_error(rc, out, err, f"{p}: no variant fits; Closest: as A: too short; as B: too long")
    rc, out, err = run_cli(capsys, "convert", p, p.with_suffix(".x"))
    assert_one_line_error(rc, out, err, "tfi-quat convert: error:", "Closest: as A: too short; as B")
    assert _info.one_line("a\n\n b:\n c \n d") == "a; b: c; d"


# ----------------------------------------------------------------------------- convert

def test_convert_hdf5_compress_and_back(capsys, h5grid, tmp_path):
    p, grid = h5grid
    q = tmp_path / "packed.h5"
    rc, out, err = run_cli(capsys, "convert", p, q, "--compress", "--compression-level", "7")
    assert rc == 0 and err == ""
    assert out == f"wrote {q}: hdf5: layout v1, gzip level 7 + shuffle, 2 block(s), 144 points\n"
    back = tfi_quat.read(q)
    assert back == grid and [b.name for b in back] == ["wing", "wake"]
    assert back.source_format == HDF5Format("gzip", 7, True)
    # HDF5 -> HDF5 keeps the input's compression unless told otherwise
    r = tmp_path / "same.h5"
    assert run_cli(capsys, "convert", q, r)[0] == 0
    assert hdf5.info(r).format == HDF5Format("gzip", 7, True)
    s = tmp_path / "plain.hdf"
    assert run_cli(capsys, "convert", q, s, "--no-compress")[0] == 0
    assert hdf5.info(s).format == HDF5Format()
    assert tfi_quat.read(s) == grid


def test_convert_keeps_extra_json(capsys, tmp_path):
    p, q = tmp_path / "a.h5", tmp_path / "b.h5"
    extra = {"connectivity": [{"blocks": [1, 2]}]}
    hdf5.write(p, two_block_grid(), extra_json=extra)
    assert run_cli(capsys, "convert", p, q, "--compress")[0] == 0
    assert hdf5.read_extra(q) == extra


def test_convert_refuses_to_overwrite(capsys, h5grid, tmp_path):
    p, grid = h5grid
    q = tmp_path / "out.h5"
    q.write_bytes(b"precious")
    rc, out, err = run_cli(capsys, "convert", p, q)
    assert_one_line_error(rc, out, err, "tfi-quat convert: error:", q, "exists", "--force")
    assert q.read_bytes() == b"precious"
    rc, out, _ = run_cli(capsys, "convert", p, q, "--force")
    assert rc == 0 and out.startswith(f"wrote {q}")
    assert tfi_quat.read(q) == grid


def test_convert_never_replaces_its_input_without_force(capsys, h5grid):
    p, grid = h5grid
    before = p.read_bytes()
    rc, out, err = run_cli(capsys, "convert", p, p, "--compress")
    assert_one_line_error(rc, out, err, p, "refusing to overwrite the input file")
    assert p.read_bytes() == before
    rc, _, _ = run_cli(capsys, "convert", p, p, "--compress", "--force")
    assert rc == 0
    assert hdf5.info(p).format.compression == "gzip"
    assert tfi_quat.read(p) == grid


@pytest.mark.parametrize("flags, fragment", [
    (["--ascii"], "--ascii/--binary/--fortran apply to Plot3D output only"),
    (["--big-endian", "--single"], "--big-endian/--little-endian, --single/--double apply to Plot3D"),
    (["--records", "coordinate"], "--records apply to Plot3D output only"),
])
def test_convert_plot3d_flags_need_plot3d_output(capsys, h5grid, tmp_path, flags, fragment):
    p, _ = h5grid
    q = tmp_path / "out.h5"
    rc, out, err = run_cli(capsys, "convert", p, q, *flags)
    assert_one_line_error(rc, out, err, q, fragment)
    assert not q.exists()


def test_convert_contradicting_compression_options(capsys, h5grid, tmp_path):
    p, _ = h5grid
    q = tmp_path / "out.h5"
    rc, out, err = run_cli(capsys, "convert", p, q, "--no-compress", "--compression-level", "3")
    assert_one_line_error(rc, out, err, q, "--compression-level contradicts --no-compress")
    assert not q.exists()
    assert run_cli(capsys, "convert", p, q, "--compression-level", "0")[0] == 0
    assert hdf5.info(q).format == HDF5Format("gzip", 0, True)


def test_convert_compress_needs_hdf5_output(capsys, h5grid, tmp_path):
    p, _ = h5grid
    q = tmp_path / "out.xyz"
    rc, out, err = run_cli(capsys, "convert", p, q, "--format", "plot3d", "--compress")
    assert_one_line_error(rc, out, err, q, "--compress/--compression-level apply to HDF5 output only")
    assert not q.exists()


def test_convert_single_block_needs_one_block(capsys, h5grid, tmp_path):
    p, _ = h5grid
    q = tmp_path / "out.xyz"
    rc, out, err = run_cli(capsys, "convert", p, q, "--format", "plot3d", "--single-block")
    assert_one_line_error(rc, out, err, "--single-block needs a one-block grid", "2 blocks")
    assert not q.exists()


def test_convert_bad_input_names_the_file(capsys, tmp_path):
    p = tmp_path / "broken.h5"
    hdf5.write(p, two_block_grid())
    with h5py.File(p, "r+") as f:
        f.attrs["version"] = 9
    q = tmp_path / "out.h5"
    rc, out, err = run_cli(capsys, "convert", p, q)
    assert_one_line_error(rc, out, err, "tfi-quat convert: error:", p, "layout version 9")
    assert not q.exists()
    rc, out, err = run_cli(capsys, "convert", tmp_path / "missing.h5", q)
    assert_one_line_error(rc, out, err, "missing.h5", "no such file")


def test_convert_input_options_are_prefixed(capsys, h5grid, tmp_path):
    p, _ = h5grid
    rc, out, err = run_cli(capsys, "convert", p, tmp_path / "o.h5", "--in-precision", "single")
    assert_one_line_error(rc, out, err, p, "--in-precision")


def test_convert_into_a_missing_folder(capsys, h5grid, tmp_path):
    p, _ = h5grid
    q = tmp_path / "nowhere" / "out.h5"
    rc, out, err = run_cli(capsys, "convert", p, q)
    assert_one_line_error(rc, out, err, "tfi-quat convert: error:", "nowhere", "does not exist")


# ----------------------------------------------------------------------------- Plot3D files

P3D_VARIANTS = [
    Plot3DFormat(),
    Plot3DFormat(encoding="binary", endian=">", precision=4, iblank=True),
    Plot3DFormat(encoding="fortran", endian="<", precision=8),
    Plot3DFormat(encoding="fortran", endian=">", precision=4, iblank=True, int_size=8),
    Plot3DFormat(encoding="fortran", records="coordinate", endian=">", iblank=True),
    Plot3DFormat(encoding="fortran", marker_size=8),
    Plot3DFormat(encoding="ascii", iblank=True),
    Plot3DFormat(encoding="ascii", precision=4),
]


def p3d_grid(variant: Plot3DFormat) -> Grid:
    """A grid the variant can hold (one block if single-block, 2-D if ndim 2)."""
    if variant.ndim == 2:
        blocks = [Block(annulus(), name=None), Block(annulus(5, 3))]
    else:
        g = two_block_grid()
        blocks = [Block(b.xyz, b.iblank) for b in g]
    if not variant.multiblock:
        blocks = blocks[:1]
    if variant.precision == 4:  # values a float32 file holds exactly
        blocks = [Block(b.xyz.astype(np.float32).astype(np.float64), b.iblank) for b in blocks]
    return Grid(blocks, variant.ndim)


VARIANTS_ALL = P3D_VARIANTS + [Plot3DFormat(ndim=2, multiblock=False),
                               Plot3DFormat(encoding="ascii", ndim=2, multiblock=False)]


@pytest.mark.parametrize("variant", VARIANTS_ALL, ids=lambda v: v.describe())
def test_info_reports_each_plot3d_variant(capsys, tmp_path, variant):
    grid = p3d_grid(variant)
    p = tmp_path / "g.xyz"
    plot3d.write(p, grid, like=variant)
    rc, out, err = run_cli(capsys, "info", p, "--json")
    assert rc == 0 and err == ""
    s = json.loads(out)
    assert s["format"] == "plot3d"
    want = variant.replace(iblank=grid.has_iblank).canonical()
    if variant.encoding == "ascii":  # text does not tell float32 from float64
        want = want.replace(precision=s["variant"]["precision"])
    assert Plot3DFormat(**s["variant"]) == want
    assert s["description"] == "plot3d: " + Plot3DFormat(**s["variant"]).describe()
    assert s["ndim"] == variant.ndim and s["nblocks"] == len(grid) and s["points"] == grid.npoints
    assert [b["dims"] for b in s["blocks"]] == [list(b.dims) for b in grid]
    grid = tfi_quat.read(p)  # ASCII float32 text reads back as its decimal values
    lo, hi = grid.bbox()
    assert s["bbox"] == {"min": lo.tolist(), "max": hi.tolist()}
    emin, emax = edge_oracle(grid)
    assert s["edge_length"]["min"] == pytest.approx(emin, rel=1e-12)
    assert s["edge_length"]["max"] == pytest.approx(emax, rel=1e-12)
    rc, out, _ = run_cli(capsys, "info", p)
    assert rc == 0 and f"format      plot3d: {variant.describe()}"[:30] in out


@pytest.mark.parametrize("variant", VARIANTS_ALL, ids=lambda v: v.describe())
def test_convert_plot3d_hdf5_plot3d_is_bit_exact(capsys, tmp_path, variant):
    grid = p3d_grid(variant)
    a, h, b = tmp_path / "a.x", tmp_path / "a.h5", tmp_path / "b.x"
    plot3d.write(a, grid, like=variant)
    original = tfi_quat.read(a)
    rc, out, _ = run_cli(capsys, "convert", a, h)
    assert rc == 0 and out.startswith(f"wrote {h}: hdf5: layout v1, uncompressed")
    assert_grids_bit_equal(tfi_quat.read(h), original)
    # back to Plot3D in the original variant, chosen by flags: the same bytes
    v = plot3d.detect(a)
    flags = ["--" + v.encoding, "--big-endian" if v.endian == ">" else "--little-endian",
             "--single" if variant.precision == 4 else "--double",  # ASCII: not detectable
             "--iblank" if v.iblank else "--no-iblank", "--records", v.records,
             "--multi-block" if v.multiblock else "--single-block",
             "--int-size", str(v.int_size), "--marker-size", str(v.marker_size)]
    rc, out, _ = run_cli(capsys, "convert", h, b, *flags)
    v = v.replace(precision=variant.precision)
    assert rc == 0 and out == f"wrote {b}: plot3d: {v.describe()}, {len(grid)} block(s), {grid.npoints:,} points\n"
    assert b.read_bytes() == a.read_bytes()


def assert_grids_bit_equal(x: Grid, y: Grid):
    assert x.ndim == y.ndim and len(x) == len(y)
    for p, q in zip(x, y):
        assert p.xyz.tobytes(order="F") == q.xyz.tobytes(order="F")
        assert (p.iblank is None) == (q.iblank is None)
        if p.iblank is not None:
            np.testing.assert_array_equal(p.iblank, q.iblank)


def test_convert_plot3d_keeps_the_variant_by_default(capsys, tmp_path):
    variant = Plot3DFormat(encoding="fortran", endian=">", precision=4, iblank=True, records="coordinate")
    a, b = tmp_path / "a.grd", tmp_path / "b.x"
    plot3d.write(a, p3d_grid(variant), like=variant)
    rc, out, _ = run_cli(capsys, "convert", a, b)
    assert rc == 0 and f"plot3d: {plot3d.detect(a).describe()}" in out
    assert plot3d.detect(b) == plot3d.detect(a)
    assert b.read_bytes() == a.read_bytes()


@pytest.mark.parametrize("flags, changes", [
    (["--ascii"], {"encoding": "ascii"}),
    (["--fortran", "--big-endian"], {"encoding": "fortran", "endian": ">"}),
    (["--single"], {"precision": 4}),
    (["--iblank"], {"iblank": True}),
    (["--fortran", "--records", "coordinate", "--int-size", "8"],
     {"encoding": "fortran", "records": "coordinate", "int_size": 8}),
    (["--fortran", "--marker-size", "8"], {"encoding": "fortran", "marker_size": 8}),
])
def test_convert_flags_are_honoured(capsys, tmp_path, flags, changes):
    a, b = tmp_path / "a.x", tmp_path / "b.x"
    grid = p3d_grid(Plot3DFormat(precision=4))
    plot3d.write(a, grid)
    rc, out, _ = run_cli(capsys, "convert", a, b, *flags)
    want = plot3d.detect(a).replace(**changes).canonical()
    assert rc == 0 and out.startswith(f"wrote {b}: plot3d: {want.describe()}")
    assert plot3d.detect(b) == want
    back = tfi_quat.read(b)
    for x, y in zip(back, grid):
        np.testing.assert_array_equal(x.xyz, y.xyz)


def test_convert_hdf5_to_plot3d_defaults_and_single_block(capsys, tmp_path):
    h, a, s = tmp_path / "g.h5", tmp_path / "g.x", tmp_path / "one.p3d"
    grid = two_block_grid()
    hdf5.write(h, grid)
    assert run_cli(capsys, "convert", h, a)[0] == 0
    assert plot3d.detect(a) == Plot3DFormat(iblank=True)
    back = tfi_quat.read(a)
    assert [b.xyz.tobytes() for b in back] == [b.xyz.tobytes() for b in grid]
    assert np.all(back[0].iblank == 1)  # a block without IBLANK is written as all 1
    np.testing.assert_array_equal(back[1].iblank, grid[1].iblank)
    one = tmp_path / "one.h5"
    hdf5.write(one, Grid([grid[0]]))
    rc, out, _ = run_cli(capsys, "convert", one, s, "--single-block", "--fortran")
    assert rc == 0
    assert plot3d.detect(s) == Plot3DFormat(encoding="fortran", multiblock=False)


def test_convert_to_an_unknown_extension(capsys, tmp_path):
    a = tmp_path / "a.x"
    plot3d.write(a, two_block_grid())
    q = tmp_path / "out.dat"
    assert run_cli(capsys, "convert", a, q, "--fortran")[0] == 0
    assert plot3d.detect(q).encoding == "fortran"
    r = tmp_path / "out2.dat"
    assert run_cli(capsys, "convert", a, r, "--compress")[0] == 0
    assert hdf5.info(r).format.compression == "gzip"
    # an unknown extension on input is read as Plot3D
    rc, out, _ = run_cli(capsys, "info", q, "--json")
    assert rc == 0 and json.loads(out)["variant"]["encoding"] == "fortran"


def test_info_input_overrides(capsys, tmp_path):
    a = tmp_path / "a.x"
    plot3d.write(a, two_block_grid(), encoding="fortran", endian=">")
    rc, out, _ = run_cli(capsys, "info", a, "--endian", "big", "--encoding", "fortran", "--json")
    assert rc == 0 and json.loads(out)["variant"]["endian"] == ">"
    rc, out, err = run_cli(capsys, "info", a, "--endian", "little")
    assert_one_line_error(rc, out, err, "tfi-quat info: error:", a)
    rc, out, err = run_cli(capsys, "convert", a, tmp_path / "b.h5", "--in-encoding", "binary")
    assert_one_line_error(rc, out, err, "tfi-quat convert: error:", a)
    assert not (tmp_path / "b.h5").exists()


def test_plot3d_bad_input_is_one_line(capsys, tmp_path):
    a = tmp_path / "a.x"
    plot3d.write(a, two_block_grid())
    data = a.read_bytes()
    t = tmp_path / "trunc.x"
    t.write_bytes(data[:-100])
    rc, out, err = run_cli(capsys, "info", t)
    assert_one_line_error(rc, out, err, "tfi-quat info: error:", t)
    e = tmp_path / "empty.x"
    e.write_bytes(b"")
    rc, out, err = run_cli(capsys, "convert", e, tmp_path / "e.h5")
    assert_one_line_error(rc, out, err, "tfi-quat convert: error:", e)


def test_convert_plot3d_never_replaces_its_input_without_force(capsys, tmp_path):
    a = tmp_path / "a.x"
    plot3d.write(a, two_block_grid())
    before = a.read_bytes()
    rc, out, err = run_cli(capsys, "convert", a, a, "--big-endian")
    assert_one_line_error(rc, out, err, a, "refusing to overwrite the input file")
    assert a.read_bytes() == before
    assert run_cli(capsys, "convert", a, a, "--big-endian", "--force")[0] == 0
    assert plot3d.detect(a).endian == ">"
    assert [b.xyz.tobytes() for b in tfi_quat.read(a)] == [b.xyz.tobytes() for b in two_block_grid()]


def test_info_lists_the_other_variants_an_ambiguous_file_fits(capsys, tmp_path):
    # 2-D with 8-byte integers: float64 without IBLANK and float32 with IBLANK are the same size;
    # dyadic x and y = 0 read as either (float32 halves of x, IBLANK 0)
    p = tmp_path / "amb.x"
    xyz = np.zeros((5, 3, 1, 3), order="F")
    xyz[..., 0, 0] = np.arange(15.0).reshape(5, 3) / 4
    plot3d.write(p, Grid([xyz], 2), int_size=8, multiblock=False)
    rc, out, err = run_cli(capsys, "info", p)
    chosen = Plot3DFormat(ndim=2, int_size=8, multiblock=False)
    other = chosen.replace(precision=4, iblank=True)
    assert rc == 0 and err == ""
    lines = out.splitlines()
    assert lines[1] == f"  format      plot3d: {chosen.describe()}"
    assert lines[2] == (f"  also fits   plot3d: {other.describe()} "
                        "(read it so with --precision single --iblank)")
    rc, out, _ = run_cli(capsys, "info", p, "--json")
    s = json.loads(out)
    assert [Plot3DFormat(**a["variant"]) for a in s["also_fits"]] == [other]
    assert s["also_fits"][0]["options"] == "--precision single --iblank"
    # the options given read the other variant, and then nothing else fits
    rc, out, _ = run_cli(capsys, "info", p, "--json", *s["also_fits"][0]["options"].split())
    s = json.loads(out)
    assert Plot3DFormat(**s["variant"]) == other and "also_fits" not in s
    assert s["iblank"] is True
    assert s["bbox"]["max"][0] == plot3d.read(p, format=other)[0].xyz[..., 0].max()


def test_info_hint_options_select_each_alternative(capsys, tmp_path):
    # a one-point grid fits several variants; every hint must read exactly its variant
    p = tmp_path / "tiny.x"
    plot3d.write(p, Grid([annulus(1, 1)], 2))
    rc, out, _ = run_cli(capsys, "info", p, "--json")
    alts = json.loads(out)["also_fits"]
    assert rc == 0 and len(alts) >= 1
    for a in alts:
        rc, out, _ = run_cli(capsys, "info", p, "--json", *a["options"].split())
        assert rc == 0 and json.loads(out)["variant"] == a["variant"], a


def test_info_unambiguous_file_has_no_also_fits(capsys, h5grid, tmp_path):
    p, _ = h5grid
    rc, out, _ = run_cli(capsys, "info", p, "--json")
    assert rc == 0 and "also_fits" not in json.loads(out)
    q = tmp_path / "a.x"
    plot3d.write(q, two_block_grid())
    rc, out, _ = run_cli(capsys, "info", q)
    assert rc == 0 and "also fits" not in out


def test_info_leaves_out_variants_with_absurd_iblank(capsys, tmp_path):
    # one 2-D float64 block in a multi-block file fits, byte for byte, a single-block 3-D
    # float32 file with IBLANK and ni = 1; its "IBLANK" would be coordinate bytes
    p = tmp_path / "c.x"
    plot3d.write(p, Grid([annulus(9, 5)], 2))
    fits = plot3d.detect_all(p)
    # detection itself sees coordinate bytes where that IBLANK would be
    assert Plot3DFormat(precision=4, iblank=True, multiblock=False) not in fits
    rc, out, _ = run_cli(capsys, "info", p, "--json")
    assert rc == 0 and "also_fits" not in json.loads(out)
    # the same shape with small integers where that IBLANK would be is listed
    q = tmp_path / "d.x"
    xyz = np.zeros((1, 9, 5, 3), order="F")
    xyz[0, :, :, :2] = annulus(9, 5)[:, :, 0, :2]
    plot3d.write(q, Grid([Block(xyz, np.ones((1, 9, 5), np.int32))]), precision=4, iblank=True,
                 multiblock=False)
    rc, out, _ = run_cli(capsys, "info", q, "--json")
    s = json.loads(out)
    # the float32 coordinates read as float64 give themselves away: only the real variant fits
    assert Plot3DFormat(**s["variant"]) == Plot3DFormat(precision=4, iblank=True, multiblock=False)
    assert "also_fits" not in s

# ----------------------------------------------------------------------------- quality, plot

def _folded_grid(path):
    """A 2-D grid with one interior point pushed through its neighbours (negative cells)."""
    i, j = np.meshgrid(np.arange(5.0), np.arange(4.0), indexing="ij")
    xyz = np.zeros((5, 4, 1, 3), order="F")
    xyz[..., 0, 0], xyz[..., 0, 1] = i, j
    xyz[2, 1, 0, :2] = (3.6, 2.7)
    g = Grid([Block(xyz)], ndim=2)
    tfi_quat.write(path, g)
    return g


def test_quality_text_and_json(capsys):
    rc, out, err = run_cli(capsys, "quality", "grids/naca0012_c_257x65.x", "--case",
                           "grids/naca0012_c_257x65.toml", "--layers", "3")
    assert rc == 0 and err == ""
    assert "0 negative (area <= 0)" in out and "near-wall orthogonality, first 3 layers" in out
    assert "1:jmin:65-193,1-1" in out
    rc, out, _ = run_cli(capsys, "quality", "grids/two_block_65x33.x", "--ref", "grids/two_block_65x33.x",
                         "--walls", "1:jmin", "2:jmin", "--json")
    d = json.loads(out)
    assert rc == 0 and d["index_base"] == 1 and d["reference"] == "grids/two_block_65x33.x"
    assert [b["block"] for b in d["blocks"]] == [1, 2] and len(d["walls"]) == 2
    assert d["metrics"]["volume_ratio"]["min"] == 1.0 and d["orthogonality"]["change_max"] == 0.0


def test_quality_reports_negative_cells_1_based(capsys, tmp_path):
    from tfi_quat.quality import quality_report
    p = tmp_path / "folded.x"
    g = _folded_grid(p)
    rep = quality_report(g)
    assert rep.negative > 0
    rc, out, _ = run_cli(capsys, "quality", p)
    assert rc == 0 and f"{rep.negative} negative" in out
    b, i, j, k = rep.negative_cells[0]
    assert f"block {b + 1} ({i + 1}, {j + 1})" in out
    rc, out, _ = run_cli(capsys, "quality", p, "--json", "--fail-on-negative")
    assert rc == 1 and json.loads(out)["negative_cells"][0] == [b + 1, i + 1, j + 1, k + 1]
    rc, _, _ = run_cli(capsys, "quality", "grids/channel_bump_129x49.x", "--fail-on-negative")
    assert rc == 0


def test_quality_bad_input_is_one_line(capsys, tmp_path):
    assert_one_line_error(*run_cli(capsys, "quality", tmp_path / "missing.x"), "missing.x")
    rc, out, err = run_cli(capsys, "quality", "grids/naca0012_c_257x65.x", "--ref", "grids/cylinder_o_129x65.x")
    assert_one_line_error(rc, out, err, "cylinder_o_129x65.x", "dimensions")
    assert_one_line_error(*run_cli(capsys, "quality", "grids/naca0012_c_257x65.x", "--walls", "2:jmin"),
                          "--walls", "1 block")
    assert_one_line_error(*run_cli(capsys, "quality", "grids/naca0012_c_257x65.x", "--walls", "1:jmid"),
                          "--walls", "jmid")
    assert_one_line_error(*run_cli(capsys, "quality", "grids/naca0012_c_257x65.x", "--walls", "1:jmin",
                                   "--layers", "0"), "--layers")


def _png_size(path):
    with open(path, "rb") as fh:
        data = fh.read(24)
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return tuple(int.from_bytes(data[n:n + 4], "big") for n in (16, 20))


def test_plot_2d_and_3d(capsys, tmp_path):
    out = tmp_path / "c.png"
    rc, text, err = run_cli(capsys, "plot", "grids/naca0012_c_257x65.x", "--case", "grids/naca0012_c_257x65.toml",
                            "--zoom", "le", "--zoom", "0.9,1.1,-0.05,0.05", "--color", "skewness",
                            "--size", "1000x450", "-o", out)
    assert rc == 0 and err == "" and "1000 x 450 pixels" in text
    assert _png_size(out) == (1000, 450)
    out3 = tmp_path / "wing.png"
    rc, text, _ = run_cli(capsys, "plot", "--case", "grids/wing_ch_501k.toml", "--cut", "1:k=10",
                          "--cut", "3:j=2", "-o", out3, "--dpi", "60")
    assert rc == 0 and _png_size(out3)[0] > 300
    # an existing figure is kept without --force
    assert_one_line_error(*run_cli(capsys, "plot", "grids/naca0012_c_257x65.x", "-o", out), "exists", "--force")
    rc, _, _ = run_cli(capsys, "plot", "grids/naca0012_c_257x65.x", "-o", out, "--force", "--size", "400x300")
    assert rc == 0 and _png_size(out) == (400, 300)


def test_plot_bad_input_is_one_line(capsys, tmp_path):
    out = tmp_path / "f.png"
    assert_one_line_error(*run_cli(capsys, "plot", "grids/naca0012_c_257x65.x", "--color", "volume_ratio",
                                   "-o", out), "needs a reference", "--ref")
    assert_one_line_error(*run_cli(capsys, "plot", "grids/naca0012_c_257x65.x", "--zoom", "te", "-o", out),
                          "needs wall patches")
    assert_one_line_error(*run_cli(capsys, "plot", "grids/wing_ch_501k.x", "--cut", "9:k=1", "-o", out),
                          "wing_ch_501k.x", "4 block(s)")
    assert_one_line_error(*run_cli(capsys, "plot", tmp_path / "nope.x", "-o", out), "nope.x")
    assert not out.exists()
    with pytest.raises(SystemExit) as exc:            # argparse: a bad window is a usage error
        main(["plot", "grids/naca0012_c_257x65.x", "--zoom", "1,2,3", "-o", str(out)])
    assert exc.value.code == 2
    capsys.readouterr()
