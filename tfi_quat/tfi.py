"""Arclength parameters and Soni transfinite interpolation (TFI) kernels.

docs/method.md §3.2, §3.4, §3.5 and §6.  Every interpolated field is a pair (Δ, Q): a
translation (3 components, blended linearly) and a unit quaternion
(``(w, x, y, z)``, slerp in the leading direction, hemisphere-aligned linear
corrections, normalised at the end).  The blending parameters are the
normalised arclengths ``s`` of the **undeformed** grid lines.

Recursive (Boolean-sum) form, directions in the order ``L, M, N``::

    U = (1 - s_L) F_L0 + s_L F_L1                                (Q: slerp)
    V = U + (1 - s_M)(F_M0 - U|M0) + s_M (F_M1 - U|M1)
    W = V + (1 - s_N)(F_N0 - V|N0) + s_N (F_N1 - V|N1)           (Q: normalise)

``U|M0`` is U at the face point (with that point's own ``s_L``); before a
quaternion residual ``F - U`` is formed, ``F`` is flipped to the hemisphere of
``U`` at that point.  A blended quaternion whose norm falls below
:data:`QNORM_MIN` is replaced by the same Boolean sum of rotation vectors
(log map in the tangent space at the slerp value ``U``), so nothing divides by
~0.

Public functions
----------------
:func:`arclength`, :func:`arclength_curve`, :func:`arclength_surface`
    blending parameters (set up once per grid); :func:`face_params` their
    values on the six faces, also set up once, for the fused kernels.
:func:`lead_order`
    direction order from the prescribed point counts of the faces.
:func:`interp_segment`
    1-D interpolation of (Δ, Q) along a segment.
:func:`patch_params`, :func:`tfi_patch_fast`
    2-D interpolation of (Δ, Q) fields on a patch, filled from its sides.
:func:`deform_block`, :func:`deform_block_2d`
    the fused volume stage ``R_d = c + Δ(x) + rot(Q(x), R_u - c)``, computed
    point by point from O(surface) precomputed data, with no full-size Δ or Q
    arrays.
:func:`gather_plan`, :func:`deform_block_gathered`
    the same stage for a caller whose face values are rows of global arrays
    (the Deformer): the faces are gathered inside the compiled set-up,
    straight into the tables, which a :class:`GatherPlan` keeps between calls.
:func:`check_xyz`
    the validation of block coordinates every driver here (and in
    :mod:`tfi_quat.blending`) applies.

The per-point formulas, slerp weights and arclength walkers these kernels
inline live in :mod:`tfi_quat.kernels` (shared with :mod:`tfi_quat.blending`
and :mod:`tfi_quat.deform`).  One definition makes every fused volume kernel
(:func:`_volume_kernel`, specialised by 2-D/3-D, quaternion or baseline,
based or not) and one dispatcher runs them (:func:`_run_volume`).  A plain
numpy reference of the same TFI, for tests, is ``tests/oracles.py``.

Fused kernel layout
-------------------
Before the volume loop, O(surface) tables are built (``_prep``): per line of
the leading direction ``L`` (indexed like face ``L``), the two end values of
Δ and Q, with the slerp angle (squared) and its ``sin(ω)/ω``; per point of
the two ``M`` faces, the residuals ``F - U``; per point of the two ``N``
faces, the residuals ``F - V``.  The volume loop then reads ``R_u`` and ``s``
once, gathers from those tables (cache-resident), and writes ``R_d``.  The
slerp weights use a polynomial ``sin(x)/x`` (no library call in the inner
loop, so it vectorises); they are exactly 0 and 1 at the ends.
"""

from __future__ import annotations

import functools
import math
import operator
import threading
from typing import Sequence

import numpy as np

from ._jit import jit, parallel_for, task_jit
from .errors import GridValueError
from .grid import FACES
from .kernels import (QNORM_MIN, face_coords, face_point, fallback_q, slerp_angle, slerp_weights,
                      u_d, u_q, v_d, v_q, w_d, w_q)

__all__ = [
    "S_DTYPE", "QNORM_MIN", "ZERO_LENGTH_RTOL",
    "arclength", "arclength_curve", "arclength_surface", "check_xyz",
    "face_params", "lead_order", "interp_segment", "patch_params", "tfi_patch_fast",
    "deform_block", "deform_block_2d",
    "GatherPlan", "gather_plan", "deform_block_gathered",
]

#: storage type of the arclength parameters returned by :func:`arclength`.
#: float64, chosen by measurement (benchmarks/results/2026-12-01-tfi.md):
#: float32 saves 12 of 72 bytes per point of the volume stage; on a quiet
#: machine that sped the quaternion loop up by 2 % (it is compute-bound) and
#: the baseline loop by 20 % (memory-bound, already 2.6x its target), while it
#: moved interior points by up to ~1e-7 of a line length, so affine fields and
#: TFI-built grids were no longer reproduced to round-off.  The kernels
#: therefore take float64 only (one compiled specialisation each).
S_DTYPE = np.float64

#: a line shorter than this times its end points' largest coordinate
#: magnitude counts as zero-length (parameters become index-uniform)
ZERO_LENGTH_RTOL = 1e-12


@jit(inline="always")
def _store_at(out, i, j, k, x0, y0, z0, cx, cy, cz, dx, dy, dz, qw, qx, qy, qz):
    """``out = R + Δ + (rot(q, R - c) - (R - c))`` for the base point ``R = (x0, y0, z0)``
    (exact identity when q = 1, Δ = 0)."""
    vx = x0 - cx
    vy = y0 - cy
    vz = z0 - cz
    tx = 2.0 * (qy * vz - qz * vy)
    ty = 2.0 * (qz * vx - qx * vz)
    tz = 2.0 * (qx * vy - qy * vx)
    out[i, j, k, 0] = x0 + dx + (qw * tx + (qy * tz - qz * ty))
    out[i, j, k, 1] = y0 + dy + (qw * ty + (qz * tx - qx * tz))
    out[i, j, k, 2] = z0 + dz + (qw * tz + (qx * ty - qy * tx))


@jit(inline="always")
def _store(xyz, out, i, j, k, cx, cy, cz, dx, dy, dz, qw, qx, qy, qz):
    """:func:`_store_at` with the base point ``R_u = xyz[i, j, k]``."""
    _store_at(out, i, j, k, xyz[i, j, k, 0], xyz[i, j, k, 1], xyz[i, j, k, 2], cx, cy, cz,
              dx, dy, dz, qw, qx, qy, qz)


@jit(inline="always")
def _store_g_at(out, i, j, k, x0, y0, z0, cx, cy, cz, dx, dy, dz, qw, qx, qy, qz, g):
    """:func:`_store_at` with the change scaled by ``g``: 1 gives its result bit for bit
    (the same sums), 0 stores the base point itself."""
    vx = x0 - cx
    vy = y0 - cy
    vz = z0 - cz
    tx = 2.0 * (qy * vz - qz * vy)
    ty = 2.0 * (qz * vx - qx * vz)
    tz = 2.0 * (qx * vy - qy * vx)
    out[i, j, k, 0] = x0 + g * dx + g * (qw * tx + (qy * tz - qz * ty))
    out[i, j, k, 1] = y0 + g * dy + g * (qw * ty + (qz * tx - qx * tz))
    out[i, j, k, 2] = z0 + g * dz + g * (qw * tz + (qx * ty - qy * tx))


@jit
def _fix_rows(xyz, s, out, rows, cx, cy, cz, L, M, N, lineD, lineQ, gD, gQ, hD, hQ,
              fbM, fbN, hasn, hasb, lineB, gB, hB):
    """Redo the points of the rows ``rows`` (row ``j + nj k``) whose blended Q is below
    QNORM_MIN, with the fallback (serial: the rare path, compiled only by a run that needs it).

    ``hasb``: about the based kernels' base point ``R_u + TFI(B)`` (tables ``lineB``,
    ``gB``, ``hB``; any tables of the right rank, never read, otherwise)."""
    for r in range(rows.shape[0]):
        j = rows[r] % xyz.shape[1]
        k = rows[r] // xyz.shape[1]
        _fix_row(xyz, s, out, j, k, cx, cy, cz, L, M, N, lineD, lineQ, gD, gQ, hD, hQ,
                 fbM, fbN, hasn, hasb, lineB, gB, hB)


@jit(inline="always")
def _fix_row(xyz, s, out, j, k, cx, cy, cz, L, M, N, lineD, lineQ, gD, gQ, hD, hQ,
             fbM, fbN, hasn, hasb, lineB, gB, hB):
    """Row (j, k) of :func:`_fix_rows`."""
    for i in range(xyz.shape[0]):
        la, lb = face_coords(i, j, k, L)
        ma, mb = face_coords(i, j, k, M)
        if hasn:
            na, nb = face_coords(i, j, k, N)
        else:
            na, nb = 0, 0
        t = np.float64(s[i, j, k, L])
        sm = np.float64(s[i, j, k, M])
        sn = np.float64(s[i, j, k, N])
        qw, qx, qy, qz = w_q(lineQ, la, lb, t, gQ, ma, mb, sm, hQ, na, nb, sn)
        if math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz) < QNORM_MIN:
            dx, dy, dz = w_d(lineD, la, lb, t, gD, ma, mb, sm, hD, na, nb, sn)
            qw, qx, qy, qz = fallback_q(lineQ, la, lb, t, fbM, ma, mb, sm, fbN, na, nb, sn, hasn)
            if hasb:
                x0, y0, z0 = _base_at(xyz, i, j, k, lineB, la, lb, t, gB, ma, mb, sm, hB, na, nb,
                                      sn)
                _store_at(out, i, j, k, x0, y0, z0, cx, cy, cz, dx, dy, dz, qw, qx, qy, qz)
            else:
                _store(xyz, out, i, j, k, cx, cy, cz, dx, dy, dz, qw, qx, qy, qz)


