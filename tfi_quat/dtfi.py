"""Derivatives of the fused volume stage: tangent (forward) and adjoint (reverse) products.

The volume stage of :func:`tfi_quat.tfi.deform_block_gathered` maps the global
boundary arrays ``D`` (G, 3) and ``Q`` (G, 4) and the base points ``R`` of a
block to::

    out = c + Δ(x) + rot(q̂(x), R - c),      q̂ = W / |W|

with ``Δ`` the Soni TFI of the gathered ``D`` (linear in ``D``) and ``W`` the
Boolean sum of ``Q`` (slerp along the leading direction, hemisphere-aligned
residuals of the M and N faces; docs/method.md §3.4, §3.5).  This module
differentiates exactly the computed map (the polynomial ``sin(x)/x`` of the
slerp weights included, :func:`tfi_quat.kernels.dsinc2`):

:func:`volume_jvp`
    ``(dD, dQ, dR) -> dout``, computing ``out`` alongside (a second pass
    takes the first one's ``out`` as its base ``R``).
:func:`volume_vjp`
    ``out_bar -> D_bar, Q_bar`` (accumulated into global arrays) and
    ``R_bar``.

Both build the forward tables with the plan
(:meth:`tfi_quat.tfi.GatherPlan.fill_tables`), then their derivative tables
of the same layout (:func:`_dtables` serially, O(surface)), then run one task
kernel over the block (made on first use per kind, like the forward kernels:
nothing here is compiled unless a derivative is asked for).

Where the map is not differentiable the derivative is the one-sided one of
the branch the forward map took: the hemisphere signs (line ends, residuals)
are those of the linearisation point and held fixed; the slerp weights are
smooth functions of the squared angle, also at zero angle.  Points whose
blended ``|W|`` is below :data:`~tfi_quat.kernels.QNORM_MIN` (the forward
map's rotation-vector fallback) are not differentiated: the drivers return
how many there are and the caller raises.

Threads: the tangent kernel writes disjoint points.  The adjoint kernel runs
a fixed number of chunks of planes (:data:`NCHUNK`, not the thread count);
the one table shared by every plane (the faces normal to the plane
direction) is accumulated per chunk and the chunks are summed in order, so
the result has the same bits on any number of threads.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ._jit import jit, parallel_for, task_jit
from .kernels import (QNORM_MIN, dslerp_weights, face_coords, face_point, slerp_weights, u_d,
                      u_q, v_d, v_q, w_d, w_q)

__all__ = ["NCHUNK", "volume_jvp", "volume_vjp"]

#: the adjoint kernel's chunks of planes (at most; fewer on small blocks): fixed, so that the
#: order of its sums does not depend on the threads
NCHUNK = 8


# =================================================================== small helpers
@jit(inline="always")
def _sgn(a, b):
    """-1 if the 4-vectors ``a``, ``b`` point into opposite hemispheres, else 1."""
    d = a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]
    return -1.0 if d < 0.0 else 1.0


@jit(inline="always")
def _angle_coef(lq, cf):
    """``cf[0:4]``, ``cf[4:8]``: the gradients of ``ω²`` (:func:`tfi_quat.kernels.slerp_angle`)
    with respect to the line's two (aligned) end quaternions ``lq[0:4]``, ``lq[4:8]``."""
    A2 = 0.0
    B2 = 0.0
    for c in range(4):
        d = lq[c] - lq[4 + c]
        p = lq[c] + lq[4 + c]
        A2 += d * d
        B2 += p * p
    A = math.sqrt(A2)
    B = math.sqrt(B2)
    om = 2.0 * math.atan2(A, B)
    r = om / A if A > 0.0 else 2.0 / B          # ω / A, smooth through A = 0
    K = 4.0 * r / (A2 + B2)
    al = K * B
    be = -K * A2 / B
    for c in range(4):
        d = lq[c] - lq[4 + c]
        p = lq[c] + lq[4 + c]
        cf[c] = al * d + be * p
        cf[4 + c] = -al * d + be * p


@jit(inline="always")
def _du_q(lineQ, dlineQ, la, lb, t):
    """Tangent of :func:`tfi_quat.kernels.u_q` (the slerp of line (la, lb)) from the line's
    tangent table (``dq0``, ``dq1``, ``dω²``)."""
    w2 = lineQ[la, lb, 8]
    sw = lineQ[la, lb, 9]
    wa, wb = slerp_weights(t, w2, sw)
    da, db = dslerp_weights(t, w2, sw)
    dw = dlineQ[la, lb, 8]
    da *= dw
    db *= dw
    return (da * lineQ[la, lb, 0] + wa * dlineQ[la, lb, 0] + db * lineQ[la, lb, 4] + wb * dlineQ[la, lb, 4],
            da * lineQ[la, lb, 1] + wa * dlineQ[la, lb, 1] + db * lineQ[la, lb, 5] + wb * dlineQ[la, lb, 5],
            da * lineQ[la, lb, 2] + wa * dlineQ[la, lb, 2] + db * lineQ[la, lb, 6] + wb * dlineQ[la, lb, 6],
            da * lineQ[la, lb, 3] + wa * dlineQ[la, lb, 3] + db * lineQ[la, lb, 7] + wb * dlineQ[la, lb, 7])


