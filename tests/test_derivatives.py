"""Derivatives of the deformation (Deformer.jvp / Deformer.vjp) and of the volume stage.

Oracles: central finite differences of the forward maps (``tfi.deform_block_gathered``,
``Deformer.deform``), the dot-product identity ``<vjp(v), u> = <v, jvp(u)>``, and the
rigid-rotation identity of the two-level method.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tfi_quat import dtfi, tfi
from tfi_quat._jit import use_threads
from tfi_quat.deform import Deformer
from tfi_quat.errors import DeformationError

import _deform_grids as G

STEPS = (1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7)


# ------------------------------------------------------------------ the volume stage
def _block(dims, order, seed):
    """A warped block, its arclength parameters and a plan whose every point is its own row."""
    rng = np.random.default_rng(seed)
    u = [np.linspace(0.0, 1.0, n) ** 1.3 for n in dims]
    x = np.stack(np.meshgrid(*u, indexing="ij"), -1) + 0.03 * rng.standard_normal(dims + (3,))
    if len(order) == 2:
        x[..., 2] = 0.0
    xyz = np.asfortranarray(x)
    s = tfi.arclength(xyz)
    ids = np.arange(xyz.shape[0] * xyz.shape[1] * xyz.shape[2]).reshape(dims, order="F")
    if len(order) == 3:
        faces = [ids[0], ids[-1], ids[:, 0], ids[:, -1], ids[:, :, 0], ids[:, :, -1]]
    else:
        faces = [ids[0, :, 0], ids[-1, :, 0], ids[:, 0, 0], ids[:, -1, 0]]
    return xyz, s, tfi.gather_plan(faces, s, order), ids.size


def _quats(n, amp, rng):
    q = np.zeros((n, 4))
    q[:, 0] = 1.0
    q[:, 1:] = amp * rng.standard_normal((n, 3))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(rng.random(n) < 0.3, -1.0, 1.0)[:, None]     # mixed hemispheres


def _case(nd, hasq, based, dbase, seed):
    dims, order = ((7, 6, 5), (2, 0, 1)) if nd == 3 else ((8, 7, 1), (1, 0))
    xyz, s, plan, n = _block(dims, order, seed)
    rng = np.random.default_rng(seed + 1)
    return dict(
        xyz=xyz, s=s, plan=plan, c=rng.standard_normal(3),
        gd=0.1 * rng.standard_normal((n, 3)), gq=_quats(n, 0.4, rng) if hasq else None,
        dgd=rng.standard_normal((n, 3)), dgq=rng.standard_normal((n, 4)) if hasq else None,
        dx=np.asfortranarray(rng.standard_normal(xyz.shape)) if dbase else None,
        base=plan.base_tables(0.05 * rng.standard_normal((n, 3))) if based else None)


def _forward(k, e):
    x = k["xyz"] if k["dx"] is None else np.asfortranarray(k["xyz"] + e * k["dx"])
    gq = None if k["gq"] is None else k["gq"] + e * k["dgq"]
    return tfi.deform_block_gathered(x, k["s"], k["gd"] + e * k["dgd"], gq, k["plan"], k["c"],
                                     base=k["base"])


def _jvp(k):
    out = np.empty_like(k["xyz"], order="F")
    dout = np.empty_like(k["xyz"], order="F")
    nbad = dtfi.volume_jvp(k["plan"], k["xyz"], k["s"], k["gd"], k["gq"], k["dgd"], k["dgq"],
                           k["c"], out, dout, base=k["base"], dxyz=k["dx"])
    return out, dout, nbad


KINDS = [(3, True, True, False), (3, True, False, True), (3, True, False, False),
         (3, False, False, False), (2, True, True, False), (2, True, False, True),
         (2, False, False, False)]


@pytest.mark.parametrize("nd, hasq, based, dbase", KINDS)
def test_volume_jvp_is_the_finite_difference(nd, hasq, based, dbase):
    """The tangent of a volume pass against central differences of deform_block_gathered
    (V curve: its best step within 1e-6); the pass's result is the forward kernel's, bit
    for bit."""
    k = _case(nd, hasq, based, dbase, 10 * nd + 2 * hasq + based)
    out, dout, nbad = _jvp(k)
    assert nbad == 0
    assert np.array_equal(out, _forward(k, 0.0))
    errs = [np.abs((_forward(k, h) - _forward(k, -h)) / (2 * h) - dout).max() for h in STEPS]
    assert min(errs) <= 1e-6 * np.abs(dout).max(), errs
    # a wrong tangent is caught: the V curve is not flat at its bottom
    assert errs[0] > 10 * min(errs) or not hasq


@pytest.mark.parametrize("nd, hasq, based, dbase", KINDS)
def test_volume_vjp_is_the_adjoint(nd, hasq, based, dbase):
    """<obar, jvp(u)> = <vjp(obar), u> to round-off, the base points' bar included."""
    k = _case(nd, hasq, based, dbase, 7 + nd)
    _, dout, _ = _jvp(k)
    rng = np.random.default_rng(3)
    ob = np.asfortranarray(rng.standard_normal(k["xyz"].shape))
    n = k["gd"].shape[0]
    gdb, gqb = np.zeros((n, 3)), np.zeros((n, 4))
    xb = np.zeros_like(k["xyz"], order="F") if dbase else None
    dtfi.volume_vjp(k["plan"], k["xyz"], k["s"], k["gd"], k["gq"], k["c"], ob, gdb, gqb,
                    base=k["base"], xbar=xb)
    lhs = np.sum(ob * dout)
    rhs = np.sum(gdb * k["dgd"]) + (np.sum(gqb * k["dgq"]) if hasq else 0.0) + \
        (np.sum(xb * k["dx"]) if dbase else 0.0)
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs)


