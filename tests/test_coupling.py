"""The coupling interface of the Deformer: the wall in the solver's terms."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import tfi_quat as tq
from tfi_quat.deform import Deformer, rigid_motion
from tfi_quat.errors import DeformationError, GridFormatError, OverwriteError
from tfi_quat.grid import face_axes
from tfi_quat.io.surface import read_surface, write_surface

import _deform_grids as G
from _cells import corner_dets

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


# ------------------------------------------------------------------ deform(xs, ids=...)


ALL_CASES = dict(CASES, channel=G.channel)


def _motion(deformer):
    """A rotation, a translation and a bend: every wall point moves differently."""
    c = deformer.wall_points().mean(axis=0)
    rot = rigid_motion(4.0, about=c, translate=(0.02, -0.01, 0.0))
    three = deformer.ndim == 3

    def move(p):
        q = rot(p)
        q[:, 1] += 0.01 * np.sin(p[:, 0])
        if three:
            q[:, 2] += 0.005 * p[:, 0]
        return q
    return move


def _same(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert np.array_equal(x.xyz, y.xyz)


@pytest.fixture(scope="module", params=sorted(ALL_CASES))
def any_deformer(request):
    grid, walls, sym, fixed = ALL_CASES[request.param]()
    return Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)


def test_array_form_is_bit_identical_to_the_callable_form(any_deformer):
    d = any_deformer
    move = _motion(d)
    want = d.deform(move)
    xs = move(d.surface_points())
    _same(d.deform(xs), want)
    _same(d.deform(xs - d.surface_points(), displacement=True), d.deform(lambda p: p + (move(p) - p)))
    ids = d.surface_ids()
    _same(d.deform(xs, ids=ids), want)


@settings(max_examples=15, deadline=None)
@given(data=st.data())
def test_ids_in_any_order_with_any_duplicates(data):
    name = data.draw(st.sampled_from(sorted(ALL_CASES)))
    d = _DEFORMERS.setdefault(name, Deformer(*_args(name)))
    move = _motion(d)
    want = d.deform(move)
    ids = d.surface_ids()
    xs = move(d.surface_points())
    n = ids.shape[0]
    perm = np.array(data.draw(st.permutations(range(n))))
    extra = np.array(data.draw(st.lists(st.integers(0, n - 1), max_size=20)), dtype=np.int64)
    rows = np.concatenate([perm, extra])
    _same(d.deform(xs[rows], ids=ids[rows]), want)
    # one copy of each distinct point is enough
    _, first = np.unique(np.round(xs, 12), axis=0, return_index=True)
    _same(d.deform(xs[first], ids=ids[first]), want)


_DEFORMERS: dict = {}


def _args(name):
    grid, walls, sym, fixed = ALL_CASES[name]()
    return (grid, walls, sym, fixed)


def test_disagreeing_copies_are_named_with_their_difference():
    grid, walls, sym, fixed = G.two_block_o()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)
    ids = d.surface_ids()
    xs = d.surface_points()
    # the points listed twice: the two blocks' copies of the wall's interface points
    keys = [tuple(np.round(p, 12)) for p in xs]
    dup = [r for r in range(len(keys)) if keys.index(keys[r]) != r]
    assert dup
    r = dup[0]
    a = keys.index(keys[r])
    xs[r, 1] += 1e-6
    with pytest.raises(DeformationError) as e:
        d.deform(xs)
    msg = str(e.value)
    assert f"rows {a} and {r}" in msg and "1e-06" in msg and "0-based" in msg
    assert f"({ids[a, 0]}, {ids[a, 1]}, {ids[a, 2]}, {ids[a, 3]})" in msg
    assert f"({ids[r, 0]}, {ids[r, 1]}, {ids[r, 2]}, {ids[r, 3]})" in msg
    # within dup_tol: accepted, the first copy wins
    loose = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed, dup_tol=2e-6)
    xs2 = xs.copy()
    xs2[r] = xs2[a]
    _same(loose.deform(xs), loose.deform(xs2))


def test_bad_ids_and_arrays_are_clear_errors():
    grid, walls, sym, fixed = G.box_pair()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)
    ids = d.surface_ids()
    xs = d.surface_points()

    def err(match, *a, **kw):
        with pytest.raises(DeformationError, match=match):
            d.deform(*a, **kw)
    err(r"shape \(n, 3\)", xs[:, :2])
    err("one row per wall point copy", xs[:-1])
    err(r"ids must have shape \(m, 4\)", xs, ids=ids[:, :3])
    err("ids has", xs, ids=ids[:-1])
    err("integers", xs, ids=ids.astype(float))
    bad = ids.copy()
    bad[5, 0] = 2
    err("ids row 5: block 2 out of range", xs, ids=bad)
    bad = ids.copy()
    bad[3, 1] = 99
    err(r"ids row 3: \(block, i, j, k\) = \(\d, 99, .*outside", xs, ids=bad)
    bad = ids.copy()
    bad[7, 1:] = 3                      # an interior point
    err(r"ids row 7: .* is not a wall point", xs, ids=bad)
    err(r"(\d+) wall point\(s\) have no row in xs, e\.g\. \(block, i, j, k\)", xs[:10], ids=ids[:10])
    nan = xs.copy()
    nan[4, 2] = np.nan
    err("xs row 4 .* not finite", nan)
    err("ids= and displacement= go with an array", _motion(d), ids=ids)
    err("ids= and displacement= go with an array", _motion(d), displacement=True)
    with pytest.raises(Exception, match="dup_tol"):
        Deformer(grid, walls=walls, dup_tol=-1.0)


def test_2d_wall_rows_need_z_zero():
    grid, walls, sym, fixed = G.o_grid()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)
    xs = d.surface_points()
    xs[:, 2] = 0.1
    with pytest.raises(DeformationError, match="z = 0"):
        d.deform(xs)


# ------------------------------------------------------------------ out=
def _layouts(d):
    """Every out layout: a Grid, Fortran and C arrays, separate x, y, z (both orders),
    a strided view."""
    strided = [np.zeros(b.dims[::-1] + (3,)).transpose(2, 1, 0, 3) for b in d.grid]
    return {"grid": d.new_grid(), "F": [b.xyz for b in d.new_grid()],
            "C": d.new_grid("C"), "xyz-F": d.new_grid("F", separate=True),
            "xyz-C": d.new_grid("C", separate=True), "strided": strided}


def _as_blocks(out):
    if hasattr(out, "blocks"):
        return [b.xyz for b in out]
    return [np.stack(o, axis=-1) if isinstance(o, tuple) else o for o in out]


def test_out_in_every_layout_gives_the_same_bits(any_deformer):
    d = any_deformer
    move = _motion(d)
    want = d.deform(move)
    xs = move(d.surface_points())
    for name, out in _layouts(d).items():
        got = d.deform(xs, out=out)
        for b, (a, w) in enumerate(zip(_as_blocks(out), want)):
            assert np.array_equal(a, w.xyz), (name, b)
        if name == "grid":
            assert got is out
        elif name == "F":
            assert all(np.shares_memory(g.xyz, a) for g, a in zip(got, out))
            assert got.connectivity is d.grid.connectivity and got.ndim == d.ndim
        else:
            assert got is None
    # the other forms into out too; the reference untouched
    ref = d.grid.copy()
    out = d.new_grid("C")
    d.deform(move, out=out)
    assert all(np.array_equal(a, w.xyz) for a, w in zip(out, want))
    assert d.grid == ref


def test_new_grid_buffers_hold_the_reference():
    grid, walls, sym, fixed = G.box_pair()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)
    g = d.new_grid()
    assert g == d.grid and not np.shares_memory(g[0].xyz, d.grid[0].xyz)
    c = d.new_grid("C")
    assert c[1].flags.c_contiguous and np.array_equal(c[1], grid[1].xyz)
    x, y, z = d.new_grid("F", separate=True)[1]
    assert x.flags.f_contiguous and x.shape == grid[1].dims and np.array_equal(z, grid[1].xyz[..., 2])
    with pytest.raises(Exception, match="order"):
        d.new_grid("K")


def test_bad_out_is_a_clear_error_and_nothing_is_written():
    grid, walls, sym, fixed = G.box_pair()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)
    xs = d.surface_points() + 0.01

    def parts(out):
        if not isinstance(out, list):
            return []
        return [p for o in out for p in (o if isinstance(o, tuple) else (o,))
                if isinstance(p, np.ndarray)]

    def err(match, out):
        keep = [a.copy() for a in parts(out)]
        with pytest.raises(DeformationError, match=match):
            d.deform(xs, out=out)
        for a, k in zip(parts(out), keep):
            assert np.array_equal(a, k)
    good = d.new_grid("C")
    err("out has 1 entries, the grid 2 blocks", good[:1])
    err(r"out\[1\]: shape", [good[0], good[1][:, :-1]])
    err(r"out\[0\]: dtype float32", [good[0].astype(np.float32), good[1]])
    ro = good[1].copy()
    ro.flags.writeable = False
    err(r"out\[1\]: the array is read-only", [good[0], ro])
    sep = d.new_grid("F", separate=True)
    err(r"out\[1\] \(x, y, z\): shape", [sep[0], (sep[1][0], sep[1][1], sep[1][2][:-1])])
    err(r"out\[0\]: expected an array", [3, good[1]])
    err("reference grid", d.grid)
    err(r"out\[0\]: shares memory with the reference", [grid[0].xyz, good[1]])
    err("out must be a Grid or a list", good[0])


def _box_with_small_wall(n=81):
    """One n^3 block; the wall: the middle quarter of jmin (its faces: fixed)."""
    s = np.linspace(0.0, 1.0, n)
    xyz = np.stack(np.meshgrid(s, s ** 1.3, s, indexing="ij"), -1)
    from tfi_quat import Block, Grid
    lo, hi = 3 * n // 8, 5 * n // 8
    return Grid([Block(np.asfortranarray(xyz))]), [f"1:jmin:{lo}-{hi},{lo}-{hi}"]


@pytest.mark.parametrize("method", ["two-level", "samareh"])
def test_a_step_into_out_allocates_nothing_grid_sized(method):
    import tracemalloc
    grid, walls = _box_with_small_wall()
    d = Deformer(grid, walls=walls, method=method)
    xs = d.surface_points()
    xs[:, 1] += 0.01 * np.sin(3.0 * xs[:, 0])
    nbytes = sum(b.xyz.nbytes for b in grid)
    for out in (d.new_grid(), d.new_grid("C"), d.new_grid("F", separate=True)):
        for check in (False, True, "raise"):
            d.deform(xs, out=out, check=check)          # compiled, scratch made
            tracemalloc.start()
            try:
                d.deform(xs, out=out, check=check)
                peak = tracemalloc.get_traced_memory()[1]
            finally:
                tracemalloc.stop()
            assert peak < 0.05 * nbytes, (type(out), check, peak / nbytes)
    # without out, a step makes its grid
    tracemalloc.start()
    try:
        d.deform(xs)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak >= nbytes


# ------------------------------------------------------------------ check=

def _cell_ratio(grid, ref, b, i, j, k):
    cell = (i, j) if grid.ndim == 2 else (i, j, k)
    jr = corner_dets(ref[b].xyz)[cell]
    return np.where(jr != 0.0, corner_dets(grid[b].xyz)[cell] / jr, np.inf).min()


def _oracle(grid, ref):
    """(min ratio, negative-Jacobian cells) in numpy."""
    lo, nj = np.inf, 0
    for b, r in zip(grid, ref):
        jd, jr = corner_dets(b.xyz), corner_dets(r.xyz)
        with np.errstate(divide="ignore", invalid="ignore"):
            q = np.where(jr != 0.0, jd / jr, np.inf).min(axis=-1)
        lo = min(lo, q.min())
        nj += int((q <= 0.0).sum())
    return lo, nj


def _fold(d, angle):
    c = d.wall_points().mean(axis=0)
    return rigid_motion(angle, about=c, axis=(0.0, 0.0, 1.0) if d.ndim == 2 else (1.0, 0.3, 0.2))


@pytest.mark.parametrize("angle", [5.0, 120.0])
def test_check_agrees_with_negative_cells_and_a_numpy_jacobian(any_deformer, angle):
    from tfi_quat.quality import CellCheck, negative_cells
    d = any_deformer
    move = _fold(d, angle)
    g = d.deform(move, check=True)
    rep = g.quality
    assert isinstance(rep, CellCheck) and d.quality is rep
    assert rep.negative == sum(len(c) for _, c in negative_cells(g, d.grid))
    lo, nj = _oracle(g, d.grid)
    assert rep.min_ratio == pytest.approx(lo, rel=1e-9, abs=1e-12)
    assert rep.negative_jacobian == nj
    assert rep.ok == (rep.negative == 0 and nj == 0)
    assert _cell_ratio(g, d.grid, *rep.min_at) == pytest.approx(rep.min_ratio, rel=1e-9, abs=1e-12)
    neg = {(b, *map(int, c)) for b, cc in negative_cells(g, d.grid) for c in cc}
    if d.ndim == 2:
        neg = {t + (0,) for t in neg}
    for cell in rep.first:
        assert _cell_ratio(g, d.grid, *cell) <= 0.0 or cell in neg
    # a check changes nothing in the grid
    _same(g, d.deform(move))
    assert d.deform(move).quality is None and d.quality is None


def test_a_small_motion_checks_valid_and_no_motion_to_ratio_one():
    grid, walls, sym, fixed = G.box_pair()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)
    rep = d.deform(lambda p: p + [0.0, 0.01, 0.0], check=True).quality
    assert rep.ok and rep.negative == 0 and rep.first == () and 0.5 < rep.min_ratio < 1.0
    rep = d.deform(lambda p: p, check=True).quality
    assert rep.ok and rep.min_ratio == 1.0


def test_check_raise_names_the_cells_and_leaves_the_buffers_alone():
    grid, walls, sym, fixed = G.o_grid()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)
    move = _fold(d, 150.0)
    rep = d.deform(move, check=True).quality
    assert not rep.ok and rep.first
    for out in _layouts(d).values():
        before = [a.copy() for a in _as_blocks(out)]
        with pytest.raises(DeformationError, match=r"invalid cells.*first: \(0, \d+, \d+, 0\)"):
            d.deform(move, out=out, check="raise")
        for a, k in zip(_as_blocks(out), before):
            assert np.array_equal(a, k)
    with pytest.raises(DeformationError, match="invalid cells"):
        d.deform(move, check="raise")
    # a valid step into the same buffers passes and fills them
    ok = _motion(d)
    want = d.deform(ok)
    for out in _layouts(d).values():
        d.deform(ok, out=out, check="raise")
        assert all(np.array_equal(a, w.xyz) for a, w in zip(_as_blocks(out), want))
    with pytest.raises(DeformationError, match="check must be"):
        d.deform(ok, check="yes")


def test_checks_overlapped_on_a_second_thread_report_what_serial_checks_report(monkeypatch):
    """With two threads, small blocks are checked on a second thread while the next block
    is made: the reports (the merged one and every field) and the grids are those of one
    thread, for every buffer layout and check="raise"; a failing check still fails the step."""
    grid, walls, sym, fixed = G.box_pair()
    one = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed, threads=1)
    two = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed, threads=2)
    submitted = []
    real = two._checker

    def spy():
        ex = real()
        submitted.append(ex)
        return ex
    monkeypatch.setattr(two, "_checker", spy)
    for angle in (5.0, 150.0):
        move = _fold(one, angle)
        want = one.deform(move, check=True)
        got = two.deform(move, check=True)
        _same(want, got)
        assert got.quality == want.quality and two.quality == one.quality
        for out in _layouts(two).values():
            if angle > 90.0:
                with pytest.raises(DeformationError, match="invalid cells"):
                    two.deform(move, out=out, check="raise")
            else:
                two.deform(move, out=out, check="raise")
                assert two.quality == want.quality
    assert len(submitted) >= 2 * len(grid)          # the overlapped path ran

    def broken(*a, **k):
        raise RuntimeError("check failed on the second thread")
    monkeypatch.setattr("tfi_quat.deform.deformer.check_block", broken)
    with pytest.raises(RuntimeError, match="second thread"):
        two.deform(_fold(one, 5.0), check=True)


# ------------------------------------------------------------------ threads=, velocity
def test_threads_apply_inside_the_deformers_calls_only(monkeypatch):
    from tfi_quat import _jit
    seen = []
    real = _jit.use_threads

    def spy(n):
        seen.append(n)
        return real(n)
    monkeypatch.setattr("tfi_quat.deform.deformer.use_threads", spy)
    grid, walls, sym, fixed = G.o_grid()
    before = _jit.threads()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed, threads=1)
    assert seen and set(seen) == {1}                  # the set-up's kernels
    n = len(seen)
    g1 = d.deform(_motion(d))
    assert len(seen) == n + 1 and set(seen) == {1} and _jit.threads() == before
    d.velocity(d.grid, g1, 0.1)
    assert len(seen) == n + 2 and set(seen) == {1}
    # the same bits with every thread count
    _same(Deformer(grid, walls=walls, symmetry=sym, fixed=fixed).deform(_motion(d)), g1)
    for bad in (0, -2, 1.5, True, "2"):
        with pytest.raises(Exception, match="threads must be"):
            Deformer(grid, walls=walls, threads=bad)


def test_velocity_in_every_layout():
    grid, walls, sym, fixed = G.box_pair()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)
    g1 = d.deform(_motion(d))
    dt = 0.3
    want = [(b.xyz - r.xyz) / dt for b, r in zip(g1, d.grid)]
    v = d.velocity(d.grid, g1, dt)
    assert all(np.array_equal(a, w) and a.flags.f_contiguous for a, w in zip(v, want))
    for name, out in _layouts(d).items():
        cur = _layouts(d)[name]
        d.deform(_motion(d), out=cur)
        got = d.velocity(d.grid, cur, dt, out=out)
        assert got is out
        assert all(np.array_equal(a, w) for a, w in zip(_as_blocks(out), want)), name
        new = d.velocity(d.grid, cur, dt)          # in the layout of cur
        assert all(np.array_equal(a, w) for a, w in zip(_as_blocks(new), want)), name
    # in place, into cur
    cur = d.new_grid("C")
    d.deform(_motion(d), out=cur)
    d.velocity(d.grid, cur, dt, out=cur)
    assert all(np.array_equal(a, w) for a, w in zip(cur, want))
    with pytest.raises(DeformationError, match="dt must be"):
        d.velocity(d.grid, g1, 0.0)
    with pytest.raises(DeformationError, match=r"cur\[1\]: shape"):
        d.velocity(d.grid, [g1[0].xyz, g1[1].xyz[:-1]], dt)
    with pytest.raises(DeformationError, match="reference grid"):
        d.velocity(d.grid, g1, dt, out=d.grid)


def test_velocity_allocates_nothing_grid_sized_with_out():
    import tracemalloc
    grid, walls = _box_with_small_wall()
    d = Deformer(grid, walls=walls)
    cur = d.new_grid("C", separate=True)
    out = d.new_grid()
    tracemalloc.start()
    try:
        d.velocity(d.grid, cur, 0.1, out=out)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 0.05 * sum(b.xyz.nbytes for b in grid)


def test_timings_count_the_check_apart():
    grid, walls, sym, fixed = G.o_grid_3d()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)
    d.deform(_motion(d))
    assert d.timings.check == 0.0
    d.deform(_motion(d), check=True)
    t = d.timings
    assert t.check > 0.0 and t.volumes > 0.0
    assert t.total == t.walls + t.skeleton + t.faces + t.volumes + t.check


@settings(max_examples=12, deadline=None)
@given(name=st.sampled_from(sorted(ALL_CASES)), amp=st.floats(0.0, 0.6), kx=st.floats(-6.0, 6.0),
       ky=st.floats(-6.0, 6.0))
def test_check_matches_the_numpy_oracle_for_random_wall_waves(name, amp, kx, ky):
    from tfi_quat.quality import negative_cells
    d = _DEFORMERS.setdefault(name, Deformer(*_args(name)))
    three = d.ndim == 3

    def wave(p):
        q = p.copy()
        q[:, 1] += amp * np.sin(kx * p[:, 0] + ky * p[:, 2])
        if three:
            q[:, 2] += 0.5 * amp * np.cos(ky * p[:, 0])
        return q
    g = d.deform(wave(d.surface_points()), check=True)
    rep = g.quality
    lo, nj = _oracle(g, d.grid)
    assert rep.min_ratio == pytest.approx(lo, rel=1e-9, abs=1e-12)
    assert rep.negative_jacobian == nj
    assert rep.negative == sum(len(c) for _, c in negative_cells(g, d.grid))


# ------------------------------------------------------------ surface files and modal motion


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
