"""The coupling interface of the Deformer: the wall in the solver's terms."""

from __future__ import annotations

import numpy as np
import pytest

from tfi_quat.deform import Deformer
from tfi_quat.grid import face_axes

import _deform_grids as G

CASES = {
    "o-grid": G.o_grid,
    "two-block": G.two_block_o,
    "o-grid-3d": G.o_grid_3d,
    "box-pair": G.box_pair,
}


@pytest.fixture(scope="module", params=sorted(CASES))
def deformer(request):
    grid, walls, sym, fixed = CASES[request.param]()
    return Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)


def test_surface_ids_list_every_wall_copy_patch_by_patch_in_fortran_order(deformer):
    ids = deformer.surface_ids()
    grid = deformer.grid
    assert ids.dtype == np.int64 and ids.shape[1] == 4
    walls = [p for p in deformer.connectivity.patches if p.kind == "wall"]
    row = 0
    for p in walls:
        spec = p.spec.resolve(grid)
        (a0, a1), (b0, b1) = spec.range
        d, a, b = face_axes(spec.face)
        n = (a1 - a0 + 1) * (b1 - b0 + 1)
        part = ids[row:row + n]
        assert np.all(part[:, 0] == spec.block)
        dims = grid[spec.block].dims
        assert np.all(part[:, 1 + d] == (0 if spec.face.endswith("min") else dims[d] - 1))
        # the first running index fastest
        want_a = np.tile(np.arange(a0, a1 + 1), b1 - b0 + 1)
        want_b = np.repeat(np.arange(b0, b1 + 1), a1 - a0 + 1)
        assert np.array_equal(part[:, 1 + a], want_a)
        assert np.array_equal(part[:, 1 + b], want_b)
        row += n
    assert row == ids.shape[0]
    if grid.ndim == 2:
        assert np.all(ids[:, 3] == 0)


def test_surface_points_are_the_grid_points_and_cover_every_wall_point(deformer):
    ids = deformer.surface_ids()
    pts = deformer.surface_points()
    for r, (b, i, j, k) in enumerate(ids):
        assert np.array_equal(pts[r], deformer.grid[b].xyz[i, j, k])
    distinct = np.unique(deformer.wall_points(), axis=0)
    assert np.array_equal(np.unique(pts, axis=0), distinct)


def test_surface_ids_are_a_copy():
    grid, walls, sym, fixed = G.o_grid()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)
    ids = d.surface_ids()
    ids[:] = -1
    assert np.all(d.surface_ids() >= 0)


# ------------------------------------------------------------ surface files and modal motion
import h5py  # noqa: E402

import tfi_quat as tq  # noqa: E402
from tfi_quat.errors import DeformationError, GridFormatError, OverwriteError  # noqa: E402
from tfi_quat.io.surface import read_surface, write_surface  # noqa: E402


def _shapes(d):
    """Two mode shapes as a structural model would compute them on surface_points(): a
    bend and a twist, equal on the copies of a point (computed from the merged point)."""
    ids = d.surface_ids()
    pts = d.surface_points()
    # the copies of a point may differ by round-off: compute on the distinct points
    _, inv = np.unique(np.round(pts, 9), axis=0, return_inverse=True)
    first = np.zeros(inv.max() + 1, dtype=np.int64)
    first[inv[::-1]] = np.arange(len(inv))[::-1]
    p = pts[first[inv.ravel()]]
    c = p.mean(axis=0)
    bend = np.zeros_like(p)
    bend[:, 1] = 0.02 * (p[:, 0] - c[0]) ** 2
    twist = np.zeros_like(p)
    twist[:, 0] = -(p[:, 1] - c[1]) * 0.05
    twist[:, 1] = (p[:, 0] - c[0]) * 0.05
    if d.ndim == 3:
        bend[:, 2] = 0.01 * (p[:, 0] - c[0])
    assert ids.shape[0] == p.shape[0]
    return np.stack([bend, twist])