@given(seed=st.integers(0, 10_000), amp=st.floats(0.0, 1.0))
@settings(max_examples=15, deadline=None)
def test_volume_jvp_over_rotations(seed, amp):
    """Random block data, rotations from none (every slerp at zero angle, where only the
    polynomial weights keep the angle's derivative finite) to large ones."""
    k = _case(3, True, False, False, seed)
    rng = np.random.default_rng(seed)
    k["gq"] = _quats(k["gd"].shape[0], amp, rng)
    out, dout, nbad = _jvp(k)
    if nbad:                                      # the fallback path: not differentiated
        return
    assert np.all(np.isfinite(dout))
    errs = [np.abs((_forward(k, h) - _forward(k, -h)) / (2 * h) - dout).max() for h in STEPS]
    assert min(errs) <= 1e-6 * max(1.0, np.abs(dout).max()), errs


def test_volume_jvp_at_zero_angle_is_finite_and_right():
    """Every boundary quaternion the same (every slerp angle 0, the angle's derivative taken
    through ω²): the tangent is finite and is the finite difference."""
    k = _case(3, True, False, False, 5)
    q = np.array([0.9, 0.3, -0.1, 0.2])
    k["gq"] = np.tile(q / np.linalg.norm(q), (k["gd"].shape[0], 1))
    _, dout, nbad = _jvp(k)
    assert nbad == 0 and np.all(np.isfinite(dout))
    errs = [np.abs((_forward(k, h) - _forward(k, -h)) / (2 * h) - dout).max() for h in STEPS]
    assert min(errs) <= 1e-6 * np.abs(dout).max()


def test_volume_jvp_sign_alignment():
    """The hemisphere alignment is not differentiable across a flip; the derivative is the
    one of the branch at the linearisation point: flipping a boundary quaternion and its
    tangent together changes nothing."""
    k = _case(3, True, False, False, 11)
    _, d1, _ = _jvp(k)
    flip = np.where(np.arange(k["gq"].shape[0]) % 3 == 0, -1.0, 1.0)[:, None]
    k["gq"] = k["gq"] * flip
    k["dgq"] = k["dgq"] * flip
    _, d2, _ = _jvp(k)
    assert np.allclose(d1, d2, rtol=0.0, atol=1e-12 * np.abs(d1).max())


def test_volume_fallback_points_are_counted():
    """Blended rotations that cancel (the forward map's rotation-vector fallback) are not
    differentiated: the drivers count them (the Deformer raises)."""
    u = np.linspace(0.0, 1.0, 5)
    v = np.linspace(0.0, 1.0, 7)                       # M = j: s = 1/2 on the middle row
    xyz = np.zeros((5, 7, 1, 3), order="F")
    xyz[..., 0, :2] = np.stack(np.meshgrid(u, v, indexing="ij"), -1)
    s = tfi.arclength(xyz)
    ids = np.arange(35).reshape(5, 7, order="F")
    plan = tfi.gather_plan([ids[0], ids[-1], ids[:, 0], ids[:, -1]], s, (0, 1))
    n = ids.size
    q = np.zeros((n, 4))
    q[:, 0] = 1.0
    q[ids[1:-1, 0]] = [0.0, 1.0, 0.0, 0.0]             # 180 degrees about x inside jmin,
    q[ids[1:-1, -1]] = [0.0, -1.0, 0.0, 0.0]           # about -x inside jmax: they cancel
    rng = np.random.default_rng(0)
    out, dout = np.empty_like(xyz, order="F"), np.empty_like(xyz, order="F")
    nbad = dtfi.volume_jvp(plan, xyz, s, np.zeros((n, 3)), q, rng.standard_normal((n, 3)),
                           rng.standard_normal((n, 4)), np.zeros(3), out, dout)
    assert nbad > 0
    gdb, gqb = np.zeros((n, 3)), np.zeros((n, 4))
    assert dtfi.volume_vjp(plan, xyz, s, np.zeros((n, 3)), q, np.zeros(3),
                           np.asfortranarray(np.ones(xyz.shape)), gdb, gqb) == nbad