# =================================================================== set-up (O(surface))
@jit
def _coherent(q):
    """Flip signs in place so that neighbouring quaternions of a face (na, nb, 4) share a hemisphere."""
    na, nb = q.shape[0], q.shape[1]
    for b in range(nb):
        for a in range(na):
            if a == 0 and b == 0:
                continue
            if b == 0:
                pa, pb = a - 1, 0
            else:
                pa, pb = a, b - 1
            d = q[a, b, 0] * q[pa, pb, 0] + q[a, b, 1] * q[pa, pb, 1] + \
                q[a, b, 2] * q[pa, pb, 2] + q[a, b, 3] * q[pa, pb, 3]
            if d < 0.0:
                for c in range(4):
                    q[a, b, c] = -q[a, b, c]


@jit(inline="always")
def _prep_line(b, hasq, FL, QL, lineD, lineQ):
    """Line table of the leading direction, column ``b`` of face L."""
    for a in range(FL.shape[0]):
        for c in range(3):
            lineD[a, b, c] = FL[a, b, c, 0]
            lineD[a, b, 3 + c] = FL[a, b, c, 1]
    if hasq:
        for a in range(QL.shape[0]):
            d = QL[a, b, 0, 0] * QL[a, b, 0, 1] + QL[a, b, 1, 0] * QL[a, b, 1, 1] + \
                QL[a, b, 2, 0] * QL[a, b, 2, 1] + QL[a, b, 3, 0] * QL[a, b, 3, 1]
            sg = -1.0 if d < 0.0 else 1.0
            for c in range(4):
                lineQ[a, b, c] = QL[a, b, c, 0]
                lineQ[a, b, 4 + c] = sg * QL[a, b, c, 1]
            w2, sw = slerp_angle(lineQ[a, b, 0], lineQ[a, b, 1], lineQ[a, b, 2], lineQ[a, b, 3],
                                  lineQ[a, b, 4], lineQ[a, b, 5], lineQ[a, b, 6], lineQ[a, b, 7])
            lineQ[a, b, 8] = w2
            lineQ[a, b, 9] = sw


@jit(inline="always")
def _prep_m(b, side, im, SM, L, M, hasq, FM, QM, lineD, lineQ, gD, gQ, fbM):
    """Residuals ``F - U`` on column ``b`` of the M face ``side`` (index ``im``)."""
    for a in range(FM.shape[0]):
        i, j, k = face_point(M, im, a, b)
        la, lb = face_coords(i, j, k, L)
        t = SM[a, b, L, side]
        x, y, z = u_d(lineD, la, lb, t)
        gD[a, b, 3 * side] = FM[a, b, 0, side] - x
        gD[a, b, 3 * side + 1] = FM[a, b, 1, side] - y
        gD[a, b, 3 * side + 2] = FM[a, b, 2, side] - z
        if hasq:
            qw, qx, qy, qz = u_q(lineQ, la, lb, t)
            d = qw * QM[a, b, 0, side] + qx * QM[a, b, 1, side] + qy * QM[a, b, 2, side] + qz * QM[a, b, 3, side]
            sg = -1.0 if d < 0.0 else 1.0
            o = 4 * side
            gQ[a, b, o] = sg * QM[a, b, 0, side] - qw
            gQ[a, b, o + 1] = sg * QM[a, b, 1, side] - qx
            gQ[a, b, o + 2] = sg * QM[a, b, 2, side] - qy
            gQ[a, b, o + 3] = sg * QM[a, b, 3, side] - qz
            n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            o = 8 * side
            fbM[a, b, o] = qw / n
            fbM[a, b, o + 1] = qx / n
            fbM[a, b, o + 2] = qy / n
            fbM[a, b, o + 3] = qz / n
            for c in range(4):
                fbM[a, b, o + 4 + c] = sg * QM[a, b, c, side]


@jit(inline="always")
def _prep_n(b, side, im, SN, L, M, N, hasq, FN, QN, lineD, lineQ, gD, gQ, fbM, hD, hQ, fbN):
    """Residuals ``F - V`` on column ``b`` of the N face ``side`` (index ``im``)."""
    for a in range(FN.shape[0]):
        i, j, k = face_point(N, im, a, b)
        la, lb = face_coords(i, j, k, L)
        ma, mb = face_coords(i, j, k, M)
        t = SN[a, b, L, side]
        sm = SN[a, b, M, side]
        x, y, z = v_d(lineD, la, lb, t, gD, ma, mb, sm)
        hD[a, b, 3 * side] = FN[a, b, 0, side] - x
        hD[a, b, 3 * side + 1] = FN[a, b, 1, side] - y
        hD[a, b, 3 * side + 2] = FN[a, b, 2, side] - z
        if hasq:
            qw, qx, qy, qz = v_q(lineQ, la, lb, t, gQ, ma, mb, sm)
            d = qw * QN[a, b, 0, side] + qx * QN[a, b, 1, side] + qy * QN[a, b, 2, side] + qz * QN[a, b, 3, side]
            sg = -1.0 if d < 0.0 else 1.0
            o = 4 * side
            hQ[a, b, o] = sg * QN[a, b, 0, side] - qw
            hQ[a, b, o + 1] = sg * QN[a, b, 1, side] - qx
            hQ[a, b, o + 2] = sg * QN[a, b, 2, side] - qy
            hQ[a, b, o + 3] = sg * QN[a, b, 3, side] - qz
            n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            if n >= QNORM_MIN:
                qw /= n
                qx /= n
                qy /= n
                qz /= n
            else:
                qw, qx, qy, qz = fallback_q(lineQ, la, lb, t, fbM, ma, mb, sm,
                                             fbN, 0, 0, 0.0, False)
            o = 8 * side
            fbN[a, b, o] = qw
            fbN[a, b, o + 1] = qx
            fbN[a, b, o + 2] = qy
            fbN[a, b, o + 3] = qz
            for c in range(4):
                fbN[a, b, o + 4 + c] = sg * QN[a, b, c, side]


def _prep(SM, SN, nm, nn, L, M, N, hasn, FL, FM, FN, QL, QM, QN, hasq, lineD, lineQ, gD, gQ, hD, hQ,
          fbM, fbN):
    """Fill the surface tables of the fused kernels (see the module docstring).

    ``FL``/``QL``: Δ (na, nb, 3, 2) and Q (na, nb, 4, 2) on the two faces
    normal to ``L`` (last index: low, high face), F order, ``QL[..., 0]``
    already sign-coherent; likewise ``FM``, ``QM``, ``FN``, ``QN``, and the
    arclength parameters ``SM``, ``SN`` (na, nb, 3, 2) on the M and N faces;
    ``nm``, ``nn``: the block's point counts along M and N.
    ``hasn`` False: 2-D (no N faces); ``hasq`` False: baseline.  Runs the
    kernel of that dimension (:func:`_prep_kernel`).
    """
    _prep_kernel(bool(hasn))(SM, SN, nm, nn, L, M, N, FL, FM, FN, QL, QM, QN, bool(hasq),
                             lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN)


@functools.lru_cache(maxsize=None)
def _prep_kernel(hasn: bool):
    """The set-up kernel of one dimension (:func:`_prep` without ``hasn``), made on first
    use: ``hasn`` is a closure constant, so a 2-D run compiles none of the N-face code (nor
    the fallback it calls); ``hasq`` is an argument, tested per face column, so the
    baseline and quaternion calls share one compiled kernel (two kernels cost a run that
    uses both ~1 s more to compile; the baseline's set-up is O(surface)).  The phases run
    in order (M needs the lines, N needs M).  Serial: the work is O(surface), and a
    parallel kernel costs seconds more to compile."""
    @jit
    def prep(SM, SN, nm, nn, L, M, N, FL, FM, FN, QL, QM, QN, hasq, lineD, lineQ, gD, gQ, hD,
             hQ, fbM, fbN):
        for b in range(lineD.shape[1]):
            _prep_line(b, hasq, FL, QL, lineD, lineQ)
        for side in range(2):
            im = 0 if side == 0 else nm - 1
            for b in range(gD.shape[1]):
                _prep_m(b, side, im, SM, L, M, hasq, FM, QM, lineD, lineQ, gD, gQ, fbM)
        if hasn:
            for side in range(2):
                im = 0 if side == 0 else nn - 1
                for b in range(hD.shape[1]):
                    _prep_n(b, side, im, SN, L, M, N, hasq, FN, QN, lineD, lineQ, gD, gQ, fbM,
                            hD, hQ, fbN)

    return prep


@jit(forceinline=True)
def _gather_col(b, gd, gq, hasq, idx, F, Q):
    """Column ``b`` of the pair tables ``F`` (na, nb, 3, 2) and ``Q`` (na, nb, 4, 2) from
    the global rows ``idx[a, b, side]`` of ``gd`` (G, 3) and ``gq`` (G, 4)."""
    for side in range(2):
        for a in range(F.shape[0]):
            g = idx[a, b, side]
            for c in range(3):
                F[a, b, c, side] = gd[g, c]
            if hasq:
                for c in range(4):
                    Q[a, b, c, side] = gq[g, c]


@jit
def _gather(gd, gq, hasq, hasn, iL, iM, iN, FL, FM, FN, QL, QM, QN):
    """Fill the pair tables that :func:`_prep` takes straight from global arrays.

    ``iL``/``iM``/``iN``: (≥ na, nb, 2) global rows of the two faces normal to
    L, M, N (last index: low, high face); ``hasn`` False: 2-D (``FN``/``QN``
    untouched); ``hasq`` False: baseline (``gq``, ``QL``.. untouched).  One
    loop over the face columns of all directions (serial, as :func:`_prep`);
    then the leading faces' quaternions are made sign-coherent in place, as
    :func:`_tables` does.
    """
    nl = FL.shape[1]
    nm = FM.shape[1]
    ncol = nl + nm + (FN.shape[1] if hasn else 0)
    for bp in range(ncol):
        b = np.int64(bp)
        if b < nl:
            _gather_col(b, gd, gq, hasq, iL, FL, QL)
        elif b < nl + nm:
            _gather_col(b - nl, gd, gq, hasq, iM, FM, QM)
        else:
            _gather_col(b - nl - nm, gd, gq, hasq, iN, FN, QN)
    if hasq:
        _coherent(QL[:, :, :, 0])