@jit(inline="always")
def _du_q_bar(lineQ, lbar, la, lb, t, bw, bx, by, bz):
    """Adjoint of :func:`_du_q`: ``(bw, bx, by, bz)``, the bar of ``U``, accumulated into the
    line's bar (``q0``, ``q1``, ``ω²`` at 0:4, 4:8, 8) at ``(la, lb)``."""
    ba = la
    bb = lb
    w2 = lineQ[la, lb, 8]
    sw = lineQ[la, lb, 9]
    wa, wb = slerp_weights(t, w2, sw)
    da, db = dslerp_weights(t, w2, sw)
    lbar[ba, bb, 0] += wa * bw
    lbar[ba, bb, 1] += wa * bx
    lbar[ba, bb, 2] += wa * by
    lbar[ba, bb, 3] += wa * bz
    lbar[ba, bb, 4] += wb * bw
    lbar[ba, bb, 5] += wb * bx
    lbar[ba, bb, 6] += wb * by
    lbar[ba, bb, 7] += wb * bz
    lbar[ba, bb, 8] += (da * (lineQ[la, lb, 0] * bw + lineQ[la, lb, 1] * bx + lineQ[la, lb, 2] * by +
                              lineQ[la, lb, 3] * bz) +
                        db * (lineQ[la, lb, 4] * bw + lineQ[la, lb, 5] * bx + lineQ[la, lb, 6] * by +
                              lineQ[la, lb, 7] * bz))


@jit(inline="always")
def _d_bar(tab, a, b, o, wt, x, y, z):
    """``tab[a, b, o:o + 3] += wt (x, y, z)``."""
    tab[a, b, o] += wt * x
    tab[a, b, o + 1] += wt * y
    tab[a, b, o + 2] += wt * z


@jit(inline="always")
def _q_bar(tab, a, b, o, wt, w, x, y, z):
    """``tab[a, b, o:o + 4] += wt (w, x, y, z)``."""
    tab[a, b, o] += wt * w
    tab[a, b, o + 1] += wt * x
    tab[a, b, o + 2] += wt * y
    tab[a, b, o + 3] += wt * z


# =================================================================== tables (O(surface))
@jit
def _dtables(dims, L, M, N, hasn, hasq, iL, iM, iN, SM, SN, gq, lineQ, gQ, dD, dQ,
             dlineD, dlineQ, dgD, dgQ, dhD, dhQ, coef):
    """The tangent tables of one block: the forward tables' layout (:mod:`tfi_quat.tfi`) with
    the tangents of their values (``dlineQ[..., 8]``: of ω²; ``coef``: the gradients of ω²,
    :func:`_angle_coef`), from the tangents ``dD`` (G, 3) and ``dQ`` (G, 4) of the global
    arrays (``dQ`` unused without ``hasq``)."""
    nm = dims[M]
    nn = dims[N] if hasn else 1
    # a face's point counts are the face coordinates of the block's dims
    naL, nbL = face_coords(dims[0], dims[1], dims[2], L)
    for b in range(nbL):
        for a in range(naL):
            g0 = iL[a, b, 0]
            g1 = iL[a, b, 1]
            for c in range(3):
                dlineD[a, b, c] = dD[g0, c]
                dlineD[a, b, 3 + c] = dD[g1, c]
            if hasq:
                s0 = _sgn(lineQ[a, b, 0:4], gq[g0])
                s1 = _sgn(lineQ[a, b, 4:8], gq[g1])
                _angle_coef(lineQ[a, b], coef[a, b])
                dw = 0.0
                for c in range(4):
                    dlineQ[a, b, c] = s0 * dQ[g0, c]
                    dlineQ[a, b, 4 + c] = s1 * dQ[g1, c]
                    dw += coef[a, b, c] * dlineQ[a, b, c] + coef[a, b, 4 + c] * dlineQ[a, b, 4 + c]
                dlineQ[a, b, 8] = dw
                dlineQ[a, b, 9] = 0.0
    naM, nbM = face_coords(dims[0], dims[1], dims[2], M)
    for side in range(2):
        im = 0 if side == 0 else nm - 1
        for b in range(nbM):
            for a in range(naM):
                i, j, k = face_point(M, im, a, b)
                la, lb = face_coords(i, j, k, L)
                t = SM[a, b, L, side]
                g = iM[a, b, side]
                x, y, z = u_d(dlineD, la, lb, t)
                dgD[a, b, 3 * side] = dD[g, 0] - x
                dgD[a, b, 3 * side + 1] = dD[g, 1] - y
                dgD[a, b, 3 * side + 2] = dD[g, 2] - z
                if hasq:
                    qw, qx, qy, qz = u_q(lineQ, la, lb, t)
                    d = qw * gq[g, 0] + qx * gq[g, 1] + qy * gq[g, 2] + qz * gq[g, 3]
                    sg = -1.0 if d < 0.0 else 1.0
                    ew, ex, ey, ez = _du_q(lineQ, dlineQ, la, lb, t)
                    o = 4 * side
                    dgQ[a, b, o] = sg * dQ[g, 0] - ew
                    dgQ[a, b, o + 1] = sg * dQ[g, 1] - ex
                    dgQ[a, b, o + 2] = sg * dQ[g, 2] - ey
                    dgQ[a, b, o + 3] = sg * dQ[g, 3] - ez
    if not hasn:
        return
    naN, nbN = face_coords(dims[0], dims[1], dims[2], N)
    for side in range(2):
        im = 0 if side == 0 else nn - 1
        for b in range(nbN):
            for a in range(naN):
                i, j, k = face_point(N, im, a, b)
                la, lb = face_coords(i, j, k, L)
                ma, mb = face_coords(i, j, k, M)
                t = SN[a, b, L, side]
                sm = SN[a, b, M, side]
                g = iN[a, b, side]
                x, y, z = v_d(dlineD, la, lb, t, dgD, ma, mb, sm)
                dhD[a, b, 3 * side] = dD[g, 0] - x
                dhD[a, b, 3 * side + 1] = dD[g, 1] - y
                dhD[a, b, 3 * side + 2] = dD[g, 2] - z
                if hasq:
                    qw, qx, qy, qz = v_q(lineQ, la, lb, t, gQ, ma, mb, sm)
                    d = qw * gq[g, 0] + qx * gq[g, 1] + qy * gq[g, 2] + qz * gq[g, 3]
                    sg = -1.0 if d < 0.0 else 1.0
                    ew, ex, ey, ez = _du_q(lineQ, dlineQ, la, lb, t)
                    um = 1.0 - sm
                    o = 4 * side
                    dhQ[a, b, o] = sg * dQ[g, 0] - (ew + um * dgQ[ma, mb, 0] + sm * dgQ[ma, mb, 4])
                    dhQ[a, b, o + 1] = sg * dQ[g, 1] - (ex + um * dgQ[ma, mb, 1] + sm * dgQ[ma, mb, 5])
                    dhQ[a, b, o + 2] = sg * dQ[g, 2] - (ey + um * dgQ[ma, mb, 2] + sm * dgQ[ma, mb, 6])
                    dhQ[a, b, o + 3] = sg * dQ[g, 3] - (ez + um * dgQ[ma, mb, 3] + sm * dgQ[ma, mb, 7])


