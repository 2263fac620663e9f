"""Derivatives of the boundary level of a step: wall targets -> volume passes and positions.

:meth:`Deformer.deform` maps the global wall targets ``rd`` (G, 3) to the fields
of its volume passes (``(Δ or K, Q)`` on every boundary point) and to the final
boundary positions ``pos`` (:meth:`Deformer._samareh_fields`,
:meth:`Deformer._two_level_fields`).  This module gives the forward (tangent) and
reverse (adjoint) products of that map's Jacobian, linearised at the targets of
the last step (the reference before any step):

* :func:`fields_jvp` ``(deformer, drd) -> (pass_tangents, dpos)``
* :func:`fields_vjp` ``(deformer, pass_bars, pos_bar) -> rd_bar``

How (docs/derivatives-boundary.md): the map is a chain of stages, each writing
some columns of some rows of one state array ``Z`` (a row per boundary point
and one per wall body) from a few rows of it.  Linearising a step
(:func:`linearise`, on first use after the step; O(surface) numbers) stores per
stage what its tangent needs:

* linear stages (the Δ / K hierarchy's vertex and gap weights, projections onto
  symmetry planes, copies): their weights (:class:`Op`);
* the rigid fits: their closed-form Jacobian (:func:`fit_jacobian`);
* the derived patches: indices and blending parameters only; the tangent and
  adjoint of the normalised Soni blend of slerps, of the two-level fade and of
  the re-basing are hand-derived compiled kernels (:class:`PatchOp`);
* rotations of positions and re-basings, the two-level pull-back, the rigid
  blend's exp: the rotation and its hand-derived derivative computed on the fly
  (:class:`RotOp`, :class:`PullOp`, :class:`ExpOp`);
* the wall quaternions (normals, two-step rotation, mean angle, mirrored halos,
  the filling of undefined normals, the merge of copies): a compiled hand-derived
  tangent of the copy's kernel (:func:`wall_q_tan`, one per neighbour coordinate),
  then the filling and merge on the stored blocks (:func:`wall_jacobian`, stored
  without padding, :func:`wall_ops`); the symmetry twist: hand-derived
  (:class:`SymOp`); the few small
  point-wise stages left (vertex and gap slerps, the bodies' log) by the complex
  step on numpy transcriptions
  (:func:`cs_jacobian`).  The branches (hemisphere signs, one-sided differences,
  fallbacks) are those of the real values, i.e. of the step's.

:func:`fields_jvp` runs the chain forward on tangents and :func:`fields_vjp` the
transposed chain backward (:func:`chain_forward`, :func:`chain_backward`); the
adjoint is exact by construction, and the bits do not depend on the thread count
(the patch kernels run on the threads item by item, their adjoint's scatter in a
fixed order).

Where the forward map is not differentiable the derivative is that of the branch
the step took: hemisphere signs are held; a wall point whose normals are
undefined follows the step's filling from its neighbours (a patch with no
defined point: 0); a patch point whose quaternion blend falls back to the
rotation-vector blend (``|V| < QNORM_MIN``, near a half turn) gets a zero
tangent of Q; a rigid fit whose normal matrix is singular (degenerate body) gets
the least-squares (pseudo-inverse) rotation tangent.
"""

from __future__ import annotations

import math

import numpy as np

from .. import tfi
from .._jit import jit, parallel_for, serial_below, task_jit
from .stages import symmetry_twist

__all__ = ["fields_jvp", "fields_vjp", "Linearisation", "linearise", "cs_jacobian",
           "fit_jacobian", "forward_record", "wall_jacobian", "wall_ops", "patch_ops", "RotOp",
           "PatchOp", "SymOp", "ExpOp", "PullOp", "chain_forward", "chain_backward", "Op"]

#: a patch point's tangent or adjoint costs about as much as this many volume points (the
#: patch kernels run on the threads when that work reaches tfi_quat._jit.SERIAL_BELOW)
PATCH_WORK = 32
#: the same for a wall point copy's 12 tangents
WALL_WORK = 64

# columns of the state Z (rows: boundary points, then one per wall body)
K0, Q0, D0, P0, POS, RD, Y, T0 = 0, 3, 7, 10, 14, 17, 20, 23
NCOL = 27
# body rows: Δ_b (0:3), q_b (3:7), v_b = log q_b (7:10), the fit's q (BQ:BQ+4) and t (+4:+7)
BQ = 10
_H = 1e-30          # complex step


# ----------------------------------------------------------------------------- chain
class Op:
    """One stage of the chain: rows ``out`` get columns ``[o0, o0 + no)`` from columns
    ``[i0, i0 + ni)`` of rows ``idx`` (n, k) (-1: none).  ``J``: (n, k) weights applied to
    every column (``diag``, ``ni == no``) or (n, no, k * ni) blocks (full)."""

    __slots__ = ("out", "o0", "no", "idx", "i0", "ni", "J", "diag")

    @property
    def nbytes(self):
        return self.out.nbytes + self.idx.nbytes + self.J.nbytes

    def __init__(self, out, o0, no, idx, i0, ni, J, diag=False):
        self.out = np.ascontiguousarray(out, dtype=np.int64)
        idx = np.asarray(idx)
        k = idx.shape[-1] if idx.ndim > 1 else 1
        self.idx = np.ascontiguousarray(np.reshape(idx, (self.out.size, k if self.out.size == 0
                                                         else -1)), dtype=np.int64)
        self.o0, self.no, self.i0, self.ni = int(o0), int(no), int(i0), int(ni)
        self.J = np.ascontiguousarray(J, dtype=np.float64)
        self.diag = bool(diag)
        if diag:
            assert self.J.shape == self.idx.shape and ni == no
        else:
            assert self.J.shape == (self.out.size, no, self.idx.shape[1] * ni)


@jit
def op_forward_diag(Z, out, o0, no, idx, i0, J):
    """Apply a weight op (``Z[out, o0:] = Σ_k J[m, k] Z[idx[m, k], i0:]``) in place, in order."""
    tmp = np.empty(no)
    for m in range(out.shape[0]):
        for a in range(no):
            tmp[a] = 0.0
        for k in range(idx.shape[1]):
            r = idx[m, k]
            if r >= 0:
                w = J[m, k]
                for a in range(no):
                    tmp[a] += w * Z[r, i0 + a]
        for a in range(no):
            Z[out[m], o0 + a] = tmp[a]


@jit
def op_forward_full(Z, out, o0, no, idx, i0, ni, J):
    """Apply a block op (``Z[out, o0:o0+no] = Σ_k J[m, :, k] Z[idx[m, k], i0:i0+ni]``)."""
    tmp = np.empty(no)
    for m in range(out.shape[0]):
        for a in range(no):
            tmp[a] = 0.0
        for k in range(idx.shape[1]):
            r = idx[m, k]
            if r >= 0:
                for a in range(no):
                    s = 0.0
                    for b in range(ni):
                        s += J[m, a, k * ni + b] * Z[r, i0 + b]
                    tmp[a] += s
        for a in range(no):
            Z[out[m], o0 + a] = tmp[a]


@jit
def op_backward_diag(Zb, out, o0, no, idx, i0, J):
    """The transpose of :func:`op_forward_diag` in place (items reversed)."""
    tmp = np.empty(no)
    for m in range(out.shape[0] - 1, -1, -1):
        o = out[m]
        for a in range(no):
            tmp[a] = Zb[o, o0 + a]
            Zb[o, o0 + a] = 0.0
        for k in range(idx.shape[1]):
            r = idx[m, k]
            if r >= 0:
                w = J[m, k]
                for a in range(no):
                    Zb[r, i0 + a] += w * tmp[a]


@jit
def op_backward_full(Zb, out, o0, no, idx, i0, ni, J):
    """The transpose of :func:`op_forward_full` in place (items reversed)."""
    tmp = np.empty(no)
    for m in range(out.shape[0] - 1, -1, -1):
        o = out[m]
        for a in range(no):
            tmp[a] = Zb[o, o0 + a]
            Zb[o, o0 + a] = 0.0
        for k in range(idx.shape[1]):
            r = idx[m, k]
            if r >= 0:
                for b in range(ni):
                    s = 0.0
                    for a in range(no):
                        s += J[m, a, k * ni + b] * tmp[a]
                    Zb[r, i0 + b] += s


class RotOp:
    """The tangent of ``out = F + sr rot(q, v)`` on rows ``out`` (reading the same rows):
    ``dF + sr (∂_q rot(q, v) dq + rot(q, dv))`` from columns ``f0`` (F), ``q0`` (q) and
    ``v0`` (v; -1: v constant), with ``q`` (n, 4) and ``v`` (n, 3) stored at the
    linearisation point: the rotation's derivative is computed on the fly (7 numbers per
    point instead of a 3 x 10 block)."""

    __slots__ = ("out", "o0", "f0", "q0", "v0", "sr", "q", "v")
    diag = False

    def __init__(self, out, o0, f0, q0, v0, sr, q, v):
        self.out = np.ascontiguousarray(out, dtype=np.int64)
        self.o0, self.f0, self.q0, self.v0, self.sr = int(o0), int(f0), int(q0), int(v0), float(sr)
        self.q = np.ascontiguousarray(q, dtype=np.float64)
        self.v = np.ascontiguousarray(v, dtype=np.float64)

    @property
    def nbytes(self):
        return self.out.nbytes + self.q.nbytes + self.v.nbytes


@jit(inline="always")
def rot_dq(q, v, d0, d1, d2, d3):
    """The derivative of ``rot(q, v) = v + 2w (u x v) + 2 u x (u x v)`` in q along d."""
    ux, uy, uz = q[1], q[2], q[3]
    tx = uy * v[2] - uz * v[1]
    ty = uz * v[0] - ux * v[2]
    tz = ux * v[1] - uy * v[0]
    sx = d2 * v[2] - d3 * v[1]
    sy = d3 * v[0] - d1 * v[2]
    sz = d1 * v[1] - d2 * v[0]
    return (2.0 * (d0 * tx + q[0] * sx + (d2 * tz - d3 * ty) + (uy * sz - uz * sy)),
            2.0 * (d0 * ty + q[0] * sy + (d3 * tx - d1 * tz) + (uz * sx - ux * sz)),
            2.0 * (d0 * tz + q[0] * sz + (d1 * ty - d2 * tx) + (ux * sy - uy * sx)))


@jit(inline="always")
def rot_sv(w, ux, uy, uz, vx, vy, vz):
    """``v + 2w (u x v) + 2 u x (u x v)`` (its transpose in v: u -> -u)."""
    tx = 2.0 * (uy * vz - uz * vy)
    ty = 2.0 * (uz * vx - ux * vz)
    tz = 2.0 * (ux * vy - uy * vx)
    return (vx + w * tx + (uy * tz - uz * ty), vy + w * ty + (uz * tx - ux * tz),
            vz + w * tz + (ux * ty - uy * tx))


@jit
def rot_forward(Z, out, o0, f0, q0, v0, sr, q, v):
    """Apply a :class:`RotOp` to the tangents ``Z`` in place."""
    for m in range(out.shape[0]):
        o = out[m]
        a, b, c = rot_dq(q[m], v[m], Z[o, q0], Z[o, q0 + 1], Z[o, q0 + 2], Z[o, q0 + 3])
        if v0 >= 0:
            x, y, z = rot_sv(q[m, 0], q[m, 1], q[m, 2], q[m, 3], Z[o, v0], Z[o, v0 + 1],
                             Z[o, v0 + 2])
            a += x
            b += y
            c += z
        fa, fb, fc = Z[o, f0], Z[o, f0 + 1], Z[o, f0 + 2]
        Z[o, o0] = fa + sr * a
        Z[o, o0 + 1] = fb + sr * b
        Z[o, o0 + 2] = fc + sr * c