#: face points (both faces of both directions) of a 2-D plan below which
#: :func:`_gather_tables` copies with numpy rather than the compiled :func:`_gather` (the same
#: values: copies; slower, but a 2-D plan's faces are lines): a run that only meets small 2-D
#: blocks, as the demo, does not compile the gather
_GATHER_NUMPY_BELOW = 1 << 12


def _gather_tables(gd, gq, hasq, hasn, iL, iM, iN, FL, FM, FN, QL, QM, QN) -> None:
    """:func:`_gather` (same arguments, same result), with numpy for small 2-D plans."""
    if hasn or 2 * (FL.shape[0] * FL.shape[1] + FM.shape[0] * FM.shape[1]) >= _GATHER_NUMPY_BELOW:
        _gather(gd, gq, hasq, hasn, iL, iM, iN, FL, FM, FN, QL, QM, QN)
        return
    for idx, F, Q in ((iL, FL, QL), (iM, FM, QM)):
        rows = idx[:F.shape[0], :F.shape[1]]
        for c in range(3):
            F[:, :, c, :] = gd[:, c][rows]
        if hasq:
            for c in range(4):
                Q[:, :, c, :] = gq[:, c][rows]
    if hasq:
        _coherent_numpy(QL[:, :, :, 0])


def _coherent_numpy(q) -> None:
    """:func:`_coherent` with numpy, the same flips: a point of the first column flips where
    its dot product with the (flipped) previous point is < 0, that is where the raw product is
    < 0 with the previous unflipped or > 0 with it flipped (the same magnitude, exactly), and
    stays where it is 0 or NaN; so the flips of the column are the parity of the raw negative
    products since the last such point.  The other columns, each after the previous one."""
    def dot(x, y):
        return x[..., 0] * y[..., 0] + x[..., 1] * y[..., 1] + x[..., 2] * y[..., 2] + \
            x[..., 3] * y[..., 3]

    na, nb = q.shape[0], q.shape[1]
    with np.errstate(all="ignore"):
        if na > 1:
            d = dot(q[1:, 0], q[:-1, 0])
            neg = np.concatenate([[0], np.cumsum(d < 0.0)])
            reset = np.concatenate([[True], ~((d < 0.0) | (d > 0.0))])
            last = np.maximum.accumulate(np.where(reset, np.arange(na), 0))
            flip = (neg - neg[last]) % 2 == 1
            q[flip, 0] = -q[flip, 0]
        for b in range(1, nb):
            flip = dot(q[:, b], q[:, b - 1]) < 0.0
            q[flip, b] = -q[flip, b]


# =================================================================== volume kernels
# One definition for the fused volume stage, specialised at compile time by
# three flags (2-D or 3-D, quaternion or displacement only, based or not):
# :func:`_point` and :func:`_row` take them as arguments, None (off) or True
# (on), so that numba compiles the row once per kind with the other kinds'
# branches pruned before typing (bool flags compiled all eight kinds' code into
# every kernel: three times the compile time); the kernel made by
# :func:`_volume_kernel` passes its kind's flags (closure constants) to the row.
# The row and the point are separate compiled functions that LLVM inlines
# (``forceinline``): numba types :func:`_point` once per kind although the row
# calls it at three places (one per role of direction i; IR inlining typed
# every copy: twice the compile time, the same machine code).

@jit(inline="always")
def _base_at(xyz, i, j, k, lineB, la, lb, t, gB, ma, mb, sm, hB, na, nb, sn):
    """The base point ``R_u + TFI(B)`` of the based kernels (``B``'s baseline TFI, the
    sums the displacement-only update makes)."""
    bx, by, bz = w_d(lineB, la, lb, t, gB, ma, mb, sm, hB, na, nb, sn)
    return xyz[i, j, k, 0] + bx, xyz[i, j, k, 1] + by, xyz[i, j, k, 2] + bz


@jit(forceinline=True)
def _point(xyz, s, out, i, j, k, cx, cy, cz, L, M, N, lineD, lineQ, la, lb, gD, gQ, ma, mb,
           hD, hQ, na, nb, lineB, gB, hB, hasq, based):
    """Fused update of one point; returns 1 when the blended Q needs the fallback.

    ``hasq`` None: the baseline, ``out = R_u + Δ`` (Q ≡ 1).  Otherwise
    ``out = R + Δ + (rot(Q, R - c) - (R - c))`` about the base point ``R``:
    ``R_u``, or with ``based`` True ``R_u + TFI(B)`` (tables ``lineB``, ``gB``,
    ``hB``).  A point that needs the fallback is stored as ``R`` itself (the
    change scaled by 0, without a branch), so that :func:`_fix_rows` still
    finds ``R_u`` there when ``out`` is ``xyz`` (in-place update).  (A select
    of Q = 1 and Δ = 0 instead cost 12 % of the loop's speed.)
    """
    t = np.float64(s[i, j, k, L])
    sm = np.float64(s[i, j, k, M])
    sn = np.float64(s[i, j, k, N])
    if hasq is None:
        dx, dy, dz = w_d(lineD, la, lb, t, gD, ma, mb, sm, hD, na, nb, sn)
        out[i, j, k, 0] = xyz[i, j, k, 0] + dx
        out[i, j, k, 1] = xyz[i, j, k, 1] + dy
        out[i, j, k, 2] = xyz[i, j, k, 2] + dz
        return 0
    if based is not None:
        x0, y0, z0 = _base_at(xyz, i, j, k, lineB, la, lb, t, gB, ma, mb, sm, hB, na, nb, sn)
    else:
        x0, y0, z0 = xyz[i, j, k, 0], xyz[i, j, k, 1], xyz[i, j, k, 2]
    dx, dy, dz = w_d(lineD, la, lb, t, gD, ma, mb, sm, hD, na, nb, sn)
    qw, qx, qy, qz = w_q(lineQ, la, lb, t, gQ, ma, mb, sm, hQ, na, nb, sn)
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    inv = 1.0 / max(n, QNORM_MIN)
    g = 1.0 if n >= QNORM_MIN else 0.0
    _store_g_at(out, i, j, k, x0, y0, z0, cx, cy, cz, dx, dy, dz, qw * inv, qx * inv, qy * inv,
                qz * inv, g)
    return 1 if n < QNORM_MIN else 0


@jit(forceinline=True)
def _row(xyz, s, out, j, k, cx, cy, cz, L, M, N, lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN,
         lineB, gB, hB, hasn, hasq, based):
    """Fused update of the row (j, k), i innermost (2-D: ``hasn`` None, k = 0, N = 2,
    ``hD``/``hQ`` zero dummies read at (0, 0)).

    The kind flags ``hasn``, ``hasq``, ``based`` are None (off) or True (on): their
    types select the code, numba prunes the ``is None`` branches before typing, and a
    row is compiled once per kind (flags taken as bool values compiled every kind's
    code into every kernel).

    The role whose direction is 0 (i) reads its table at a fixed (j, k); the
    others read a contiguous run along i.  Returns the number of points whose
    blended Q needs the fallback (:func:`_run_volume` has them redone by
    :func:`_fix_rows`).
    """
    ni = xyz.shape[0]
    nbad = 0
    if hasn is not None:
        if L == 0:
            cm = k if M == 1 else j
            cn = k if N == 1 else j
            for i in range(ni):
                nbad += _point(xyz, s, out, i, j, k, cx, cy, cz, L, M, N, lineD, lineQ, j, k,
                               gD, gQ, i, cm, hD, hQ, i, cn, lineB, gB, hB, hasq, based)
        elif M == 0:
            cl = k if L == 1 else j
            cn = k if N == 1 else j
            for i in range(ni):
                nbad += _point(xyz, s, out, i, j, k, cx, cy, cz, L, M, N, lineD, lineQ, i, cl,
                               gD, gQ, j, k, hD, hQ, i, cn, lineB, gB, hB, hasq, based)
        else:
            cl = k if L == 1 else j
            cm = k if M == 1 else j
            for i in range(ni):
                nbad += _point(xyz, s, out, i, j, k, cx, cy, cz, L, M, N, lineD, lineQ, i, cl,
                               gD, gQ, i, cm, hD, hQ, j, k, lineB, gB, hB, hasq, based)
    else:
        # z (0) and n2 (N = 2) as int64, not literals: the point then has the 3-D rows'
        # argument types (one compilation per kind for a run with 2-D and 3-D blocks)
        z = np.int64(0)
        n2 = np.int64(2)
        if L == 0:
            for i in range(ni):
                nbad += _point(xyz, s, out, i, j, z, cx, cy, cz, L, M, n2, lineD, lineQ, j, z,
                               gD, gQ, i, z, hD, hQ, z, z, lineB, gB, hB, hasq, based)
        else:
            for i in range(ni):
                nbad += _point(xyz, s, out, i, j, z, cx, cy, cz, L, M, n2, lineD, lineQ, i, z,
                               gD, gQ, j, z, hD, hQ, z, z, lineB, gB, hB, hasq, based)
    return nbad


def _volume_kernel(hasn: bool, hasq: bool, based: bool):
    """The fused volume kernel of one kind (made on first use, then kept).

    Signature of every kind: ``(xyz, s, out, cx, cy, cz, L, M, N, lineD,
    lineQ, gD, gQ, hD, hQ, fbM, fbN, lineB, gB, hB, bad)``; 2-D (``hasn`` False):
    ``N = 2``, parallel over rows; 3-D: parallel over k-planes.  Tables a
    kind does not read are any tables of the right rank (the dummies of
    :func:`_work_tables`; ``lineD, gD, hD`` for ``lineB, gB, hB``).  ``bad``
    (nj nk,) bool receives, per row ``j + nj k``, whether some point of the
    row needs the fallback (left as R there; :func:`_run_volume` then calls
    :func:`_fix_rows`, so runs that never need it never compile it).
    """
    key = (bool(hasn), bool(hasq), bool(based))
    kern = _VOLUME.get(key)
    if kern is None:
        with _VOLUME_LOCK:
            kern = _VOLUME.get(key)
            if kern is None:
                kern = _VOLUME[key] = _make_volume_kernel(*key)
    return kern


