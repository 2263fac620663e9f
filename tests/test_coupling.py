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