@jit
def _tables_bar(dims, L, M, N, hasn, hasq, iL, iM, iN, SM, SN, gq, lineQ, gQ,
                blineD, blineQ, bgD, bgQ, bhD, bhQ, Dbar, Qbar):
    """Adjoint of :func:`_dtables`: the bars of the tables (summed over the chunks; consumed)
    pushed back, in reverse order, to the global bars ``Dbar`` (G, 3), ``Qbar`` (G, 4)."""
    nm = dims[M]
    nn = dims[N] if hasn else 1
    if hasn:
        naN, nbN = face_coords(dims[0], dims[1], dims[2], N)
        for side in range(2):
            im = 0 if side == 0 else nn - 1
            for b in range(nbN):
                for a in range(naN):
                    i, j, k = face_point(N, im, a, b)
                    la, lb = face_coords(i, j, k, L)
                    ma, mb = face_coords(i, j, k, M)
                    t = SN[a, b, L, side]
                    sm = SN[a, b, M, side]
                    um = 1.0 - sm
                    g = iN[a, b, side]
                    o = 3 * side
                    x, y, z = bhD[a, b, o], bhD[a, b, o + 1], bhD[a, b, o + 2]
                    Dbar[g, 0] += x
                    Dbar[g, 1] += y
                    Dbar[g, 2] += z
                    _d_bar(blineD, la, lb, 0, -(1.0 - t), x, y, z)
                    _d_bar(blineD, la, lb, 3, -t, x, y, z)
                    _d_bar(bgD, ma, mb, 0, -um, x, y, z)
                    _d_bar(bgD, ma, mb, 3, -sm, x, y, z)
                    if hasq:
                        qw, qx, qy, qz = v_q(lineQ, la, lb, t, gQ, ma, mb, sm)
                        d = qw * gq[g, 0] + qx * gq[g, 1] + qy * gq[g, 2] + qz * gq[g, 3]
                        sg = -1.0 if d < 0.0 else 1.0
                        o = 4 * side
                        w, x, y, z = bhQ[a, b, o], bhQ[a, b, o + 1], bhQ[a, b, o + 2], bhQ[a, b, o + 3]
                        Qbar[g, 0] += sg * w
                        Qbar[g, 1] += sg * x
                        Qbar[g, 2] += sg * y
                        Qbar[g, 3] += sg * z
                        _q_bar(bgQ, ma, mb, 0, -um, w, x, y, z)
                        _q_bar(bgQ, ma, mb, 4, -sm, w, x, y, z)
                        _du_q_bar(lineQ, blineQ, la, lb, t, -w, -x, -y, -z)
    naM, nbM = face_coords(dims[0], dims[1], dims[2], M)
    for side in range(2):
        im = 0 if side == 0 else nm - 1
        for b in range(nbM):
            for a in range(naM):
                i, j, k = face_point(M, im, a, b)
                la, lb = face_coords(i, j, k, L)
                t = SM[a, b, L, side]
                g = iM[a, b, side]
                o = 3 * side
                x, y, z = bgD[a, b, o], bgD[a, b, o + 1], bgD[a, b, o + 2]
                Dbar[g, 0] += x
                Dbar[g, 1] += y
                Dbar[g, 2] += z
                _d_bar(blineD, la, lb, 0, -(1.0 - t), x, y, z)
                _d_bar(blineD, la, lb, 3, -t, x, y, z)
                if hasq:
                    qw, qx, qy, qz = u_q(lineQ, la, lb, t)
                    d = qw * gq[g, 0] + qx * gq[g, 1] + qy * gq[g, 2] + qz * gq[g, 3]
                    sg = -1.0 if d < 0.0 else 1.0
                    o = 4 * side
                    w, x, y, z = bgQ[a, b, o], bgQ[a, b, o + 1], bgQ[a, b, o + 2], bgQ[a, b, o + 3]
                    Qbar[g, 0] += sg * w
                    Qbar[g, 1] += sg * x
                    Qbar[g, 2] += sg * y
                    Qbar[g, 3] += sg * z
                    _du_q_bar(lineQ, blineQ, la, lb, t, -w, -x, -y, -z)
    naL, nbL = face_coords(dims[0], dims[1], dims[2], L)
    cf = np.empty(8)
    for b in range(nbL):
        for a in range(naL):
            g0 = iL[a, b, 0]
            g1 = iL[a, b, 1]
            for c in range(3):
                Dbar[g0, c] += blineD[a, b, c]
                Dbar[g1, c] += blineD[a, b, 3 + c]
            if hasq:
                s0 = _sgn(lineQ[a, b, 0:4], gq[g0])
                s1 = _sgn(lineQ[a, b, 4:8], gq[g1])
                _angle_coef(lineQ[a, b], cf)
                wb = blineQ[a, b, 8]
                for c in range(4):
                    Qbar[g0, c] += s0 * (blineQ[a, b, c] + wb * cf[c])
                    Qbar[g1, c] += s1 * (blineQ[a, b, 4 + c] + wb * cf[4 + c])