def _grids_equal(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert np.array_equal(x.xyz, y.xyz)


def test_modal_motion_is_the_callable_form_of_the_summed_shapes(deformer, tmp_path):
    d = deformer
    shapes = _shapes(d)
    motion = d.modal(shapes)
    a = np.array([0.7, -1.3])
    # the distinct wall points in wall_points() order, moved by the same sums
    disp = motion.displacements(a)
    assert disp.shape == d.surface_points().shape
    assert np.allclose(disp, np.tensordot(a, shapes, axes=1), rtol=0, atol=1e-15)
    wall_disp = motion.wall_displacements(a)
    want = d.deform(lambda p: p + wall_disp)
    _grids_equal(motion(a), want)
    # the walls of the result are the undeformed surface plus the displacement
    ids = d.surface_ids()
    got = motion(a)
    moved = np.array([got[b].xyz[i, j, k] for b, i, j, k in ids])
    assert np.allclose(moved, d.surface_points() + disp, rtol=0, atol=1e-12)
    # linear in the surface
    b = np.array([-0.2, 0.4])
    assert np.allclose(motion.displacements(a + b), motion.displacements(a) + motion.displacements(b),
                       rtol=0, atol=1e-15)
    # zero amplitudes: the reference grid
    _grids_equal(motion([0.0, 0.0]), d.deform(lambda p: p))


def test_write_surface_round_trip_and_modal_from_the_file(deformer, tmp_path):
    d = deformer
    shapes = _shapes(d)
    path = tmp_path / "MODES.h5"
    d.write_surface(path, shapes, names=["bend", "twist"])
    f = read_surface(path)
    assert f.ids.dtype == np.int64 and np.array_equal(f.ids, d.surface_ids())
    assert f.points.dtype == np.float64 and np.array_equal(f.points, d.surface_points())
    assert np.array_equal(f.modes, shapes) and f.names == ("bend", "twist") and f.ndim == d.ndim
    with h5py.File(path, "r") as h:
        assert h.attrs["format"] == b"tfi_quat-surface" and int(h.attrs["version"]) == 1
        assert h["modes"].shape == (2,) + d.surface_points().shape
    motion = d.modal(path)
    assert motion.names == ("bend", "twist") and motion.source == str(path)
    a = [0.5, 0.25]
    _grids_equal(motion(a), d.modal(shapes)(a))
    # the template: ids and points, no modes, no names
    tmpl = tmp_path / "SURF.h5"
    d.write_surface(tmpl)
    t = read_surface(tmpl)
    assert t.modes.shape == (0,) + d.surface_points().shape and t.names == ()
    with pytest.raises(DeformationError, match=r"SURF\.h5: no mode shapes"):
        d.modal(tmpl)


def test_a_permuted_file_is_matched_by_its_ids(tmp_path):
    grid, walls, sym, fixed = G.two_block_o()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)
    shapes = _shapes(d)
    perm = np.random.default_rng(3).permutation(d.surface_ids().shape[0])
    path = tmp_path / "perm.h5"
    write_surface(path, d.surface_ids()[perm], d.surface_points()[perm], shapes[:, perm],
                  ndim=d.ndim)
    a = [1.0, -0.5]
    motion = d.modal(path)
    assert np.array_equal(motion.shapes, shapes)
    _grids_equal(motion(a), d.modal(shapes)(a))


def _write_raw(path, ids, points, modes, **attrs):
    with h5py.File(path, "w") as f:
        f.attrs["format"] = attrs.get("format", "tfi_quat-surface")
        f.attrs["version"] = attrs.get("version", 1)
        f.attrs["ndim"] = attrs.get("ndim", 2)
        f["ids"] = ids
        f["points"] = points
        f["modes"] = modes


