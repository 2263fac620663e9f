"""Derivatives of the boundary level (tfi_quat.deform.dskeleton): tangents against central
finite differences of the forward stages, adjoints by the dot-product test."""

import numpy as np
import pytest

from tfi_quat import io
from tfi_quat.case import load_case
from tfi_quat.deform import dskeleton as ds
from tfi_quat.deform.deformer import Deformer, rigid_motion
from tfi_quat.fit import fit_rigid
from tfi_quat._jit import use_threads

from _deform_grids import box_pair, o_grid, o_grid_3d, two_block_o

METHODS = ("tfi", "samareh", "two-level")


def _case(name):
    from pathlib import Path
    root = Path(__file__).resolve().parent.parent / "grids"
    case = load_case(root / f"{name}.toml")
    return io.read(root / Path(case.grid).name), case


def _deformer(kind, method):
    if kind == "ogrid":
        g, w, s, f = o_grid(25, 13)
    elif kind == "two_block":
        g, w, s, f = two_block_o(25, 13)
    elif kind == "ogrid3d":
        g, w, s, f = o_grid_3d(17, 9, 3)
    elif kind == "box":
        g, w, s, f = box_pair(6)
    else:
        raise AssertionError(kind)
    return Deformer(g, walls=w, symmetry=s, fixed=f, method=method)


def _motion(d, amp=0.02, rot=7.0):
    """A rotation of every wall plus a smooth deformation (in the grid's plane for 2-D)."""
    move = rigid_motion(rot, axis=(0.0, 0.0, 1.0), about=(0.1, 0.2, 0.0),
                        translate=(0.03, -0.02, 0.0))
    flat = np.array([1.0, 1.0, 0.0 if d.ndim == 2 else 1.0])

    def f(x):
        return move(x) + amp * np.sin(2.0 * x + 0.3) * flat
    return f


def _direction(d, rng):
    P = d.skeleton.points.P
    wall = d.skeleton.points.wall
    drd = np.zeros_like(P)
    drd[wall] = rng.standard_normal((wall.size, 3))
    if d.ndim == 2:
        drd[:, 2] = 0.0
    return drd


def _fd(d, drd, h=1e-6):
    r0 = d.last_targets
    a = ds.forward_record(d, r0 + h * drd)
    b = ds.forward_record(d, r0 - h * drd)
    passes = []
    for pa, pb in zip(a["passes"], b["passes"]):
        passes.append(((pa[0] - pb[0]) / (2 * h),
                       None if pa[1] is None else (pa[1] - pb[1]) / (2 * h)))
    return passes, (a["pos"] - b["pos"]) / (2 * h)


def _rel(a, b):
    return np.abs(a - b).max() / max(np.abs(b).max(), 1e-12)


def _check(d, rng, tol=1e-6, fd=True):
    drd = _direction(d, rng)
    pt, dpos = ds.fields_jvp(d, drd)
    assert len(pt) == len(d.linear_passes())
    if fd:
        # central differences at a few steps: each quantity at its best step (the FD error
        # falls as h^2 until round-off; near sharp trailing edges the good step is small)
        errs = []
        for h in (1e-5, 1e-6, 1e-7, 1e-8):
            fp, fpos = _fd(d, drd, h)
            e = [_rel(dpos, fpos)]
            for (dD, dQ), (fD, fQ) in zip(pt, fp):
                e.append(_rel(dD, fD))
                assert (dQ is None) == (fQ is None)
                e.append(0.0 if fQ is None else _rel(dQ, fQ))
            errs.append(e)
        assert np.min(errs, axis=0).max() < tol
    # adjoint: the dot-product test
    bars = [(rng.standard_normal(a.shape), None if b is None else rng.standard_normal(b.shape))
            for a, b in pt]
    pb = rng.standard_normal(dpos.shape)
    rb = ds.fields_vjp(d, bars, pb)
    lhs = (dpos * pb).sum()
    for (a, b), (x, y) in zip(pt, bars):
        lhs += (a * x).sum() + (0.0 if b is None else (b * y).sum())
    rhs = (rb * drd).sum()
    assert abs(lhs - rhs) <= 1e-12 * max(abs(lhs), 1.0)
    off = np.ones(d.n_global, bool)
    off[d.skeleton.points.wall] = False
    assert not rb[off].any()


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("kind", ["ogrid", "two_block", "ogrid3d", "box"])
def test_jvp_vjp_small_grids(kind, method):
    rng = np.random.default_rng(hash((kind, method)) % 2 ** 32)
    d = _deformer(kind, method)
    # (the box pair has wall points with undefined normals, filled from their neighbours)
    _check(d, rng)                      # at the reference (before any step)
    d.deform(_motion(d))
    _check(d, rng)                      # at the last step