def _make_volume_kernel(hasn: bool, hasq: bool, based: bool):
    # the flags are closure constants (numba keys its disk cache on them); the row takes
    # them as None or True (a closure over a compiled function would not be cached)
    nflag = True if hasn else None
    qflag = True if hasq else None
    bflag = True if based else None

    @task_jit
    def volume(lo, hi, xyz, s, out, cx, cy, cz, L, M, N, lineD, lineQ, gD, gQ, hD, hQ, fbM,
               fbN, lineB, gB, hB, bad):
        nj = xyz.shape[1]
        ninner = nj if hasn else 1
        for p in range(lo, hi):
            for q in range(ninner):
                j = q if hasn else p
                k = p if hasn else 0
                bad[j + nj * k] = _row(xyz, s, out, j, k, cx, cy, cz, L, M, N, lineD, lineQ, gD,
                                       gQ, hD, hQ, fbM, fbN, lineB, gB, hB, nflag, qflag,
                                       bflag) > 0

    volume.__doc__ = (f"Fused {'3' if hasn else '2'}-D {'quaternion' if hasq else 'baseline'} "
                      f"update{' about R_u + TFI(B)' if based else ''} (:func:`_volume_kernel`).")
    return volume


_VOLUME: dict = {}
_VOLUME_LOCK = threading.Lock()


def _run_volume(xyz, s, out, c, order, tables, hasq: bool, base=None) -> None:
    """The one dispatcher of the fused volume stage: pick the kernel for the block's
    dimension (``len(order)``), ``hasq`` and ``base`` (tables ``(lineB, gB, hB)``) and
    run it on the 8 tables of :func:`_tables` / :meth:`GatherPlan._fill`."""
    hasn = len(order) == 3
    L, M, N = order if hasn else (order[0], order[1], 2)
    lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN = tables
    lineB, gB, hB = (lineD, gD, hD) if base is None else base
    bad = np.zeros(xyz.shape[1] * xyz.shape[2], dtype=np.bool_)
    parallel_for(_volume_kernel(hasn, hasq, base is not None), xyz.shape[2 if hasn else 1],
                 xyz, s, out, c[0], c[1], c[2], L, M, N, lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN,
                 lineB, gB, hB, bad)
    if hasq and bad.any():
        _fix_rows(xyz, s, out, np.flatnonzero(bad), c[0], c[1], c[2], L, M, N, lineD, lineQ,
                  gD, gQ, hD, hQ, fbM, fbN, hasn, base is not None, lineB, gB, hB)


@task_jit
def _fields2(lo, hi, s, outD, outQ, hasq, L, M, lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN):
    """2-D Soni TFI of the fields themselves (Δ and unit Q), for patches: rows ``lo <= j < hi``
    (a task kernel: :func:`tfi_quat._jit.parallel_for` runs the rows on the threads)."""
    ni = s.shape[0]
    for j in range(lo, hi):
        for i in range(ni):
            if L == 0:
                la, lb, ma, mb = j, 0, i, 0
            else:
                la, lb, ma, mb = i, 0, j, 0
            t = np.float64(s[i, j, 0, L])
            sm = np.float64(s[i, j, 0, M])
            dx, dy, dz = w_d(lineD, la, lb, t, gD, ma, mb, sm, hD, 0, 0, 0.0)
            outD[i, j, 0] = dx
            outD[i, j, 1] = dy
            outD[i, j, 2] = dz
            if hasq:
                qw, qx, qy, qz = w_q(lineQ, la, lb, t, gQ, ma, mb, sm, hQ, 0, 0, 0.0)
                n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
                if n < QNORM_MIN:
                    qw, qx, qy, qz = fallback_q(lineQ, la, lb, t, fbM, ma, mb, sm, fbN, 0, 0, 0.0,
                                                 False)
                    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
                outQ[i, j, 0] = qw / n
                outQ[i, j, 1] = qx / n
                outQ[i, j, 2] = qy / n
                outQ[i, j, 3] = qz / n


@jit
def _segment_q(q0, q1, s, out):
    """Slerp along a segment: ``out[m] = slerp(q0, q1, s[m])``, shortest arc, exact at s = 0 and 1."""
    d = q0[0] * q1[0] + q0[1] * q1[1] + q0[2] * q1[2] + q0[3] * q1[3]
    sg = -1.0 if d < 0.0 else 1.0
    b0 = sg * q1[0]
    b1 = sg * q1[1]
    b2 = sg * q1[2]
    b3 = sg * q1[3]
    w2, sw = slerp_angle(q0[0], q0[1], q0[2], q0[3], b0, b1, b2, b3)
    for m in range(s.shape[0]):
        t = np.float64(s[m])
        if t == 0.0:
            for c in range(4):
                out[m, c] = q0[c]
        elif t == 1.0:
            out[m, 0] = b0
            out[m, 1] = b1
            out[m, 2] = b2
            out[m, 3] = b3
        else:
            wa, wb = slerp_weights(t, w2, sw)
            w = wa * q0[0] + wb * b0
            x = wa * q0[1] + wb * b1
            y = wa * q0[2] + wb * b2
            z = wa * q0[3] + wb * b3
            n = math.sqrt(w * w + x * x + y * y + z * z)
            out[m, 0] = w / n
            out[m, 1] = x / n
            out[m, 2] = y / n
            out[m, 3] = z / n


# =================================================================== validation helpers
def _fail(msg: str):
    raise GridValueError(msg)


def check_xyz(xyz, name: str) -> np.ndarray:
    """Block coordinates as the kernels take them, else a :class:`GridValueError` naming ``name``:
    a float64 Fortran-ordered ``(ni, nj, nk, 3)`` array (``Block.xyz``); returned as is."""
    if not isinstance(xyz, np.ndarray):
        _fail(f"{name}: expected a numpy array of shape (ni, nj, nk, 3), got {type(xyz).__name__}")
    if xyz.ndim != 4 or xyz.shape[-1] != 3 or min(xyz.shape[:3]) < 1:
        _fail(f"{name}: expected shape (ni, nj, nk, 3), got {xyz.shape}")
    if xyz.dtype != np.float64:
        _fail(f"{name}: expected dtype float64, got {xyz.dtype}")
    if not xyz.flags.f_contiguous:
        _fail(f"{name}: expected a Fortran-ordered (i fastest) array, as Block.xyz is")
    return xyz


def _check_s(s, dims, name: str = "s") -> np.ndarray:
    if not isinstance(s, np.ndarray):
        _fail(f"{name}: expected a numpy array of shape {tuple(dims) + (3,)}, got {type(s).__name__}")
    if s.shape != tuple(dims) + (3,):
        _fail(f"{name}: expected shape {tuple(dims) + (3,)} (the block's arclength parameters), "
              f"got {s.shape}")
    if s.dtype != S_DTYPE:
        _fail(f"{name}: expected dtype float64 (as arclength() returns), got {s.dtype}")
    if not s.flags.f_contiguous:
        _fail(f"{name}: expected a Fortran-ordered array, as arclength() returns")
    return s


def _check_field(a, shape, ncomp: int, name: str, copy: bool = True) -> np.ndarray:
    """A face/side/patch field of the expected shape, float64, finite (unit if ncomp == 4).

    Returns an F-ordered copy, or with ``copy=False`` the input itself when it
    already is float64 (the fused drivers copy once, into their tables).
    """
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise GridValueError(f"{name}: cannot be read as an array of floats ({exc})") from None
    want = tuple(shape) + (ncomp,)
    if arr.shape != want:
        _fail(f"{name}: expected shape {want}, got {arr.shape}")
    if ncomp == 4:
        n2 = arr[..., 0] * arr[..., 0] + arr[..., 1] * arr[..., 1] + \
            arr[..., 2] * arr[..., 2] + arr[..., 3] * arr[..., 3]
        bad = float(np.max(np.abs(n2 - 1.0), initial=0.0))
        if not bad <= 2e-6:       # also catches NaN and inf
            if not np.all(np.isfinite(arr)):
                _fail(f"{name}: holds non-finite values")
            _fail(f"{name}: quaternions must be unit (max | |q|^2 - 1 | = {bad:.3g})")
    elif not np.isfinite(np.sum(arr)) and not np.all(np.isfinite(arr)):
        _fail(f"{name}: holds non-finite values")
    return np.array(arr, order="F", copy=True) if copy else arr


def _check_order(order, ndim: int, name: str = "order") -> tuple:
    try:
        o = tuple(operator.index(v) for v in order)
    except TypeError:
        raise GridValueError(f"{name}: expected a permutation of {tuple(range(ndim))}, "
                             f"got {order!r}") from None
    if sorted(o) != list(range(ndim)):
        _fail(f"{name}: expected a permutation of {tuple(range(ndim))}, got {order!r}")
    return o


def _check_centre(centre) -> np.ndarray:
    c = np.asarray(centre, dtype=np.float64)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        _fail(f"centre: expected 3 finite numbers, got {centre!r}")
    return c


def _check_out(out, dims) -> np.ndarray:
    if out is None:
        return np.empty(tuple(dims) + (3,), dtype=np.float64, order="F")
    if not isinstance(out, np.ndarray) or out.shape != tuple(dims) + (3,) or \
            out.dtype != np.float64 or not out.flags.f_contiguous or not out.flags.writeable:
        _fail(f"out: expected a writeable float64 Fortran-ordered array of shape "
              f"{tuple(dims) + (3,)}, got {getattr(out, 'shape', type(out).__name__)} "
              f"{getattr(out, 'dtype', '')}")
    return out