def test_volume_vjp_same_bits_on_1_and_2_threads():
    """The adjoint's sums do not depend on the threads (fixed chunks, summed in order); the
    tangent's points neither (called here without the Deformer's serial_below, so that two
    threads really run on this small block)."""
    k = _case(3, True, False, True, 2)
    xyz, s, plan, n = _block((9, 8, 20), (0, 1, 2), 2)
    rng = np.random.default_rng(0)
    gd, gq = 0.1 * rng.standard_normal((n, 3)), _quats(n, 0.4, rng)
    ob = np.asfortranarray(rng.standard_normal(xyz.shape))
    res = []
    for nt in (1, 2):
        gdb, gqb = np.zeros((n, 3)), np.zeros((n, 4))
        xb = np.zeros_like(xyz, order="F")
        out, dout = np.empty_like(xyz, order="F"), np.empty_like(xyz, order="F")
        with use_threads(nt):
            dtfi.volume_vjp(plan, xyz, s, gd, gq, k["c"], ob, gdb, gqb, xbar=xb)
            dtfi.volume_jvp(plan, xyz, s, gd, gq, gdb, gqb, k["c"], out, dout, dxyz=ob)
        res.append((gdb, gqb, xb, out, dout))
    for a, b in zip(*res):
        assert np.array_equal(a, b)


# ------------------------------------------------------------------ Deformer.jvp / vjp
def _deformer(builder, method, all_walls=False, **kw):
    grid, walls, sym, fixed = builder(**kw)
    if all_walls:
        walls, fixed = walls + fixed, []
    return Deformer(grid, walls=walls, symmetry=sym, fixed=fixed, method=method)


def _smooth(P, seed, ndim, amp=0.05):
    r = np.random.default_rng(seed)
    v = P @ r.standard_normal((3, 3)).T * amp + amp * r.standard_normal(3) + \
        0.4 * amp * np.sin(3.0 * P[:, [1, 2, 0]])
    if ndim == 2:
        v[:, 2] = 0.0
    return v


GRIDS = [("o_grid", dict(ni=17, nj=9)), ("two_block_o", dict(ni=17, nj=9)),
         ("o_grid_3d", dict(ni=13, nj=7)), ("channel", dict(ni=15, nj=9))]


def _fd_errors(d, xs, u, J):
    """The V curve: per step of STEPS, the largest difference between the central difference
    of deform about ``xs`` along ``u`` and the tangent ``J``, relative to the tangent's size
    (deform is left at ``xs - h u`` of the last step)."""
    scale = max(np.abs(j).max() for j in J)
    errs = []
    for h in STEPS:
        gp, gm = d.deform(xs + h * u), d.deform(xs - h * u)
        errs.append(max(np.abs((a.xyz - b.xyz) / (2 * h) - j).max()
                        for a, b, j in zip(gp, gm, J)) / scale)
    return errs


@pytest.mark.parametrize("method", ["two-level", "samareh", "tfi"])
@pytest.mark.parametrize("name, kw", GRIDS)
def test_jvp_is_the_finite_difference_of_deform(method, name, kw):
    """jvp against central differences of deform about a deformed state: the best step of
    the V curve within 1e-6 of the tangent's size."""
    d = _deformer(getattr(G, name), method, **kw)
    P = d.surface_points()
    xs = P + _smooth(P, 2, d.ndim)
    u = _smooth(P, 3, d.ndim)
    d.deform(xs)
    J = d.jvp(u)
    errs = _fd_errors(d, xs, u, J)
    assert min(errs) <= 1e-6, errs