@pytest.mark.parametrize("name", ["naca0012_c_257x65", "naca4412_o_257x65", "two_block_65x33"])
def test_jvp_vjp_shipped_2d(name):
    g, case = _case(name)
    for method in METHODS:
        d = Deformer(g, walls=case.walls, symmetry=case.symmetry, fixed=case.fixed, method=method)
        d.deform(_motion(d, amp=0.002, rot=3.0))
        _check(d, np.random.default_rng(5))


def test_rigid_rotation_two_level():
    """Rigid motion of every wall: the rigid pass's tangent carries it, the residual's is 0."""
    d = _deformer("ogrid3d", "two-level")
    d.deform(rigid_motion(20.0, axis=(0.0, 0.0, 1.0), about=(0.3, 0.0, 0.0)))
    P = d.skeleton.points.P
    wall = d.skeleton.points.wall
    r = d.last_targets
    omega = np.array([0.0, 0.0, 1.0])
    drd = np.zeros_like(P)
    drd[wall] = np.cross(omega, r[wall] - np.array([0.5, 0.1, 0.0])) + np.array([0.1, -0.2, 0.0])
    (dK, dQl), (dD, dQ) = ds.fields_jvp(d, drd)[0]
    assert np.abs(dK).max() < 1e-9 and np.abs(dQl).max() < 1e-9
    assert np.abs(dD).max() > 1e-2 and np.abs(dQ).max() > 1e-2


def test_fit_jacobian():
    rng = np.random.default_rng(3)
    pu = rng.standard_normal((12, 3))
    pd = pu @ np.array([[0.9, -0.3, 0.1], [0.3, 0.95, 0.0], [0.0, 0.1, 1.0]]) + 0.1
    for axis in (None, np.array([0.0, 0.0, 1.0]), np.zeros(3)):
        q, t = fit_rigid(pu, pd, axis, None)
        J = ds.fit_jacobian(pu, pd, q, axis, None)
        dp = rng.standard_normal(pd.shape)
        h = 1e-6
        qa_, ta = fit_rigid(pu, pd + h * dp, axis, None)
        qb, tb = fit_rigid(pu, pd - h * dp, axis, None)
        fd = np.concatenate([qa_ - qb, ta - tb]) / (2 * h)
        assert _rel(J @ dp.ravel(), fd) < 1e-7


def test_threads_same_bits(monkeypatch):
    # small grids run serially below a work threshold: raise the per-point work so that
    # the patch kernels do go on 2 threads here
    monkeypatch.setattr(ds, "PATCH_WORK", 10 ** 9)
    monkeypatch.setattr(ds, "WALL_WORK", 10 ** 9)
    d = _deformer("ogrid3d", "two-level")
    d.deform(_motion(d))
    drd = _direction(d, np.random.default_rng(1))
    out = []
    for n in (1, 2):
        d._linear = None
        with use_threads(n):
            pt, dpos = ds.fields_jvp(d, drd)
            rb = ds.fields_vjp(d, [(a, b) for a, b in pt], dpos)
        out.append((pt, dpos, rb))
    (p1, x1, r1), (p2, x2, r2) = out
    assert np.array_equal(x1, x2) and np.array_equal(r1, r2)
    for (a, b), (c, e) in zip(p1, p2):
        assert np.array_equal(a, c) and np.array_equal(b, e)


def test_linear_passes_match_deform():
    """linear_passes gives the step's own passes (both, for two-level, also when rigid)."""
    d = _deformer("ogrid", "two-level")
    assert len(d.linear_passes()) == 2
    d.deform(_motion(d))
    lp = d.linear_passes()
    assert len(lp) == 2
    ds_ = _deformer("ogrid", "samareh")
    ds_.deform(_motion(ds_))
    (gd, gq, c, _), = ds_.linear_passes()
    g2 = ds_.deform(_motion(ds_))
    assert np.isfinite(gd).all() and np.isfinite(gq).all() and g2 is not None


# ----------------------------------------------------------------------------- stage by stage
def _apply(op, Zin, G, nb=0):
    Z = np.zeros((G + nb, ds.NCOL))
    Z[:G] = Zin
    ds.chain_forward([op], Z)
    return Z


