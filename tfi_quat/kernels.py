"""Numba building blocks of the TFI kernels, shared by :mod:`tfi_quat.tfi`,
:mod:`tfi_quat.blending` and :mod:`tfi_quat.deform`.

Every function here is a compiled helper inlined into the kernels that call it
(:func:`fallback_q` is an ordinary compiled function on the rare path).  The
face indexing, the fallback's tangent-space maps and the arclength walkers
are inlined by LLVM (``forceinline``):
each is compiled once per argument types and shared by every kernel that calls
it, where numba's own ``inline="always"`` typed a copy at every call site (~40 %
of the line walkers' compile time).  The per-point TFI formulas and the slerp
helpers keep numba's inlining: LLVM-inlined, they made the 3-D based volume
kernel ~11 % slower (CPU time, one thread) for ~20 % less compile time of the
volume kernels.  None validates, allocates or raises.  They are public so that
the kernels of several modules use one definition; they are not part of the
user-level API (``tfi_quat.tfi`` is).

Per-point TFI formulas (docs/method.md §3.4 and §3.5)
    :func:`u_d`, :func:`v_d`, :func:`w_d` (Δ) and :func:`u_q`, :func:`v_q`,
    :func:`w_q` (Q) evaluate the Boolean sum ``U``, ``V``, ``W`` of one point
    from the O(surface) tables of the fused kernels (layout in
    :mod:`tfi_quat.tfi`): ``lineD``/``lineQ`` per line of the leading
    direction, ``gD``/``gQ`` the residuals on the M faces, ``hD``/``hQ`` on
    the N faces.  :func:`fallback_q` is the rotation-vector Boolean sum used
    where the blended quaternion's norm is below :data:`QNORM_MIN`.
Slerp
    :func:`slerp_angle` and :func:`slerp_weights` (polynomial ``sin(x)/x``,
    :func:`sinc2`, so the inner loops vectorise; exact at the ends);
    :func:`rel_log` and :func:`exp_times`, the tangent-space maps of the
    fallback.
Face indexing
    :func:`face_coords` (block point -> face coordinates) and
    :func:`face_point` (face coordinates -> block point).
Arclength walkers
    :func:`arc_line_i` (one line of direction i) and :func:`arc_tile` (a tile
    of :data:`TILE` lines of direction j or k, parameterised by the axis),
    with :func:`dist`, :func:`max_abs`, :func:`at` and :func:`line_point`;
    :func:`by_direction` runs a direction's task kernel on the threads (the
    one Python function here).

numba caches a kernel by its own file: after editing a helper here, clear the
package's ``__pycache__`` (see :mod:`tfi_quat._jit`).
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import jit, parallel_for
from .quaternion import log_s

__all__ = [
    "QNORM_MIN",
    "sinc2", "dsinc2", "slerp_angle", "slerp_weights", "dslerp_weights", "rel_log", "exp_times",
    "face_coords", "face_point",
    "u_d", "v_d", "w_d", "u_q", "v_q", "w_q", "fallback_q",
    "dist", "max_abs", "at", "line_point", "arc_line_i", "arc_tile", "TILE", "by_direction",
]

#: a blended quaternion with a smaller norm falls back to the rotation-vector blend
QNORM_MIN = 1e-3
#: lines i per tile of the line walkers of directions j and k: a tile's lines are
#: processed together, i innermost, in (n, TILE) buffers, so memory is read and
#: written along i, as it lies
TILE = 128

# Taylor coefficients of sin(x)/x in x**2 (terms up to x**20 / 21!): on
# 0 <= x <= pi/2 the truncation error is below 2e-16.
_S1 = -1.0 / 6.0
_S2 = 1.0 / 120.0
_S3 = -1.0 / 5040.0
_S4 = 1.0 / 362880.0
_S5 = -1.0 / 39916800.0
_S6 = 1.0 / 6227020800.0
_S7 = -1.0 / 1307674368000.0
_S8 = 1.0 / 355687428096000.0
_S9 = -1.0 / 121645100408832000.0
_S10 = 1.0 / 51090942171709440000.0


@jit(inline="always")
def sinc2(x2):
    """``sin(x)/x`` as a function of ``x2 = x**2``, for ``0 <= x <= pi/2``."""
    return 1.0 + x2 * (_S1 + x2 * (_S2 + x2 * (_S3 + x2 * (_S4 + x2 * (
        _S5 + x2 * (_S6 + x2 * (_S7 + x2 * (_S8 + x2 * (_S9 + x2 * _S10)))))))))


@jit(inline="always")
def dsinc2(x2):
    """The derivative of :func:`sinc2` with respect to ``x2`` (of the polynomial itself, so
    that the derivative kernels differentiate exactly what the volume kernels compute)."""
    return _S1 + x2 * (2.0 * _S2 + x2 * (3.0 * _S3 + x2 * (4.0 * _S4 + x2 * (5.0 * _S5 + x2 * (
        6.0 * _S6 + x2 * (7.0 * _S7 + x2 * (8.0 * _S8 + x2 * (9.0 * _S9 + x2 * 10.0 * _S10))))))))


@jit(inline="always")
def slerp_angle(a0, a1, a2, a3, b0, b1, b2, b3):
    """Angle between two unit quaternions (as 4-vectors, ``b`` already aligned): ``(ω², sinc(ω))``."""
    d0 = a0 - b0
    d1 = a1 - b1
    d2 = a2 - b2
    d3 = a3 - b3
    p0 = a0 + b0
    p1 = a1 + b1
    p2 = a2 + b2
    p3 = a3 + b3
    om = 2.0 * math.atan2(math.sqrt(d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3),
                          math.sqrt(p0 * p0 + p1 * p1 + p2 * p2 + p3 * p3))
    w2 = om * om
    return w2, sinc2(w2)


@jit(inline="always")
def slerp_weights(t, w2, sw):
    """Slerp weights ``sin((1-t)ω)/sin ω`` and ``sin(tω)/sin ω``; exactly (1, 0) at t=0, (0, 1) at t=1."""
    u = 1.0 - t
    return u * sinc2(u * u * w2) / sw, t * sinc2(t * t * w2) / sw


@jit(forceinline=True)
def dslerp_weights(t, w2, sw):
    """The derivatives of :func:`slerp_weights` with respect to ``w2`` (``sw = sinc2(w2)``)."""
    u = 1.0 - t
    ds = dsinc2(w2) / sw
    uu = u * u * w2
    tt = t * t * w2
    return (u * (u * u * dsinc2(uu) - sinc2(uu) * ds) / sw,
            t * (t * t * dsinc2(tt) - sinc2(tt) * ds) / sw)


@jit(forceinline=True)
def rel_log(bw, bx, by, bz, qw, qx, qy, qz):
    """Rotation half-vector ``log(conj(b) ⊗ q) / 2`` (q taken in b's hemisphere).

    The product is formed here (its sums are part of the fallback's bit-exact
    contract); the log is :func:`tfi_quat.quaternion.log_s`, whose halving is
    exact.
    """
    w = bw * qw + bx * qx + by * qy + bz * qz
    x = bw * qx - qw * bx - (by * qz - bz * qy)
    y = bw * qy - qw * by - (bz * qx - bx * qz)
    z = bw * qz - qw * bz - (bx * qy - by * qx)
    rx, ry, rz = log_s(w, x, y, z)
    return 0.5 * rx, 0.5 * ry, 0.5 * rz


@jit(forceinline=True)
def exp_times(bw, bx, by, bz, rx, ry, rz):
    """``b ⊗ exp(r)`` for a rotation half-vector ``r``."""
    th = math.sqrt(rx * rx + ry * ry + rz * rz)
    c = math.cos(th)
    if th > 1e-8:
        f = math.sin(th) / th
    else:
        f = 1.0 - th * th / 6.0
    ew = c
    ex = rx * f
    ey = ry * f
    ez = rz * f
    w = bw * ew - bx * ex - by * ey - bz * ez
    x = bw * ex + bx * ew + by * ez - bz * ey
    y = bw * ey - bx * ez + by * ew + bz * ex
    z = bw * ez + bx * ey - by * ex + bz * ew
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return w / n, x / n, y / n, z / n


@jit(forceinline=True)
def face_coords(i, j, k, d):
    """Face coordinates of block point (i, j, k) on a face normal to direction ``d``."""
    if d == 0:
        return j, k
    if d == 1:
        return i, k
    return i, j


@jit(forceinline=True)
def face_point(d, idx, a, b):
    """Block point of face coordinates (a, b) on the face ``index_d = idx``."""
    if d == 0:
        return idx, a, b
    if d == 1:
        return a, idx, b
    return a, b, idx


@jit(inline="always")
def u_d(lineD, la, lb, t):
    """Δ of the leading-direction blend ``U`` at parameter ``t`` on line ``(la, lb)``."""
    u = 1.0 - t
    return (u * lineD[la, lb, 0] + t * lineD[la, lb, 3],
            u * lineD[la, lb, 1] + t * lineD[la, lb, 4],
            u * lineD[la, lb, 2] + t * lineD[la, lb, 5])


@jit(inline="always")
def v_d(lineD, la, lb, t, gD, ma, mb, sm):
    """Δ of ``V = U + M-face corrections`` (residuals ``gD[ma, mb]``, parameter ``sm``)."""
    x, y, z = u_d(lineD, la, lb, t)
    um = 1.0 - sm
    return (x + um * gD[ma, mb, 0] + sm * gD[ma, mb, 3],
            y + um * gD[ma, mb, 1] + sm * gD[ma, mb, 4],
            z + um * gD[ma, mb, 2] + sm * gD[ma, mb, 5])


@jit(inline="always")
def w_d(lineD, la, lb, t, gD, ma, mb, sm, hD, na, nb, sn):
    """Δ of ``W = V + N-face corrections`` (residuals ``hD[na, nb]``, parameter ``sn``)."""
    x, y, z = v_d(lineD, la, lb, t, gD, ma, mb, sm)
    un = 1.0 - sn
    return (x + un * hD[na, nb, 0] + sn * hD[na, nb, 3],
            y + un * hD[na, nb, 1] + sn * hD[na, nb, 4],
            z + un * hD[na, nb, 2] + sn * hD[na, nb, 5])


@jit(inline="always")
def u_q(lineQ, la, lb, t):
    """Q of ``U``: the slerp of line ``(la, lb)`` at ``t`` (unit)."""
    wa, wb = slerp_weights(t, lineQ[la, lb, 8], lineQ[la, lb, 9])
    return (wa * lineQ[la, lb, 0] + wb * lineQ[la, lb, 4],
            wa * lineQ[la, lb, 1] + wb * lineQ[la, lb, 5],
            wa * lineQ[la, lb, 2] + wb * lineQ[la, lb, 6],
            wa * lineQ[la, lb, 3] + wb * lineQ[la, lb, 7])


@jit(inline="always")
def v_q(lineQ, la, lb, t, gQ, ma, mb, sm):
    """Q of ``V`` (not normalised)."""
    w, x, y, z = u_q(lineQ, la, lb, t)
    um = 1.0 - sm
    return (w + um * gQ[ma, mb, 0] + sm * gQ[ma, mb, 4],
            x + um * gQ[ma, mb, 1] + sm * gQ[ma, mb, 5],
            y + um * gQ[ma, mb, 2] + sm * gQ[ma, mb, 6],
            z + um * gQ[ma, mb, 3] + sm * gQ[ma, mb, 7])


@jit(inline="always")
def w_q(lineQ, la, lb, t, gQ, ma, mb, sm, hQ, na, nb, sn):
    """Q of ``W`` (not normalised)."""
    w, x, y, z = v_q(lineQ, la, lb, t, gQ, ma, mb, sm)
    un = 1.0 - sn
    return (w + un * hQ[na, nb, 0] + sn * hQ[na, nb, 4],
            x + un * hQ[na, nb, 1] + sn * hQ[na, nb, 5],
            y + un * hQ[na, nb, 2] + sn * hQ[na, nb, 6],
            z + un * hQ[na, nb, 3] + sn * hQ[na, nb, 7])


@jit(forceinline=True)
def _side_log(w, x, y, z, fb, o):
    """``log(F') - log(U|)`` of one side in the tangent space at ``(w, x, y, z)``;
    ``fb[o:o + 4]`` is the side's ``U|``, ``fb[o + 4:o + 8]`` its ``F'``."""
    fx, fy, fz = rel_log(w, x, y, z, fb[o + 4], fb[o + 5], fb[o + 6], fb[o + 7])
    ux, uy, uz = rel_log(w, x, y, z, fb[o], fb[o + 1], fb[o + 2], fb[o + 3])
    return fx - ux, fy - uy, fz - uz


@jit
def fallback_q(lineQ, la, lb, t, fbM, ma, mb, sm, fbN, na, nb, sn, hasn):
    """Boolean sum of rotation vectors in the tangent space at the slerp value U.

    ``fbM[ma, mb]`` holds ``(U|M0, F'_M0, U|M1, F'_M1)`` and ``fbN[na, nb]``
    ``(V̂|N0, F'_N0, V̂|N1, F'_N1)``, all unit.  Returns a unit quaternion.
    """
    w, x, y, z = u_q(lineQ, la, lb, t)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w /= n
    x /= n
    y /= n
    z /= n
    rx = 0.0
    ry = 0.0
    rz = 0.0
    for side in range(2):
        wt = (1.0 - sm) if side == 0 else sm
        dx, dy, dz = _side_log(w, x, y, z, fbM[ma, mb], 8 * side)
        rx += wt * dx
        ry += wt * dy
        rz += wt * dz
        if hasn:
            wt = (1.0 - sn) if side == 0 else sn
            dx, dy, dz = _side_log(w, x, y, z, fbN[na, nb], 8 * side)
            rx += wt * dx
            ry += wt * dy
            rz += wt * dz
    return exp_times(w, x, y, z, rx, ry, rz)


@jit(forceinline=True)
def dist(xyz, i0, j0, k0, i1, j1, k1):
    """Distance between two points of a block."""
    dx = xyz[i1, j1, k1, 0] - xyz[i0, j0, k0, 0]
    dy = xyz[i1, j1, k1, 1] - xyz[i0, j0, k0, 1]
    dz = xyz[i1, j1, k1, 2] - xyz[i0, j0, k0, 2]
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@jit(forceinline=True)
def max_abs(xyz, i0, j0, k0, i1, j1, k1):
    """Largest coordinate magnitude of two points of a block (the zero-length test's scale)."""
    return max(abs(xyz[i0, j0, k0, 0]), abs(xyz[i0, j0, k0, 1]), abs(xyz[i0, j0, k0, 2]),
               abs(xyz[i1, j1, k1, 0]), abs(xyz[i1, j1, k1, 1]), abs(xyz[i1, j1, k1, 2]))


@jit(forceinline=True)
def at(u0, w):
    """Index ``u0 + w`` as an unsigned integer: numba then adds no negative-index
    wrap-around, and a loop over ``w`` reads memory as one contiguous stream
    (with the signed ``i0 + w`` the direction-j sums took 5 times as long)."""
    return u0 + np.uint64(w)


@jit(forceinline=True)
def arc_line_i(xyz, rtol, j, k, buf):
    """Cumulative arclength of line (j, k) of direction i (ni >= 2) into ``buf``.

    Returns the line's length and the divisor that normalises ``buf``: the
    length, or ``ni - 1`` where the line counts as zero-length (``buf`` then
    holds the indices).
    """
    ni = xyz.shape[0]
    a = 0.0
    buf[0] = 0.0
    for i in range(1, ni):
        # i as uint64, as the tile walker's (at()): one compiled dist and max_abs for both
        a += dist(xyz, np.uint64(i - 1), j, k, np.uint64(i), j, k)
        buf[i] = a
    length = a
    if not a > rtol * max_abs(xyz, np.uint64(0), j, k, np.uint64(ni - 1), j, k):
        for i in range(ni):
            buf[i] = i
        a = ni - 1.0
    return length, a


@jit(forceinline=True)
def line_point(axis, i, m, c):
    """Block index of point ``m`` of the line of direction ``axis`` (1: j, 2: k) through
    point ``i`` of direction i and index ``c`` of the third direction."""
    if axis == 1:
        return i, m, c
    return i, c, m


@jit(forceinline=True)
def arc_tile(xyz, rtol, axis, u0, nw, c, cum, ln, den):
    """Cumulative arclength of a tile of lines of direction ``axis`` (1: j, 2: k; n >= 2
    points): lines ``i = u0 + w`` (w < nw) with third index ``c`` (k for axis 1, j for 2).

    ``cum[m, w]`` receives the arclength up to point m, ``ln[w]`` the line's
    length and ``den[w]`` the divisor that normalises ``cum[:, w]`` (as
    :func:`arc_line_i`).  The lines of a tile are summed together, i
    innermost, so memory is read along i as it lies.  ``axis`` is a constant
    at every call site: the index arithmetic folds away.
    """
    n = xyz.shape[axis]
    for w in range(nw):
        cum[0, w] = 0.0
        ln[w] = 0.0
    for m in range(1, n):
        for w in range(nw):
            i = at(u0, w)
            i0, j0, k0 = line_point(axis, i, m - 1, c)
            i1, j1, k1 = line_point(axis, i, m, c)
            ln[w] += dist(xyz, i0, j0, k0, i1, j1, k1)
            cum[m, w] = ln[w]
    for w in range(nw):
        i = at(u0, w)
        i0, j0, k0 = line_point(axis, i, np.int64(0), c)       # int64 (a literal 0 would
        # compile another specialisation of line_point)
        i1, j1, k1 = line_point(axis, i, n - 1, c)
        if not ln[w] > rtol * max_abs(xyz, i0, j0, k0, i1, j1, k1):
            for m in range(n):
                cum[m, w] = m
            den[w] = n - 1.0
        else:
            den[w] = ln[w]


def by_direction(kern_i, kern_jk, d: int, xyz, *args) -> None:
    """Run the line kernels of direction ``d`` of the block ``xyz`` (ni, nj, nk, 3) on the
    threads (:func:`tfi_quat._jit.parallel_for`).

    ``d = 0``: ``kern_i(lo, hi, xyz, *args)`` over the lines ``jk`` (``j = jk % nj``,
    ``k = jk // nj``); ``d = 1, 2``: ``kern_jk(lo, hi, xyz, *args, kdir)`` over the
    tiles ``t`` of :data:`TILE` lines i (``nt`` tiles per plane of the third direction,
    the plane ``t // nt``, the tile ``t % nt``), with ``kdir`` None for j and True for k:
    its type selects the direction, so each kernel is compiled once per direction with
    the axis a constant.
    """
    ni, nj, nk = xyz.shape[0], xyz.shape[1], xyz.shape[2]
    if d == 0:
        parallel_for(kern_i, nj * nk, xyz, *args)
    else:
        ntasks = (nk if d == 1 else nj) * ((ni + TILE - 1) // TILE)
        parallel_for(kern_jk, ntasks, xyz, *args, True if d == 2 else None)