# =================================================================== point kernels
@jit(inline="always")
def _rot_parts(qw, qx, qy, qz, vx, vy, vz):
    """``t = 2 u × v`` and ``rot(q, v) - v = w t + u × t`` (the volume kernels' sums)."""
    tx = 2.0 * (qy * vz - qz * vy)
    ty = 2.0 * (qz * vx - qx * vz)
    tz = 2.0 * (qx * vy - qy * vx)
    return tx, ty, tz, qw * tx + (qy * tz - qz * ty), qw * ty + (qz * tx - qx * tz), \
        qw * tz + (qx * ty - qy * tx)


@jit(inline="always")
def _drot(qw, qx, qy, qz, tx, ty, tz, vx, vy, vz, dw, dx, dy, dz, ex, ey, ez):
    """Tangent of ``rot(q, v) - v`` for ``dq = (dw, dx, dy, dz)`` and ``dv = (ex, ey, ez)``
    (``t = 2 u × v``)."""
    # dt = 2 (du × v + u × dv)
    sx = 2.0 * (dy * vz - dz * vy + qy * ez - qz * ey)
    sy = 2.0 * (dz * vx - dx * vz + qz * ex - qx * ez)
    sz = 2.0 * (dx * vy - dy * vx + qx * ey - qy * ex)
    return (dw * tx + qw * sx + (dy * tz - dz * ty) + (qy * sz - qz * sy),
            dw * ty + qw * sy + (dz * tx - dx * tz) + (qz * sx - qx * sz),
            dw * tz + qw * sz + (dx * ty - dy * tx) + (qx * sy - qy * sx))


@jit(forceinline=True)
def _jvp_point(xyz, dxyz, s, out, dout, i, j, k, cx, cy, cz, L, M, N, lineD, lineQ, la, lb,
               gD, gQ, ma, mb, hD, hQ, na, nb, dlineD, dlineQ, dgD, dgQ, dhD, dhQ, lineB, gB, hB,
               hasn, hasq, based, dbased):
    """Tangent of one point (flags None or True, as the forward kernels' ``tfi._point``:
    numba prunes the branches of the kinds off); returns 1 where the blended Q is below
    QNORM_MIN (not differentiated)."""
    t = s[i, j, k, L]
    sm = s[i, j, k, M]
    if hasn is not None:
        sn = s[i, j, k, N]
    else:                       # 2-D: the N tables are zero dummies, read at (0, 0)
        sn = 0.0
        na = 0
        nb = 0
    if based is not None:
        bx, by, bz = w_d(lineB, la, lb, t, gB, ma, mb, sm, hB, na, nb, sn)
        x0 = xyz[i, j, k, 0] + bx
        y0 = xyz[i, j, k, 1] + by
        z0 = xyz[i, j, k, 2] + bz
    else:
        x0 = xyz[i, j, k, 0]
        y0 = xyz[i, j, k, 1]
        z0 = xyz[i, j, k, 2]
    if dbased is not None:
        ex = dxyz[i, j, k, 0]
        ey = dxyz[i, j, k, 1]
        ez = dxyz[i, j, k, 2]
    else:
        ex = ey = ez = 0.0
    dx, dy, dz = w_d(lineD, la, lb, t, gD, ma, mb, sm, hD, na, nb, sn)
    fx, fy, fz = w_d(dlineD, la, lb, t, dgD, ma, mb, sm, dhD, na, nb, sn)
    if hasq is None:
        out[i, j, k, 0] = x0 + dx
        out[i, j, k, 1] = y0 + dy
        out[i, j, k, 2] = z0 + dz
        dout[i, j, k, 0] = ex + fx
        dout[i, j, k, 1] = ey + fy
        dout[i, j, k, 2] = ez + fz
        return 0
    qw, qx, qy, qz = w_q(lineQ, la, lb, t, gQ, ma, mb, sm, hQ, na, nb, sn)
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    inv = 1.0 / max(n, QNORM_MIN)
    qw *= inv
    qx *= inv
    qy *= inv
    qz *= inv
    # dW: the slerp's tangent plus the residuals' (linear)
    aw, ax, ay, az = _du_q(lineQ, dlineQ, la, lb, t)
    um = 1.0 - sm
    aw += um * dgQ[ma, mb, 0] + sm * dgQ[ma, mb, 4]
    ax += um * dgQ[ma, mb, 1] + sm * dgQ[ma, mb, 5]
    ay += um * dgQ[ma, mb, 2] + sm * dgQ[ma, mb, 6]
    az += um * dgQ[ma, mb, 3] + sm * dgQ[ma, mb, 7]
    if hasn is not None:
        un = 1.0 - sn
        aw += un * dhQ[na, nb, 0] + sn * dhQ[na, nb, 4]
        ax += un * dhQ[na, nb, 1] + sn * dhQ[na, nb, 5]
        ay += un * dhQ[na, nb, 2] + sn * dhQ[na, nb, 6]
        az += un * dhQ[na, nb, 3] + sn * dhQ[na, nb, 7]
    # dq̂ = (dW - q̂ (q̂ . dW)) / |W|
    pr = qw * aw + qx * ax + qy * ay + qz * az
    aw = (aw - qw * pr) * inv
    ax = (ax - qx * pr) * inv
    ay = (ay - qy * pr) * inv
    az = (az - qz * pr) * inv
    vx = x0 - cx
    vy = y0 - cy
    vz = z0 - cz
    tx, ty, tz, rx, ry, rz = _rot_parts(qw, qx, qy, qz, vx, vy, vz)
    out[i, j, k, 0] = x0 + dx + rx
    out[i, j, k, 1] = y0 + dy + ry
    out[i, j, k, 2] = z0 + dz + rz
    gx, gy, gz = _drot(qw, qx, qy, qz, tx, ty, tz, vx, vy, vz, aw, ax, ay, az, ex, ey, ez)
    dout[i, j, k, 0] = ex + fx + gx
    dout[i, j, k, 1] = ey + fy + gy
    dout[i, j, k, 2] = ez + fz + gz
    return 1 if n < QNORM_MIN else 0