def _dot_test(ops, G, nb, rng):
    """<J x, y> == <x, J^T y> for random full states."""
    x = rng.standard_normal((G + nb, ds.NCOL))
    y = rng.standard_normal((G + nb, ds.NCOL))
    Jx = x.copy()
    ds.chain_forward(ops, Jx)
    JTy = y.copy()
    ds.chain_backward(ops, JTy)
    a, b = (Jx * y).sum(), (x * JTy).sum()
    assert abs(a - b) <= 1e-12 * max(abs(a), 1.0)


@pytest.mark.parametrize("kind", ["ogrid", "ogrid3d", "box"])
def test_wall_quaternion_stage(kind):
    """The merged wall quaternions (normals, two-step rotation, mean angle, mirrored halos,
    filled degenerate points) against central differences of stages.wall_quaternions."""
    from tfi_quat.deform import stages
    d = _deformer(kind, "samareh")
    d.deform(_motion(d))
    sk = d.skeleton
    rd = d.last_targets
    rng = np.random.default_rng(7)
    drd = _direction(d, rng)
    idx, Jw = ds.wall_jacobian(sk, rd, d.centre)
    op = ds.Op(sk.points.wall, ds.P0, 4, idx, ds.RD, 3, Jw)
    Z = np.zeros((d.n_global, ds.NCOL))
    Z[:, ds.RD:ds.RD + 3] = drd
    got = _apply(op, Z, d.n_global)[sk.points.wall, ds.P0:ds.P0 + 4]
    best = min(_rel(got, (stages.wall_quaternions(sk, rd + h * drd, d.centre)
                          - stages.wall_quaternions(sk, rd - h * drd, d.centre)) / (2 * h))
               for h in (1e-5, 1e-6, 1e-7))
    assert best < 1e-7
    _dot_test([op], d.n_global, 0, rng)


@pytest.mark.parametrize("kind", ["ogrid3d", "box"])
def test_wall_ops_compact(kind):
    """The wall op stored compactly (ds.wall_ops: the stencil rows at width 5, the rest at
    their own width) gives the padded single op's tangent (same bits) and adjoint."""
    d = _deformer(kind, "samareh")
    d.deform(_motion(d))
    sk = d.skeleton
    idx, Jw = ds.wall_jacobian(sk, d.last_targets, d.centre)
    wall = sk.points.wall
    one = ds.Op(wall, ds.P0, 4, idx, ds.RD, 3, Jw)
    ops = ds.wall_ops(wall, ds.P0, idx, ds.RD, Jw)
    assert sum(op.out.size for op in ops) == wall.size
    assert sum(op.nbytes for op in ops) <= one.nbytes
    if kind == "box":                       # corners: rows with more reads than the stencil
        assert len(ops) == 2 and ops[0].idx.shape[1] == 5 < ops[1].idx.shape[1]
    rng = np.random.default_rng(3)
    x = rng.standard_normal((d.n_global, ds.NCOL))
    a, b = x.copy(), x.copy()
    ds.chain_forward([one], a)
    ds.chain_forward(ops, b)
    assert np.array_equal(a, b)
    a, b = x.copy(), x.copy()
    ds.chain_backward([one], a)
    ds.chain_backward(ops, b)
    # the adjoint's scatter visits the rows in another order: the same to round-off
    assert np.abs(a - b).max() <= 1e-14 * np.abs(a).max()
    assert not np.array_equal(a, x)
    _dot_test(ops, d.n_global, 0, rng)