@pytest.mark.parametrize("method", ["two-level", "samareh"])
def test_jvp_and_vjp_on_the_shipped_c_grid(method):
    """The NACA 0012 C-grid of grids/ (its case file: the airfoil a wall, a wake cut, the far
    field fixed): jvp against central differences of deform, and the dot-product test."""
    import tfi_quat as tq
    from tfi_quat.case import load_case
    from tfi_quat.demo import sample_path
    case = load_case(sample_path("naca0012_c_257x65.toml"))
    d = Deformer(tq.read(case.grid), walls=case.walls, symmetry=case.symmetry,
                 fixed=case.fixed, method=method)
    P = d.surface_points()
    xs = P + _smooth(P, 12, 2, 0.02)
    u = _smooth(P, 13, 2, 0.02)
    d.deform(xs)
    J = d.jvp(u)
    errs = _fd_errors(d, xs, u, J)
    assert min(errs) <= 1e-6, errs
    d.deform(xs)
    v = [np.random.default_rng(14).standard_normal(b.xyz.shape) for b in d.grid]
    v[0][..., 2] = 0.0
    rhs = sum(np.sum(a * b) for a, b in zip(v, J))
    assert abs(np.sum(d.vjp(v) * u) - rhs) <= 1e-10 * abs(rhs)


@pytest.mark.parametrize("method", ["two-level", "samareh", "tfi"])
@pytest.mark.parametrize("name, kw", GRIDS[:3])
def test_vjp_is_the_adjoint_of_jvp(method, name, kw):
    """|<vjp(v), u> - <v, jvp(u)>| <= 1e-10 |<v, jvp(u)>|."""
    d = _deformer(getattr(G, name), method, **kw)
    P = d.surface_points()
    d.deform(P + _smooth(P, 4, d.ndim))
    u = _smooth(P, 5, d.ndim)
    rng = np.random.default_rng(6)
    v = [rng.standard_normal(b.xyz.shape) for b in d.grid]
    J = d.jvp(u)
    g = d.vjp(v)
    rhs = sum(np.sum(a * b) for a, b in zip(v, J))
    assert abs(np.sum(g * u) - rhs) <= 1e-10 * abs(rhs)


@pytest.mark.parametrize("name, kw", [("o_grid", dict(ni=17, nj=9)),
                                      ("two_block_o", dict(ni=17, nj=9)),
                                      ("o_grid_3d", dict(ni=13, nj=7))])
@pytest.mark.parametrize("deformed", [False, True])
def test_jvp_of_a_rigid_rotation_rotates_every_point(name, kw, deformed):
    """Two-level, every boundary a wall: an infinitesimal rotation of every wall point moves
    every grid point by the same rotation (at the reference and at a deformed state)."""
    d = _deformer(getattr(G, name), "two-level", all_walls=True, **kw)
    P = d.surface_points()
    xs = P + (_smooth(P, 7, d.ndim, 0.02) if deformed else 0.0)
    X = [b.xyz for b in d.deform(xs)]
    w = np.array([0.0, 0.0, 0.7])                       # o_grid_3d: about its symmetry planes
    c = np.array([0.3, -0.2, 0.1 if d.ndim == 3 else 0.0])
    J = d.jvp(np.cross(w, xs - c))
    for j, x in zip(J, X):
        assert np.abs(j - np.cross(w, x - c)).max() <= 1e-12 * np.abs(x).max()


@pytest.mark.parametrize("method", ["two-level", "tfi"])
def test_jvp_and_vjp_same_bits_on_1_and_2_threads(method):
    """Deformer(threads=1) and threads=2 (on blocks this small the kernels run serially
    below tfi_quat._jit.SERIAL_BELOW; the kernels' own thread test is above)."""
    grid, walls, sym, fixed = G.o_grid_3d(ni=13, nj=7, nk=12)
    res = []
    for nt in (1, 2):
        d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed, method=method, threads=nt)
        P = d.surface_points()
        d.deform(P + _smooth(P, 8, 3))
        v = [np.random.default_rng(9).standard_normal(b.xyz.shape) for b in grid]
        res.append((d.jvp(_smooth(P, 9, 3)), d.vjp(v)))
    (j1, g1), (j2, g2) = res
    assert all(np.array_equal(a, b) for a, b in zip(j1, j2))
    assert np.array_equal(g1, g2)