@jit(forceinline=True)
def _vjp_point(xyz, s, obar, xbar, i, j, k, cx, cy, cz, L, M, N, lineQ, la, lb, gQ, ma, mb,
               hQ, na, nb, lineB, gB, hB, scr, hasn, hasq, based, rbar):
    """Adjoint of :func:`_jvp_point`, the point-wise part: the bar ``o`` of ``out`` at the
    point (read before ``xbar``, which may be ``obar``, is written), the bar of ``W`` and the
    line's slerp terms into the row's scratch ``scr[:, i]`` (``o`` at 7:10; with ``hasq``:
    ``W_bar`` at 0:4, the slerp weights at 4, 5, the bar of ω² at 6), the base points' bar
    into ``xbar``.  The tables' bars are added from the scratch afterwards (:func:`_bar_run`,
    :func:`_bar_fixed`): the point loop writes two arrays only, so that it vectorises.
    Returns 1 below QNORM_MIN."""
    t = s[i, j, k, L]
    sm = s[i, j, k, M]
    if hasn is not None:
        sn = s[i, j, k, N]
    else:                       # 2-D: the N tables are zero dummies, read at (0, 0)
        sn = 0.0
        na = 0
        nb = 0
    ox = obar[i, j, k, 0]
    oy = obar[i, j, k, 1]
    oz = obar[i, j, k, 2]
    scr[7, i] = ox
    scr[8, i] = oy
    scr[9, i] = oz
    if hasq is None:
        if rbar is not None:
            xbar[i, j, k, 0] = ox
            xbar[i, j, k, 1] = oy
            xbar[i, j, k, 2] = oz
        return 0
    if based is not None:
        bx, by, bz = w_d(lineB, la, lb, t, gB, ma, mb, sm, hB, na, nb, sn)
        x0 = xyz[i, j, k, 0] + bx
        y0 = xyz[i, j, k, 1] + by
        z0 = xyz[i, j, k, 2] + bz
    else:
        x0 = xyz[i, j, k, 0]
        y0 = xyz[i, j, k, 1]
        z0 = xyz[i, j, k, 2]
    qw, qx, qy, qz = w_q(lineQ, la, lb, t, gQ, ma, mb, sm, hQ, na, nb, sn)
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    inv = 1.0 / max(n, QNORM_MIN)
    qw *= inv
    qx *= inv
    qy *= inv
    qz *= inv
    vx = x0 - cx
    vy = y0 - cy
    vz = z0 - cz
    tx = 2.0 * (qy * vz - qz * vy)
    ty = 2.0 * (qz * vx - qx * vz)
    tz = 2.0 * (qx * vy - qy * vx)
    # rot(q, v) = v + w t + u × t,  t = 2 u × v
    bw = tx * ox + ty * oy + tz * oz
    sx = qw * ox + (oy * qz - oz * qy)                      # t_bar = w o + o × u
    sy = qw * oy + (oz * qx - ox * qz)
    sz = qw * oz + (ox * qy - oy * qx)
    bx_ = ty * oz - tz * oy + 2.0 * (vy * sz - vz * sy)     # u_bar = t × o + 2 v × t_bar
    by_ = tz * ox - tx * oz + 2.0 * (vz * sx - vx * sz)
    bz_ = tx * oy - ty * ox + 2.0 * (vx * sy - vy * sx)
    if rbar is not None:                                    # v_bar = o + 2 t_bar × u
        xbar[i, j, k, 0] = ox + 2.0 * (sy * qz - sz * qy)
        xbar[i, j, k, 1] = oy + 2.0 * (sz * qx - sx * qz)
        xbar[i, j, k, 2] = oz + 2.0 * (sx * qy - sy * qx)
    # W_bar = (q̂_bar - q̂ (q̂ . q̂_bar)) / |W|
    pr = qw * bw + qx * bx_ + qy * by_ + qz * bz_
    ww = (bw - qw * pr) * inv
    wx = (bx_ - qx * pr) * inv
    wy = (by_ - qy * pr) * inv
    wz = (bz_ - qz * pr) * inv
    scr[0, i] = ww
    scr[1, i] = wx
    scr[2, i] = wy
    scr[3, i] = wz
    # the slerp of the line (:func:`_du_q_bar`, the same sums)
    w2 = lineQ[la, lb, 8]
    sw = lineQ[la, lb, 9]
    wa, wb = slerp_weights(t, w2, sw)
    da, db = dslerp_weights(t, w2, sw)
    scr[4, i] = wa
    scr[5, i] = wb
    scr[6, i] = (da * (lineQ[la, lb, 0] * ww + lineQ[la, lb, 1] * wx + lineQ[la, lb, 2] * wy +
                       lineQ[la, lb, 3] * wz) +
                 db * (lineQ[la, lb, 4] * ww + lineQ[la, lb, 5] * wx + lineQ[la, lb, 6] * wy +
                       lineQ[la, lb, 7] * wz))
    return 1 if n < QNORM_MIN else 0