@pytest.mark.parametrize("curve", [False, True])
def test_wall_copy_tangent(curve):
    """The hand-derived tangent of one wall point copy's quaternion (ds.wall_q_tan: normals,
    two-step rotation, mean edge angle) against central differences of its own value, on
    random stencils with and without missing neighbours (one-sided differences)."""
    rng = np.random.default_rng(21 + curve)
    e = np.array([0.0, 0.0, 1.0]) if curve else np.zeros(3)
    n = 60
    pu = rng.standard_normal((n, 5, 3)) * 0.3
    pu[:, 1:] += np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]]) + pu[:, :1]
    if curve:
        pu[:, :, 2] = 0.0
        pu[:, 3:] = 0.0
    R = rigid_motion(25.0, axis=(0.3, 0.2, 1.0) if not curve else (0, 0, 1))
    pd = R(pu.reshape(-1, 3)).reshape(pu.shape) + 0.1 * rng.standard_normal(pu.shape) * (
        np.array([1.0, 1.0, 0.0 if curve else 1.0]))
    ok = np.ones((n, 5), dtype=bool)
    if curve:
        ok[:, 3:] = False
    ok[np.arange(n // 2, n), rng.integers(1, 3 if curve else 5, n - n // 2)] = False  # 1-sided
    qc = np.empty((n, 4))
    Jc = np.empty((n, 4, 15))
    good = np.empty(n, dtype=bool)
    ds.wall_copies_tan(0, n, pu, pd, ok, e, curve, qc, Jc, good)
    assert good.sum() >= n - 3 and (~ok[good]).any()

    def q_of(x, m):
        out, dout = np.empty(4), np.empty(4)
        w = [np.empty((4, 3)), np.empty((4, 3))] + [np.empty(3) for _ in range(6)]
        assert ds.wall_q_tan(pu[m], x, ok[m], e, curve, np.zeros((4, 3)), out, dout, *w)
        return out
    h = 1e-6
    for m in np.flatnonzero(good):
        dp = rng.standard_normal((5, 3)) * ok[m][:, None]
        if curve:
            dp[:, 2] = 0.0
        fd = (q_of(pd[m] + h * dp, m) - q_of(pd[m] - h * dp, m)) / (2 * h)
        assert np.abs(qc[m] - q_of(pd[m], m)).max() == 0.0
        assert np.abs(Jc[m] @ dp.ravel() - fd).max() <= 1e-7 * max(np.abs(fd).max(), 1.0)


def test_pull_op():
    """The two-level pull-back y = rot(q*, rd - t) (ds.PullOp, derivative on the fly) against
    the complex step of its numpy transcription (q not normalised: the formula is the
    polynomial's) and central differences; its transpose by the dot-product test."""
    rng = np.random.default_rng(11)
    n, nb = 40, 2
    body = np.arange(n) % nb
    qb = rng.standard_normal((nb, 4))
    tb = rng.standard_normal((nb, 3))
    rd = rng.standard_normal((n, 3))

    def fy(X):
        qc = X[:, :4] * np.array([1.0, -1.0, -1.0, -1.0])
        u, v = qc[:, 1:], X[:, 7:10] - X[:, 4:7]
        t = 2.0 * np.cross(u, v)
        return v + qc[:, :1] * t + np.cross(u, t)
    X = np.concatenate([qb[body], tb[body], rd], axis=1)
    op = ds.PullOp(np.arange(n), n + body, qb[body] * np.array([1.0, -1.0, -1.0, -1.0]),
                   rd - tb[body])
    Z = rng.standard_normal((n + nb, ds.NCOL))
    dX = np.concatenate([Z[n + body, ds.BQ:ds.BQ + 7], Z[:n, ds.RD:ds.RD + 3]], axis=1)
    Jz = Z.copy()
    ds.chain_forward([op], Jz)
    ref = np.einsum("nak,nk->na", ds.cs_jacobian(fy, X), dX)
    got = Jz[:n, ds.Y:ds.Y + 3]
    assert np.abs(got - ref).max() <= 1e-13 * np.abs(ref).max()
    h = 1e-6
    fd = (fy(X + h * dX) - fy(X - h * dX)) / (2 * h)
    assert np.abs(got - fd).max() <= 1e-7 * np.abs(fd).max()
    others = np.ones(ds.NCOL, dtype=bool)
    others[ds.Y:ds.Y + 3] = False
    assert np.array_equal(Jz[:, others], Z[:, others])
    _dot_test([op], n, nb, rng)


def test_linearisation_after_next_step():
    """The linearisation may hold the step's own buffers: after another step the
    derivatives are those at the new step (same as a fresh Deformer's)."""
    d = _deformer("box", "samareh")
    e = _deformer("box", "samareh")
    f1, f2 = _motion(d), _motion(d, amp=0.04, rot=-5.0)
    u = np.random.default_rng(5).standard_normal(d.surface_points().shape) * 0.01
    d.deform(f1)
    d.jvp(u)
    d.deform(f2)
    e.deform(f2)
    for a, b in zip(d.jvp(u), e.jvp(u)):
        assert np.array_equal(a, b)
    assert np.array_equal(d.vjp(d.jvp(u)), e.vjp(e.jvp(u)))


@pytest.mark.parametrize("two", [False, True])
def test_patch_stage(two):
    """The derived patches' Δ/K and Q (normalised Soni blend of slerps, two-level fade and
    re-basing) against central differences of stages.patch_stage."""
    from tfi_quat.deform import stages
    d = _deformer("ogrid3d", "two-level" if two else "samareh")
    d.deform(_motion(d, amp=0.05, rot=25.0))
    sk = d.skeleton
    rec = ds.forward_record(d, d.last_targets)
    D, Q = (a.copy() for a in rec["pre"])
    tl = d.two_level
    damp = tl.damp if two else stages.NONE
    shift = tl.shift if two else stages.NONE3
    op, = ds.patch_ops(sk, Q, ds.K0 if two else ds.D0, ds.Q0 if two else ds.P0, tl if two else None)
    rng = np.random.default_rng(11)
    dD = rng.standard_normal(D.shape)
    dQ = rng.standard_normal(Q.shape)

    def run(h):
        Dh, Qh = D + h * dD, Q + h * dQ
        stages.patch_stage(sk, Dh, Qh, damp, shift)
        return Dh, Qh

    c0 = op.d0
    Z = np.zeros((d.n_global, ds.NCOL))
    Z[:, c0:c0 + 3] = dD
    Z[:, op.q0:op.q0 + 4] = dQ
    Z = _apply(op, Z, d.n_global)
    rows = op.ii[:, 0]
    errs = []
    for h in (1e-5, 1e-6, 1e-7):
        (Da, Qa), (Db, Qb) = run(h), run(-h)
        errs.append(max(_rel(Z[rows, c0:c0 + 3], ((Da - Db) / (2 * h))[rows]),
                        _rel(Z[rows, op.q0:op.q0 + 4], ((Qa - Qb) / (2 * h))[rows])))
    assert min(errs) < 1e-7
    _dot_test([op], d.n_global, 0, rng)


def test_rot_op():
    rng = np.random.default_rng(2)
    n, G = 7, 9
    q = rng.standard_normal((n, 4))
    v = rng.standard_normal((n, 3))
    rows = rng.permutation(G)[:n]
    op = ds.RotOp(rows, ds.POS, ds.D0, ds.P0, ds.POS, -1.0, q, v)
    _dot_test([op], G, 0, rng)
    from tfi_quat.quaternion import rotate
    dq = rng.standard_normal((n, 4))
    dv = rng.standard_normal((n, 3))
    Z = np.zeros((G, ds.NCOL))
    Z[rows, ds.P0:ds.P0 + 4] = dq
    Z[rows, ds.POS:ds.POS + 3] = dv
    ds.chain_forward([op], Z)
    h = 1e-7

    def rot_any(q, v):          # the kernels' formula, for any q
        u = q[:, 1:]
        t = 2.0 * np.cross(u, v)
        return v + q[:, :1] * t + np.cross(u, t)
    fd = -(rot_any(q + h * dq, v + h * dv) - rot_any(q - h * dq, v - h * dv)) / (2 * h)
    assert _rel(Z[rows, ds.POS:ds.POS + 3], fd) < 1e-7
    assert rotate is not None


def test_wing_end_to_end():
    """The shipped wing (symmetry plane, tip cap with degenerate normals), two-level."""
    g, case = _case("wing_ch_501k")
    d = Deformer(g, walls=case.walls, symmetry=case.symmetry, fixed=case.fixed)
    P = d.skeleton.points.P
    d.deform(lambda x: x + 0.02 * np.sin(3.0 * x) * np.array([0.0, 1.0, 0.2]))
    wall = d.skeleton.points.wall
    drd = np.zeros_like(P)
    drd[wall] = np.sin(3.0 * P[wall]) + 0.5 * np.cos(2.0 * P[wall][:, [1, 2, 0]])
    pt, dpos = ds.fields_jvp(d, drd)
    fp, fpos = _fd(d, drd, 1e-6)
    assert _rel(dpos, fpos) < 1e-6
    for (a, b), (c, e) in zip(pt, fp):
        assert _rel(a, c) < 1e-6 and _rel(b, e) < 1e-6
    bars = [(np.sin(a), np.cos(b)) for a, b in pt]
    rb = ds.fields_vjp(d, bars, np.cos(dpos))
    lhs = (dpos * np.cos(dpos)).sum() + sum((a * x).sum() + (b * y).sum()
                                            for (a, b), (x, y) in zip(pt, bars))
    assert abs(lhs - (rb * drd).sum()) <= 1e-12 * abs(lhs)