def test_duplicates_ids_and_the_linearisation_point():
    """Copies of a wall point: jvp reads the first, vjp gives it the whole gradient and the
    others 0; ids= reorders rows as deform's; before any deform, and with at=, the map is
    linearised at the given wall (the reference first)."""
    d = _deformer(G.two_block_o, "two-level", ni=17, nj=9)
    P = d.surface_points()
    ids = d.surface_ids()
    key = [tuple(r) for r in np.round(P, 12)]
    first = {}
    dup = np.array([first.setdefault(k, r) != r for r, k in enumerate(key)])
    assert dup.any()                                    # the two blocks share wall points
    u = _smooth(P, 1, 2)
    J0 = d.jvp(u)                                       # before any deform: at the reference
    # the interfaces (i = 0 and i = -1 of both blocks are the same points): one tangent
    assert np.array_equal(J0[0][-1], J0[1][-1]) and np.array_equal(J0[0][0], J0[1][0])
    assert np.abs(J0[0][-1]).max() > 0.0
    u2 = u.copy()
    u2[dup] = 123.0                                     # ignored copies
    assert all(np.array_equal(a, b) for a, b in zip(J0, d.jvp(u2)))
    perm = np.random.default_rng(0).permutation(len(u))
    J1 = d.jvp(u[perm], ids=ids[perm])
    # the first copy in the permuted order may be the other copy: same value (u is smooth)
    assert all(np.allclose(a, b, atol=1e-12) for a, b in zip(J0, J1))
    v = [np.ones(b.xyz.shape) for b in d.grid]
    g = d.vjp(v)
    assert np.all(g[dup] == 0.0) and np.abs(g[~dup]).max() > 0.0
    xs = P + _smooth(P, 2, 2)
    Ja = d.jvp(u, at=xs)
    d.deform(xs)
    Jb = d.jvp(u)
    assert all(np.array_equal(a, b) for a, b in zip(Ja, Jb))
    assert not all(np.allclose(a, b) for a, b in zip(J0, Jb))


def test_jvp_out_buffers_and_layouts():
    d = _deformer(G.o_grid_3d, "tfi", ni=13, nj=7)
    P = d.surface_points()
    u = _smooth(P, 1, 3)
    J = d.jvp(u)
    outs = [tuple(np.empty(b.dims) for _ in range(3)) for b in d.grid]
    assert d.jvp(u, out=outs) is outs
    for o, j in zip(outs, J):
        assert all(np.array_equal(o[c], j[..., c]) for c in range(3))
    c_order = [np.ascontiguousarray(j) for j in J]
    assert np.array_equal(d.vjp(c_order), d.vjp(J))


def test_bad_input():
    d = _deformer(G.o_grid, "two-level", ni=17, nj=9)
    n = len(d.surface_ids())
    with pytest.raises(DeformationError, match="shape"):
        d.jvp(np.zeros((n, 2)))
    with pytest.raises(DeformationError, match="rows"):
        d.jvp(np.zeros((n - 1, 3)))
    bad = np.zeros((n, 3))
    bad[3, 0] = np.nan
    with pytest.raises(DeformationError, match="row 3"):
        d.jvp(bad)
    z = np.zeros((n, 3))
    z[:, 2] = 1.0
    with pytest.raises(DeformationError, match="z = 0"):
        d.jvp(z)
    with pytest.raises(DeformationError, match="entries"):
        d.vjp([])
    v = [np.zeros(b.xyz.shape) for b in d.grid]
    v[0][0, 0, 0, 0] = np.inf
    with pytest.raises(DeformationError, match="non-finite"):
        d.vjp(v)
    with pytest.raises(DeformationError, match="shape"):
        d.vjp([np.zeros((3, 3, 1, 3))])


def test_docs_worked_example_runs():
    """docs/derivatives.md's example runs as written: the vjp gradient of the cell-area
    objective agrees with central differences (the example asserts it)."""
    import re
    from pathlib import Path
    text = (Path(__file__).resolve().parents[1] / "docs" / "derivatives.md").read_text("utf-8")
    blocks = re.findall(r"^```python\n(.*?)^```$", text, flags=re.S | re.M)
    assert len(blocks) == 1
    ns = {"__name__": "derivatives_page"}
    exec(compile(blocks[0], "docs/derivatives.md", "exec"), ns)
    assert ns["grad"].shape == (len(ns["d"].surface_ids()), 3)


def test_nothing_of_the_derivatives_is_loaded_by_a_step():
    """The derivative kernels are made on first use: a process that only deforms never
    imports tfi_quat.dtfi nor the boundary level's derivatives (issue 13's cold start)."""
    import subprocess
    import sys
    code = ("import sys; import numpy as np; sys.path.insert(0, 'tests'); "
            "import _deform_grids as G; from tfi_quat.deform import Deformer; "
            "g, w, s, f = G.o_grid(ni=9, nj=5); d = Deformer(g, walls=w, fixed=f); "
            "d.deform(d.surface_points() * 1.01); "
            "print(sorted(m for m in sys.modules if m.endswith(('dtfi', 'dvolume', 'dskeleton'))))")
    from pathlib import Path
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1], check=True).stdout
    assert out.strip() == "[]"