@jit(forceinline=True)
def _bar_run(tD, tQ, c, s, scr, j, k, d, ni, line, hasq):
    """The bars of a row's points added into the tables ``tD``, ``tQ`` of a role whose
    entries run along i (entry ``(i, c)``; ``d`` the role's direction): the weights
    ``(1 - s_d, s_d)``, for the Q of the line role (``line`` True) the slerp weights and
    the bar of ω² (``scr``: :func:`_vjp_point`)."""
    for i in range(ni):
        t = s[i, j, k, d]
        u = 1.0 - t
        ox = scr[7, i]
        oy = scr[8, i]
        oz = scr[9, i]
        tD[i, c, 0] += u * ox
        tD[i, c, 1] += u * oy
        tD[i, c, 2] += u * oz
        tD[i, c, 3] += t * ox
        tD[i, c, 4] += t * oy
        tD[i, c, 5] += t * oz
        if hasq is not None:
            if line:
                wa = scr[4, i]
                wb = scr[5, i]
            else:
                wa = u
                wb = t
            ww = scr[0, i]
            wx = scr[1, i]
            wy = scr[2, i]
            wz = scr[3, i]
            tQ[i, c, 0] += wa * ww
            tQ[i, c, 1] += wa * wx
            tQ[i, c, 2] += wa * wy
            tQ[i, c, 3] += wa * wz
            tQ[i, c, 4] += wb * ww
            tQ[i, c, 5] += wb * wx
            tQ[i, c, 6] += wb * wy
            tQ[i, c, 7] += wb * wz
            if line:
                tQ[i, c, 8] += scr[6, i]


@jit(forceinline=True)
def _bar_fixed(tD, tQ, s, scr, j, k, d, ni, line, hasq):
    """As :func:`_bar_run` for the role whose direction is i: every point of the row reads
    its entry ``(j, k)``; the row's sum (in the order of i) is added once."""
    a0 = a1 = a2 = a3 = a4 = a5 = 0.0
    q0 = q1 = q2 = q3 = q4 = q5 = q6 = q7 = q8 = 0.0
    for i in range(ni):
        t = s[i, j, k, d]
        u = 1.0 - t
        ox = scr[7, i]
        oy = scr[8, i]
        oz = scr[9, i]
        a0 += u * ox
        a1 += u * oy
        a2 += u * oz
        a3 += t * ox
        a4 += t * oy
        a5 += t * oz
        if hasq is not None:
            if line:
                wa = scr[4, i]
                wb = scr[5, i]
                q8 += scr[6, i]
            else:
                wa = u
                wb = t
            ww = scr[0, i]
            wx = scr[1, i]
            wy = scr[2, i]
            wz = scr[3, i]
            q0 += wa * ww
            q1 += wa * wx
            q2 += wa * wy
            q3 += wa * wz
            q4 += wb * ww
            q5 += wb * wx
            q6 += wb * wy
            q7 += wb * wz
    tD[j, k, 0] += a0
    tD[j, k, 1] += a1
    tD[j, k, 2] += a2
    tD[j, k, 3] += a3
    tD[j, k, 4] += a4
    tD[j, k, 5] += a5
    if hasq is not None:
        tQ[j, k, 0] += q0
        tQ[j, k, 1] += q1
        tQ[j, k, 2] += q2
        tQ[j, k, 3] += q3
        tQ[j, k, 4] += q4
        tQ[j, k, 5] += q5
        tQ[j, k, 6] += q6
        tQ[j, k, 7] += q7
        if line:
            tQ[j, k, 8] += q8


def _jvp_kernel(hasn: bool, hasq: bool, based: bool, dbased: bool):
    """The tangent kernel of one kind (made on first use, then kept): tasks are planes
    (3-D: k, 2-D: j).

    Signature: ``(lo, hi, xyz, dxyz, s, out, dout, cx, cy, cz, L, M, N, lineD, lineQ, gD, gQ,
    hD, hQ, dlineD, dlineQ, dgD, dgQ, dhD, dhQ, lineB, gB, hB, bad)``;
    ``xyz`` the base points ``R`` (with ``based``: ``R = xyz + TFI(B)``), ``dxyz`` their
    tangent (read with ``dbased``); ``bad[p]``: points of plane ``p`` below QNORM_MIN.
    (Every flag a compile-time kind: with ``based``/``dbased`` run-time flags the kernel
    compiled in half the time but ran 10 times slower.)
    """
    return _kernel("jvp", hasn, hasq, based, dbased)


def _vjp_kernel(hasn: bool, hasq: bool, based: bool, rbar: bool):
    """The adjoint kernel of one kind (made on first use, then kept): tasks are the chunks
    of planes ``[p0[c], p0[c + 1])``.

    Signature: ``(lo, hi, p0, xyz, s, obar, xbar, cx, cy, cz, L, M, N, lineQ, gQ, hQ,
    lineB, gB, hB, blineD, blineQ, bgD, bgQ, bhD, bhQ, share, bad)``: ``obar``
    the bar of ``out``; ``xbar`` receives the bar of the base points (with ``rbar``); the
    table bars have a last chunk axis, whose index is the chunk for the tables in ``share``
    (role L, M, N) and 0 for the others (whose entries each chunk's planes own).
    """
    return _kernel("vjp", hasn, hasq, based, rbar)