@jit
def rot_backward(Zb, out, o0, f0, q0, v0, sr, q, v):
    """The transpose of :func:`rot_forward` in place (items reversed)."""
    for m in range(out.shape[0] - 1, -1, -1):
        o = out[m]
        bx, by, bz = Zb[o, o0], Zb[o, o0 + 1], Zb[o, o0 + 2]
        Zb[o, o0] = 0.0
        Zb[o, o0 + 1] = 0.0
        Zb[o, o0 + 2] = 0.0
        Zb[o, f0] += bx
        Zb[o, f0 + 1] += by
        Zb[o, f0 + 2] += bz
        for j in range(4):
            e0 = 1.0 if j == 0 else 0.0
            e1 = 1.0 if j == 1 else 0.0
            e2 = 1.0 if j == 2 else 0.0
            e3 = 1.0 if j == 3 else 0.0
            a, b, c = rot_dq(q[m], v[m], e0, e1, e2, e3)
            Zb[o, q0 + j] += sr * (a * bx + b * by + c * bz)
        if v0 >= 0:
            x, y, z = rot_sv(q[m, 0], -q[m, 1], -q[m, 2], -q[m, 3], bx, by, bz)
            Zb[o, v0] += sr * x
            Zb[o, v0 + 1] += sr * y
            Zb[o, v0 + 2] += sr * z


# ----------------------------------------------------------------------------- patches, compiled
@jit(inline="always")
def sinc_x2(x2):
    """sin(x) / x as a function of x2 = x^2."""
    if x2 < 1e-6:
        return 1.0 - x2 / 6.0 + x2 * x2 / 120.0
    x = math.sqrt(x2)
    return math.sin(x) / x


@jit(inline="always")
def sinc_x2_d(x2):
    """d/dx2 of :func:`sinc_x2`."""
    if x2 < 1e-3:
        return -1.0 / 6.0 + x2 / 60.0 - x2 * x2 / 2520.0 + x2 * x2 * x2 / 181440.0
    x = math.sqrt(x2)
    return (math.cos(x) - math.sin(x) / x) / (2.0 * x2)


@jit(inline="always")
def atan_over(r2):
    """atan(sqrt(r2)) / sqrt(r2)."""
    if r2 < 1e-8:
        return 1.0 - r2 / 3.0 + r2 * r2 / 5.0
    r = math.sqrt(r2)
    return math.atan(r) / r


@jit(inline="always")
def line_terms(a, b, t, ga, gb, h):
    """The slerp of the volume kernels (weights from the angle, not normalised) between unit
    ``a`` and aligned ``b`` at ``t``: returns ``(wa, wb, ga (4), gb (4))`` with the output
    ``wa a + wb b`` and its derivative ``wa da + wb db + (ga . da + gb . db)(wa' a + wb' b)``
    through the angle; ``ga``, ``gb`` are ``∂ω²/∂a``, ``∂ω²/∂b`` and the last vector is
    returned as ``h`` (4) in the tuple ``(wa, wb, ga, gb, h)``."""
    dn2 = 0.0
    pn2 = 0.0
    for c in range(4):
        dn2 += (a[c] - b[c]) * (a[c] - b[c])
        pn2 += (a[c] + b[c]) * (a[c] + b[c])
    r2 = dn2 / pn2
    A = atan_over(r2)
    w2 = 4.0 * r2 * A * A
    cw = 4.0 * A / (1.0 + r2)                  # dω²/dr²
    u = 1.0 - t
    S0 = sinc_x2(w2)
    Su = sinc_x2(u * u * w2)
    St = sinc_x2(t * t * w2)
    D0 = sinc_x2_d(w2)
    wa = u * Su / S0
    wb = t * St / S0
    wa_d = u * (u * u * sinc_x2_d(u * u * w2) * S0 - Su * D0) / (S0 * S0)
    wb_d = t * (t * t * sinc_x2_d(t * t * w2) * S0 - St * D0) / (S0 * S0)
    p4 = pn2 * pn2
    for c in range(4):
        dv = a[c] - b[c]
        pv = a[c] + b[c]
        ga[c] = cw * (2.0 * dv * pn2 - 2.0 * dn2 * pv) / p4
        gb[c] = cw * (-2.0 * dv * pn2 - 2.0 * dn2 * pv) / p4
        h[c] = wa_d * a[c] + wb_d * b[c]
    return wa, wb


@jit(inline="always")
def _dot4(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]


@jit(inline="always")
def line_tan(a, b, da, db, t, dU, ws):
    """``dU`` = the tangent of :func:`line_terms`' slerp; returns nothing, fills dU (4)
    (``ws``: scratch (3, 4))."""
    ga, gb, h = ws[0], ws[1], ws[2]
    wa, wb = line_terms(a, b, t, ga, gb, h)
    dw = _dot4(ga, da) + _dot4(gb, db)
    for c in range(4):
        dU[c] = wa * da[c] + wb * db[c] + dw * h[c]


@jit(inline="always")
def line_adj(a, b, t, Ub, ab, bb, ws):
    """The adjoint of :func:`line_tan`: ``ab += ∂/∂a``, ``bb += ∂/∂b`` of ``Ub . U``."""
    ga, gb, h = ws[0], ws[1], ws[2]
    wa, wb = line_terms(a, b, t, ga, gb, h)
    g = _dot4(h, Ub)
    for c in range(4):
        ab[c] += wa * Ub[c] + g * ga[c]
        bb[c] += wb * Ub[c] + g * gb[c]


@jit(inline="always")
def _aligned(Q, g, s, out):
    for c in range(4):
        out[c] = s * Q[g, c]


@jit(inline="always")
def patch_state(Q, ii, ff, m, qa, qb, a0, b0, a1, b1, s):
    """The aligned quaternions of patch point ``m`` and the signs (line m, side lines, the side
    points): ``s`` = (sg_m, sg_0, sg_1, ss_0, ss_1)."""
    _aligned(Q, ii[m, 1], ff[m, 4], qa)
    s[0] = -1.0 if _dot4(qa, Q[ii[m, 2]]) < 0.0 else 1.0
    _aligned(Q, ii[m, 2], s[0], qb)
    _aligned(Q, ii[m, 3], ff[m, 5], a0)
    s[1] = -1.0 if _dot4(a0, Q[ii[m, 4]]) < 0.0 else 1.0
    _aligned(Q, ii[m, 4], s[1], b0)
    _aligned(Q, ii[m, 6], ff[m, 6], a1)
    s[2] = -1.0 if _dot4(a1, Q[ii[m, 7]]) < 0.0 else 1.0
    _aligned(Q, ii[m, 7], s[2], b1)


@jit(inline="always")
def patch_value(Q, ii, ff, m, V, sc, s, ws, lt):
    """V (not normalised) of patch point m into ``V``; ``sc`` (9, 4): the aligned quaternions
    (qa, qb, a0, b0, a1, b1) and U, U0, U1; ``s`` (5,): the signs; ``ws`` (3, 3, 4) and ``lt``
    (3, 2): the three lines' :func:`line_terms` (ga, gb, h; wa, wb)."""
    patch_state(Q, ii, ff, m, sc[0], sc[1], sc[2], sc[3], sc[4], sc[5], s)
    for k in range(3):
        a = sc[2 * k]
        b = sc[2 * k + 1]
        t = ff[m, 0] if k == 0 else ff[m, 1 + k]
        wa, wb = line_terms(a, b, t, ws[k, 0], ws[k, 1], ws[k, 2])
        lt[k, 0] = wa
        lt[k, 1] = wb
        for c in range(4):
            sc[6 + k, c] = wa * a[c] + wb * b[c]
    U, U0, U1 = sc[6], sc[7], sc[8]
    s[3] = -1.0 if _dot4(U0, Q[ii[m, 5]]) < 0.0 else 1.0
    s[4] = -1.0 if _dot4(U1, Q[ii[m, 8]]) < 0.0 else 1.0
    sm = ff[m, 1]
    for c in range(4):
        V[c] = (U[c] + (1.0 - sm) * (s[3] * Q[ii[m, 5], c] - U0[c])
                + sm * (s[4] * Q[ii[m, 8], c] - U1[c]))


@jit(inline="always")
def lt_tan(k, da, db, dU, ws, lt):
    """The tangent of line ``k`` of :func:`patch_value` from its stored terms."""
    dw = _dot4(ws[k, 0], da) + _dot4(ws[k, 1], db)
    for c in range(4):
        dU[c] = lt[k, 0] * da[c] + lt[k, 1] * db[c] + dw * ws[k, 2, c]


@jit(inline="always")
def lt_adj(k, Ub, ab, bb, ws, lt):
    """The adjoint of :func:`lt_tan` (accumulating into ``ab``, ``bb``)."""
    g = _dot4(ws[k, 2], Ub)
    for c in range(4):
        ab[c] += lt[k, 0] * Ub[c] + g * ws[k, 0, c]
        bb[c] += lt[k, 1] * Ub[c] + g * ws[k, 1, c]


PATCH_W = 8


@jit(inline="always")
def patch_weight(ff, m, k):
    t, sm, t0, t1 = ff[m, 0], ff[m, 1], ff[m, 2], ff[m, 3]
    if k == 0:
        return 1.0 - t
    if k == 1:
        return t
    if k == 2:
        return -(1.0 - sm) * (1.0 - t0)
    if k == 3:
        return -(1.0 - sm) * t0
    if k == 4:
        return 1.0 - sm
    if k == 5:
        return -sm * (1.0 - t1)
    if k == 6:
        return -sm * t1
    return sm


# the D reads in patch_weight's order: g0m, g1m, g00, g10, gs0, g0e, g1e, gs1 -> columns of ii
_DREAD = (1, 2, 3, 4, 5, 6, 7, 8)


@task_jit
def patch_forward_items(lo, hi, Z, d0, q0, use_q, two, ii, ff, Q, shift, qmin):
    """Tangents of the derived patches' points, in place: Δ/K (8 weights), Q (the normalised
    Soni blend, faded for two-level), the two-level re-basing ``K += rot(Q, shift)``.

    ``ii`` (n, 9): the point and its reads (line ends g0m, g1m; side-0 line ends, side
    point; side-1 line ends, side point); ``ff`` (n, 8): t, sm, t0, t1, the line first-end
    signs (line m, side 0, side 1), the fade; ``Q`` the quaternions the patches read and
    write (the points' own final Q for the re-basing), ``shift`` (G, 3) the re-basing shifts."""
    one = np.zeros(4)
    one[0] = 1.0
    zero = np.zeros(4)
    da = np.empty(4)
    db = np.empty(4)
    dU = np.empty(4)
    dV = np.empty(4)
    V = np.empty(4)
    q = np.empty(4)
    dq = np.empty(4)
    sc = np.empty((9, 4))
    sg = np.empty(5)
    ws = np.empty((3, 3, 4))
    lt = np.empty((3, 2))
    wf = np.empty((3, 4))
    for m in range(lo, hi):
        g = ii[m, 0]
        for c in range(3):
            s = 0.0
            for k in range(8):
                s += patch_weight(ff, m, k) * Z[ii[m, 1 + k], d0 + c]
            Z[g, d0 + c] = s
        if not use_q:
            continue
        patch_value(Q, ii, ff, m, V, sc, sg, ws, lt)
        nv = math.sqrt(_dot4(V, V))
        if nv < qmin:
            for c in range(4):
                Z[g, q0 + c] = 0.0
            continue
        sm = ff[m, 1]
        for c in range(4):
            da[c] = ff[m, 4] * Z[ii[m, 1], q0 + c]
            db[c] = sg[0] * Z[ii[m, 2], q0 + c]
        lt_tan(0, da, db, dU, ws, lt)
        for c in range(4):
            dV[c] = dU[c]
        for side in range(2):
            o = 3 * side
            for c in range(4):
                da[c] = ff[m, 5 + side] * Z[ii[m, 3 + o], q0 + c]
                db[c] = sg[1 + side] * Z[ii[m, 4 + o], q0 + c]
            lt_tan(1 + side, da, db, dU, ws, lt)
            w = (1.0 - sm) if side == 0 else sm
            for c in range(4):
                dV[c] += w * (sg[3 + side] * Z[ii[m, 5 + o], q0 + c] - dU[c])
        for c in range(4):
            q[c] = V[c] / nv
        p = _dot4(q, dV)
        for c in range(4):
            dq[c] = (dV[c] - q[c] * p) / nv
        if two:
            f = ff[m, 7]
            if f <= 0.0:
                for c in range(4):
                    dq[c] = 0.0
            elif f < 1.0:
                sq = -1.0 if q[0] < 0.0 else 1.0
                for c in range(4):
                    q[c] *= sq
                    dq[c] *= sq
                line_tan(one, q, zero, dq, f, dU, wf)
                for c in range(4):
                    dq[c] = dU[c]
            a, b, c3 = rot_dq(Q[g], shift[g], dq[0], dq[1], dq[2], dq[3])
            Z[g, d0] += a
            Z[g, d0 + 1] += b
            Z[g, d0 + 2] += c3
        for c in range(4):
            Z[g, q0 + c] = dq[c]