def test_bad_surface_files_are_named_errors(tmp_path):
    grid, walls, sym, fixed = G.two_block_o()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)
    ids, pts, shapes = d.surface_ids(), d.surface_points(), _shapes(d)
    n = ids.shape[0]
    path = tmp_path / "bad.h5"

    def err(kind, match, **changes):
        arrays = dict(ids=ids, points=pts, modes=shapes)
        attrs = {k: changes.pop(k) for k in ("format", "version", "ndim") if k in changes}
        arrays.update(changes)
        _write_raw(path, **arrays, **attrs)
        with pytest.raises(kind, match=match) as e:
            d.modal(path)
        assert str(path) in str(e.value)

    # an interior point instead of a wall point copy
    wrong = ids.copy()
    wrong[5, 2] += 3
    err(DeformationError, r"ids do not match the grid's wall: 1 wall point copies are missing, e\.g\. "
        r"\(block, i, j, k\) = \(\d+, \d+, \d+, 0\).*row 5 .* is not a wall point copy", ids=wrong)
    dup = ids.copy()
    dup[7] = dup[3]
    err(DeformationError, r"ids rows 3 and 7 both list", ids=dup)
    out = ids.copy()
    out[2, 1] = 10_000
    err(DeformationError, r"row 2 .* lies outside block", ids=out)
    err(GridFormatError, rf"/ids: {n - 1} rows, expected {n}", ids=ids[:-1], points=pts[:-1],
        modes=shapes[:, :-1])
    err(GridFormatError, r"dataset /ids: dtype float64, expected integers", ids=ids.astype(float))
    err(GridFormatError, r"dataset /points: shape .*expected \(\d+, 3\)", points=pts[:, :2])
    err(GridFormatError, r"dataset /modes: shape \(\d+, 3\), expected \(n_modes", modes=shapes[0])
    nan = shapes.copy()
    nan[1, 9, 0] = np.nan
    err(GridFormatError, r"dataset /modes: 1 non-finite value\(s\); first at mode 2, row 9 "
        r"\(block, i, j, k\) = .*component x", modes=nan)
    inf = pts.copy()
    inf[4, 1] = np.inf
    err(GridFormatError, r"dataset /points: 1 non-finite .*row 4 .*component y", points=inf)
    err(DeformationError, r"dataset /points: row \d+ .* from the grid's point", points=pts * 1.01)
    err(GridFormatError, r"root attribute format = 'tfi_quat-grid'", format="tfi_quat-grid")
    err(GridFormatError, r"layout version 2 is not supported", version=2)
    err(DeformationError, r"written for a 3-D grid", ndim=3)
    # a chunked dataset with a chunk never written (HDF5 would read zeros)
    with h5py.File(path, "w") as f:
        f.attrs["format"], f.attrs["version"], f.attrs["ndim"] = "tfi_quat-surface", 1, 2
        f["ids"], f["points"] = ids, pts
        m = f.create_dataset("modes", shape=shapes.shape, dtype="f8", chunks=(1, 16, 3))
        m[0] = shapes[0]
    with pytest.raises(GridFormatError, match=r"dataset /modes: only \d+ of \d+ chunks are stored"):
        d.modal(path)
    # a declared size that cannot be held: refused before anything is allocated
    with h5py.File(path, "w") as f:
        f.attrs["format"], f.attrs["version"], f.attrs["ndim"] = "tfi_quat-surface", 1, 2
        f["ids"], f["points"] = ids, pts
        f.create_dataset("modes", shape=(10**9, n, 3), dtype="f8", chunks=(1, n, 3))
    assert path.stat().st_size < 1 << 20
    with pytest.raises(GridFormatError, match=r"dataset /modes: declares [\d,]+ points"):
        d.modal(path)
    # copies of one point moving apart
    loc = {tuple(np.round(p, 9)): r for r, p in enumerate(pts)}
    twin = next(r for r, p in enumerate(pts) if loc[tuple(np.round(p, 9))] != r)
    apart = shapes.copy()
    apart[0, twin, 1] += 1e-3
    err(DeformationError, r"are copies of one wall point, and their mode shapes differ by 0\.001",
        modes=apart)
    # not a surface file at all
    other = tmp_path / "grid.h5"
    tq.write(other, grid)
    with pytest.raises(GridFormatError, match=r"grid\.h5: root attribute format = 'tfi_quat-grid'"):
        d.modal(other)
    text = tmp_path / "modes.txt"
    text.write_text("1 2 3\n")
    with pytest.raises(GridFormatError, match=r"modes\.txt: not an HDF5 file"):
        d.modal(text)
    with pytest.raises(FileNotFoundError):
        d.modal(tmp_path / "missing.h5")


def test_bad_mode_arrays_and_amplitudes():
    grid, walls, sym, fixed = G.box_pair()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)
    shapes = _shapes(d)
    with pytest.raises(DeformationError, match=r"modes must have shape \(n_modes, \d+, 3\)"):
        d.modal(shapes[:, :-1])
    nan = shapes.copy()
    nan[0, 2, 2] = np.nan
    with pytest.raises(DeformationError, match=r"modes: 1 non-finite value\(s\); first in mode 1 at "
                                               r"row 2 .*component z"):
        d.modal(nan)
    with pytest.raises(DeformationError, match="real numbers"):
        d.modal(np.full(shapes.shape, "x"))
    motion = d.modal(shapes)
    assert motion.n_modes == 2 and motion.names == ("mode 1", "mode 2")
    for bad, match in (([1.0], r"2 amplitude\(s\) expected, one per mode \(mode 1, mode 2\), got "
                                r"shape \(1,\)"),
                       ([1.0, 2.0, 3.0], "got shape"),
                       ([[1.0, 2.0]], "got shape"),
                       ([1.0, np.nan], "must be finite"),
                       (["a", "b"], "real numbers")):
        with pytest.raises(DeformationError, match=match):
            motion(bad)
    # a single mode given as (n, 3)
    one = d.modal(shapes[0])
    _grids_equal(one(0.5), motion([0.5, 0.0]))


