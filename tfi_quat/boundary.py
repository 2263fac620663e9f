"""Boundary quaternions: the rotation and translation of every wall point (docs/method.md §3.1).

For each point of a structured wall patch, with undeformed position ``r_u``
and deformed position ``r_d``:

1. normals ``n_u``, ``n_d`` from in-surface tangents (central differences,
   one-sided at patch ends, central across an edge where a halo row gives the
   neighbour in the next block or across a periodic seam).  A 2-D wall is a
   curve in the plane with normal ``e``: ``n = t x e``;
2. ``Q1``: the minimal rotation taking ``n_u`` to ``n_d`` (normalised axis;
   for a curve the rotation about ``e`` by the signed angle between them);
3. ``Q2``: the rotation about ``n_d`` by
   ``theta = atan2(sum n_d . (a x b), sum a . b)``, ``a``/``b`` the unit
   projections onto the plane normal to ``n_d`` of the undeformed edges to
   the neighbours rotated by ``Q1`` / of the deformed edges;
4. ``Q = Q2 ⊗ Q1`` (``Q1`` applied first);
5. ``delta = r_d - c - rot(Q, r_u - c)``, so ``c + delta + rot(Q, r_u - c)``
   is ``r_d`` to round-off.

Degenerate points (no normal: zero-length or collapsed edges, wing-tip caps,
O-O poles, coincident neighbours) take ``Q`` as the hemisphere-aligned blend
(:func:`tfi_quat.quaternion.kblend`) of their valid neighbours, propagated
sweep by sweep when whole rows are degenerate; a patch without a single
valid point gets the identity.  Signs are made consistent along the patch
(``q . q_neighbour >= 0``, first point ``w >= 0``).  See ``docs/method.md``.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import jit, parallel_for, task_jit
from .errors import DeformationError, GridValueError
from .quaternion import from_two_units_s, mul_s, kblend

__all__ = ["boundary_motion", "surface_normals", "motion_padded"]

#: a normal is undefined where |t_a x t_b| <= DEGENERATE * |t_a| |t_b|, or where
#: one tangent is shorter than DEGENERATE times the other (collapsed edge)
DEGENERATE = 1e-10


@jit(inline="always")
def _inv_sqrt(x):
    """``1 / sqrt(x)`` for ``x > 0``; 1 otherwise (zero, NaN).

    The straight-line kernels compute everything and decide validity from
    flags afterwards; this keeps them free of division by zero (an error in
    plain Python, ``TFI_QUAT_JIT=0``) and of inf/NaN intermediates.
    """
    return 1.0 / math.sqrt(x if x > 0.0 else 1.0)


# ------------------------------------------------------------------ kernels
@jit
def _valid(P, ii, jj):
    """Is ``P[ii, jj]`` (padded index) inside the array and not NaN?"""
    if ii < 0 or jj < 0 or ii >= P.shape[0] or jj >= P.shape[1]:
        return False
    return P[ii, jj, 0] == P[ii, jj, 0]


@jit
def _edge(P, ii, jj, a, b):
    """Edge vector ``P[a, b] - P[ii, jj]`` to a neighbour (a, b); returns (x, y, z, exists).
    (The neighbour as an index, not an offset: constant offsets would be typed as literals,
    one compilation per offset.)"""
    if not _valid(P, a, b):
        return 0.0, 0.0, 0.0, False
    return P[a, b, 0] - P[ii, jj, 0], P[a, b, 1] - P[ii, jj, 1], P[a, b, 2] - P[ii, jj, 2], True


@jit
def _edge_if(P, ii, jj, a, b, ok):
    """Edge vector ``P[a, b] - P[ii, jj]`` where ``ok`` is already known; else zero."""
    if not ok:
        return 0.0, 0.0, 0.0
    return P[a, b, 0] - P[ii, jj, 0], P[a, b, 1] - P[ii, jj, 1], P[a, b, 2] - P[ii, jj, 2]


@jit
def _diff(px, py, pz, pok, mx, my, mz, mok):
    """Tangent from the edges to the + and - neighbours: central, one-sided, or zero."""
    if pok and mok:
        return px - mx, py - my, pz - mz
    if pok:
        return px, py, pz
    if mok:
        return -mx, -my, -mz
    return 0.0, 0.0, 0.0


@jit
def _unit_normal(ax, ay, az, bx, by, bz, curve):
    """``a x b / |a x b|``; returns (nx, ny, nz, defined).

    Undefined when a tangent is zero, when ``|a x b| <= DEGENERATE |a| |b|``
    (parallel tangents) or, for a surface, when one tangent is shorter than
    ``DEGENERATE`` times the other (a collapsed edge whose round-off would
    otherwise give a random normal).
    """
    la2 = ax * ax + ay * ay + az * az
    lb2 = bx * bx + by * by + bz * bz
    nx = ay * bz - az * by
    ny = az * bx - ax * bz
    nz = ax * by - ay * bx
    ln2 = nx * nx + ny * ny + nz * nz
    d2 = DEGENERATE * DEGENERATE
    if (not (la2 > 0.0 and lb2 > 0.0)) or ln2 <= d2 * la2 * lb2:
        return 0.0, 0.0, 0.0, False
    if (not curve) and (la2 <= d2 * lb2 or lb2 <= d2 * la2):
        return 0.0, 0.0, 0.0, False
    inv = _inv_sqrt(ln2)
    return nx * inv, ny * inv, nz * inv, True


@jit
def _normal(P, ii, jj, curve, e):
    """Unit normal at padded index (ii, jj); returns (nx, ny, nz, defined)."""
    px, py, pz, pok = _edge(P, ii, jj, ii + 1, jj)
    mx, my, mz, mok = _edge(P, ii, jj, ii - 1, jj)
    ax, ay, az = _diff(px, py, pz, pok, mx, my, mz, mok)
    if curve:
        bx = e[0]
        by = e[1]
        bz = e[2]
    else:
        px, py, pz, pok = _edge(P, ii, jj, ii, jj + 1)
        mx, my, mz, mok = _edge(P, ii, jj, ii, jj - 1)
        bx, by, bz = _diff(px, py, pz, pok, mx, my, mz, mok)
    return _unit_normal(ax, ay, az, bx, by, bz, curve)


@jit
def _rot_s(w, x, y, z, vx, vy, vz):
    """rot(q, v) for a unit quaternion given as scalars; returns a 3-tuple."""
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    return (vx + w * tx + (y * tz - z * ty),
            vy + w * ty + (z * tx - x * tz),
            vz + w * tz + (x * ty - y * tx))


@jit
def _delta(Pu, Pd, ii, jj, c, q, out):
    """out = r_d - c - rot(q, r_u - c)."""
    rx, ry, rz = _rot_s(q[0], q[1], q[2], q[3],
                        Pu[ii, jj, 0] - c[0], Pu[ii, jj, 1] - c[1], Pu[ii, jj, 2] - c[2])
    out[0] = Pd[ii, jj, 0] - c[0] - rx
    out[1] = Pd[ii, jj, 1] - c[1] - ry
    out[2] = Pd[ii, jj, 2] - c[2] - rz


@jit
def _angle_terms(ok, ex, ey, ez, fx, fy, fz, t1x, t1y, t1z, t2x, t2y, t2z,
                 T1x, T1y, T1z, T2x, T2y, T2z):
    """Sine and cosine of the angle about ``n_d`` from ``rot(Q1, e)`` to ``f``, projected.

    ``(t1, t2)`` is an orthonormal basis of the plane normal to ``n_u`` and
    ``(T1, T2) = (rot(Q1, t1), rot(Q1, t2))`` the same basis carried to the
    plane normal to ``n_d``, with ``T1 x T2 = n_d``.  Because ``Q1``
    preserves dot products, ``rot(Q1, e)`` projected onto that plane has
    coordinates ``(e . t1, e . t2)``: one rotation per point instead of one
    per edge.  Returns (0, 0) for a missing or zero-length edge, or an edge
    along the normal (no in-plane direction).
    """
    if not ok:
        return 0.0, 0.0
    a1 = ex * t1x + ey * t1y + ez * t1z
    a2 = ex * t2x + ey * t2y + ez * t2z
    b1 = fx * T1x + fy * T1y + fz * T1z
    b2 = fx * T2x + fy * T2y + fz * T2z
    la2 = a1 * a1 + a2 * a2
    lb2 = b1 * b1 + b2 * b2
    d2 = DEGENERATE * DEGENERATE
    if not (la2 > d2 * (ex * ex + ey * ey + ez * ez) and lb2 > d2 * (fx * fx + fy * fy + fz * fz)):
        return 0.0, 0.0
    inv = _inv_sqrt(la2 * lb2)
    return (a1 * b2 - a2 * b1) * inv, (a1 * b1 + a2 * b2) * inv


@jit(inline="always")
def _point_quaternion(Pu, Pd, ii, jj, surf, e):
    """Q = Q2 ⊗ Q1 at padded index (ii, jj); returns (w, x, y, z, defined).

    ``surf``: None for a wall curve (in the plane of normal ``e``), True for a surface
    (the type selects the code).  Pu and Pd have the same NaN pattern (checked by the
    driver), so an edge exists in both or in neither.
    """
    # edges to the four neighbours, undeformed (e*) and deformed (f*)
    e1x, e1y, e1z, ok1 = _edge(Pu, ii, jj, ii + 1, jj)
    e2x, e2y, e2z, ok2 = _edge(Pu, ii, jj, ii - 1, jj)
    f1x, f1y, f1z = _edge_if(Pd, ii, jj, ii + 1, jj, ok1)
    f2x, f2y, f2z = _edge_if(Pd, ii, jj, ii - 1, jj, ok2)
    if surf is None:
        e3x, e3y, e3z, ok3 = 0.0, 0.0, 0.0, False
        e4x, e4y, e4z, ok4 = 0.0, 0.0, 0.0, False
        f3x, f3y, f3z = 0.0, 0.0, 0.0
        f4x, f4y, f4z = 0.0, 0.0, 0.0
        bux, buy, buz = e[0], e[1], e[2]
        bdx, bdy, bdz = e[0], e[1], e[2]
    else:
        e3x, e3y, e3z, ok3 = _edge(Pu, ii, jj, ii, jj + 1)
        e4x, e4y, e4z, ok4 = _edge(Pu, ii, jj, ii, jj - 1)
        f3x, f3y, f3z = _edge_if(Pd, ii, jj, ii, jj + 1, ok3)
        f4x, f4y, f4z = _edge_if(Pd, ii, jj, ii, jj - 1, ok4)
        bux, buy, buz = _diff(e3x, e3y, e3z, ok3, e4x, e4y, e4z, ok4)
        bdx, bdy, bdz = _diff(f3x, f3y, f3z, ok3, f4x, f4y, f4z, ok4)
    aux, auy, auz = _diff(e1x, e1y, e1z, ok1, e2x, e2y, e2z, ok2)
    adx, ady, adz = _diff(f1x, f1y, f1z, ok1, f2x, f2y, f2z, ok2)
    curve = surf is None
    ux, uy, uz, oku = _unit_normal(aux, auy, auz, bux, buy, buz, curve)
    dx, dy, dz, okd = _unit_normal(adx, ady, adz, bdx, bdy, bdz, curve)
    if not (oku and okd):
        return 1.0, 0.0, 0.0, 0.0, False
    if surf is None:
        # rotation about the plane normal by the signed angle n_u -> n_d
        cx = uy * dz - uz * dy
        cy = uz * dx - ux * dz
        cz = ux * dy - uy * dx
        h = 0.5 * math.atan2(e[0] * cx + e[1] * cy + e[2] * cz, ux * dx + uy * dy + uz * dz)
        sh = math.sin(h)
        a0, a1, a2, a3 = math.cos(h), e[0] * sh, e[1] * sh, e[2] * sh
    else:
        a0, a1, a2, a3 = from_two_units_s(ux, uy, uz, dx, dy, dz)
    # tangent-plane bases: t1 along the first tangent (normal to n_u by construction)
    inv = 1.0 / math.sqrt(aux * aux + auy * auy + auz * auz)
    t1x = aux * inv
    t1y = auy * inv
    t1z = auz * inv
    t2x = uy * t1z - uz * t1y              # n_u x t1
    t2y = uz * t1x - ux * t1z
    t2z = ux * t1y - uy * t1x
    T1x, T1y, T1z = _rot_s(a0, a1, a2, a3, t1x, t1y, t1z)
    T2x = dy * T1z - dz * T1y              # n_d x T1
    T2y = dz * T1x - dx * T1z
    T2z = dx * T1y - dy * T1x
    s1, c1 = _angle_terms(ok1, e1x, e1y, e1z, f1x, f1y, f1z, t1x, t1y, t1z, t2x, t2y, t2z,
                          T1x, T1y, T1z, T2x, T2y, T2z)
    s2, c2 = _angle_terms(ok2, e2x, e2y, e2z, f2x, f2y, f2z, t1x, t1y, t1z, t2x, t2y, t2z,
                          T1x, T1y, T1z, T2x, T2y, T2z)
    if surf is None:                       # no edges 3, 4 (what _angle_terms gives for them)
        s3, c3, s4, c4 = 0.0, 0.0, 0.0, 0.0
    else:
        s3, c3 = _angle_terms(ok3, e3x, e3y, e3z, f3x, f3y, f3z, t1x, t1y, t1z, t2x, t2y, t2z,
                              T1x, T1y, T1z, T2x, T2y, T2z)
        s4, c4 = _angle_terms(ok4, e4x, e4y, e4z, f4x, f4y, f4z, t1x, t1y, t1z, t2x, t2y, t2z,
                              T1x, T1y, T1z, T2x, T2y, T2z)
    ss = s1 + s2 + s3 + s4
    cc = c1 + c2 + c3 + c4
    # Q2 = [cos(theta/2), n_d sin(theta/2)], theta = atan2(ss, cc), without trigonometry:
    # (cos, sin)(theta/2) is parallel to (r + cc, ss) and to (ss, r - cc), r = |(ss, cc)|
    r = math.sqrt(ss * ss + cc * cc)
    if cc >= 0.0:
        hw = r + cc
        hs = ss
    else:
        hw = ss
        hs = r - cc
        if hw < 0.0:
            hw = -hw
            hs = -hs
    hn = hw * hw + hs * hs
    if hn > 0.0:
        inv = 1.0 / math.sqrt(hn)
        hw *= inv
        hs *= inv
    else:
        hw = 1.0
        hs = 0.0
    w, x, y, z = mul_s(hw, dx * hs, dy * hs, dz * hs, a0, a1, a2, a3)
    return w, x, y, z, True


@jit(inline="always")
def _edge_angle_fast(ex, ey, ez, fx, fy, fz, t1x, t1y, t1z, t2x, t2y, t2z,
                     T1x, T1y, T1z, T2x, T2y, T2z):
    """:func:`_angle_terms` without branches; returns (sin, cos, usable)."""
    a1 = ex * t1x + ey * t1y + ez * t1z
    a2 = ex * t2x + ey * t2y + ez * t2z
    b1 = fx * T1x + fy * T1y + fz * T1z
    b2 = fx * T2x + fy * T2y + fz * T2z
    la2 = a1 * a1 + a2 * a2
    lb2 = b1 * b1 + b2 * b2
    d2 = DEGENERATE * DEGENERATE
    good = (la2 > d2 * (ex * ex + ey * ey + ez * ez)) & (lb2 > d2 * (fx * fx + fy * fy + fz * fz))
    inv = _inv_sqrt(la2 * lb2)
    return (a1 * b2 - a2 * b1) * inv, (a1 * b1 + a2 * b2) * inv, good


@jit(inline="always")
def _interior_quaternion(Pu, Pd, ii, jj):
    """:func:`_point_quaternion` for a surface point with all four neighbours present.

    The common case (defined normals, ``n_u . n_d >= 0``, every edge usable,
    summed cosine ``>= 0``) as straight-line code: the same operations, so
    the same result, without the validity tests and branches that make the
    general kernel latency-bound.  Returns (w, x, y, z, ok); where ``ok`` is
    False (a rare case, or NaN from a degenerate point) the caller uses
    :func:`_point_quaternion`.
    """
    e1x = Pu[ii + 1, jj, 0] - Pu[ii, jj, 0]
    e1y = Pu[ii + 1, jj, 1] - Pu[ii, jj, 1]
    e1z = Pu[ii + 1, jj, 2] - Pu[ii, jj, 2]
    e2x = Pu[ii - 1, jj, 0] - Pu[ii, jj, 0]
    e2y = Pu[ii - 1, jj, 1] - Pu[ii, jj, 1]
    e2z = Pu[ii - 1, jj, 2] - Pu[ii, jj, 2]
    e3x = Pu[ii, jj + 1, 0] - Pu[ii, jj, 0]
    e3y = Pu[ii, jj + 1, 1] - Pu[ii, jj, 1]
    e3z = Pu[ii, jj + 1, 2] - Pu[ii, jj, 2]
    e4x = Pu[ii, jj - 1, 0] - Pu[ii, jj, 0]
    e4y = Pu[ii, jj - 1, 1] - Pu[ii, jj, 1]
    e4z = Pu[ii, jj - 1, 2] - Pu[ii, jj, 2]
    f1x = Pd[ii + 1, jj, 0] - Pd[ii, jj, 0]
    f1y = Pd[ii + 1, jj, 1] - Pd[ii, jj, 1]
    f1z = Pd[ii + 1, jj, 2] - Pd[ii, jj, 2]
    f2x = Pd[ii - 1, jj, 0] - Pd[ii, jj, 0]
    f2y = Pd[ii - 1, jj, 1] - Pd[ii, jj, 1]
    f2z = Pd[ii - 1, jj, 2] - Pd[ii, jj, 2]
    f3x = Pd[ii, jj + 1, 0] - Pd[ii, jj, 0]
    f3y = Pd[ii, jj + 1, 1] - Pd[ii, jj, 1]
    f3z = Pd[ii, jj + 1, 2] - Pd[ii, jj, 2]
    f4x = Pd[ii, jj - 1, 0] - Pd[ii, jj, 0]
    f4y = Pd[ii, jj - 1, 1] - Pd[ii, jj, 1]
    f4z = Pd[ii, jj - 1, 2] - Pd[ii, jj, 2]
    d2 = DEGENERATE * DEGENERATE
    # undeformed normal
    aux = e1x - e2x
    auy = e1y - e2y
    auz = e1z - e2z
    bux = e3x - e4x
    buy = e3y - e4y
    buz = e3z - e4z
    la2 = aux * aux + auy * auy + auz * auz
    lb2 = bux * bux + buy * buy + buz * buz
    ux = auy * buz - auz * buy
    uy = auz * bux - aux * buz
    uz = aux * buy - auy * bux
    ln2 = ux * ux + uy * uy + uz * uz
    good = (ln2 > d2 * la2 * lb2) & (la2 > d2 * lb2) & (lb2 > d2 * la2)
    inv = _inv_sqrt(ln2)
    ux *= inv
    uy *= inv
    uz *= inv
    # deformed normal
    adx = f1x - f2x
    ady = f1y - f2y
    adz = f1z - f2z
    bdx = f3x - f4x
    bdy = f3y - f4y
    bdz = f3z - f4z
    ma2 = adx * adx + ady * ady + adz * adz
    mb2 = bdx * bdx + bdy * bdy + bdz * bdz
    dx = ady * bdz - adz * bdy
    dy = adz * bdx - adx * bdz
    dz = adx * bdy - ady * bdx
    mn2 = dx * dx + dy * dy + dz * dz
    good &= (mn2 > d2 * ma2 * mb2) & (ma2 > d2 * mb2) & (mb2 > d2 * ma2)
    inv = _inv_sqrt(mn2)
    dx *= inv
    dy *= inv
    dz *= inv
    # Q1 for n_u . n_d >= 0: [1 + c, n_u x n_d] normalised (as from_two_units_s)
    c = ux * dx + uy * dy + uz * dz
    good &= c >= 0.0
    vx = uy * dz - uz * dy
    vy = uz * dx - ux * dz
    vz = ux * dy - uy * dx
    w = 1.0 + c
    inv = _inv_sqrt(w * w + vx * vx + vy * vy + vz * vz)
    a0 = w * inv
    a1 = vx * inv
    a2 = vy * inv
    a3 = vz * inv
    # tangent-plane bases
    inv = _inv_sqrt(la2)
    t1x = aux * inv
    t1y = auy * inv
    t1z = auz * inv
    t2x = uy * t1z - uz * t1y
    t2y = uz * t1x - ux * t1z
    t2z = ux * t1y - uy * t1x
    T1x, T1y, T1z = _rot_s(a0, a1, a2, a3, t1x, t1y, t1z)
    T2x = dy * T1z - dz * T1y
    T2y = dz * T1x - dx * T1z
    T2z = dx * T1y - dy * T1x
    s1, c1, g1 = _edge_angle_fast(e1x, e1y, e1z, f1x, f1y, f1z, t1x, t1y, t1z, t2x, t2y, t2z,
                                  T1x, T1y, T1z, T2x, T2y, T2z)
    s2, c2, g2 = _edge_angle_fast(e2x, e2y, e2z, f2x, f2y, f2z, t1x, t1y, t1z, t2x, t2y, t2z,
                                  T1x, T1y, T1z, T2x, T2y, T2z)
    s3, c3, g3 = _edge_angle_fast(e3x, e3y, e3z, f3x, f3y, f3z, t1x, t1y, t1z, t2x, t2y, t2z,
                                  T1x, T1y, T1z, T2x, T2y, T2z)
    s4, c4, g4 = _edge_angle_fast(e4x, e4y, e4z, f4x, f4y, f4z, t1x, t1y, t1z, t2x, t2y, t2z,
                                  T1x, T1y, T1z, T2x, T2y, T2z)
    ss = s1 + s2 + s3 + s4
    cc = c1 + c2 + c3 + c4
    good &= g1 & g2 & g3 & g4 & (cc >= 0.0)
    # Q2 for cc >= 0: (r + cc, ss) normalised
    r = math.sqrt(ss * ss + cc * cc)
    hw = r + cc
    hs = ss
    hn = hw * hw + hs * hs
    good &= hn > 0.0                       # the four edge directions cancel: general kernel
    inv = _inv_sqrt(hn)
    hw *= inv
    hs *= inv
    w, x, y, z = mul_s(hw, dx * hs, dy * hs, dz * hs, a0, a1, a2, a3)
    return w, x, y, z, good


@task_jit
def _motion_rows(lo, hi, Pu, Pd, oi, oj, e, c, q, delta, ok, surf):
    """Q, delta and the defined flag at every point of the patch rows ``lo <= i < hi`` of a
    wall curve (``surf`` None) or surface (True): compiled once per kind, the other's code
    pruned before typing, so a run compiles the code of the walls it has only.

    Interior surface points try the straight-line :func:`_interior_quaternion`
    first; within a row the sign of q follows the previous defined point.  (The row is
    a loop here, not a compiled function of its own: one compiled level fewer.)
    """
    for i in range(lo, hi):
        na = q.shape[0]
        nb = q.shape[1]
        have = False
        p0 = 1.0
        p1 = 0.0
        p2 = 0.0
        p3 = 0.0
        for j in range(nb):
            good = False
            w = 1.0
            x = 0.0
            y = 0.0
            z = 0.0
            if surf is not None:
                if 0 < i < na - 1 and 0 < j < nb - 1:
                    w, x, y, z, good = _interior_quaternion(Pu, Pd, i + oi, j + oj)
            if not good:
                w, x, y, z, good = _point_quaternion(Pu, Pd, i + oi, j + oj, surf, e)
            if good:
                if have and w * p0 + x * p1 + y * p2 + z * p3 < 0.0:
                    w = -w
                    x = -x
                    y = -y
                    z = -z
                have = True
                p0 = w
                p1 = x
                p2 = y
                p3 = z
                ok[i, j] = 1
            else:
                ok[i, j] = 0
            q[i, j, 0] = w
            q[i, j, 1] = x
            q[i, j, 2] = y
            q[i, j, 3] = z
            # delta = r_d - c - rot(q, r_u - c)
            rx, ry, rz = _rot_s(w, x, y, z, Pu[i + oi, j + oj, 0] - c[0],
                                Pu[i + oi, j + oj, 1] - c[1], Pu[i + oi, j + oj, 2] - c[2])
            delta[i, j, 0] = Pd[i + oi, j + oj, 0] - c[0] - rx
            delta[i, j, 1] = Pd[i + oi, j + oj, 1] - c[1] - ry
            delta[i, j, 2] = Pd[i + oi, j + oj, 2] - c[2] - rz


@jit
def _fill_degenerate(Pu, Pd, oi, oj, c, q, delta, ok):
    """Give undefined points the blend of their defined neighbours (8-neighbourhood).

    Sweeps until every point is defined; a point filled in one sweep serves
    its neighbours from the next sweep on, so the result does not depend on
    the loop order.  Points with no defined point anywhere get the identity.
    Returns the number of points filled.
    """
    na = q.shape[0]
    nb = q.shape[1]
    qs = np.empty((8, 4))
    wt = np.ones(8)
    orig = ok.copy()
    cur = ok.copy()
    while True:
        filled = 0
        left = 0
        for i in range(na):
            for j in range(nb):
                if ok[i, j] != 0:
                    continue
                m = 0
                for di in range(-1, 2):
                    for dj in range(-1, 2):
                        a = i + di
                        b = j + dj
                        if (di == 0 and dj == 0) or a < 0 or b < 0 or a >= na or b >= nb:
                            continue
                        if ok[a, b] != 0:
                            qs[m, 0] = q[a, b, 0]
                            qs[m, 1] = q[a, b, 1]
                            qs[m, 2] = q[a, b, 2]
                            qs[m, 3] = q[a, b, 3]
                            m += 1
                if m > 0:
                    kblend(qs[:m], wt[:m], q[i, j])
                    cur[i, j] = 1
                    filled += 1
                else:
                    left += 1
        for i in range(na):
            for j in range(nb):
                ok[i, j] = cur[i, j]
        if left == 0 or filled == 0:
            break
    count = 0
    for i in range(na):
        for j in range(nb):
            if orig[i, j] == 0:
                if ok[i, j] == 0:          # nothing defined anywhere
                    q[i, j, 0] = 1.0
                    q[i, j, 1] = 0.0
                    q[i, j, 2] = 0.0
                    q[i, j, 3] = 0.0
                _delta(Pu, Pd, i + oi, j + oj, c, q[i, j], delta[i, j])
                count += 1
    return count


@jit
def _align_rows_serial(q):
    """Make q . q_previous >= 0 along every row (used after filling)."""
    for i in range(q.shape[0]):
        for j in range(1, q.shape[1]):
            if (q[i, j, 0] * q[i, j - 1, 0] + q[i, j, 1] * q[i, j - 1, 1]
                    + q[i, j, 2] * q[i, j - 1, 2] + q[i, j, 3] * q[i, j - 1, 3]) < 0.0:
                for k in range(4):
                    q[i, j, k] = -q[i, j, k]


@jit
def _align_columns(q):
    """Flip whole rows so that column 0 is sign-consistent and q[0, 0] has w >= 0.

    Rows are consistent already; the decision is sequential over rows and
    only flipped rows are touched (none for a smooth field).
    """
    na = q.shape[0]
    nb = q.shape[1]
    p0 = 1.0
    p1 = 0.0
    p2 = 0.0
    p3 = 0.0
    for i in range(na):
        if q[i, 0, 0] * p0 + q[i, 0, 1] * p1 + q[i, 0, 2] * p2 + q[i, 0, 3] * p3 < 0.0:
            for j in range(nb):
                for k in range(4):
                    q[i, j, k] = -q[i, j, k]
        p0 = q[i, 0, 0]
        p1 = q[i, 0, 1]
        p2 = q[i, 0, 2]
        p3 = q[i, 0, 3]


@jit
def _centroid(r):
    """Mean of the points ``r (n, 3)``."""
    sx = 0.0
    sy = 0.0
    sz = 0.0
    n = r.shape[0]
    for k in range(n):
        sx += r[k, 0]
        sy += r[k, 1]
        sz += r[k, 2]
    out = np.empty(3)
    out[0] = sx / n
    out[1] = sy / n
    out[2] = sz / n
    return out


@task_jit
def _normals_rows(lo, hi, P, oi, oj, curve, e, out, ok):
    """Unit normals of the patch rows ``lo <= i < hi`` (:func:`surface_normals`)."""
    for i in range(lo, hi):
        for j in range(out.shape[1]):
            x, y, z, good = _normal(P, i + oi, j + oj, curve, e)
            out[i, j, 0] = x
            out[i, j, 1] = y
            out[i, j, 2] = z
            ok[i, j] = good


# ------------------------------------------------------------------ drivers
def _points(a, name: str) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise GridValueError(f"{name}: expected an array of real numbers ({exc})") from None
    if arr.ndim not in (2, 3) or arr.shape[-1] != 3 or 0 in arr.shape:
        raise GridValueError(f"{name}: expected wall points of shape (na, nb, 3) (a surface) or "
                             f"(n, 3) (a curve), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr).all(axis=-1))[0]
        raise GridValueError(f"{name}: NaN or infinite coordinates, first at index {tuple(int(b) for b in bad)}")
    return arr


def _vector3(a, name: str, unit: bool = False) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise GridValueError(f"{name}: expected 3 real numbers ({exc})") from None
    if arr.shape != (3,):
        raise GridValueError(f"{name}: expected shape (3,), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise GridValueError(f"{name}: NaN or infinite values {arr.tolist()}")
    if unit:
        n = float(np.sqrt(arr @ arr))
        if not n > 0.0:
            raise GridValueError(f"{name}: zero vector, expected a direction")
        arr = arr / n
    return arr


def _padded(r, halo, name: str, interior, other_missing=None):
    """Validate a halo array against the patch ``r``; returns the halo (C order) and its missing mask."""
    curve = r.ndim == 2
    want = (r.shape[0] + 2, 3) if curve else (r.shape[0] + 2, r.shape[1] + 2, 3)
    try:
        h = np.asarray(halo, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise GridValueError(f"{name}: expected an array of real numbers ({exc})") from None
    if h.shape != want:
        raise DeformationError(f"{name}: expected the patch padded by one row on every side, "
                               f"shape {want}, got shape {h.shape}")
    inner = h[1:-1] if curve else h[1:-1, 1:-1]
    if not np.array_equal(inner, r):
        raise DeformationError(f"{name}: its interior differs from {interior}; the halo must be "
                               f"{interior} padded by one row of neighbour points")
    missing = np.isnan(h).any(axis=-1)
    if np.any(~np.isfinite(h[~missing])):
        raise GridValueError(f"{name}: infinite coordinates (use NaN where there is no neighbour)")
    if other_missing is not None and not np.array_equal(missing, other_missing):
        raise DeformationError(f"{name}: NaN (no neighbour) at other places than in halo_u")
    h = h.copy()
    h[missing] = np.nan
    return h, missing


def _prepare(ru, rd, plane_normal, halo_u, halo_d, names=("ru", "rd")):
    """Shared validation; returns (Pu, Pd, oi, oj, curve, e, shape)."""
    ru = _points(ru, names[0])
    curve = ru.ndim == 2
    if rd is not None:
        rd = _points(rd, names[1])
        if rd.shape != ru.shape:
            raise DeformationError(f"{names[1]}: shape {rd.shape} differs from {names[0]} {ru.shape}: "
                                   f"deformed and undeformed points must match one to one")
    if curve:
        if plane_normal is None:
            raise GridValueError(f"plane_normal: required for a wall curve ({names[0]} has shape "
                                 f"{ru.shape}), e.g. (0, 0, 1) for a grid in the x-y plane")
        e = _vector3(plane_normal, "plane_normal", unit=True)
    else:
        if plane_normal is not None:
            raise GridValueError(f"plane_normal: only for wall curves of shape (n, 3); "
                                 f"{names[0]} is a surface of shape {ru.shape}")
        e = np.zeros(3)
    if halo_u is None and min(ru.shape[:-1]) < 2:
        what = "curve (n, 3) needs n >= 2" if curve else "surface (na, nb, 3) needs na, nb >= 2"
        hint = "" if curve else "; the wall of a 2-D grid is a curve (n, 3) with plane_normal"
        raise GridValueError(f"{names[0]}: shape {ru.shape}: a wall {what} to have tangents, "
                             f"unless a halo supplies the neighbours{hint}")
    if (halo_u is None) != (halo_d is None) and rd is not None:
        given, lack = ("halo_u", "halo_d") if halo_d is None else ("halo_d", "halo_u")
        raise DeformationError(f"{lack}: missing while {given} is given; pass both or neither")
    if halo_u is not None:
        Pu, miss = _padded(ru, halo_u, names[2] if len(names) > 2 else "halo_u", names[0])
        Pd = None
        if rd is not None:
            Pd, _ = _padded(rd, halo_d, "halo_d", names[1], miss)
        oi, oj = 1, (0 if curve else 1)
    else:
        Pu, Pd = np.ascontiguousarray(ru), (None if rd is None else np.ascontiguousarray(rd))
        oi, oj = 0, 0
    if curve:
        Pu = Pu[:, None, :]
        Pd = None if Pd is None else Pd[:, None, :]
    return Pu, Pd, oi, oj, curve, e, ru.shape[:-1]


def boundary_motion(ru, rd, centre=None, *, plane_normal=None, halo_u=None, halo_d=None):
    """Boundary quaternions and translations of one structured wall patch (docs/method.md §3.1).

    Parameters
    ----------
    ru, rd : array_like, shape (na, nb, 3) or (n, 3), float64
        Undeformed and deformed points of a surface patch, or of the wall
        curve of a 2-D grid (then ``plane_normal`` is required).  Any memory
        order (copied to C order when needed); must be finite.
    centre : array_like, shape (3,), optional
        Rotation centre ``c``.  Default: the centroid of ``ru``.  Pass one
        centre for all walls of a grid (e.g. the centroid of all walls), so
        that the field moves with the problem (docs/method.md §3.6).
    plane_normal : array_like, shape (3,), optional
        For a curve: the normal of the grid plane, e.g. ``(0, 0, 1)``; the
        curve normal is ``t x plane_normal`` with ``t`` along increasing index.
    halo_u, halo_d : array_like, shape (na+2, nb+2, 3) or (n+2, 3), optional
        ``ru`` / ``rd`` padded by one row of neighbour points on every side
        (where the wall continues into another block or across a periodic
        seam), NaN where there is no neighbour; corners are not used.  The
        interior must equal ``ru`` / ``rd`` and the NaN pattern must agree.

    Returns
    -------
    q : ndarray, shape (na, nb, 4) or (n, 4), float64
        Unit quaternions ``(w, x, y, z)``, signs consistent between
        neighbours (``q[0, 0]`` has ``w >= 0``).
    delta : ndarray, shape (na, nb, 3) or (n, 3), float64
        ``rd - c - rot(q, ru - c)``: ``c + delta + rot(q, ru - c)`` gives
        ``rd`` to round-off.

    Raises
    ------
    GridValueError
        An argument of the wrong shape, non-finite points, a missing or zero
        ``plane_normal``, a patch one point wide without a halo.
    DeformationError
        ``rd`` or a halo that does not match ``ru`` (shape, interior, NaN
        pattern), or only one halo.

    Notes
    -----
    A rigid motion of the patch gives the same ``q`` (up to sign) and the
    same ``delta`` at every point to round-off.  Points without a normal
    (collapsed edges, coincident neighbours) take the blend of their
    neighbours' ``q``; never NaN.
    """
    Pu, Pd, oi, oj, curve, e, shape = _prepare(ru, rd, plane_normal, halo_u, halo_d)
    if centre is None:
        c = _centroid(np.ascontiguousarray(ru, dtype=np.float64).reshape(-1, 3))
    else:
        c = _vector3(centre, "centre")
    na = shape[0]
    nb = 1 if curve else shape[1]
    q, delta = motion_padded(Pu, Pd, oi, oj, curve, e, c, na, nb)
    return q.reshape(shape + (4,)), delta.reshape(shape + (3,))


def motion_padded(Pu, Pd, oi, oj, curve, e, c, na, nb):
    """:func:`boundary_motion` on validated, halo-padded input; nothing is checked.

    The building block for a caller that pads a patch once and calls every
    step (the Deformer).  ``Pu``/``Pd``: the undeformed and deformed points
    with their halos, float64, C order, as ``_prepare`` builds them; ``oi``,
    ``oj``: the halo widths (offset of point (0, 0)); ``curve``: a 2-D
    boundary curve (``nb == 1``) in the plane of normal ``e`` (3,); ``c``
    (3,): the rotation centre; ``na``, ``nb``: the patch's point counts.

    Returns ``q`` (na, nb, 4) and ``delta`` (na, nb, 3), float64.
    """
    q = np.empty((na, nb, 4))
    delta = np.empty((na, nb, 3))
    ok = np.empty((na, nb), dtype=np.uint8)
    parallel_for(_motion_rows, na, Pu, Pd, oi, oj, e, c, q, delta, ok, None if curve else True)
    if not ok.all():
        _fill_degenerate(Pu, Pd, oi, oj, c, q, delta, ok)
        _align_rows_serial(q)
    _align_columns(q)
    return q, delta


def surface_normals(r, halo=None, plane_normal=None):
    """Unit normals of a wall patch from in-surface tangents (as used by :func:`boundary_motion`).

    Parameters
    ----------
    r : array_like, shape (na, nb, 3) or (n, 3), float64
        Surface patch, or wall curve (then ``plane_normal`` is required).
    halo : array_like, shape (na+2, nb+2, 3) or (n+2, 3), optional
        ``r`` padded by one row of neighbour points, NaN where none.
    plane_normal : array_like, shape (3,), optional
        Grid-plane normal for a curve; the normal is ``t x plane_normal``.

    Returns
    -------
    n : ndarray, shape (na, nb, 3) or (n, 3), float64
        Unit normals ``t_a x t_b / |t_a x t_b|`` (``a`` the first index);
        the zero vector where undefined.
    defined : ndarray of bool, shape (na, nb) or (n,)
        False where the normal is undefined (zero-length or collapsed edges,
        parallel tangents).
    """
    P, _, oi, oj, curve, e, shape = _prepare(r, None, plane_normal, halo, None,
                                             names=("r", "rd", "halo"))
    na = shape[0]
    nb = 1 if curve else shape[1]
    out = np.empty((na, nb, 3))
    ok = np.empty((na, nb), dtype=np.bool_)
    parallel_for(_normals_rows, na, P, oi, oj, curve, e, out, ok)
    return out.reshape(shape + (3,)), ok.reshape(shape)