def patch_forward(Z, d0, q0, use_q, two, ii, ff, Q, shift, qmin):
    """Tangents of the derived patches' points in place (:func:`patch_forward_items` on the
    threads: each point writes its own row and reads the patches' sides only)."""
    with serial_below(PATCH_WORK * ii.shape[0]):
        parallel_for(patch_forward_items, ii.shape[0], Z, d0, q0, use_q, two, ii, ff, Q, shift,
                     qmin)


@task_jit
def patch_adj_items(lo, hi, Zb, d0, q0, use_q, two, ii, ff, Q, shift, qmin, C):
    """The Q adjoints of the patch points ``lo <= m < hi`` (:func:`patch_forward`'s transpose)
    into ``C`` (n, 8, 4), one row per read; ``Zb`` is only read (independent tasks)."""
    one = np.zeros(4)
    one[0] = 1.0
    V = np.empty(4)
    Kb = np.empty(3)
    qb_ = np.empty(4)
    ab = np.empty(4)
    bb = np.empty(4)
    junk = np.empty(4)
    q = np.empty(4)
    Vb = np.empty(4)
    Ub = np.empty(4)
    e = np.empty(4)
    sc = np.empty((9, 4))
    sg = np.empty(5)
    ws = np.empty((3, 3, 4))
    lt = np.empty((3, 2))
    wf = np.empty((3, 4))
    for m in range(lo, hi):
        g = ii[m, 0]
        for k in range(8):
            for c in range(4):
                C[m, k, c] = 0.0
        for c in range(3):
            Kb[c] = Zb[g, d0 + c]
        for c in range(4):
            qb_[c] = Zb[g, q0 + c]
        patch_value(Q, ii, ff, m, V, sc, sg, ws, lt)
        nv = math.sqrt(_dot4(V, V))
        if nv < qmin:
            continue
        for c in range(4):
            q[c] = V[c] / nv
        if two:
            # K += rot(qfin, shift): the faded Q's adjoint gets rot_dq^T Kb
            for j in range(4):
                for c in range(4):
                    e[c] = 0.0
                e[j] = 1.0
                a, b, c3 = rot_dq(Q[g], shift[g], e[0], e[1], e[2], e[3])
                qb_[j] += a * Kb[0] + b * Kb[1] + c3 * Kb[2]
            f = ff[m, 7]
            if f <= 0.0:
                for c in range(4):
                    qb_[c] = 0.0
            elif f < 1.0:
                sq = -1.0 if q[0] < 0.0 else 1.0
                for c in range(4):
                    q[c] *= sq
                    bb[c] = 0.0
                    junk[c] = 0.0
                line_adj(one, q, f, qb_, junk, bb, wf)
                for c in range(4):
                    qb_[c] = sq * bb[c]
                    q[c] *= sq
        p = _dot4(q, qb_)
        for c in range(4):
            Vb[c] = (qb_[c] - q[c] * p) / nv
        sm = ff[m, 1]
        for c in range(4):
            ab[c] = 0.0
            bb[c] = 0.0
        lt_adj(0, Vb, ab, bb, ws, lt)
        for c in range(4):
            C[m, 0, c] += ff[m, 4] * ab[c]
            C[m, 1, c] += sg[0] * bb[c]
        for side in range(2):
            o = 3 * side
            w = (1.0 - sm) if side == 0 else sm
            for c in range(4):
                C[m, 4 + o, c] += w * sg[3 + side] * Vb[c]
                Ub[c] = -w * Vb[c]
                ab[c] = 0.0
                bb[c] = 0.0
            lt_adj(1 + side, Ub, ab, bb, ws, lt)
            for c in range(4):
                C[m, 2 + o, c] += ff[m, 5 + side] * ab[c]
                C[m, 3 + o, c] += sg[1 + side] * bb[c]


@jit
def patch_adj_scatter(Zb, d0, q0, use_q, ii, ff, C):
    """The serial scatter of :func:`patch_adj_items`' adjoints (items reversed, fixed order)."""
    Kb = np.empty(3)
    for m in range(ii.shape[0] - 1, -1, -1):
        g = ii[m, 0]
        for c in range(3):
            Kb[c] = Zb[g, d0 + c]
            Zb[g, d0 + c] = 0.0
        if use_q:
            for c in range(4):
                Zb[g, q0 + c] = 0.0
        for k in range(8):
            w = patch_weight(ff, m, k)
            r = ii[m, 1 + k]
            for c in range(3):
                Zb[r, d0 + c] += w * Kb[c]
            if use_q:
                for c in range(4):
                    Zb[r, q0 + c] += C[m, k, c]


def patch_backward(Zb, d0, q0, use_q, two, ii, ff, Q, shift, qmin):
    """The transpose of :func:`patch_forward` on the adjoints ``Zb`` in place: the items'
    adjoints on the threads, then their scatter in a fixed order (the same bits on any
    number of threads)."""
    C = np.empty((ii.shape[0] if use_q else 0, 8, 4))
    if use_q:
        with serial_below(PATCH_WORK * ii.shape[0]):
            parallel_for(patch_adj_items, ii.shape[0], Zb, d0, q0, use_q, two, ii, ff, Q, shift,
                         qmin, C)
    patch_adj_scatter(Zb, d0, q0, use_q, ii, ff, C if use_q else np.zeros((0, 8, 4)))


class PatchOp:
    """The derived patches (:func:`patch_forward`): 9 indices and 8 numbers per point, the
    derivatives computed on the fly from the quaternions ``Q`` (G, 4) the patches read."""

    __slots__ = ("d0", "q0", "use_q", "two", "ii", "ff", "Q", "shift")
    diag = False

    def __init__(self, d0, q0, use_q, two, ii, ff, Q, shift):
        self.d0, self.q0, self.use_q, self.two = int(d0), int(q0), bool(use_q), bool(two)
        self.ii = np.ascontiguousarray(ii, dtype=np.int32)
        self.ff = np.ascontiguousarray(ff, dtype=np.float64)
        self.Q = np.ascontiguousarray(Q, dtype=np.float64)
        self.shift = np.ascontiguousarray(shift, dtype=np.float64)

    @property
    def nbytes(self):
        return self.ii.nbytes + self.ff.nbytes + self.Q.nbytes

    def args(self):
        return (self.d0, self.q0, self.use_q, self.two, self.ii, self.ff, self.Q, self.shift,
                tfi.QNORM_MIN)


@jit
def exp_forward(Z, rows, i0, o0, v):
    """Tangent of ``Q = [cos(|v|/2), sin(|v|/2) v / |v|]`` (the rigid blend) on rows ``rows``:
    from columns ``i0`` (dv) into ``o0`` (dQ), ``v`` (n, 3) stored."""
    for m in range(rows.shape[0]):
        r = rows[m]
        h2 = 0.25 * (v[m, 0] * v[m, 0] + v[m, 1] * v[m, 1] + v[m, 2] * v[m, 2])
        S = sinc_x2(h2)
        Sd = sinc_x2_d(h2)
        vd = v[m, 0] * Z[r, i0] + v[m, 1] * Z[r, i0 + 1] + v[m, 2] * Z[r, i0 + 2]
        Z[r, o0] = -0.25 * S * vd
        for c in range(3):
            Z[r, o0 + 1 + c] = 0.5 * S * Z[r, i0 + c] + 0.25 * Sd * vd * v[m, c]


@jit
def exp_backward(Zb, rows, i0, o0, v):
    """The transpose of :func:`exp_forward`."""
    for m in range(rows.shape[0] - 1, -1, -1):
        r = rows[m]
        h2 = 0.25 * (v[m, 0] * v[m, 0] + v[m, 1] * v[m, 1] + v[m, 2] * v[m, 2])
        S = sinc_x2(h2)
        Sd = sinc_x2_d(h2)
        b0 = Zb[r, o0]
        b1, b2, b3 = Zb[r, o0 + 1], Zb[r, o0 + 2], Zb[r, o0 + 3]
        for c in range(4):
            Zb[r, o0 + c] = 0.0
        vb = v[m, 0] * b1 + v[m, 1] * b2 + v[m, 2] * b3
        g = -0.25 * S * b0 + 0.25 * Sd * vb
        Zb[r, i0] += 0.5 * S * b1 + g * v[m, 0]
        Zb[r, i0 + 1] += 0.5 * S * b2 + g * v[m, 1]
        Zb[r, i0 + 2] += 0.5 * S * b3 + g * v[m, 2]


class ExpOp:
    """The rigid blend's ``Q = exp(v)`` (3 numbers per point, hand-derived kernels)."""

    __slots__ = ("rows", "i0", "o0", "v")
    diag = False

    def __init__(self, rows, i0, o0, v):
        self.rows = np.ascontiguousarray(rows, dtype=np.int64)
        self.i0, self.o0 = int(i0), int(o0)
        self.v = np.ascontiguousarray(v, dtype=np.float64)

    @property
    def nbytes(self):
        return self.rows.nbytes + self.v.nbytes

    def args(self):
        return self.rows, self.i0, self.o0, self.v


@jit
def pull_forward(Z, out, body, q, v):
    """Apply a :class:`PullOp` to the tangents ``Z`` in place: ``dy = ∂_q rot(q*, v) dq* +
    rot(q*, drd - dt)``, ``(dq, dt)`` from the body row's columns ``BQ:BQ+7``."""
    for m in range(out.shape[0]):
        o, b = out[m], body[m]
        a0, a1, a2 = rot_dq(q[m], v[m], Z[b, BQ], -Z[b, BQ + 1], -Z[b, BQ + 2], -Z[b, BQ + 3])
        x, y, z = rot_sv(q[m, 0], q[m, 1], q[m, 2], q[m, 3], Z[o, RD] - Z[b, BQ + 4],
                         Z[o, RD + 1] - Z[b, BQ + 5], Z[o, RD + 2] - Z[b, BQ + 6])
        Z[o, Y] = a0 + x
        Z[o, Y + 1] = a1 + y
        Z[o, Y + 2] = a2 + z


@jit
def pull_backward(Zb, out, body, q, v):
    """The transpose of :func:`pull_forward` in place (items reversed)."""
    for m in range(out.shape[0] - 1, -1, -1):
        o, b = out[m], body[m]
        bx, by, bz = Zb[o, Y], Zb[o, Y + 1], Zb[o, Y + 2]
        Zb[o, Y] = 0.0
        Zb[o, Y + 1] = 0.0
        Zb[o, Y + 2] = 0.0
        for j in range(4):
            e0 = 1.0 if j == 0 else 0.0
            e1 = 1.0 if j == 1 else 0.0
            e2 = 1.0 if j == 2 else 0.0
            e3 = 1.0 if j == 3 else 0.0
            a, c, d = rot_dq(q[m], v[m], e0, e1, e2, e3)
            g = a * bx + c * by + d * bz
            Zb[b, BQ + j] += g if j == 0 else -g
        x, y, z = rot_sv(q[m, 0], -q[m, 1], -q[m, 2], -q[m, 3], bx, by, bz)
        Zb[o, RD] += x
        Zb[o, RD + 1] += y
        Zb[o, RD + 2] += z
        Zb[b, BQ + 4] -= x
        Zb[b, BQ + 5] -= y
        Zb[b, BQ + 6] -= z