def test_2d_mode_shapes_need_z_zero():
    grid, walls, sym, fixed = G.o_grid()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)
    shapes = _shapes(d)
    assert np.all(shapes[..., 2] == 0.0)
    d.modal(shapes)
    shapes[1, 3, 2] = 1e-3
    with pytest.raises(DeformationError, match="2-D grid must have z = 0"):
        d.modal(shapes)


def test_write_surface_refuses_bad_input_and_keeps_the_grid_file(tmp_path):
    grid, walls, sym, fixed = G.o_grid()
    src = tmp_path / "grid.x"
    tq.write(src, grid)
    d = Deformer(tq.read(src), walls=walls, symmetry=sym, fixed=fixed)
    shapes = _shapes(d)
    with pytest.raises(OverwriteError):
        d.write_surface(src, shapes)
    with pytest.raises(tq.GridValueError, match=r"modes must have shape"):
        d.write_surface(tmp_path / "m.h5", shapes[:, 1:])
    with pytest.raises(tq.GridValueError, match="names must be 2 strings"):
        d.write_surface(tmp_path / "m.h5", shapes, names=["one"])
    with pytest.raises(tq.GridValueError, match="non-finite"):
        d.write_surface(tmp_path / "m.h5", np.where(shapes > 0, np.inf, shapes))
    assert not (tmp_path / "m.h5").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["grid.x"]      # no temporary left


# ------------------------------------------------------------ tfi-quat deform --modes
def test_cli_modes_and_write_surface(tmp_path, capsys):
    from tfi_quat.cli import main
    grid, walls, sym, fixed = G.two_block_o()
    src = tmp_path / "grid.x"
    tq.write(src, grid)
    spec = [a for w in walls for a in ("--wall", w)] + [a for w in fixed for a in ("--fixed", w)]
    surf = tmp_path / "SURF.h5"
    rc = main(["deform", str(src), *spec, "--write-surface", str(surf)])
    out, err = capsys.readouterr()
    assert rc == 0, err
    assert out.startswith(f"wrote {surf}: ") and "no modes" in out
    ref = tq.read(src)
    d = Deformer(ref, walls=walls, fixed=fixed)
    t = read_surface(surf)
    assert np.array_equal(t.ids, d.surface_ids()) and t.n_modes == 0
    # fill the template as a user would, with h5py
    shapes = _shapes(d)
    modes = tmp_path / "MODES.h5"
    import shutil
    shutil.copy(surf, modes)
    with h5py.File(modes, "r+") as f:
        del f["modes"]
        f["modes"] = shapes
    moved = tmp_path / "moved.x"
    rc = main(["deform", str(src), *spec, "--modes", str(modes), "--amplitudes", "0.5,-1", "-o",
               str(moved)])
    out, err = capsys.readouterr()
    assert rc == 0, err
    assert f"walls moved by the modes of {modes}, amplitudes 0.5, -1" in out
    _grids_equal(tq.read(moved), d.modal(shapes)([0.5, -1.0]))

    def fails(*argv, match):
        rc = main(["deform", str(src), *spec, *argv])
        _, err = capsys.readouterr()
        assert rc == 2, err
        assert err.count("\n") == 1 and match in err, err

    o = ["-o", str(tmp_path / "x.x")]
    fails("--modes", str(modes), "--amplitudes", "1", *o,
          match=f"error: {modes}: 2 mode(s), but 1 amplitude(s) given")
    fails("--modes", str(modes), *o, match=f"--modes {modes}: give the amplitudes")
    fails("--amplitudes", "1,2", *o, match="--amplitudes goes with --modes")
    fails("--modes", str(modes), "--amplitudes", "1,2", "--rotate", "3", *o,
          match="give either --modes or --moved")
    with pytest.raises(SystemExit) as e:       # argparse's usage error, status 2
        main(["deform", str(src), *spec, "--modes", str(modes), "--amplitudes", "1,nan", *o])
    assert e.value.code == 2 and "expected finite numbers A1,A2,..." in capsys.readouterr().err
    fails("--modes", str(src), "--amplitudes", "1", *o, match=f"{src}: not an HDF5 file")
    fails("--modes", str(tmp_path / "none.h5"), "--amplitudes", "1", *o,
          match=f"{tmp_path / 'none.h5'}: No such file")
    fails("--write-surface", str(surf), match=f"{surf}: exists; refusing to overwrite it")
    fails("--write-surface", str(tmp_path / "s2.h5"), *o, match="--write-surface writes the walls only")
    fails("--write-surface", str(tmp_path / "s2.h5"), "--amplitudes", "1",
          match="--write-surface writes the walls only")