def _face_dims(dims, d):
    return tuple(n for e, n in enumerate(dims) if e != d)


def _faces(face_fields, dims, ncomp: int, name: str, nfaces: int = 6) -> tuple:
    if face_fields is None or isinstance(face_fields, np.ndarray) or len(face_fields) != nfaces:
        _fail(f"{name}: expected a sequence of {nfaces} face arrays (imin, imax, jmin, jmax"
              f"{', kmin, kmax' if nfaces == 6 else ''})")
    return tuple(_check_field(face_fields[f], _face_dims(dims, f // 2), ncomp,
                              f"{name}[{f}] ({FACES[f]})", copy=False) for f in range(nfaces))


def _check_edges(fd, fq, dims, name_d: str, name_q: str):
    """Faces must agree where they meet (Δ to 1e-9 relative, Q to 1e-9 up to sign)."""
    nd = len(dims)
    for d1 in range(nd):
        for d2 in range(d1 + 1, nd):
            for s1 in range(2):
                for s2 in range(2):
                    f1, f2 = 2 * d1 + s1, 2 * d2 + s2
                    # face f1 (normal d1) restricted to index_d2 = end; its axes skip d1
                    ax1 = [e for e in range(nd) if e != d1].index(d2)
                    ax2 = [e for e in range(nd) if e != d2].index(d1)
                    i1 = 0 if s2 == 0 else dims[d2] - 1
                    i2 = 0 if s1 == 0 else dims[d1] - 1
                    for arrs, nm, isq in ((fd, name_d, False), (fq, name_q, True)):
                        if arrs is None:
                            continue
                        e1 = arrs[f1][(slice(None),) * ax1 + (i1,)]
                        e2 = arrs[f2][(slice(None),) * ax2 + (i2,)]
                        if isq:
                            dot = np.einsum("...c,...c->...", e1, e2)
                            e2 = e2 * np.where(dot < 0.0, -1.0, 1.0)[..., None]
                        scale = 1.0 if isq else max(1.0, float(np.max(np.abs(e1), initial=0.0)))
                        err = float(np.max(np.abs(e1 - e2), initial=0.0))
                        if err > 1e-9 * scale:
                            _fail(f"{nm}: faces {FACES[f1]} and {FACES[f2]} disagree on their "
                                  f"common edge (max difference {err:.3g})")


# =================================================================== public API
def arclength(xyz, *, rtol: float = ZERO_LENGTH_RTOL) -> np.ndarray:
    """Normalised cumulative arclength along every grid line of a block.

    Parameters
    ----------
    xyz : ndarray, shape (ni, nj, nk, 3), float64, Fortran order
        Block coordinates (``Block.xyz``), the **undeformed** grid.
    rtol : float
        A line shorter than ``rtol`` times its end points' largest coordinate
        magnitude counts as zero-length.

    Returns
    -------
    s : ndarray, shape (ni, nj, nk, 3), float64 (:data:`S_DTYPE`), Fortran order
        ``s[..., d]`` is the arclength from the low face along the line in
        index direction ``d``, divided by the line's length: exactly 0 on the
        low face and exactly 1 on the high face, non-decreasing; ``index /
        (n - 1)`` on a zero-length line (collapsed edges, poles); 0 where
        ``n == 1``.

    Raises
    ------
    GridValueError
        Wrong shape, dtype or memory order of ``xyz``.
    """
    check_xyz(xyz, "xyz")
    # the one arclength kernel family: the wall-layer arclength with no layer (blending
    # imports this module, hence the import here); a run compiles it once for both
    from .blending import wall_layer_arclength
    return wall_layer_arclength(xyz, (), ndim=0, rtol=rtol)


def arclength_curve(r) -> np.ndarray:
    """Normalised cumulative arclength of a curve (a segment).

    Parameters
    ----------
    r : array_like, shape (n, 3), float
        Points along the curve.

    Returns
    -------
    s : ndarray, shape (n,), float64
        0 at the first point, exactly 1 at the last, index-uniform if the
        curve has zero length, 0 if ``n == 1``.
    """
    if np.ndim(r) != 2:
        _fail(f"r: expected shape (n, 3), got {np.shape(r)}")
    arr = _check_field(r, np.shape(r)[:1], 3, "r")
    return arclength(np.asfortranarray(arr[:, None, None, :]))[:, 0, 0, 0].copy()


def arclength_surface(r) -> np.ndarray:
    """Arclength parameters of a surface patch.

    Parameters
    ----------
    r : array_like, shape (na, nb, 3), float
        Patch points (e.g. ``Block.face(f)``).

    Returns
    -------
    s : ndarray, shape (na, nb, 2), float64, Fortran order
        ``s[..., 0]`` along ``a`` and ``s[..., 1]`` along ``b``, as in
        :func:`arclength`.
    """
    if np.ndim(r) != 3:
        _fail(f"r: expected shape (na, nb, 3), got {np.shape(r)}")
    arr = _check_field(r, np.shape(r)[:2], 3, "r")
    return np.asfortranarray(arclength(np.asfortranarray(arr[:, :, None, :]))[:, :, 0, :2])


def face_params(s) -> tuple:
    """The block's arclength parameters on its six faces, for ``deform_block(..., face_s=...)``.

    Reading them out of ``s`` touches one cache line per point on the faces
    normal to i; a caller that deforms the same block many times (the
    Deformer) computes them once here and passes them on every step.

    Parameters
    ----------
    s : ndarray, shape (ni, nj, nk, 3), float64, Fortran order
        Arclength parameters (:func:`arclength`).

    Returns
    -------
    face_s : tuple of 6 ndarray
        Face ``f`` (imin, imax, jmin, jmax, kmin, kmax) of shape
        ``Block.face(f).shape[:2] + (3,)``, float64, Fortran order (copies).
    """
    if not isinstance(s, np.ndarray) or s.ndim != 4:
        _fail(f"s: expected an array of shape (ni, nj, nk, 3), got {getattr(s, 'shape', type(s))}")
    _check_s(s, s.shape[:3])
    out = []
    for f in range(6):
        idx = [slice(None)] * 3
        idx[f // 2] = s.shape[f // 2] - 1 if f % 2 else 0
        out.append(np.array(s[tuple(idx)], order="F"))
    return tuple(out)


def _check_face_s(face_s, s, dims, nfaces: int) -> tuple:
    if face_s is None:
        return face_params(s)
    if isinstance(face_s, np.ndarray) or len(face_s) not in (nfaces, 6):
        _fail(f"face_s: expected the {nfaces} face arrays of face_params(s)")
    out = []
    for f in range(nfaces):
        want = _face_dims(dims, f // 2) + (3,)
        a = face_s[f]
        if not isinstance(a, np.ndarray) or a.dtype != np.float64 or a.shape != want:
            _fail(f"face_s[{f}] ({FACES[f]}): expected a float64 array of shape {want} "
                  f"(from face_params(s)), got {getattr(a, 'shape', type(a).__name__)}")
        out.append(a)
    return tuple(out)


def lead_order(prescribed_counts: Sequence[int]) -> tuple:
    """Direction order for TFI: lead with the direction whose end faces carry most prescribed points.

    Parameters
    ----------
    prescribed_counts : sequence of 6 (3-D) or 4 (2-D) non-negative ints
        Number of prescribed (wall or fixed) points on faces imin, imax,
        jmin, jmax[, kmin, kmax].

    Returns
    -------
    order : tuple of int
        ``(L, M, N)`` (or ``(L, M)``): directions sorted by the summed counts
        of their two end faces, largest first; ties go to the lower
        direction index.
    """
    try:
        c = [operator.index(v) for v in prescribed_counts]
    except TypeError:
        raise GridValueError(f"prescribed_counts: expected 4 or 6 integers, got "
                             f"{prescribed_counts!r}") from None
    if len(c) not in (4, 6) or min(c) < 0:
        _fail(f"prescribed_counts: expected 4 or 6 non-negative integers, got {prescribed_counts!r}")
    nd = len(c) // 2
    return tuple(sorted(range(nd), key=lambda d: (-(c[2 * d] + c[2 * d + 1]), d)))


def interp_segment(delta0, q0, delta1, q1, s):
    """1-D interpolation of (Δ, Q) along a segment.

    Parameters
    ----------
    delta0, delta1 : array_like, shape (3,)
        Translations at the two ends.
    q0, q1 : array_like, shape (4,), or None
        Unit quaternions ``(w, x, y, z)`` at the ends; both None for the
        classic baseline (``method="tfi"``).
    s : array_like, shape (n,)
        Parameters in [0, 1] (arclength of the undeformed segment).

    Returns
    -------
    delta : ndarray, shape (n, 3), float64
        ``(1 - s) delta0 + s delta1`` (exact at s = 0 and 1).
    q : ndarray, shape (n, 4), float64, or None
        Slerp along the shortest arc: ``q0`` exactly at s = 0 and ``±q1``
        (the sign continuing the arc) exactly at s = 1; unit to round-off.
    """
    d0 = _check_field(delta0, (), 3, "delta0")
    d1 = _check_field(delta1, (), 3, "delta1")
    t = np.asarray(s, dtype=np.float64)
    if t.ndim != 1 or not np.all(np.isfinite(t)) or np.any(t < 0.0) or np.any(t > 1.0):
        _fail(f"s: expected a 1-D array of parameters in [0, 1], got shape {t.shape}")
    tt = t[:, None]
    delta = (1.0 - tt) * d0 + tt * d1
    if (q0 is None) != (q1 is None):
        _fail("q0, q1: give both quaternions or neither")
    if q0 is None:
        return delta, None
    a = _check_field(q0, (), 4, "q0")
    b = _check_field(q1, (), 4, "q1")
    q = np.empty((t.shape[0], 4))
    _segment_q(a, b, np.ascontiguousarray(t), q)
    return delta, q


def _sides_as_faces(sides, dims, ncomp: int, name: str) -> tuple:
    """2-D sides imin, imax (nj, c), jmin, jmax (ni, c) -> (n, 1, c) face arrays."""
    if sides is None or isinstance(sides, np.ndarray) or len(sides) != 4:
        _fail(f"{name}: expected a sequence of 4 side arrays (imin, imax, jmin, jmax)")
    ni, nj = dims[0], dims[1]
    out = []
    for f in range(4):
        n = nj if f < 2 else ni
        a = _check_field(sides[f], (n,), ncomp, f"{name}[{f}] ({FACES[f]})")
        out.append(np.asfortranarray(a[:, None, :]))
    return tuple(out)


def patch_params(s) -> tuple:
    """Precompute what :func:`tfi_patch_fast` needs from a patch's ``s`` (na, nb, 2):
    the parameters in block layout ``(na, nb, 1, 3)`` and their side tables."""
    sa = np.asarray(s, dtype=np.float64)
    if sa.ndim != 3 or sa.shape[-1] != 2:
        _fail(f"s: expected a float array of shape (na, nb, 2), got {sa.shape}")
    s4 = np.zeros(sa.shape[:2] + (1, 3), order="F")
    s4[:, :, 0, :2] = sa
    return s4, face_params(s4)


def tfi_patch_fast(delta, q, params, lead: int = 0) -> None:
    """2-D Soni TFI of (Δ, Q) on a patch, in place: fill the interior from the four sides.

    ``params`` is :func:`patch_params` of the patch's arclength parameters
    (from the **undeformed** surface, :func:`arclength_surface`), computed
    once; ``delta`` (na, nb, 3) and ``q`` (na, nb, 4) of unit quaternions, or
    None for the baseline, are filled in place from their four sides
    ``a = 0``, ``a = na - 1``, ``b = 0``, ``b = nb - 1`` (consistent at the
    corners; left as they are).  ``lead`` 0: slerp between the sides a = 0
    and a = na - 1; 1: between b = 0 and b = nb - 1.  The numpy reference it
    is tested against is ``tests/oracles.py``.
    """
    s4, fs = params
    na, nb = s4.shape[:2]
    if delta.shape != (na, nb, 3) or (q is not None and q.shape != (na, nb, 4)):
        _fail(f"delta/q: expected shapes {(na, nb, 3)} / {(na, nb, 4)}, got {delta.shape} / "
              f"{None if q is None else q.shape}")
    if lead not in (0, 1):
        _fail(f"lead: expected 0 or 1, got {lead!r}")
    if na <= 2 or nb <= 2:
        return
    dims = (na, nb, 1)
    fd = _sides_as_faces([delta[0], delta[-1], delta[:, 0], delta[:, -1]], dims, 3, "delta")
    fq = None
    if q is not None:
        fq = _sides_as_faces([q[0], q[-1], q[:, 0], q[:, -1]], dims, 4, "q")
    L, M = lead, 1 - lead
    lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN = _tables(dims, (L, M, 2), fd, fq, fs[:4], False)
    outD = np.empty((na, nb, 3), order="F")
    outQ = np.empty((na, nb, 4), order="F") if q is not None else np.empty((2, 2, 4), order="F")
    parallel_for(_fields2, nb, s4, outD, outQ, q is not None, L, M, lineD, lineQ, gD, gQ, hD,
                 hQ, fbM, fbN)
    delta[1:-1, 1:-1] = outD[1:-1, 1:-1]
    if q is not None:
        q[1:-1, 1:-1] = outQ[1:-1, 1:-1]


# ------------------------------------------------------------------ fused drivers
def _pair(faces, d, ncomp: int) -> np.ndarray:
    """Stack the low and high faces normal to ``d``: (na, nb, ncomp, 2), F order."""
    f0 = faces[2 * d]
    out = np.empty(f0.shape + (2,), order="F")
    out[..., 0] = f0
    out[..., 1] = faces[2 * d + 1]
    return out


def _padded(dims, d):
    """Shape of a table indexed like the faces normal to ``d``, first axis padded to >= 2:
    a (1, 1, c) table would be typed C-contiguous and compile another specialisation of
    every kernel."""
    na, nb = _face_dims(dims, d)
    return max(2, na), nb


def _work_tables(dims, o, hasn, hasq):
    """Allocate the tables :func:`_prep` fills: ``lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN``.

    Dummy tables are (2, 2, ·) zeros, so that their numba type (F layout)
    never changes, which keeps one compiled specialisation per kernel; the
    volume kernels read the zeros of ``hD``/``hQ`` in 2-D.
    """
    L, M, N = o
    sh = functools.partial(_padded, dims)
    dummy = lambda c: np.zeros((2, 2, c), order="F")  # noqa: E731
    lineD = np.empty(sh(L) + (6,), order="F")
    gD = np.empty(sh(M) + (6,), order="F")
    hD = np.empty(sh(N) + (6,), order="F") if hasn else dummy(6)
    if hasq:
        lineQ = np.empty(sh(L) + (10,), order="F")
        gQ = np.empty(sh(M) + (8,), order="F")
        fbM = np.empty(sh(M) + (16,), order="F")
        hQ = np.empty(sh(N) + (8,), order="F") if hasn else dummy(8)
        fbN = np.empty(sh(N) + (16,), order="F") if hasn else dummy(16)
    else:
        lineQ, gQ, hQ, fbM, fbN = dummy(10), dummy(8), dummy(8), dummy(16), dummy(16)
    return lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN


def _tables(dims, o, fd, fq, fs, hasn):
    """Allocate and fill the O(surface) tables of the fused kernels (see :func:`_work_tables`)."""
    L, M, N = o
    hasq = fq is not None
    lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN = _work_tables(dims, o, hasn, hasq)
    FL, FM = _pair(fd, L, 3), _pair(fd, M, 3)
    FN = _pair(fd, N, 3) if hasn else np.zeros((2, 2, 3, 2), order="F")
    if hasq:
        QL, QM = _pair(fq, L, 4), _pair(fq, M, 4)
        QN = _pair(fq, N, 4) if hasn else np.zeros((2, 2, 4, 2), order="F")
        q0 = np.array(QL[..., 0], order="F")
        _coherent(q0)
        QL[..., 0] = q0
    else:
        QL = QM = QN = np.zeros((2, 2, 4, 2), order="F")
    SM = _pair(fs, M, 3)
    SN = _pair(fs, N, 3) if hasn else np.zeros((2, 2, 3, 2), order="F")
    _prep(SM, SN, dims[M], dims[N], L, M, N, hasn, FL, FM, FN, QL, QM, QN, hasq,
          lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN)
    return lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN


def deform_block(xyz_u, s, face_delta, face_q, centre, order, out=None, *,
                 face_s=None, check: bool = True) -> np.ndarray:
    """Fused volume stage of one 3-D block: ``R_d = c + Δ(x) + rot(Q(x), R_u - c)``.

    (Δ, Q) is the Soni TFI of the six faces' values (docs/method.md §3.4), evaluated
    point by point inside the update: no full-size Δ or Q array is formed.
    Parallel over k-planes; i innermost.

    Parameters
    ----------
    xyz_u : ndarray, shape (ni, nj, nk, 3), float64, Fortran order
        Undeformed block coordinates.
    s : ndarray, shape (ni, nj, nk, 3), float64, Fortran order
        Its arclength parameters (:func:`arclength`).
    face_delta : sequence of 6 array_like
        Δ on faces imin, imax, jmin, jmax, kmin, kmax, face ``f`` of shape
        ``Block.face(f).shape[:2] + (3,)``; consistent on shared edges.
    face_q : sequence of 6 array_like (na, nb, 4) of unit quaternions, or None
        Q on the same faces (consistent on edges up to sign).  None: the
        classic baseline, Q ≡ 1 and Δ the displacement, ``R_d = R_u + Δ``.
    centre : array_like, shape (3,)
        Rotation centre ``c``.
    order : sequence of 3 int
        ``(L, M, N)``, a permutation of (0, 1, 2) (:func:`lead_order`).
    out : ndarray, shape (ni, nj, nk, 3), float64, Fortran order, optional
        Receives the result; may be ``xyz_u`` itself (in place).
    face_s : tuple of 6 ndarray, optional
        ``face_params(s)``, computed once by a caller that deforms the block
        repeatedly (saves ~20 ms per call on a 10 M-point block when a face
        normal to i is an M or N face).  Must be the faces of ``s``.
    check : bool
        Validate every argument (default).  ``False`` is for callers that
        build the arguments themselves and call every step (the Deformer):
        float64 arrays of the documented shapes and layouts, faces that agree
        on their edges, ``out`` and ``face_s`` given; nothing is checked.

    Returns
    -------
    xyz_d : ndarray, shape (ni, nj, nk, 3), float64, Fortran order
        ``out`` if given.  Zero Δ with identity Q returns ``xyz_u`` bit for bit.

    Raises
    ------
    GridValueError
        A wrong shape, dtype or memory order (the message names the
        argument), non-finite or non-unit face values, or faces that disagree
        on a shared edge.
    """
    if check:
        check_xyz(xyz_u, "xyz_u")
        dims = xyz_u.shape[:3]
        _check_s(s, dims)
        o = _check_order(order, 3)
        fd = _faces(face_delta, dims, 3, "face_delta")
        fq = None if face_q is None else _faces(face_q, dims, 4, "face_q")
        _check_edges(fd, fq, dims, "face_delta", "face_q")
        c = _check_centre(centre)
        out = _check_out(out, dims)
        fs = _check_face_s(face_s, s, dims, 6)
    else:
        dims = xyz_u.shape[:3]
        o, fd, fq, c, fs = tuple(order), face_delta, face_q, np.asarray(centre, dtype=np.float64), face_s
    _run_volume(xyz_u, s, out, c, o, _tables(dims, o, fd, fq, fs, True), fq is not None)
    return out


def deform_block_2d(xyz_u, s, side_delta, side_q, centre, order, out=None, *,
                    face_s=None, check: bool = True) -> np.ndarray:
    """Fused volume stage of one 2-D block (``nk == 1``).

    Parameters
    ----------
    xyz_u : ndarray, shape (ni, nj, 1, 3), float64, Fortran order
        Undeformed block coordinates.
    s : ndarray, shape (ni, nj, 1, 3), float64, Fortran order
        Its arclength parameters (:func:`arclength`).
    side_delta : sequence of 4 array_like
        Δ on the sides imin, imax ``(nj, 3)`` and jmin, jmax ``(ni, 3)``;
        consistent at the corners.
    side_q : sequence of 4 array_like (n, 4) of unit quaternions, or None
        Q on the same sides; None for the baseline (``R_d = R_u + Δ``).
    centre : array_like, shape (3,)
        Rotation centre.
    order : sequence of 2 int
        ``(L, M)``, a permutation of (0, 1).
    out : ndarray, shape (ni, nj, 1, 3), float64, Fortran order, optional
        Receives the result; may be ``xyz_u``.
    face_s : tuple of 4 (or 6) ndarray, optional
        ``face_params(s)`` (its first four faces are the sides), computed once.
    check : bool
        As for :func:`deform_block` (``False``: sides as ``(n, 1, c)`` arrays,
        ``out`` and ``face_s`` given, nothing checked).

    Returns
    -------
    xyz_d : ndarray, shape (ni, nj, 1, 3), float64, Fortran order
    """
    check_xyz(xyz_u, "xyz_u")
    dims = xyz_u.shape[:3]
    if check:
        if dims[2] != 1:
            _fail(f"xyz_u: a 2-D block needs nk == 1, got shape {xyz_u.shape}")
        _check_s(s, dims)
        o = _check_order(order, 2)
        fd = _sides_as_faces(side_delta, dims, 3, "side_delta")
        fq = None if side_q is None else _sides_as_faces(side_q, dims, 4, "side_q")
        _check_edges(fd, fq, dims[:2], "side_delta", "side_q")
        c = _check_centre(centre)
        out = _check_out(out, dims)
        fs = _check_face_s(face_s, s, dims, 4)
    else:
        o, fd, fq, c, fs = tuple(order), side_delta, side_q, np.asarray(centre, dtype=np.float64), face_s
    L, M = o
    _run_volume(xyz_u, s, out, c, (L, M), _tables(dims, (L, M, 2), fd, fq, fs, False), fq is not None)
    return out


# ------------------------------------------------------------------ faces from global arrays
class GatherPlan:
    """What :func:`deform_block_gathered` needs of one block, set up once by :func:`gather_plan`.

    Holds, per direction, the global rows of the two faces normal to it as
    one ``(na, nb, 2)`` index array, the arclength parameters of the M and N
    faces stacked the same way, and (``keep_tables=True``) the O(surface)
    tables of the fused kernels, allocated on first use and overwritten on
    every call.  Treat it as opaque; its public attributes are read-only
    descriptions.

    Attributes
    ----------
    dims : tuple of 3 int
        The block's point counts ``(ni, nj, nk)``.
    order : tuple of int
        ``(L, M, N)`` or ``(L, M)``.
    n_index : int
        One more than the largest global row the faces use: the global arrays
        must have at least this many rows.
    keep_tables : bool
        Whether the tables are kept between calls.

    Notes
    -----
    Calls that share a plan run one at a time (a lock: with ``keep_tables``
    they share the tables), so sharing a plan between threads is safe but
    serialises them; make one plan per thread to deform one block from
    several threads at once.  Kept tables take ~180 bytes per face point
    with quaternions, ~70 for the baseline only (:attr:`nbytes`): 51 MB for
    a 216³ block (0.21 of its coordinates), 0.7 of the coordinates of a 64³
    block, 1.9 of a 24³ one.
    """

    __slots__ = ("dims", "order", "n_index", "keep_tables", "_index", "_SM", "_SN", "_hasn",
                 "_tab", "_lock")

    def __init__(self, dims, order, n_index, keep_tables, index, SM, SN):
        self.dims = tuple(dims)
        self.order = tuple(order)
        self.n_index = int(n_index)
        self.keep_tables = bool(keep_tables)
        self._index = index
        self._SM, self._SN = SM, SN
        self._hasn = len(order) == 3
        self._tab = {}
        self._lock = threading.Lock()

    @property
    def ndim(self) -> int:
        """2 or 3."""
        return len(self.order)

    @property
    def nbytes(self) -> int:
        """Bytes held by the plan now (indices, face parameters, kept tables)."""
        arrs = {id(a): a for a in list(self._index) + [self._SM, self._SN]}
        for t in self._tab.values():
            arrs.update((id(a), a) for a in t)
        return int(sum(a.nbytes for a in arrs.values()))

    def __repr__(self) -> str:
        return (f"GatherPlan(dims={self.dims}, order={self.order}, n_index={self.n_index}, "
                f"keep_tables={self.keep_tables}, nbytes={self.nbytes})")

    def _o3(self):
        return self.order if self._hasn else self.order + (2,)

    def _new_tables(self, hasq: bool) -> tuple:
        """New tables: ``(FL, FM, FN, lineD, gD, hD)`` and ``(QL, QM, QN, lineQ, gQ, hQ, fbM,
        fbN)`` (dummies for the baseline), the pair tables and :func:`_work_tables`."""
        L, M, N = o = self._o3()
        dims, hasn = self.dims, self._hasn
        pair = lambda d, c: np.empty(_face_dims(dims, d) + (c, 2), order="F")  # noqa: E731
        dummy = lambda c: np.zeros((2, 2, c, 2), order="F")  # noqa: E731
        lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN = _work_tables(dims, o, hasn, hasq)
        tab_d = (pair(L, 3), pair(M, 3), pair(N, 3) if hasn else dummy(3), lineD, gD, hD)
        if hasq:
            Q = (pair(L, 4), pair(M, 4), pair(N, 4) if hasn else dummy(4))
        else:
            Q = (dummy(4),) * 3
        return tab_d, Q + (lineQ, gQ, hQ, fbM, fbN)

    def _tables(self, hasq: bool) -> tuple:
        """The tables of a call: kept ones (Δ tables shared by both kinds of call) or new."""
        if not self.keep_tables:
            return self._new_tables(hasq)
        tab_d, tab_q = self._tab.get("d"), self._tab.get(hasq)
        if tab_q is None:
            new_d, tab_q = self._new_tables(hasq)       # new_d: never touched if dropped
            self._tab[hasq] = tab_q
            if tab_d is None:
                tab_d = self._tab["d"] = new_d
        return tab_d, tab_q

    def _fill(self, gd, gq) -> tuple:
        """Gather the faces' values and build the tables; returns the 8 tables of the
        volume kernels (``lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN``)."""
        hasq = gq is not None
        (FL, FM, FN, lineD, gD, hD), (QL, QM, QN, lineQ, gQ, hQ, fbM, fbN) = self._tables(hasq)
        L, M, N = self._o3()
        iL, iM, iN = self._index
        _gather_tables(gd, gq if hasq else _NO_Q, hasq, self._hasn, iL, iM, iN, FL, FM, FN, QL, QM,
                       QN)
        _prep(self._SM, self._SN, self.dims[M], self.dims[N], L, M, N, self._hasn,
              FL, FM, FN, QL, QM, QN, hasq, lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN)
        return lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN

    @property
    def face_rows(self) -> tuple:
        """The global rows of the faces normal to L, M, N: three ``(>= na, nb, 2)`` int64 arrays
        (last index: low, high face; a 2-D plan's third is a dummy).  Read-only use."""
        return self._index

    @property
    def face_pairs(self) -> tuple:
        """The arclength parameters on the M and N faces, ``(SM, SN)``, each ``(na, nb, 3, 2)``
        (a 2-D plan's ``SN`` is a dummy).  Read-only use."""
        return self._SM, self._SN

    def fill_tables(self, g_delta, g_q) -> tuple:
        """The 8 tables the volume kernels read (``lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN``;
        layout in the module docstring) for the global arrays ``g_delta`` (G, 3) and ``g_q``
        (G, 4) or None, built as :func:`deform_block_gathered` builds them.  With
        ``keep_tables`` they are the plan's own, overwritten by its next call: for a caller
        that uses them at once (the derivatives, :mod:`tfi_quat.dtfi`)."""
        gd = _check_global(g_delta, 3, self.n_index, "g_delta")
        gq = None if g_q is None else _check_global(g_q, 4, self.n_index, "g_q")
        with self._lock:
            return self._fill(gd, gq)

    def base_tables(self, g_base) -> tuple:
        """The tables of the baseline TFI of a fixed field ``g_base`` (G, 3) over this
        block's faces, for ``deform_block_gathered(..., base=...)``: a copy (O(surface)),
        kept by the caller."""
        gb = _check_global(g_base, 3, self.n_index, "g_base")
        with self._lock:
            lineD, _, gD, _, hD, _, _, _ = self._fill(gb, None)
            return lineD.copy(order="F"), gD.copy(order="F"), hD.copy(order="F")


_NO_Q = np.zeros((1, 4))            # stands for g_q in the baseline (never read)


def _check_face_index(face_index, dims, nd: int) -> tuple:
    """Face index arrays as int64 ``(na, nb)``, non-negative, agreeing on shared edges."""
    nf = 2 * nd
    if face_index is None or isinstance(face_index, np.ndarray) or len(face_index) != nf:
        _fail(f"face_index: expected a sequence of {nf} integer arrays (imin, imax, jmin, jmax"
              f"{', kmin, kmax' if nd == 3 else ''})")
    out = []
    for f in range(nf):
        want = _face_dims(dims, f // 2)
        a = np.asarray(face_index[f])
        if nd == 2 and a.shape == want[:1]:
            a = a[:, None]
        if a.shape != want:
            _fail(f"face_index[{f}] ({FACES[f]}): expected shape {want}"
                  f"{f' or {want[:1]}' if nd == 2 else ''}, got {a.shape}")
        if a.dtype.kind not in "iu":
            _fail(f"face_index[{f}] ({FACES[f]}): expected integers, got dtype {a.dtype}")
        if a.size and int(a.min()) < 0:
            _fail(f"face_index[{f}] ({FACES[f]}): negative row {int(a.min())}")
        out.append(a.astype(np.int64))
    for d1 in range(nd):
        for d2 in range(d1 + 1, nd):
            ax1 = [e for e in range(nd) if e != d1].index(d2)
            ax2 = [e for e in range(nd) if e != d2].index(d1)
            for s1 in range(2):
                for s2 in range(2):
                    f1, f2 = 2 * d1 + s1, 2 * d2 + s2
                    e1 = out[f1][(slice(None),) * ax1 + (0 if s2 == 0 else dims[d2] - 1,)]
                    e2 = out[f2][(slice(None),) * ax2 + (0 if s1 == 0 else dims[d1] - 1,)]
                    if not np.array_equal(e1, e2):
                        _fail(f"face_index: faces {FACES[f1]} and {FACES[f2]} name different "
                              f"rows on their common edge")
    return tuple(out)


def _index_pair(faces, dims, d) -> np.ndarray:
    """The rows of the low and high faces normal to ``d``: (≥ na, nb, 2) int64, F order."""
    na, nb = _face_dims(dims, d)
    idx = np.zeros(_padded(dims, d) + (2,), dtype=np.int64, order="F")
    idx[:na, :, 0] = faces[2 * d]
    idx[:na, :, 1] = faces[2 * d + 1]
    return idx


def gather_plan(face_index, s, order, *, face_s=None, keep_tables: bool = True) -> GatherPlan:
    """Set up :func:`deform_block_gathered` for one block whose face values live in global arrays.

    Done once per block (and direction order); the plan is then passed on
    every call.

    Parameters
    ----------
    face_index : sequence of 6 (3-D) or 4 (2-D) array_like of int
        For each face imin, imax, jmin, jmax[, kmin, kmax], the row of each
        of its points in the global arrays: face ``f`` of shape
        ``Block.face(f).shape[:2]`` ``(na, nb)``; in 2-D the sides imin, imax
        ``(nj, 1)`` or ``(nj,)`` and jmin, jmax ``(ni, 1)`` or ``(ni,)``.
        Faces must name the same rows where they meet (then the values agree
        on every edge at every call, by construction).
    s : ndarray, shape (ni, nj, nk, 3), float64, Fortran order
        The block's arclength parameters (:func:`arclength`): gives the block
        size, and ``face_params(s)`` when ``face_s`` is not given.  The
        parameters on the faces are copied into the plan: make a new plan if
        ``s`` changes.
    order : sequence of 3 (or 2) int
        ``(L, M, N)`` (``(L, M)`` for a 2-D block, ``nk == 1``), a permutation
        (:func:`lead_order`).
    face_s : tuple of 6 (or 4) ndarray, optional
        ``face_params(s)``, if the caller already has it.
    keep_tables : bool
        Keep the O(surface) tables of the fused kernels in the plan between
        calls (default): saves allocating them and faulting their pages in
        on every call (~20 ms on a 216³ block when the heap has been
        churned), at ~180 bytes per face point held for the plan's lifetime
        (:attr:`GatherPlan.nbytes`).  ``False`` allocates them per call, as
        :func:`deform_block` does (for many small blocks, where the kept
        tables would outweigh the coordinates).

    Returns
    -------
    plan : GatherPlan

    Raises
    ------
    GridValueError
        Wrong shapes or dtypes (the message names the argument and face),
        negative rows, or faces that name different rows on a common edge.
    """
    if not isinstance(s, np.ndarray) or s.ndim != 4:
        _fail(f"s: expected an array of shape (ni, nj, nk, 3), got {getattr(s, 'shape', type(s))}")
    dims = s.shape[:3]
    _check_s(s, dims)
    nd = len(order) if hasattr(order, "__len__") else 0
    if nd not in (2, 3):
        _fail(f"order: expected (L, M, N) or (L, M), got {order!r}")
    o = _check_order(order, nd)
    if nd == 2 and dims[2] != 1:
        _fail(f"s: a 2-D order needs nk == 1, got shape {s.shape}")
    faces = _check_face_index(face_index, dims, nd)
    fs = _check_face_s(face_s, s, dims, 2 * nd)
    n_index = 1 + max(int(a.max(initial=-1)) for a in faces)
    hasn = nd == 3
    L, M, N = o if hasn else o + (2,)
    index = (_index_pair(faces, dims, L), _index_pair(faces, dims, M),
             _index_pair(faces, dims, N) if hasn else np.zeros((2, 2, 2), dtype=np.int64, order="F"))
    SM = _pair(fs, M, 3)
    SN = _pair(fs, N, 3) if hasn else np.zeros((2, 2, 3, 2), order="F")
    return GatherPlan(dims, o, n_index, keep_tables, index, SM, SN)


def _check_global(a, ncomp: int, n_index: int, name: str) -> np.ndarray:
    if not isinstance(a, np.ndarray) or a.ndim != 2 or a.shape[1] != ncomp or a.dtype != np.float64:
        _fail(f"{name}: expected a float64 array of shape (G, {ncomp}), got "
              f"{getattr(a, 'shape', type(a).__name__)} {getattr(a, 'dtype', '')}")
    if a.shape[0] < n_index:
        _fail(f"{name}: the plan's faces use rows up to {n_index - 1}, got only {a.shape[0]} rows")
    return a


def deform_block_gathered(xyz_u, s, g_delta, g_q, plan, centre, out=None, *,
                          base=None) -> np.ndarray:
    """:func:`deform_block` (or :func:`deform_block_2d`) with the face values read from global arrays.

    Gives bit for bit the result of ``deform_block(xyz_u, s, [g_delta[g] for
    g in face_index], [g_q[g] for g in face_index], centre, order, out,
    face_s=face_s)`` (``deform_block_2d`` for a 2-D plan), where
    ``face_index``, ``order`` and ``face_s`` are those the plan was made
    with, but gathers the faces inside the compiled set-up, straight into
    the tables, with no per-face copies.

    Only shapes and dtypes are checked (O(1)); the values are not: the
    quaternions must be unit and finite (what :func:`deform_block` would
    check).  Edge agreement holds by construction (:func:`gather_plan`).

    Parameters
    ----------
    xyz_u : ndarray, shape (ni, nj, nk, 3), float64, Fortran order
        Undeformed block coordinates (``nk == 1`` for a 2-D plan).
    s : ndarray, shape (ni, nj, nk, 3), float64, Fortran order
        Its arclength parameters, the array the plan was made with.
    g_delta : ndarray, shape (G, 3), float64
        Δ of every global point (``G >= plan.n_index``).
    g_q : ndarray, shape (G, 4), float64, or None
        Unit quaternions ``(w, x, y, z)`` of every global point; None for the
        baseline (Q ≡ 1, ``R_d = R_u + Δ``).
    plan : GatherPlan
        From :func:`gather_plan` for this block.
    centre : array_like, shape (3,)
        Rotation centre ``c``.
    out : ndarray, shape (ni, nj, nk, 3), float64, Fortran order, optional
        Receives the result; may be ``xyz_u`` itself (in place), but not with ``base``.
    base : tuple, optional
        :meth:`GatherPlan.base_tables` of a field ``B``: the update is made about
        the base point ``R_u + TFI(B)`` instead of ``R_u``, bit for bit as if that
        point (the baseline kernel's result with Δ = B) had been passed as
        ``xyz_u``, without storing it.  Quaternion calls only.

    Returns
    -------
    xyz_d : ndarray, shape (ni, nj, nk, 3), float64, Fortran order
        ``out`` if given.

    Raises
    ------
    GridValueError
        A wrong type, shape, dtype or memory order (the message names the
        argument), or global arrays with fewer rows than the plan uses.

    Examples
    --------
    >>> import numpy as np
    >>> from tfi_quat import tfi
    >>> u = np.linspace(0.0, 1.0, 4)
    >>> xyz = np.asfortranarray(np.stack(np.meshgrid(u, u, u, indexing="ij"), -1))
    >>> s = tfi.arclength(xyz)
    >>> ids = np.arange(64).reshape(4, 4, 4, order="F")     # every point is its own row
    >>> face_index = [ids[0], ids[-1], ids[:, 0], ids[:, -1], ids[:, :, 0], ids[:, :, -1]]
    >>> plan = tfi.gather_plan(face_index, s, (0, 1, 2))     # once per block
    >>> g_delta = np.zeros((64, 3))
    >>> g_delta[:, 2] = 0.1                                  # lift every face by 0.1
    >>> out = tfi.deform_block_gathered(xyz, s, g_delta, None, plan, np.zeros(3))
    >>> bool(np.allclose(out, xyz + [0.0, 0.0, 0.1]))
    True
    """
    if not isinstance(plan, GatherPlan):
        _fail(f"plan: expected a GatherPlan from gather_plan(), got {type(plan).__name__}")
    dims = plan.dims
    check_xyz(xyz_u, "xyz_u")
    if xyz_u.shape[:3] != dims:
        _fail(f"xyz_u: the plan is for a block of {dims} points, got shape {xyz_u.shape}")
    _check_s(s, dims)
    gd = _check_global(g_delta, 3, plan.n_index, "g_delta")
    gq = None if g_q is None else _check_global(g_q, 4, plan.n_index, "g_q")
    c = _check_centre(centre)
    out = _check_out(out, dims)
    if base is not None:
        if gq is None:
            _fail("base: only for quaternion calls (g_q given)")
        if out is xyz_u:
            _fail("base: the update cannot be made in place (out is xyz_u)")
        lineB, gB, hB = base
        if lineB.shape[:2] != _padded(dims, plan.order[0]) or lineB.shape[2] != 6:
            _fail(f"base: tables of another block (line table {lineB.shape})")
    with plan._lock:
        _run_volume(xyz_u, s, out, c, plan.order, plan._fill(gd, gq), gq is not None, base)
    return out