class PullOp:
    """The two-level pull-back ``y = rot(q*, rd - t)`` of the wall rows ``out`` (column
    ``Y``) from their ``rd`` and their body rows' fit ``(q, t)`` (``body``): ``q*`` (n, 4)
    and ``v = rd - t`` (n, 3) stored, the derivative computed on the fly
    (:func:`pull_forward`, :func:`pull_backward`)."""

    __slots__ = ("out", "body", "q", "v")
    diag = False

    def __init__(self, out, body, q, v):
        self.out = np.ascontiguousarray(out, dtype=np.int64)
        self.body = np.ascontiguousarray(body, dtype=np.int64)
        self.q = np.ascontiguousarray(q, dtype=np.float64)
        self.v = np.ascontiguousarray(v, dtype=np.float64)

    @property
    def nbytes(self):
        return self.out.nbytes + self.body.nbytes + self.q.nbytes + self.v.nbytes

    def args(self):
        return self.out, self.body, self.q, self.v


def chain_forward(ops, Z):
    """Run the ops on the tangent state ``Z`` in place."""
    for op in ops:
        if isinstance(op, RotOp):
            rot_forward(Z, op.out, op.o0, op.f0, op.q0, op.v0, op.sr, op.q, op.v)
        elif isinstance(op, PatchOp):
            patch_forward(Z, *op.args())
        elif isinstance(op, SymOp):
            sym_forward(Z, *op.args())
        elif isinstance(op, ExpOp):
            exp_forward(Z, *op.args())
        elif isinstance(op, PullOp):
            pull_forward(Z, *op.args())
        elif op.diag:
            op_forward_diag(Z, op.out, op.o0, op.no, op.idx, op.i0, op.J)
        else:
            op_forward_full(Z, op.out, op.o0, op.no, op.idx, op.i0, op.ni, op.J)


def chain_backward(ops, Zb):
    """Run the transposed ops backward on the adjoint state ``Zb`` in place."""
    for op in reversed(ops):
        if isinstance(op, RotOp):
            rot_backward(Zb, op.out, op.o0, op.f0, op.q0, op.v0, op.sr, op.q, op.v)
        elif isinstance(op, PatchOp):
            patch_backward(Zb, *op.args())
        elif isinstance(op, SymOp):
            sym_backward(Zb, *op.args())
        elif isinstance(op, ExpOp):
            exp_backward(Zb, *op.args())
        elif isinstance(op, PullOp):
            pull_backward(Zb, *op.args())
        elif op.diag:
            op_backward_diag(Zb, op.out, op.o0, op.no, op.idx, op.i0, op.J)
        else:
            op_backward_full(Zb, op.out, op.o0, op.no, op.idx, op.i0, op.ni, op.J)


def _self(rows):
    return np.asarray(rows, dtype=np.int64)[:, None]


def wall_ops(out, o0, idx, i0, J):
    """The wall quaternions' block op (:func:`wall_jacobian`'s ``idx`` (n, k), ``J``
    (n, 4, 3 k)) stored compactly: the rows with at most the usual 5 reads (the stencil) in
    one op of width 5, the few with more (corners, merged copies) in one of their own width
    (the rows are disjoint and the reads precede -1 padding, so the sums and their order are
    those of the single op)."""
    cnt = np.count_nonzero(idx >= 0, axis=1)
    k = idx.shape[1]
    kc = min(k, 5)
    small = cnt <= kc
    ops = []
    for sel, w in ((small, kc), (~small, k)):
        if sel.any():
            ops.append(Op(out[sel], o0, 4, idx[sel, :w], i0, 3, J[sel, :, :3 * w]))
    return ops


def _copy_op(rows, o0, i0, n):
    rows = np.asarray(rows, dtype=np.int64)
    return Op(rows, o0, n, _self(rows), i0, n, np.ones((rows.size, 1)), diag=True)


# ----------------------------------------------------------------------------- complex step
def cs_jacobian(f, X, *args):
    """Jacobian ``(n, m, k)`` of a row-wise function ``f(X (n, k) complex, *args) -> (n, m)``
    by the complex step (exact to round-off: no difference is taken).  The k probes run as
    one call on k n rows (array arguments with n rows are tiled)."""
    X = np.asarray(X, dtype=np.float64)
    n, k = X.shape
    if n == 0:
        m = np.asarray(f(X.astype(np.complex128), *args)).shape[-1]
        return np.zeros((0, m, k))
    Xc = np.tile(X.astype(np.complex128), (k, 1))
    Xc[np.arange(k * n), np.repeat(np.arange(k), n)] += 1j * _H
    out = np.asarray(f(Xc, *[_tile(a, n, k) for a in args])).imag / _H
    return np.moveaxis(out.reshape(k, n, -1), 0, 2)


def _tile(a, n, k):
    if isinstance(a, np.ndarray) and a.ndim >= 1 and a.shape[0] == n:
        return np.tile(a, (k,) + (1,) * (a.ndim - 1))
    return a


def _dot(a, b):
    return np.sum(a * b, axis=-1)


def _cross(a, b):
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _qmul(a, b):
    a0, a1, a2, a3 = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    b0, b1, b2, b3 = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack([a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3,
                     a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
                     a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1,
                     a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0], axis=-1)


def _rot(q, v):
    """rot(q, v) = v + 2w (u x v) + 2 u x (u x v) (any q; unit for a rotation)."""
    u = q[..., 1:]
    t = 2.0 * _cross(u, v)
    return v + q[..., :1] * t + _cross(u, t)


def _normalize(x):
    return x / np.sqrt(_dot(x, x))[..., None]


def _sign(x):
    return np.where(np.real(x) < 0.0, -1.0, 1.0)


def _atan_over(r2):
    """atan(sqrt(r2)) / sqrt(r2), smooth in r2 >= 0 (complex-step safe at 0)."""
    small = np.abs(np.real(r2)) < 1e-6
    safe = np.where(small, 1.0, r2)
    r = np.sqrt(safe)
    big = np.arctan(r) / r
    ser = 1.0 - r2 / 3.0 + r2 * r2 / 5.0 - r2 ** 3 / 7.0
    return np.where(small, ser, big)


def _sinc_sq(x2):
    """sin(x) / x as a function of x2 = x^2 (complex-step safe)."""
    small = np.abs(np.real(x2)) < 1e-6
    safe = np.where(small, 1.0, x2)
    x = np.sqrt(safe)
    return np.where(small, 1.0 - x2 / 6.0 + x2 * x2 / 120.0, np.sin(x) / x)


def _atan2(y, x):
    """atan2 on complex-step numbers (first order in the imaginary parts)."""
    yr, xr = np.real(y), np.real(x)
    d = xr * xr + yr * yr
    d = np.where(d == 0.0, 1.0, d)
    return np.arctan2(yr, xr) + 1j * (xr * np.imag(y) - yr * np.imag(x)) / d


def _omega2(a, b):
    """The slerp angle squared between unit quaternions a and (aligned) b: 4 atan(|a-b|/|a+b|)^2."""
    dn2 = _dot(a - b, a - b)
    pn2 = _dot(a + b, a + b)
    r2 = dn2 / pn2
    return 4.0 * r2 * _atan_over(r2) ** 2


def _slerp_w(t, w2):
    """Slerp weights (sin((1-t)w)/sin w, sin(tw)/sin w) from w2 = w^2."""
    u = 1.0 - t
    sw = _sinc_sq(w2)
    return u * _sinc_sq(u * u * w2) / sw, t * _sinc_sq(t * t * w2) / sw


def cs_slerp(a, b, t, normalise=True):
    """kslerp (normalised) or the volume kernels' slerp (not normalised), b aligned to a."""
    b = _sign(_dot(a, b))[..., None] * b
    wa, wb = _slerp_w(t, _omega2(a, b))
    q = wa[..., None] * a + wb[..., None] * b
    return _normalize(q) if normalise else q


def cs_fade(q, f):
    """fade_and_rebase's ``q <- slerp(1, q, f)`` (exact 1 at f <= 0, q at f >= 1)."""
    one = np.zeros_like(q)
    one[..., 0] = 1.0
    s = _sign(q[..., 0])[..., None]
    out = cs_slerp(one, s * q, f, normalise=False) * 1.0
    out = np.where((np.asarray(f) >= 1.0)[..., None], q, out)
    out = np.where((np.asarray(f) <= 0.0)[..., None], one, out)
    return out


def cs_log(q):
    """quaternion.log_s: the rotation vector of q (w >= 0 taken)."""
    q = _sign(q[..., 0])[..., None] * q
    v = q[..., 1:]
    n2 = _dot(v, v)
    w = q[..., 0]
    # 2 atan2(n, w) / n = 2 atan(n / w) / n / w ... written smooth in n2 for w > 0
    small = np.abs(np.real(n2)) < 1e-24
    ww = np.where(np.real(w) > 0.0, w, 1.0)
    f_pos = 2.0 * _atan_over(n2 / (ww * ww)) / ww
    nn = np.sqrt(np.where(small, 1.0, n2))
    f_gen = 2.0 * _atan2(nn, w) / nn
    f = np.where(np.real(w) > 0.5, f_pos, np.where(small, 2.0 / ww, f_gen))
    return v * f[..., None]


# ----------------------------------------------------------------------------- the fits
def _free_fit(a, R, q, S, cu, tproj):
    from .. import quaternion as qa
    n = a.shape[0]
    M = np.trace(S) * np.eye(3) - S
    Minv = np.linalg.pinv(M, rcond=1e-12)
    J = np.zeros((7, n, 3))
    Q = qa.to_matrix(q)
    for c in range(3):
        rc = R[c]                                  # column c of R^T
        omega = (np.cross(a, rc)) @ Minv.T         # (n, 3)
        dq = 0.5 * _qmul(np.broadcast_to(q, (n, 4)),
                         np.concatenate([np.zeros((n, 1)), omega], axis=1))
        J[:4, :, c] = dq.T
        e = np.zeros(3)
        e[c] = 1.0
        dt = e[None, :] / n - (np.cross(omega, cu) @ Q.T)
        J[4:, :, c] = (dt @ np.asarray(tproj).T).T
    return J.reshape(7, 3 * n)


def fit_jacobian(pu, pd, q, axis, tproj):
    """Jacobian (7, 3n) of ``fit_rigid(pu, pd, axis, tproj) = (q, t)`` in ``pd`` at its result
    ``q``.

    Free rotation (Kabsch): ``S = R^T K`` (``K = Σ b a^T``, centred points) is symmetric at
    the optimum, so the body-frame rotation tangent ``ω`` (``dR = R [ω]x``) solves
    ``(tr S I - S) ω = vee(R^T dK - dK^T R)`` (least squares where singular);
    ``dq = q ⊗ [0, ω] / 2``.  One allowed axis ``n``: ``θ = atan2(Σ n·(a x b), Σ a·(I - n n^T) b)``
    and ``dq = [-sin, cos n] dθ / 2``.  ``t = tproj (cd - rot(q, cu))``.
    """
    from .. import quaternion as qa
    pu = np.asarray(pu, dtype=np.float64)
    pd = np.asarray(pd, dtype=np.float64)
    n = pu.shape[0]
    tproj = np.eye(3) if tproj is None else np.asarray(tproj, dtype=np.float64)
    cu = pu.mean(axis=0)
    a = pu - cu
    b = pd - pd.mean(axis=0)
    R = qa.to_matrix(q)
    if axis is None:
        S = R.T @ (b.T @ a)
        S = 0.5 * (S + S.T)
        return _free_fit(a, R, q, S, cu, tproj)
    J = np.zeros((7, n, 3))
    dtheta = np.zeros((n, 3))
    if np.any(axis):
        nrm = np.asarray(axis, dtype=np.float64)
        sin_ = float(np.sum(_cross(a, b) @ nrm))
        P = np.eye(3) - np.outer(nrm, nrm)
        cos_ = float(np.sum(a @ P * b))
        den = sin_ * sin_ + cos_ * cos_
        if den > 0.0:
            dtheta = (cos_ * _cross(np.broadcast_to(nrm, a.shape), a) - sin_ * (a @ P)) / den
        half = 0.5 * np.arctan2(sin_, cos_)
        J[0] = -np.sin(half) * 0.5 * dtheta
        for k in range(3):
            J[1 + k] = np.cos(half) * nrm[k] * 0.5 * dtheta
        rcu = np.cross(nrm, R @ cu)
    else:
        rcu = np.zeros(3)
    for c in range(3):
        e = np.zeros(3)
        e[c] = 1.0
        dt = e[None, :] / n - dtheta[:, c:c + 1] * rcu[None, :]
        J[4:, :, c] = (dt @ tproj.T).T
    return J.reshape(7, 3 * n)


