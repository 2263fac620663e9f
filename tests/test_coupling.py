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


# ------------------------------------------------------------------ deform(xs, ids=...)
from hypothesis import given, settings, strategies as st  # noqa: E402

from tfi_quat import DeformationError  # noqa: E402
from tfi_quat.deform import rigid_motion  # noqa: E402

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
def _corner_dets(x):
    """Per cell and corner, the Jacobian (the determinant of the edges leaving the corner
    along +i, +j, +k; 2-D: +i, +j), numpy whole-array code: (ncells..., 8 or 4)."""
    if x.shape[2] == 1:
        p = x[:, :, 0, :2]
        di = p[1:] - p[:-1]
        dj = p[:, 1:] - p[:, :-1]
        out = []
        for a in (0, 1):
            for b in (0, 1):
                u = di[:, b:b + dj.shape[1]]
                v = dj[a:a + di.shape[0]]
                out.append(u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0])
        return np.stack(out, -1)
    di, dj, dk = x[1:] - x[:-1], x[:, 1:] - x[:, :-1], x[:, :, 1:] - x[:, :, :-1]
    ni, nj, nk = x.shape[:3]
    out = []
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                u = di[:, b:b + nj - 1, c:c + nk - 1]
                v = dj[a:a + ni - 1, :, c:c + nk - 1]
                w = dk[a:a + ni - 1, b:b + nj - 1]
                out.append(np.einsum("...i,...i->...", np.cross(u, v), w))
    return np.stack(out, -1)


def _cell_ratio(grid, ref, b, i, j, k):
    cell = (i, j) if grid.ndim == 2 else (i, j, k)
    jr = _corner_dets(ref[b].xyz)[cell]
    return np.where(jr != 0.0, _corner_dets(grid[b].xyz)[cell] / jr, np.inf).min()


def _oracle(grid, ref):
    """(min ratio, negative-Jacobian cells) in numpy."""
    lo, nj = np.inf, 0
    for b, r in zip(grid, ref):
        jd, jr = _corner_dets(b.xyz), _corner_dets(r.xyz)
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


# ------------------------------------------------------------------ threads=, velocity
def test_threads_apply_inside_the_deformers_calls_only(monkeypatch):
    import numba
    from tfi_quat import _jit
    seen = []
    real = _jit.use_threads

    def spy(n):
        seen.append(n)
        return real(n)
    monkeypatch.setattr("tfi_quat.deform.deformer.use_threads", spy)
    grid, walls, sym, fixed = G.o_grid()
    before = numba.get_num_threads()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed, threads=1)
    assert seen and set(seen) == {1}                  # the set-up's kernels
    n = len(seen)
    g1 = d.deform(_motion(d))
    assert len(seen) == n + 1 and set(seen) == {1} and numba.get_num_threads() == before
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