@functools.lru_cache(maxsize=None)
def _kernel(kind, hasn, hasq, based, extra):
    nflag = True if hasn else None
    qflag = True if hasq else None
    bflag = True if based else None
    xflag = True if extra else None
    if kind == "jvp":
        @task_jit
        def jvp(lo, hi, xyz, dxyz, s, out, dout, cx, cy, cz, L, M, N, lineD, lineQ, gD, gQ,
                hD, hQ, dlineD, dlineQ, dgD, dgQ, dhD, dhQ, lineB, gB, hB, bad):
            ni = xyz.shape[0]
            nj = xyz.shape[1]
            for p in range(lo, hi):
                nbad = 0
                for q in range(nj if hasn else 1):
                    j = q if hasn else p
                    k = p if hasn else 0
                    # as the forward rows (tfi._row): the role whose direction is i reads
                    # one table entry all along the row, the others a run along i; the
                    # branch is taken once per row, not per point
                    if hasn:
                        cl = k if L == 1 else j
                        cm = k if M == 1 else j
                        cn = k if N == 1 else j
                    else:
                        cl = cm = cn = 0
                    if L == 0:
                        for i in range(ni):
                            nbad += _jvp_point(xyz, dxyz, s, out, dout, i, j, k, cx, cy, cz,
                                               L, M, N, lineD, lineQ, j, k, gD, gQ, i, cm, hD,
                                               hQ, i, cn, dlineD, dlineQ, dgD, dgQ, dhD, dhQ,
                                               lineB, gB, hB, nflag, qflag, bflag, xflag)
                    elif M == 0:
                        for i in range(ni):
                            nbad += _jvp_point(xyz, dxyz, s, out, dout, i, j, k, cx, cy, cz,
                                               L, M, N, lineD, lineQ, i, cl, gD, gQ, j, k, hD,
                                               hQ, i, cn, dlineD, dlineQ, dgD, dgQ, dhD, dhQ,
                                               lineB, gB, hB, nflag, qflag, bflag, xflag)
                    else:
                        for i in range(ni):
                            nbad += _jvp_point(xyz, dxyz, s, out, dout, i, j, k, cx, cy, cz,
                                               L, M, N, lineD, lineQ, i, cl, gD, gQ, i, cm, hD,
                                               hQ, j, k, dlineD, dlineQ, dgD, dgQ, dhD, dhQ,
                                               lineB, gB, hB, nflag, qflag, bflag, xflag)
                bad[p] = nbad
        return jvp

    @task_jit
    def vjp(lo, hi, p0, xyz, s, obar, xbar, cx, cy, cz, L, M, N, lineQ, gQ, hQ,
            lineB, gB, hB, blineD, blineQ, bgD, bgQ, bhD, bhQ, share, bad):
        ni = xyz.shape[0]
        nj = xyz.shape[1]
        for ch in range(lo, hi):
            bLD = blineD[:, :, :, ch if share[0] else 0]
            bLQ = blineQ[:, :, :, ch if share[0] else 0]
            bMD = bgD[:, :, :, ch if share[1] else 0]
            bMQ = bgQ[:, :, :, ch if share[1] else 0]
            bND = bhD[:, :, :, ch if share[2] else 0]
            bNQ = bhQ[:, :, :, ch if share[2] else 0]
            scr = np.empty((10, ni))
            nbad = 0
            for p in range(p0[ch], p0[ch + 1]):
                for q in range(nj if hasn else 1):
                    j = q if hasn else p
                    k = p if hasn else 0
                    cl = k if L == 1 else j
                    cm = k if M == 1 else j
                    cn = k if N == 1 else j
                    if L == 0:
                        for i in range(ni):
                            nbad += _vjp_point(xyz, s, obar, xbar, i, j, k, cx, cy, cz, L, M,
                                               N, lineQ, j, k, gQ, i, cm, hQ, i, cn, lineB,
                                               gB, hB, scr, nflag, qflag, bflag, xflag)
                    elif M == 0:
                        for i in range(ni):
                            nbad += _vjp_point(xyz, s, obar, xbar, i, j, k, cx, cy, cz, L, M,
                                               N, lineQ, i, cl, gQ, j, k, hQ, i, cn, lineB,
                                               gB, hB, scr, nflag, qflag, bflag, xflag)
                    else:
                        for i in range(ni):
                            nbad += _vjp_point(xyz, s, obar, xbar, i, j, k, cx, cy, cz, L, M,
                                               N, lineQ, i, cl, gQ, i, cm, hQ, j, k, lineB,
                                               gB, hB, scr, nflag, qflag, bflag, xflag)
                    # the tables' bars, role by role (the role whose direction is i: a
                    # sum along the row into one entry)
                    if L == 0:
                        _bar_fixed(bLD, bLQ, s, scr, j, k, L, ni, True, qflag)
                    else:
                        _bar_run(bLD, bLQ, cl, s, scr, j, k, L, ni, True, qflag)
                    if M == 0:
                        _bar_fixed(bMD, bMQ, s, scr, j, k, M, ni, False, qflag)
                    else:
                        _bar_run(bMD, bMQ, cm, s, scr, j, k, M, ni, False, qflag)
                    if hasn:
                        if N == 0:
                            _bar_fixed(bND, bNQ, s, scr, j, k, N, ni, False, qflag)
                        else:
                            _bar_run(bND, bNQ, cn, s, scr, j, k, N, ni, False, qflag)
            bad[ch] = nbad
    return vjp