# ----------------------------------------------------------------------------- linearisation
class Linearisation:
    """The chain of ops of a Deformer at one linearisation point (:func:`linearise`)."""

    def __init__(self, ops, G, nb, passes, two, values):
        #: the passes at the linearisation point (:meth:`Deformer.linear_passes`)
        self.values = values
        self.ops = ops
        self.G = G
        self.nb = nb
        self.passes = passes
        self.two = two


def fields_jvp(deformer, drd):
    """Tangent of the boundary level: ``drd`` (G, 3) -> ``(pass_tangents, dpos)``.

    ``pass_tangents`` is parallel to :meth:`Deformer.linear_passes`: per pass ``(dD, dQ)``,
    ``dD`` (G, 3) and ``dQ`` (G, 4) or None (method "tfi"); ``dpos`` (G, 3) the tangent of
    the boundary points' final positions.  Rows of ``drd`` off the walls are ignored.
    """
    lin = deformer.linearisation()
    G = lin.G
    drd = np.asarray(drd, dtype=np.float64)
    if drd.shape != (G, 3):
        raise ValueError(f"drd must have shape ({G}, 3), got {drd.shape}")
    Z = np.zeros((G + lin.nb, NCOL))
    Z[:G, RD:RD + 3] = drd
    chain_forward(lin.ops, Z)
    return _pass_parts(lin, Z), Z[:G, POS:POS + 3].copy()


def _pass_parts(lin, Z):
    G = lin.G
    out = []
    for d0, q0 in lin.passes:
        out.append((Z[:G, d0:d0 + 3].copy(), None if q0 is None else Z[:G, q0:q0 + 4].copy()))
    return out


def fields_vjp(deformer, pass_bars, pos_bar):
    """The adjoint of :func:`fields_jvp`: ``(pass_bars, pos_bar) -> rd_bar`` (G, 3) (zero off
    the walls).  ``pass_bars``: per pass ``(D_bar, Q_bar)`` (Q_bar None for "tfi"; either, or
    the pair, may be None for zero)."""
    lin = deformer.linearisation()
    G = lin.G
    Zb = np.zeros((G + lin.nb, NCOL))
    if len(pass_bars) != len(lin.passes):
        raise ValueError(f"pass_bars must have {len(lin.passes)} entries, got {len(pass_bars)}")
    for (d0, q0), bars in zip(lin.passes, pass_bars):
        if bars is None:
            continue
        db, qb = bars
        if db is not None:
            Zb[:G, d0:d0 + 3] += np.asarray(db, dtype=np.float64).reshape(G, 3)
        if qb is not None and q0 is not None:
            Zb[:G, q0:q0 + 4] += np.asarray(qb, dtype=np.float64).reshape(G, 4)
    if pos_bar is not None:
        Zb[:G, POS:POS + 3] += np.asarray(pos_bar, dtype=np.float64).reshape(G, 3)
    chain_backward(lin.ops, Zb)
    return Zb[:G, RD:RD + 3].copy()


# ----------------------------------------------------------------------------- stages
# ------------------------------------------------------------------------ wall copies, compiled
@jit(inline="always")
def _c3(ax, ay, az, bx, by, bz):
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@jit
def wall_q_tan(pu, pd, ok, e, curve, dF, out, dout, E, F, au, ad, bu, bd, dad, dbd):
    """The quaternion of one wall point copy (boundary._point_quaternion) on the deformed
    stencil ``pd`` (5, 3) into ``out`` (4) and its hand-derived tangent along the edge
    tangents ``dF`` (4, 3) (edge k: neighbour 1 + k minus the centre) into ``dout`` (4);
    returns False where a normal is undefined."""
    for k in range(4):
        for c in range(3):
            if ok[1 + k]:
                E[k, c] = pu[1 + k, c] - pu[0, c]
                F[k, c] = pd[1 + k, c] - pd[0, c]
            else:
                E[k, c] = 0.0
                F[k, c] = 0.0
    for c in range(3):
        au[c] = 0.0
        ad[c] = 0.0
        bu[c] = 0.0
        bd[c] = 0.0
        dad[c] = 0.0
        dbd[c] = 0.0
        if ok[1] and ok[2]:
            au[c] = E[0, c] - E[1, c]
            ad[c] = F[0, c] - F[1, c]
            dad[c] = dF[0, c] - dF[1, c]
        elif ok[1]:
            au[c] = E[0, c]
            ad[c] = F[0, c]
            dad[c] = dF[0, c]
        elif ok[2]:
            au[c] = -E[1, c]
            ad[c] = -F[1, c]
            dad[c] = -dF[1, c]
        if curve:
            bu[c] = e[c]
            bd[c] = e[c]
        elif ok[3] and ok[4]:
            bu[c] = E[2, c] - E[3, c]
            bd[c] = F[2, c] - F[3, c]
            dbd[c] = dF[2, c] - dF[3, c]
        elif ok[3]:
            bu[c] = E[2, c]
            bd[c] = F[2, c]
            dbd[c] = dF[2, c]
        elif ok[4]:
            bu[c] = -E[3, c]
            bd[c] = -F[3, c]
            dbd[c] = -dF[3, c]
    nx, ny, nz = _c3(au[0], au[1], au[2], bu[0], bu[1], bu[2])
    nn = nx * nx + ny * ny + nz * nz
    mx, my, mz = _c3(ad[0], ad[1], ad[2], bd[0], bd[1], bd[2])
    p1 = _c3(dad[0], dad[1], dad[2], bd[0], bd[1], bd[2])
    p2 = _c3(ad[0], ad[1], ad[2], dbd[0], dbd[1], dbd[2])
    dmx, dmy, dmz = p1[0] + p2[0], p1[1] + p2[1], p1[2] + p2[2]
    mn = mx * mx + my * my + mz * mz
    la = au[0] * au[0] + au[1] * au[1] + au[2] * au[2]
    lb = bu[0] * bu[0] + bu[1] * bu[1] + bu[2] * bu[2]
    ma = ad[0] * ad[0] + ad[1] * ad[1] + ad[2] * ad[2]
    mb = bd[0] * bd[0] + bd[1] * bd[1] + bd[2] * bd[2]
    d2 = 1e-20
    if not (la > 0.0 and lb > 0.0 and nn > d2 * la * lb and ma > 0.0 and mb > 0.0
            and mn > d2 * ma * mb):
        return False
    if not curve and (la <= d2 * lb or lb <= d2 * la or ma <= d2 * mb or mb <= d2 * ma):
        return False
    sn = math.sqrt(nn)
    ux, uy, uz = nx / sn, ny / sn, nz / sn
    sm = math.sqrt(mn)
    dx, dy, dz = mx / sm, my / sm, mz / sm
    pr = dx * dmx + dy * dmy + dz * dmz
    ddx, ddy, ddz = (dmx - dx * pr) / sm, (dmy - dy * pr) / sm, (dmz - dz * pr) / sm
    if curve:
        cx, cy, cz = _c3(ux, uy, uz, dx, dy, dz)
        dcx, dcy, dcz = _c3(ux, uy, uz, ddx, ddy, ddz)
        y = e[0] * cx + e[1] * cy + e[2] * cz
        x = ux * dx + uy * dy + uz * dz
        dy_ = e[0] * dcx + e[1] * dcy + e[2] * dcz
        dx_ = ux * ddx + uy * ddy + uz * ddz
        den = x * x + y * y
        if den == 0.0:
            den = 1.0
        h = 0.5 * math.atan2(y, x)
        dh = 0.5 * (x * dy_ - y * dx_) / den
        sh, ch = math.sin(h), math.cos(h)
        a0, a1, a2, a3 = ch, e[0] * sh, e[1] * sh, e[2] * sh
        da0, da1, da2, da3 = -sh * dh, e[0] * ch * dh, e[1] * ch * dh, e[2] * ch * dh
    else:
        cc_ = ux * dx + uy * dy + uz * dz
        dcc_ = ux * ddx + uy * ddy + uz * ddz
        vx, vy, vz = _c3(ux, uy, uz, dx, dy, dz)
        dvx, dvy, dvz = _c3(ux, uy, uz, ddx, ddy, ddz)
        w = 1.0 + cc_
        n = math.sqrt(w * w + vx * vx + vy * vy + vz * vz)
        a0, a1, a2, a3 = w / n, vx / n, vy / n, vz / n
        dn = (w * dcc_ + vx * dvx + vy * dvy + vz * dvz) / n
        da0, da1, da2, da3 = ((dcc_ - a0 * dn) / n, (dvx - a1 * dn) / n, (dvy - a2 * dn) / n,
                              (dvz - a3 * dn) / n)
    st = math.sqrt(au[0] * au[0] + au[1] * au[1] + au[2] * au[2])
    t1x, t1y, t1z = au[0] / st, au[1] / st, au[2] / st
    t2x, t2y, t2z = _c3(ux, uy, uz, t1x, t1y, t1z)
    qx = 2.0 * (a2 * t1z - a3 * t1y)
    qy = 2.0 * (a3 * t1x - a1 * t1z)
    qz = 2.0 * (a1 * t1y - a2 * t1x)
    dqx = 2.0 * (da2 * t1z - da3 * t1y)
    dqy = 2.0 * (da3 * t1x - da1 * t1z)
    dqz = 2.0 * (da1 * t1y - da2 * t1x)
    T1x = t1x + a0 * qx + (a2 * qz - a3 * qy)
    T1y = t1y + a0 * qy + (a3 * qx - a1 * qz)
    T1z = t1z + a0 * qz + (a1 * qy - a2 * qx)
    dT1x = da0 * qx + a0 * dqx + (da2 * qz + a2 * dqz - da3 * qy - a3 * dqy)
    dT1y = da0 * qy + a0 * dqy + (da3 * qx + a3 * dqx - da1 * qz - a1 * dqz)
    dT1z = da0 * qz + a0 * dqz + (da1 * qy + a1 * dqy - da2 * qx - a2 * dqx)
    T2x, T2y, T2z = _c3(dx, dy, dz, T1x, T1y, T1z)
    r1 = _c3(ddx, ddy, ddz, T1x, T1y, T1z)
    r2 = _c3(dx, dy, dz, dT1x, dT1y, dT1z)
    dT2x, dT2y, dT2z = r1[0] + r2[0], r1[1] + r2[1], r1[2] + r2[2]
    ss = 0.0
    cc = 0.0
    dss = 0.0
    dcc = 0.0
    for k in range(4):
        if not ok[1 + k]:
            continue
        ex, ey, ez = E[k, 0], E[k, 1], E[k, 2]
        fx, fy, fz = F[k, 0], F[k, 1], F[k, 2]
        gx, gy, gz = dF[k, 0], dF[k, 1], dF[k, 2]
        a1_ = ex * t1x + ey * t1y + ez * t1z
        a2_ = ex * t2x + ey * t2y + ez * t2z
        b1 = fx * T1x + fy * T1y + fz * T1z
        b2 = fx * T2x + fy * T2y + fz * T2z
        db1 = gx * T1x + gy * T1y + gz * T1z + fx * dT1x + fy * dT1y + fz * dT1z
        db2 = gx * T2x + gy * T2y + gz * T2z + fx * dT2x + fy * dT2y + fz * dT2z
        la2 = a1_ * a1_ + a2_ * a2_
        lb2 = b1 * b1 + b2 * b2
        if not (la2 > d2 * (ex * ex + ey * ey + ez * ez) and
                lb2 > d2 * (fx * fx + fy * fy + fz * fz)):
            continue
        inv = 1.0 / math.sqrt(la2 * lb2)
        dinv = -inv * (b1 * db1 + b2 * db2) / lb2
        s_ = a1_ * b2 - a2_ * b1
        c_ = a1_ * b1 + a2_ * b2
        ss += s_ * inv
        cc += c_ * inv
        dss += (a1_ * db2 - a2_ * db1) * inv + s_ * dinv
        dcc += (a1_ * db1 + a2_ * db2) * inv + c_ * dinv
    r = math.sqrt(ss * ss + cc * cc)
    dr = (ss * dss + cc * dcc) / r
    if cc >= 0.0:
        hw, hs = r + cc, ss
        dhw, dhs = dr + dcc, dss
    else:
        hw, hs = ss, r - cc
        dhw, dhs = dss, dr - dcc
        if hw < 0.0:
            hw, hs, dhw, dhs = -hw, -hs, -dhw, -dhs
    hn = math.sqrt(hw * hw + hs * hs)
    hw = hw / hn
    hs = hs / hn
    dhn = hw * dhw + hs * dhs
    dhw = (dhw - hw * dhn) / hn
    dhs = (dhs - hs * dhn) / hn
    b0, b1_, b2_, b3 = hw, dx * hs, dy * hs, dz * hs
    db0, db1_, db2_, db3 = dhw, ddx * hs + dx * dhs, ddy * hs + dy * dhs, ddz * hs + dz * dhs
    out[0] = b0 * a0 - b1_ * a1 - b2_ * a2 - b3 * a3
    out[1] = b0 * a1 + b1_ * a0 + b2_ * a3 - b3 * a2
    out[2] = b0 * a2 - b1_ * a3 + b2_ * a0 + b3 * a1
    out[3] = b0 * a3 + b1_ * a2 - b2_ * a1 + b3 * a0
    dout[0] = (db0 * a0 - db1_ * a1 - db2_ * a2 - db3 * a3
               + b0 * da0 - b1_ * da1 - b2_ * da2 - b3 * da3)
    dout[1] = (db0 * a1 + db1_ * a0 + db2_ * a3 - db3 * a2
               + b0 * da1 + b1_ * da0 + b2_ * da3 - b3 * da2)
    dout[2] = (db0 * a2 - db1_ * a3 + db2_ * a0 + db3 * a1
               + b0 * da2 - b1_ * da3 + b2_ * da0 + b3 * da1)
    dout[3] = (db0 * a3 + db1_ * a2 - db2_ * a1 + db3 * a0
               + b0 * da3 + b1_ * da2 - b2_ * da1 + b3 * da0)
    return True


@task_jit
def wall_copies_tan(lo, hi, pu_s, pd_s, ok, e, curve, qc, Jc, good):
    """The copies ``lo <= m < hi`` of a wall patch: the quaternion ``qc`` (n, 4), its
    Jacobian ``Jc`` (n, 4, 15) in the deformed stencil (hand-derived tangents of
    :func:`wall_q_tan`, one per neighbour coordinate) and the defined flag ``good``
    (independent items)."""
    out = np.empty(4)
    dout = np.empty(4)
    dF = np.zeros((4, 3))
    E = np.empty((4, 3))
    F = np.empty((4, 3))
    au = np.empty(3)
    ad = np.empty(3)
    bu = np.empty(3)
    bd = np.empty(3)
    dad = np.empty(3)
    dbd = np.empty(3)
    for m in range(lo, hi):
        g = wall_q_tan(pu_s[m], pd_s[m], ok[m], e, curve, dF, out, dout, E, F, au, ad, bu,
                       bd, dad, dbd)
        good[m] = g
        for c in range(4):
            qc[m, c] = out[c] if g else np.nan
        for j in range(3, 15):
            s, c0 = j // 3, j % 3
            if not (g and ok[m, s]):
                for c in range(4):
                    Jc[m, c, j] = 0.0
                continue
            dF[s - 1, c0] = 1.0
            wall_q_tan(pu_s[m], pd_s[m], ok[m], e, curve, dF, out, dout, E, F, au, ad, bu,
                       bd, dad, dbd)
            dF[s - 1, c0] = 0.0
            for c in range(4):
                Jc[m, c, j] = dout[c]
        # q depends on the stencil through its edges only: the centre's column is minus
        # the sum of the neighbours'
        for c in range(4):
            for c0 in range(3):
                acc = 0.0
                for s in range(1, 5):
                    acc += Jc[m, c, 3 * s + c0]
                Jc[m, c, c0] = -acc


@jit
def sym_forward(Z, rows, c0, Y, arm, carm, point, normal):
    """Tangent of the symmetry fix (stages.symmetry_fix with Q) on rows ``rows`` (columns
    ``c0:c0+7`` = (F, Q)), hand-derived, from the stored inputs ``Y`` (n, 7) and arms:
    ``dF' = (I - n n^T)(dF + ∂_q rot(q, arm) dq) - ∂_q rot(tw, arm) dtw``, ``tw`` the
    normalised twist ``[q0, (q_v . n) n]``."""
    tw = np.empty(4)
    for m in range(rows.shape[0]):
        r = rows[m]
        nrm = normal[m]
        nr = symmetry_twist(Y[m, 3], Y[m, 4], Y[m, 5], Y[m, 6], nrm[0], nrm[1], nrm[2], tw)
        q = Y[m, 3:7]
        a0, a1, a2 = rot_dq(q, arm[m], Z[r, c0 + 3], Z[r, c0 + 4], Z[r, c0 + 5], Z[r, c0 + 6])
        x0 = Z[r, c0] + a0
        x1 = Z[r, c0 + 1] + a1
        x2 = Z[r, c0 + 2] + a2
        dn = x0 * nrm[0] + x1 * nrm[1] + x2 * nrm[2]
        x0 -= dn * nrm[0]
        x1 -= dn * nrm[1]
        x2 -= dn * nrm[2]
        if nr == 0.0:
            d0 = d1 = d2 = d3 = 0.0
        else:
            du = Z[r, c0 + 4] * nrm[0] + Z[r, c0 + 5] * nrm[1] + Z[r, c0 + 6] * nrm[2]
            r0, r1, r2, r3 = Z[r, c0 + 3], du * nrm[0], du * nrm[1], du * nrm[2]
            p = tw[0] * r0 + tw[1] * r1 + tw[2] * r2 + tw[3] * r3
            d0 = (r0 - tw[0] * p) / nr
            d1 = (r1 - tw[1] * p) / nr
            d2 = (r2 - tw[2] * p) / nr
            d3 = (r3 - tw[3] * p) / nr
        b0, b1, b2 = rot_dq(tw, arm[m], d0, d1, d2, d3)
        Z[r, c0] = x0 - b0
        Z[r, c0 + 1] = x1 - b1
        Z[r, c0 + 2] = x2 - b2
        Z[r, c0 + 3] = d0
        Z[r, c0 + 4] = d1
        Z[r, c0 + 5] = d2
        Z[r, c0 + 6] = d3


@jit
def sym_backward(Zb, rows, c0, Y, arm, carm, point, normal):
    """The transpose of :func:`sym_forward` in place (items reversed)."""
    tw = np.empty(4)
    tb = np.empty(4)
    for m in range(rows.shape[0] - 1, -1, -1):
        r = rows[m]
        nrm = normal[m]
        nr = symmetry_twist(Y[m, 3], Y[m, 4], Y[m, 5], Y[m, 6], nrm[0], nrm[1], nrm[2], tw)
        q = Y[m, 3:7]
        a0, a1, a2 = Zb[r, c0], Zb[r, c0 + 1], Zb[r, c0 + 2]
        for c in range(4):
            tb[c] = Zb[r, c0 + 3 + c]
        for c in range(7):
            Zb[r, c0 + c] = 0.0
        dn = a0 * nrm[0] + a1 * nrm[1] + a2 * nrm[2]
        p0, p1, p2 = a0 - dn * nrm[0], a1 - dn * nrm[1], a2 - dn * nrm[2]
        Zb[r, c0] += p0
        Zb[r, c0 + 1] += p1
        Zb[r, c0 + 2] += p2
        for j in range(4):
            e0 = 1.0 if j == 0 else 0.0
            e1 = 1.0 if j == 1 else 0.0
            e2 = 1.0 if j == 2 else 0.0
            e3 = 1.0 if j == 3 else 0.0
            x, y, z = rot_dq(q, arm[m], e0, e1, e2, e3)
            Zb[r, c0 + 3 + j] += x * p0 + y * p1 + z * p2
            x, y, z = rot_dq(tw, arm[m], e0, e1, e2, e3)
            tb[j] -= x * a0 + y * a1 + z * a2
        if nr == 0.0:
            continue
        p = tw[0] * tb[0] + tw[1] * tb[1] + tw[2] * tb[2] + tw[3] * tb[3]
        for c in range(4):
            tb[c] = (tb[c] - tw[c] * p) / nr
        Zb[r, c0 + 3] += tb[0]
        du = tb[1] * nrm[0] + tb[2] * nrm[1] + tb[3] * nrm[2]
        for c in range(3):
            Zb[r, c0 + 4 + c] += du * nrm[c]


class SymOp:
    """The symmetry fix with Q: 7 + 3 numbers per point (its inputs and arm), the
    hand-derived kernels :func:`sym_forward`, :func:`sym_backward`."""

    __slots__ = ("rows", "c0", "Y", "arm", "carm", "point", "normal")
    diag = False

    def __init__(self, rows, c0, Y, arm, carm, point, normal):
        self.rows = np.ascontiguousarray(rows, dtype=np.int64)
        self.c0 = int(c0)
        self.Y = np.ascontiguousarray(Y, dtype=np.float64)
        self.arm = np.ascontiguousarray(arm, dtype=np.float64)
        self.carm = np.ascontiguousarray(carm, dtype=np.float64)
        self.point = point
        self.normal = normal

    @property
    def nbytes(self):
        return self.rows.nbytes + self.Y.nbytes + self.arm.nbytes

    def args(self):
        return self.rows, self.c0, self.Y, self.arm, self.carm, self.point, self.normal


def wall_jacobian(sk, rd_in, centre):
    """The Jacobian of the merged wall quaternions (:func:`stages.wall_quaternions`) in the
    targets ``rd_in`` (G, 3): ``(idx (n_wall, k), J (n_wall, 4, 3 k))``, -1 for no read."""
    with np.errstate(all="ignore"):         # undefined normals: NaN, then filled
        return _wall_jacobian(sk, rd_in, centre)