# =================================================================== drivers
def _setup(plan):
    dims = plan.dims
    hasn = plan.ndim == 3
    L, M, N = plan.order if hasn else (plan.order[0], plan.order[1], 2)
    return dims, hasn, L, M, N


def _dims_arr(dims):
    return np.array(dims, dtype=np.int64)


def _like(tab):
    return np.zeros(tab.shape, order="F")


def volume_jvp(plan, xyz, s, gd, gq, dgd, dgq, centre, out, dout, *, base=None,
               dxyz=None) -> int:
    """Tangent of one volume pass of a block (:func:`tfi_quat.tfi.deform_block_gathered`).

    ``xyz`` the base points (the reference, or the previous pass's result), ``dxyz`` their
    tangent (None: 0); ``gd``/``gq`` the global boundary arrays (``gq`` None: the baseline)
    and ``dgd``/``dgq`` their tangents; ``base``: the plan's base tables
    (:meth:`~tfi_quat.tfi.GatherPlan.base_tables`, constant).  Writes ``out`` (the pass's
    result, as the forward kernel computes it) and ``dout`` (its tangent), both Fortran
    (ni, nj, nk, 3).  Nothing is validated.  Returns the number of points on the forward
    map's fallback path (their derivative is not computed; the caller raises).
    """
    dims, hasn, L, M, N = _setup(plan)
    hasq = gq is not None
    lineD, lineQ, gD, gQ, hD, hQ, _, _ = plan.fill_tables(gd, gq)
    dlineD, dlineQ, dgD, dgQ, dhD, dhQ = (_like(a) for a in (lineD, lineQ, gD, gQ, hD, hQ))
    coef = np.zeros(lineQ.shape[:2] + (8,))
    iL, iM, iN = plan.face_rows
    SM, SN = plan.face_pairs
    _dtables(_dims_arr(dims), L, M, N, hasn, hasq, iL, iM, iN, SM, SN,
             gq if hasq else _NO_Q, lineQ, gQ, dgd, dgq if hasq else _NO_Q,
             dlineD, dlineQ, dgD, dgQ, dhD, dhQ, coef)
    lineB, gB, hB = (lineD, gD, hD) if base is None else base
    nplanes = dims[2] if hasn else dims[1]
    bad = np.zeros(nplanes, dtype=np.int64)
    kern = _jvp_kernel(hasn, hasq, base is not None, dxyz is not None)
    c = np.asarray(centre, dtype=np.float64)
    parallel_for(kern, nplanes, xyz, xyz if dxyz is None else dxyz, s, out, dout,
                 c[0], c[1], c[2], L, M, N, lineD, lineQ, gD, gQ, hD, hQ,
                 dlineD, dlineQ, dgD, dgQ, dhD, dhQ, lineB, gB, hB, bad)
    return int(bad.sum())


def volume_vjp(plan, xyz, s, gd, gq, centre, obar, gd_bar, gq_bar, *, base=None,
               xbar=None) -> int:
    """Adjoint of :func:`volume_jvp`: for the bar ``obar`` of ``out`` (Fortran (ni, nj, nk, 3)),
    accumulates into the global bars ``gd_bar`` (G, 3) and ``gq_bar`` (G, 4; ignored for the
    baseline) and writes the bar of the base points into ``xbar`` (None: not wanted).  The
    same bits on any number of threads (module docstring).  Returns the number of points
    on the fallback path (as :func:`volume_jvp`)."""
    dims, hasn, L, M, N = _setup(plan)
    hasq = gq is not None
    lineD, lineQ, gD, gQ, hD, hQ, _, _ = plan.fill_tables(gd, gq)
    nplanes = dims[2] if hasn else dims[1]
    pdir = 2 if hasn else 1
    nch = min(NCHUNK, nplanes)
    p0 = np.array([nplanes * c // nch for c in range(nch + 1)], dtype=np.int64)
    roles = (L, M, N)
    share = np.array([r == pdir for r in roles], dtype=np.bool_)
    tabs = (lineD, lineQ, gD, gQ, hD, hQ)
    rank = (0, 0, 1, 1, 2, 2)
    # F order, the chunk last: each chunk's table is laid out as the forward one (i fastest)
    bars = [np.zeros(a.shape + (nch if share[r] else 1,), order="F") for a, r in zip(tabs, rank)]
    lineB, gB, hB = (lineD, gD, hD) if base is None else base
    bad = np.zeros(nch, dtype=np.int64)
    kern = _vjp_kernel(hasn, hasq, base is not None, xbar is not None)
    c = np.asarray(centre, dtype=np.float64)
    parallel_for(kern, nch, p0, xyz, s, obar, xyz if xbar is None else xbar, c[0], c[1], c[2],
                 L, M, N, lineQ, gQ, hQ, lineB, gB, hB, *bars, share, bad)
    summed = [_chunk_sum(b) for b in bars]
    iL, iM, iN = plan.face_rows
    SM, SN = plan.face_pairs
    _tables_bar(_dims_arr(dims), L, M, N, hasn, hasq, iL, iM, iN, SM, SN,
                gq if hasq else _NO_Q, lineQ, gQ, *summed, gd_bar,
                gq_bar if hasq else np.zeros((1, 4)))
    return int(bad.sum())


def _chunk_sum(b):
    """The chunks of a table bar (its last axis) summed in order: the same bits on any
    number of threads."""
    out = np.array(b[..., 0], order="F")
    for c in range(1, b.shape[-1]):
        out += b[..., c]
    return out


_NO_Q = np.zeros((1, 4))