def _wall_jacobian(sk, rd_in, centre):
    from ..boundary import motion_padded
    from .stages import halo_points
    pts = sk.points
    wall = pts.wall
    nw = wall.size
    curve = sk.ndim == 2
    e = np.array([0.0, 0.0, 1.0]) if curve else np.zeros(3)
    seq_w, seq_q = [], []                     # the copies, in the step's merge order
    r_w, r_g, r_b = [], [], []                # their reads: copy, gid, (4, 3) block
    ident = np.eye(3)
    for w, lid in zip(sk.walls.patches, sk.walls.local):
        pd = np.empty_like(w.pu)
        halo_points(rd_in, w.halo.ravel(), w.mirror.ravel(), pts.plane_o, pts.plane_n,
                    pd.reshape(-1, 3))
        na = pd.shape[0] - 2
        nb = 1 if curve else pd.shape[1] - 2
        qf, _ = motion_padded(w.pu, pd, 1, 0 if curve else 1, curve, e, centre, na, nb)
        qf = qf.reshape(-1, 4)
        halo = w.halo.reshape(na + 2, -1) if not curve else w.halo.reshape(-1, 1)
        mirror = w.mirror.reshape(halo.shape)
        pu_p = w.pu.reshape(halo.shape + (3,)) if not curve else w.pu.reshape(-1, 1, 3)
        pd_p = pd.reshape(pu_p.shape)
        I, J = np.meshgrid(np.arange(na) + 1, np.arange(nb) + (0 if curve else 1), indexing="ij")
        I, J = I.ravel(), J.ravel()
        offs = [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)]
        gids = np.full((I.size, 5), -1, dtype=np.int64)
        mirr = np.full((I.size, 5), -1, dtype=np.int64)
        pu_s = np.zeros((I.size, 5, 3))
        pd_s = np.zeros((I.size, 5, 3))
        for s, (di, dj) in enumerate(offs):
            if curve and dj != 0:
                continue
            a, b = I + di, J + dj
            inside = (a >= 0) & (b >= 0) & (a < halo.shape[0]) & (b < halo.shape[1])
            a2, b2 = np.where(inside, a, 0), np.where(inside, b, 0)
            g = np.where(inside, halo[a2, b2], -1)
            gids[:, s] = g
            mirr[:, s] = np.where(inside, mirror[a2, b2], -1)
            pu_s[:, s] = np.where((g >= 0)[:, None], pu_p[a2, b2], 0.0)
            pd_s[:, s] = np.where((g >= 0)[:, None], pd_p[a2, b2], 0.0)
        ok = gids >= 0
        qc = np.empty((I.size, 4))
        Jc = np.empty((I.size, 4, 15))
        good = np.empty(I.size, dtype=np.bool_)
        with serial_below(WALL_WORK * I.size):
            parallel_for(wall_copies_tan, I.size, pu_s, pd_s, ok, e, curve, qc, Jc, good)
        # defined normals; the others the step fills from their neighbours (below)
        good &= np.all(np.isfinite(qc), axis=1) & (np.abs(np.sum(qc * qf, axis=1)) > 1.0 - 1e-8)
        Jb = Jc.reshape(-1, 4, 5, 3)
        mm = mirr >= 0
        if mm.any():                         # mirrored halo points: X -> (I - 2 n n^T) X
            Jb = Jb.copy()
            nn = pts.plane_n[mirr[mm]]
            M = ident - 2.0 * nn[:, :, None] * nn[:, None, :]
            mi, mk = np.nonzero(mm)
            Jb[mi, :, mk] = np.matmul(Jb[mi, :, mk], M)
        qcur = np.where(good[:, None], qc, np.nan)
        rows = _Rows(gids, Jb)
        _fill_rows(qcur, rows, good, na, nb)
        sg = np.where(np.sum(qcur * qf, axis=1) < 0.0, -1.0, 1.0)
        n0 = len(seq_w)
        seq_w.extend(lid.tolist())
        seq_q.append(qf)
        dense = good[:, None] & (gids >= 0)
        r_w.append(np.broadcast_to((n0 + np.arange(I.size))[:, None], gids.shape)[dense])
        r_g.append(gids[dense])
        r_b.append((sg[:, None, None, None] * np.moveaxis(Jb, 2, 1))[dense])
        for m in np.flatnonzero(~good):
            if rows[m]:
                gl = sorted(rows[m])
                r_w.append(np.full(len(gl), n0 + m))
                r_g.append(np.array(gl, dtype=np.int64))
                r_b.append(sg[m] * np.array([rows[m][g] for g in gl]))
    # the hemisphere-aligned merge of the copies of each wall point, in the step's order
    cw = np.array(seq_w, dtype=np.int64)
    cq = np.concatenate(seq_q) if seq_q else np.zeros((0, 4))
    order = np.argsort(cw, kind="stable")
    first = np.r_[True, cw[order][1:] != cw[order][:-1]]
    rank = np.empty(cw.size, dtype=np.int64)
    start = np.maximum.accumulate(np.where(first, np.arange(cw.size), 0))
    rank[order] = np.arange(cw.size) - start
    acc = np.zeros((nw, 4))
    csg = np.ones(cw.size)
    for r in range(int(rank.max(initial=-1)) + 1):
        sel = np.flatnonzero(rank == r)
        w_ = cw[sel]
        if r:
            csg[sel] = np.where(np.sum(acc[w_] * cq[sel], axis=1) >= 0.0, 1.0, -1.0)
        acc[w_] += csg[sel, None] * cq[sel]
    nrm = np.linalg.norm(acc, axis=1)
    qn = acc / nrm[:, None]
    Pm = (np.eye(4)[None] - qn[:, :, None] * qn[:, None, :]) / nrm[:, None, None]
    # the reads of every wall point: (wall point, gid) summed over copies
    rc = np.concatenate(r_w) if r_w else np.zeros(0, np.int64)
    rg = np.concatenate(r_g) if r_g else np.zeros(0, np.int64)
    rb = np.concatenate(r_b) if r_b else np.zeros((0, 4, 3))
    rw = cw[rc]
    rb = np.matmul(Pm[rw], rb * csg[rc, None, None])
    key, inv = np.unique(rw * (pts.n_global + 1) + rg, return_inverse=True)
    blocks = np.zeros((key.size, 4, 3))
    np.add.at(blocks, inv, rb)
    kw = key // (pts.n_global + 1)
    kg = key % (pts.n_global + 1)
    firstk = np.r_[True, kw[1:] != kw[:-1]]
    slot = np.arange(key.size) - np.maximum.accumulate(np.where(firstk, np.arange(key.size), 0))
    kmax = int(slot.max(initial=0)) + 1
    idx = np.full((nw, kmax), -1, dtype=np.int64)
    Jw = np.zeros((nw, kmax, 4, 3))
    idx[kw, slot] = kg
    Jw[kw, slot] = blocks
    return idx, np.ascontiguousarray(np.moveaxis(Jw, 1, 2).reshape(nw, 4, 3 * kmax))


class _Rows(dict):
    """Sparse Jacobian rows of the wall point copies of a patch (gid -> (4, 3)), made on
    demand from the dense stencil blocks of the defined copies."""

    def __init__(self, gids, Jb):
        super().__init__()
        self.gids = gids
        self.Jb = Jb

    def __missing__(self, m):
        row = {}
        for k in range(5):
            g = int(self.gids[m, k])
            if g >= 0:
                row[g] = row.get(g, 0.0) + self.Jb[m, :, k]
        self[m] = row
        return row


def _fill_rows(q, rows, ok, na, nb):
    """The forward's filling of undefined wall points (boundary._fill_degenerate: sweeps, each
    undefined point the normalised hemisphere-aligned sum of its defined 8-neighbours) on the
    values ``q`` (n, 4) and the sparse Jacobian rows ``rows`` (gid -> (4, 3)), in place.
    Points with no defined point anywhere get an empty row."""
    okm = ok.copy()
    while not okm.all():
        cur = okm.copy()
        filled = left = 0
        for m in np.flatnonzero(~okm):
            i, j = divmod(int(m), nb)
            nbrs = [(a * nb + b) for a in range(i - 1, i + 2) for b in range(j - 1, j + 2)
                    if (a, b) != (i, j) and 0 <= a < na and 0 <= b < nb and okm[a * nb + b]]
            if not nbrs:
                left += 1
                continue
            ref = q[nbrs[0]]
            acc = np.zeros(4)
            row = {}
            for k in nbrs:
                s = -1.0 if q[k] @ ref < 0.0 else 1.0
                acc += s * q[k]
                for g, blk in rows[k].items():
                    row[g] = row.get(g, 0.0) + s * blk
            nrm = np.linalg.norm(acc)
            qn = acc / nrm
            Pm = (np.eye(4) - np.outer(qn, qn)) / nrm
            q[m] = qn
            rows[m] = {g: Pm @ blk for g, blk in row.items()}
            cur[m] = True
            filled += 1
        okm[:] = cur
        if left == 0 or filled == 0:
            break
    for m in np.flatnonzero(~okm):
        rows[m] = {}
        q[m] = (1.0, 0.0, 0.0, 0.0)


def _vertex_ops(sk, Qcur, dcol, qcol, two):
    """Free vertices: Δ/K (diag), the aligned weighted sum into T (diag), Q = slerp(1,
    normalise(T), decay)."""
    vx = sk.vertices
    if vx.idw is None:
        return []
    src, w, decay, ref = vx.idw
    free = vx.free
    ops = [Op(free, dcol, 3, np.broadcast_to(src, w.shape), dcol, 3, decay[:, None] * w, diag=True)]
    if qcol is None:
        return ops
    qs = Qcur[src]
    qref = qs[ref]
    sign = np.where(qref @ qs.T >= 0.0, 1.0, -1.0)
    qbar = (w * sign) @ qs
    norm = np.linalg.norm(qbar, axis=1)
    small = norm < 1e-6
    W = np.where(small[:, None], 0.0, w * sign)
    idxs = np.broadcast_to(src, w.shape).copy()
    if small.any():
        W[small] = 0.0
        W[small, ref[small]] = 1.0
    ops.append(Op(free, T0, 4, idxs, qcol, 4, W, diag=True))
    Tv = np.where(small[:, None], qref, qbar)

    def f(X, dec, sm):
        q = np.where(sm[:, None], X, _normalize(X))
        one = np.zeros_like(q)
        one[:, 0] = 1.0
        return cs_slerp(one, q, dec)

    ops.append(Op(free, qcol, 4, _self(free), T0, 4, cs_jacobian(f, Tv, decay, small)))
    return ops


def _rebase_op(rows, Q, shift):
    """K[p] += rot(Q[p], shift[p]) (two-level re-basing), reading K and Q of the row."""
    return RotOp(rows, K0, K0, Q0, -1, 1.0, Q[rows], shift[rows])


def _segment_ops(sk, Qcur, dcol, qcol, two):
    """The gaps level by level (a level reads earlier levels only)."""
    if sk.segments is None:
        return []
    left, right, ptr, pts, s = sk.segments.arrays()
    level = np.zeros(sk.n_global, dtype=np.int64)
    glev = np.zeros(left.size, dtype=np.int64)
    for g in range(left.size):
        lv = 1 + max(level[left[g]], level[right[g]])
        glev[g] = lv
        level[pts[ptr[g]:ptr[g + 1]]] = lv
    counts = np.diff(ptr)
    pa = np.repeat(left, counts)
    pb = np.repeat(right, counts)
    plev = np.repeat(glev, counts)
    ops = []
    for lv in range(1, int(glev.max(initial=0)) + 1):
        sel = plev == lv
        rows, a, b, t = pts[sel], pa[sel], pb[sel], s[sel]
        ops.append(Op(rows, dcol, 3, np.stack([a, b], 1), dcol, 3,
                      np.stack([1.0 - t, t], 1), diag=True))
        if qcol is None:
            continue
        damp = two.damp[rows] if two is not None else None

        def f(X, t, damp):
            q = cs_slerp(X[:, :4], X[:, 4:], t)
            return q if damp is None else cs_fade(q, damp)

        X = np.concatenate([Qcur[a], Qcur[b]], axis=1)
        ops.append(Op(rows, qcol, 4, np.stack([a, b], 1), qcol, 4, cs_jacobian(f, X, t, damp)))
        if two is not None:
            ops.append(_rebase_op(rows, Qcur, two.shift))
    return ops


def patch_ops(sk, Qcur, dcol, qcol, two):
    """The derived patches: Δ/K (diag, 8 reads), Q (the normalised Soni blend of 8 quaternions,
    faded for two-level), the re-basing."""
    rows, idx, wd, X, cst = [], [], [], [], []
    for p in sk.patches.items:
        lead = p.lead
        Gp = p.gid if lead == 0 else p.gid.T
        Sp = p.s if lead == 0 else np.transpose(p.s, (1, 0, 2))
        Wp = p.write if lead == 0 else p.write.T
        nl, nm = Gp.shape
        if nl < 3 or nm < 3:
            continue
        tt = Sp[..., lead]
        ss = Sp[..., 1 - lead]
        s0 = np.ones(nm)
        if qcol is not None:
            prev = None
            for m in range(nm):
                q = Qcur[Gp[0, m]]
                if prev is not None and prev @ q < 0.0:
                    s0[m] = -1.0
                prev = s0[m] * q
        L, M = np.meshgrid(np.arange(1, nl - 1), np.arange(1, nm - 1), indexing="ij")
        keep = Wp[L, M]
        L, M = L[keep], M[keep]
        g = Gp[L, M]
        t, sm = tt[L, M], ss[L, M]
        t0, t1 = tt[L, 0], tt[L, nm - 1]
        reads = np.stack([Gp[0, M], Gp[nl - 1, M], Gp[0, 0].repeat(L.size),
                          Gp[nl - 1, 0].repeat(L.size),
                          Gp[L, 0], Gp[0, nm - 1].repeat(L.size), Gp[nl - 1, nm - 1].repeat(L.size),
                          Gp[L, nm - 1]], 1)
        wts = np.stack([1.0 - t, t, -(1.0 - sm) * (1.0 - t0), -(1.0 - sm) * t0, 1.0 - sm,
                        -sm * (1.0 - t1), -sm * t1, sm], 1)
        rows.append(g)
        idx.append(reads)
        wd.append(wts)
        cst.append(np.stack([t, sm, t0, t1, s0[M], np.full(L.size, s0[0]),
                             np.full(L.size, s0[-1])], 1))
    if not rows:
        return []
    rows = np.concatenate(rows)
    ii = np.concatenate([rows[:, None], np.concatenate(idx)], axis=1)
    cst = np.concatenate(cst)
    damp = two.damp[rows] if two is not None else np.zeros(rows.size)
    ff = np.concatenate([cst, damp[:, None]], axis=1)
    use_q = qcol is not None
    Q = Qcur if use_q else np.zeros((1, 4))
    shift = two.shift if two is not None else np.zeros((1, 3))
    return [PatchOp(dcol, qcol if use_q else 0, use_q, two is not None, ii, ff, Q, shift)]


def _symmetry_op(sk, F, Q, X, carm, dcol, use_q):
    """Symmetry points (stages.symmetry_fix): reads F and Q of the row, writes both."""
    sym = sk.symmetry
    g = sym.gids
    if not g.size:
        return []
    n = sym.normal
    if not use_q:
        J = np.eye(3)[None] - n[:, :, None] * n[:, None, :]
        return [Op(g, dcol, 3, _self(g), dcol, 3, J)]

    Y = np.concatenate([F[g], Q[g]], axis=1)
    return [SymOp(g, dcol, Y, X[g] - carm, carm, sym.point, n)]


def _project_op(sk, col=POS):
    sym = sk.symmetry
    g = sym.gids
    if not g.size:
        return []
    n = sym.normal
    J = np.eye(3)[None] - n[:, :, None] * n[:, None, :]
    return [Op(g, col, 3, _self(g), col, 3, J)]


def linearise(deformer, rd):
    """The chain of ops of ``deformer``'s boundary level at the wall targets ``rd`` (G, 3)."""
    # degenerate items (undefined normals, ...) give non-finite transcriptions: their
    # tangents are set to zero (the module docstring), so the warnings are not wanted
    with np.errstate(all="ignore"):
        return _build(deformer, np.asarray(rd, dtype=np.float64))


def _build(deformer, rd):
    sk = deformer.skeleton
    G = sk.n_global
    wall = sk.points.wall
    der = sk.derived
    P = sk.points.P
    c = np.asarray(deformer.centre, dtype=np.float64)
    two = deformer.two_level
    ops = []
    if two is None:
        use_q = deformer.method != "tfi"
        rec = forward_record(deformer, rd)
        (gd, gq, _, _), = rec["passes"]
        Dpre, Qpre = rec["pre"]
        if use_q:
            idx, Jw = wall_jacobian(sk, rd, c)
            ops += wall_ops(wall, P0, idx, RD, Jw)
            ops.append(RotOp(wall, D0, RD, P0, -1, -1.0, Qpre[wall], P[wall] - c))
        else:
            ops.append(_copy_op(wall, D0, RD, 3))
        qcol = P0 if use_q else None
        ops += _vertex_ops(sk, Qpre, D0, qcol, None)
        ops += _segment_ops(sk, Qpre, D0, qcol, None)
        ops += patch_ops(sk, Qpre, D0, qcol, None)
        ops += _symmetry_op(sk, Dpre, Qpre, P, c, D0, use_q)
        if use_q:
            ops.append(RotOp(der, POS, D0, P0, -1, 1.0, gq[der], P[der] - c))
        else:
            ops.append(_copy_op(der, POS, D0, 3))
        ops += _project_op(sk)
        ops.append(_copy_op(wall, POS, RD, 3))
        return Linearisation(ops, G, 0, [(D0, P0 if use_q else None)], False, rec["passes"])
    # ---- two-level
    rec = forward_record(deformer, rd)
    (K, ql, _, _), (gd, qg, _, _) = rec["passes"]
    Kpre, qlpre = rec["pre"]
    fits = rec["fits"]
    y = rec["y"]
    nb = len(two.bodies)
    brow = G + np.arange(nb)
    # the fits: body rows (q, t) from the body's targets
    for b, (body, (q, t)) in enumerate(zip(two.bodies, fits)):
        g = body.gids
        Jf = fit_jacobian(P[g], rd[g], q, body.axis, body.tproj)
        ops.append(Op(brow[b:b + 1], BQ, 7, g[None, :], RD, 3, Jf[None]))
    # y = rot(q)^-1 (rd - t) on the walls: reads the row's rd and the body's (q, t)
    bwall = np.empty(wall.size, dtype=np.int64)
    pos_w = np.full(G, -1, dtype=np.int64)
    pos_w[wall] = np.arange(wall.size)
    for b, body in enumerate(two.bodies):
        bwall[pos_w[body.gids]] = b

    qw = np.zeros((wall.size, 4))
    vw = rd[wall]
    for b, (q, t) in enumerate(fits):
        sel = bwall == b
        qw[sel] = q * np.array([1.0, -1.0, -1.0, -1.0])
        vw[sel] -= t
    ops.append(PullOp(wall, G + bwall, qw, vw))
    # residual pass
    idx, Jw = wall_jacobian(sk, y, c)
    ops += wall_ops(wall, Q0, idx, Y, Jw)
    ops.append(_copy_op(wall, K0, Y, 3))
    ops += _vertex_ops(sk, qlpre, K0, Q0, two)
    if sk.vertices.idw is not None:
        ops.append(_rebase_op(sk.vertices.free, qlpre, two.shift))
    ops += _segment_ops(sk, qlpre, K0, Q0, two)
    ops += patch_ops(sk, qlpre, K0, Q0, two)
    ops += _symmetry_op(sk, Kpre, qlpre, two.arm, np.zeros(3), K0, True)

    ops.append(RotOp(der, POS, K0, Q0, -1, 1.0, ql[der], two.arm[der]))
    ops.append(_copy_op(wall, POS, Y, 3))
    # rigid pass: body rows Δ_b, q_b, v_b from (q, t)
    qts = np.array([np.concatenate([q, t]) for q, t in fits]).reshape(nb, 7)

    def fb(X):
        q, t = X[:, :4], X[:, 4:7]
        cc = np.broadcast_to(c, t.shape)
        return np.concatenate([t + _rot(q, cc) - cc, q, cs_log(q)], axis=1)
    ops.append(Op(brow, 0, 10, _self(brow), BQ, 7, cs_jacobian(fb, qts)))
    bq = fb(qts.astype(np.complex128)).real
    ops.append(Op(wall, D0, 7, (G + bwall)[:, None], 0, 7, np.ones((wall.size, 1)), diag=True))
    if der.size:
        # Δ = Σ φ_b Δ_b, v = Σ φ_b v_b (into the scratch columns), Q = exp(v)
        phi = two.phi
        reads = np.broadcast_to(brow, (der.size, nb))
        ops.append(Op(der, D0, 3, reads, 0, 3, phi, diag=True))
        ops.append(Op(der, T0, 3, reads, 7, 3, phi, diag=True))
        ops.append(ExpOp(der, T0, P0, phi @ bq[:, 7:10]))
    ops += _symmetry_op(sk, *rec["rigid_pre"], P, c, D0, True)

    ops.append(RotOp(der, POS, D0, P0, POS, 1.0, qg[der], rec["posl"][der] - c))
    ops += _project_op(sk)
    ops.append(_copy_op(wall, POS, RD, 3))
    return Linearisation(ops, G, nb, [(K0, Q0), (D0, P0)], True, rec["passes"])


def forward_record(deformer, rd):
    """The boundary level of a step at the targets ``rd`` (G, 3) with what its linearisation
    reads: a dict with ``passes`` (always both passes for two-level) and the fields before
    the symmetry stages.  The same stage calls as :meth:`Deformer.deform`, on new arrays."""
    from .. import quaternion as qa
    from . import stages, twolevel
    sk = deformer.skeleton
    wall = sk.points.wall
    der = sk.derived
    P = sk.points.P
    c = np.asarray(deformer.centre, dtype=np.float64)
    G = sk.n_global
    rec = {}
    one = np.zeros((G, 4))
    one[:, 0] = 1.0
    two = deformer.two_level
    if two is None:
        use_q = deformer.method != "tfi"
        gd = np.zeros((G, 3))
        gq = one.copy() if use_q else None
        if use_q:
            qw = stages.wall_quaternions(sk, rd, c)
            gq[wall] = qw
            gd[wall] = rd[wall] - c - qa.rotate(qw, P[wall] - c)
        else:
            gd[wall] = rd[wall] - P[wall]
        stages.vertex_stage(sk, gd, gq)
        stages.segment_stage(sk, gd, gq)
        stages.patch_stage(sk, gd, gq)
        rec["pre"] = (gd.copy(), one.copy() if gq is None else gq.copy())
        stages.symmetry_stage(sk, gd, gq, c)
        pos = P.copy()
        if gq is not None:
            stages.positions_global(gd, gq, c, der, pos)
        else:
            pos[der] = P[der] + gd[der]
        stages.onto_symmetry(sk, pos)
        pos[wall] = rd[wall]
        rec["pos"] = pos
        rec["passes"] = [(gd, gq, c, None)]
        return rec
    y = P.copy()
    fits = twolevel.fit_bodies(sk, two, rd, y)
    rec["fits"] = fits
    rec["y"] = y
    qwall = stages.wall_quaternions(sk, y, c)
    K = two.c.copy()
    ql = one.copy()
    A = two.arm
    ql[wall] = qwall
    K[wall] = y[wall]
    vx = sk.vertices
    if vx.idw is not None:
        src, w, decay, _ = vx.idw
        free = vx.free
        K[free] = decay[:, None] * (w @ K[src]) + (1.0 - decay)[:, None] * P[free]
        ql[free] = stages.vertex_q(vx, ql, decay)
        K[free] += qa.rotate(ql[free], two.shift[free])
    if sk.segments is not None:
        stages.fill_gaps(K, ql, *sk.segments.arrays(), True, two.damp, two.shift)
    stages.patch_stage(sk, K, ql, two.damp, two.shift)
    rec["pre"] = (K.copy(), ql.copy())
    sym = sk.symmetry
    if sym.gids.size:
        stages.symmetry_fix(K, ql, True, A, np.zeros(3), sym.gids, sym.point, sym.normal)
    pos = P.copy()
    stages.positions_local(K, ql, A, der, pos)
    pos[wall] = y[wall]
    rec["posl"] = pos
    gd = np.zeros((G, 3))
    qg = one.copy()
    nb = len(two.bodies)
    Db = np.empty((nb, 3))
    Qb = np.empty((nb, 4))
    for b, (body, (q, t)) in enumerate(zip(two.bodies, fits)):
        Db[b] = t + qa.rotate(q, c) - c
        Qb[b] = q
        gd[body.gids] = Db[b]
        qg[body.gids] = q
    stages.rigid_blend(two.phi, der, Db, qa.log(Qb), gd, qg)
    rec["rigid_pre"] = (gd.copy(), qg.copy())
    stages.symmetry_stage(sk, gd, qg, c)
    pos = pos.copy()
    stages.positions_global(gd, qg, c, der, pos)
    stages.onto_symmetry(sk, pos)
    pos[wall] = rd[wall]
    rec["pos"] = pos
    rec["passes"] = [(K, ql, np.zeros(3), two.base), (gd, qg, c, None)]
    return rec
