"""Quaternion algebra: numba kernels on single quaternions, and array drivers.

Kernel contract
---------------
* A quaternion is a float64 array of 4 values, **scalar first** ``(w, x, y, z)``.
* Kernels act on one quaternion (or one vector): inputs first, the output
  array last; they write the output and return nothing (or a scalar), never
  allocate, never raise.  Output may alias an input unless stated.
* Rotations are unit quaternions; ``q`` and ``-q`` are the same rotation.
  The rotation of a vector ``v`` is ``q [0, v] q*``.
* The composition "first ``a``, then ``b``" is ``b ⊗ a`` (:func:`kmul` (b, a, out)).

* Scalar helpers (``_s`` suffix: :func:`mul_s`, :func:`log_s`,
  :func:`exp_s`, :func:`from_two_units_s`, :func:`from_two_vectors_s`)
  take and return tuples of floats; the array kernels are thin wrappers over
  them, and composite kernels (:func:`kblend`, and those of
  :mod:`tfi_quat.kernels` and :mod:`tfi_quat.boundary`) use them so that no
  scratch array is ever needed.  :func:`log_s` is the package's one
  quaternion log.

Conventions
-----------
* Rotation matrix ``R`` of ``q``: ``R @ v == rot(q, v)`` (active rotation).
* Rotation vector (:func:`klog`, :func:`kexp`): ``angle * axis``, the
  shortest one, ``|v| <= pi``.
* Axis-angle (:func:`kto_axis_angle`): unit axis and angle in ``[0, pi]``.

Array drivers (no leading ``k``) take arrays of any leading shape
``(..., 4)`` / ``(..., 3)`` / ``(..., 3, 3)``, broadcast against each other,
validate them (raising :class:`tfi_quat.errors.GridValueError` that names the
argument, also when leading shapes do not broadcast) and return new float64
arrays.  Each runs its kernel over the flattened arrays in a compiled loop
made by :func:`_many` (one template per number of inputs), through one
Python helper, :func:`_drive`.
"""

from __future__ import annotations

import math
import types

import numpy as np

from ._jit import jit
from .errors import GridValueError

__all__ = [
    # kernels
    "kmul", "kconj", "knormalize", "krotate", "kslerp", "kdot",
    "kfrom_axis_angle", "kto_axis_angle", "kfrom_matrix", "kto_matrix",
    "kfrom_two_vectors", "klog", "kexp", "kblend",
    # scalar helpers (building blocks of other kernels)
    "mul_s", "log_s", "exp_s", "from_two_units_s", "from_two_vectors_s",
    # drivers
    "multiply", "conjugate", "normalize", "rotate", "slerp",
    "from_axis_angle", "to_axis_angle", "from_matrix", "to_matrix",
    "from_two_vectors", "log", "exp", "blend",
]


# ------------------------------------------------------------------ kernels
@jit(inline="always")
def kdot(a, b):
    """4-D dot product of two quaternions."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]


@jit(inline="always")
def kmul(a, b, out):
    """``out = a ⊗ b`` (Hamilton product).  ``out`` may alias ``a`` or ``b``."""
    w = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3]
    x = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2]
    y = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1]
    z = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0]
    out[0] = w
    out[1] = x
    out[2] = y
    out[3] = z


@jit(inline="always")
def kconj(a, out):
    """``out = a*``."""
    out[0] = a[0]
    out[1] = -a[1]
    out[2] = -a[2]
    out[3] = -a[3]


@jit(inline="always")
def knormalize(a, out):
    """``out = a / |a|``; returns ``|a|``.  A zero quaternion gives the identity.

    Norms so small (or large) that the squares under- or overflow are
    handled by scaling with the largest component first, so the result is
    unit to round-off for every finite nonzero input.
    """
    n2 = a[0] * a[0] + a[1] * a[1] + a[2] * a[2] + a[3] * a[3]
    if 1e-200 < n2 < 1e200:
        n = math.sqrt(n2)
        inv = 1.0 / n
        out[0] = a[0] * inv
        out[1] = a[1] * inv
        out[2] = a[2] * inv
        out[3] = a[3] * inv
        return n
    m = max(max(abs(a[0]), abs(a[1])), max(abs(a[2]), abs(a[3])))
    if not (m > 0.0):
        out[0] = 1.0
        out[1] = 0.0
        out[2] = 0.0
        out[3] = 0.0
        return 0.0
    b0 = a[0] / m
    b1 = a[1] / m
    b2 = a[2] / m
    b3 = a[3] / m
    r = math.sqrt(b0 * b0 + b1 * b1 + b2 * b2 + b3 * b3)
    out[0] = b0 / r
    out[1] = b1 / r
    out[2] = b2 / r
    out[3] = b3 / r
    return m * r


@jit(inline="always")
def krotate(q, v, out):
    """``out = rot(q, v)`` for a unit quaternion ``q`` and a 3-vector ``v``.

    Uses ``v + 2w (u × v) + 2 u × (u × v)`` with ``u = (x, y, z)``, which is
    ``q [0, v] q*`` without forming the products.  ``out`` may alias ``v``.
    """
    w = q[0]
    ux = q[1]
    uy = q[2]
    uz = q[3]
    vx = v[0]
    vy = v[1]
    vz = v[2]
    # t = 2 u × v
    tx = 2.0 * (uy * vz - uz * vy)
    ty = 2.0 * (uz * vx - ux * vz)
    tz = 2.0 * (ux * vy - uy * vx)
    out[0] = vx + w * tx + (uy * tz - uz * ty)
    out[1] = vy + w * ty + (uz * tx - ux * tz)
    out[2] = vz + w * tz + (ux * ty - uy * tx)


@jit(inline="always")
def _sinc(x):
    """sin(x)/x, accurate near 0."""
    if abs(x) < 1e-4:
        return 1.0 - x * x / 6.0
    return math.sin(x) / x


@jit(inline="always")
def kslerp(a, b, t, out):
    """Spherical linear interpolation of unit quaternions along the shortest arc.

    ``t = 0`` gives ``a`` and ``t = 1`` gives ``b`` (or ``-b``, the same
    rotation) exactly; the angle is computed as ``2 atan2(|a-b|, |a+b|)``,
    accurate for tiny and large angles, and the weights as ratios of sinc
    values, so nothing divides by a small number.  ``out`` may alias ``a``.
    """
    s = 1.0
    if kdot(a, b) < 0.0:
        s = -1.0
    if t == 0.0:
        out[0] = a[0]
        out[1] = a[1]
        out[2] = a[2]
        out[3] = a[3]
        return
    if t == 1.0:
        out[0] = s * b[0]
        out[1] = s * b[1]
        out[2] = s * b[2]
        out[3] = s * b[3]
        return
    d0 = a[0] - s * b[0]
    d1 = a[1] - s * b[1]
    d2 = a[2] - s * b[2]
    d3 = a[3] - s * b[3]
    p0 = a[0] + s * b[0]
    p1 = a[1] + s * b[1]
    p2 = a[2] + s * b[2]
    p3 = a[3] + s * b[3]
    dn = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3)
    pn = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2 + p3 * p3)
    om = 2.0 * math.atan2(dn, pn)          # angle between a and s*b, in [0, pi/2]
    sc = _sinc(om)
    wa = (1.0 - t) * _sinc((1.0 - t) * om) / sc
    wb = s * t * _sinc(t * om) / sc
    w = wa * a[0] + wb * b[0]
    x = wa * a[1] + wb * b[1]
    y = wa * a[2] + wb * b[2]
    z = wa * a[3] + wb * b[3]
    n = math.sqrt(w * w + x * x + y * y + z * z)
    inv = 1.0 / n
    out[0] = w * inv
    out[1] = x * inv
    out[2] = y * inv
    out[3] = z * inv


# ------------------------------------------------------- scalar helpers
@jit(inline="always")
def mul_s(a0, a1, a2, a3, b0, b1, b2, b3):
    """Hamilton product of two quaternions given as scalars; returns a 4-tuple."""
    return (a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3,
            a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
            a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1,
            a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0)


@jit(inline="always")
def log_s(w, x, y, z):
    """Shortest rotation vector ``angle * axis`` of a (not necessarily unit) quaternion.

    The angle is ``2 atan2(|v|, |w|)`` (accurate near 0 and near pi); the
    factor ``angle / |v|`` needs no series because ``atan2`` is accurate for
    tiny arguments, only ``|v| == 0`` is special.  A zero quaternion gives 0.
    """
    if w < 0.0:
        w = -w
        x = -x
        y = -y
        z = -z
    n = math.sqrt(x * x + y * y + z * z)
    if n < 1e-150:
        if w > 0.0:
            f = 2.0 / w
        else:
            f = 0.0
    else:
        f = 2.0 * math.atan2(n, w) / n
    return x * f, y * f, z * f


@jit(inline="always")
def exp_s(x, y, z):
    """Unit quaternion of the rotation vector ``(x, y, z)``; returns a 4-tuple."""
    t = math.sqrt(x * x + y * y + z * z)
    h = 0.5 * t
    s = 0.5 * _sinc(h)                     # sin(t/2) / t
    return math.cos(h), x * s, y * s, z * s


@jit(inline="always")
def from_two_units_s(ax, ay, az, bx, by, bz):
    """Minimal rotation taking unit vector ``a`` to unit vector ``b``; returns a 4-tuple.

    For ``c = a . b >= 0`` the quaternion ``[1 + c, a x b]`` is normalised
    (no cancellation, no trigonometry).  For ``c < 0`` the angle is
    ``atan2(|a x b|, c)`` and the axis ``a x b``, first made exactly
    perpendicular to ``m = a - b`` so that round-off in a short cross product
    cannot tilt it out of the plane of rotation; exactly antiparallel inputs
    rotate by pi about ``m x e_k``, ``e_k`` the axis of ``m``'s smallest
    component.  ``w >= 0``.
    """
    c = ax * bx + ay * by + az * bz
    ux = ay * bz - az * by
    uy = az * bx - ax * bz
    uz = ax * by - ay * bx
    if c >= 0.0:
        w = 1.0 + c
        inv = 1.0 / math.sqrt(w * w + ux * ux + uy * uy + uz * uz)
        return w * inv, ux * inv, uy * inv, uz * inv
    mx = ax - bx
    my = ay - by
    mz = az - bz
    mm = mx * mx + my * my + mz * mz        # in (2, 4]
    p = (ux * mx + uy * my + uz * mz) / mm
    ux -= p * mx
    uy -= p * my
    uz -= p * mz
    s = math.sqrt(ux * ux + uy * uy + uz * uz)
    if s < 1e-150:
        amx = abs(mx)
        amy = abs(my)
        amz = abs(mz)
        if amx <= amy and amx <= amz:
            px, py, pz = 0.0, mz, -my       # m x e_x
        elif amy <= amz:
            px, py, pz = -mz, 0.0, mx       # m x e_y
        else:
            px, py, pz = my, -mx, 0.0       # m x e_z
        pn = 1.0 / math.sqrt(px * px + py * py + pz * pz)
        return 0.0, px * pn, py * pn, pz * pn
    h = 0.5 * math.atan2(s, c)
    f = math.sin(h) / s
    w = math.cos(h)
    x = ux * f
    y = uy * f
    z = uz * f
    inv = 1.0 / math.sqrt(w * w + x * x + y * y + z * z)
    return w * inv, x * inv, y * inv, z * inv


@jit(inline="always")
def from_two_vectors_s(ax, ay, az, bx, by, bz):
    """:func:`from_two_units_s` after normalising ``a`` and ``b``; a zero input gives the identity."""
    na = math.sqrt(ax * ax + ay * ay + az * az)
    nb = math.sqrt(bx * bx + by * by + bz * bz)
    if not (na > 0.0 and nb > 0.0):
        return 1.0, 0.0, 0.0, 0.0
    return from_two_units_s(ax / na, ay / na, az / na, bx / nb, by / nb, bz / nb)


# ------------------------------------------------------- more kernels
@jit(inline="always")
def kfrom_axis_angle(axis, angle, out):
    """``out = [cos(angle/2), axis/|axis| sin(angle/2)]``; a zero axis gives the identity."""
    n = math.sqrt(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2])
    h = 0.5 * angle
    if n > 0.0:
        s = math.sin(h) / n
        out[0] = math.cos(h)
        out[1] = axis[0] * s
        out[2] = axis[1] * s
        out[3] = axis[2] * s
    else:
        out[0] = 1.0
        out[1] = 0.0
        out[2] = 0.0
        out[3] = 0.0


@jit(inline="always")
def kto_axis_angle(q, out_axis):
    """Unit axis into ``out_axis`` (3,); returns the angle in ``[0, pi]``.

    ``q`` and ``-q`` give the same result.  The identity gives the axis
    ``(1, 0, 0)`` and angle 0.  ``q`` need not be unit.
    """
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    if w < 0.0:
        w = -w
        x = -x
        y = -y
        z = -z
    n = math.sqrt(x * x + y * y + z * z)
    if n > 0.0:
        out_axis[0] = x / n
        out_axis[1] = y / n
        out_axis[2] = z / n
        return 2.0 * math.atan2(n, w)
    out_axis[0] = 1.0
    out_axis[1] = 0.0
    out_axis[2] = 0.0
    return 0.0


@jit(inline="always")
def kto_matrix(q, out):
    """Rotation matrix ``out`` (3, 3) with ``out @ v == rot(q, v)``.

    ``q`` need not be unit: it is scaled by ``2 / |q|^2``, so the result is
    always orthogonal; a zero quaternion gives the identity matrix.
    """
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    nn = w * w + x * x + y * y + z * z
    s = 0.0
    if nn > 0.0:
        s = 2.0 / nn
    out[0, 0] = 1.0 - s * (y * y + z * z)
    out[0, 1] = s * (x * y - w * z)
    out[0, 2] = s * (x * z + w * y)
    out[1, 0] = s * (x * y + w * z)
    out[1, 1] = 1.0 - s * (x * x + z * z)
    out[1, 2] = s * (y * z - w * x)
    out[2, 0] = s * (x * z - w * y)
    out[2, 1] = s * (y * z + w * x)
    out[2, 2] = 1.0 - s * (x * x + y * y)


@jit(inline="always")
def kfrom_matrix(m, out):
    """Unit quaternion (``w >= 0``) of a rotation matrix ``m`` (3, 3), Shepperd's method.

    The largest of ``4w^2, 4x^2, 4y^2, 4z^2`` (read off the trace and the
    diagonal) is taken by a square root and the others from off-diagonal
    sums/differences divided by it, so nothing divides by a small number.
    """
    m00 = m[0, 0]
    m11 = m[1, 1]
    m22 = m[2, 2]
    tr = m00 + m11 + m22
    if tr >= m00 and tr >= m11 and tr >= m22:
        r = math.sqrt(max(1.0 + tr, 0.0))           # 2|w|
        f = 0.5 / r
        w = 0.5 * r
        x = (m[2, 1] - m[1, 2]) * f
        y = (m[0, 2] - m[2, 0]) * f
        z = (m[1, 0] - m[0, 1]) * f
    elif m00 >= m11 and m00 >= m22:
        r = math.sqrt(max(1.0 + m00 - m11 - m22, 0.0))
        f = 0.5 / r
        x = 0.5 * r
        w = (m[2, 1] - m[1, 2]) * f
        y = (m[0, 1] + m[1, 0]) * f
        z = (m[0, 2] + m[2, 0]) * f
    elif m11 >= m22:
        r = math.sqrt(max(1.0 - m00 + m11 - m22, 0.0))
        f = 0.5 / r
        y = 0.5 * r
        w = (m[0, 2] - m[2, 0]) * f
        x = (m[0, 1] + m[1, 0]) * f
        z = (m[1, 2] + m[2, 1]) * f
    else:
        r = math.sqrt(max(1.0 - m00 - m11 + m22, 0.0))
        f = 0.5 / r
        z = 0.5 * r
        w = (m[1, 0] - m[0, 1]) * f
        x = (m[0, 2] + m[2, 0]) * f
        y = (m[1, 2] + m[2, 1]) * f
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not (n > 0.0):
        out[0] = 1.0
        out[1] = 0.0
        out[2] = 0.0
        out[3] = 0.0
        return
    if w < 0.0:
        n = -n
    out[0] = w / n
    out[1] = x / n
    out[2] = y / n
    out[3] = z / n


@jit(inline="always")
def kfrom_two_vectors(a, b, out):
    """Minimal rotation taking direction ``a`` (3,) to direction ``b`` (3,).

    Axis ``a x b / |a x b|`` (normalised, docs/method.md §3.8), angle
    ``atan2(|a x b|, a . b)``; parallel inputs give the identity, exactly
    antiparallel ones a rotation by pi about a perpendicular axis.  Inputs
    are normalised here; a zero input gives the identity.  ``w >= 0``.
    """
    w, x, y, z = from_two_vectors_s(a[0], a[1], a[2], b[0], b[1], b[2])
    out[0] = w
    out[1] = x
    out[2] = y
    out[3] = z


@jit(inline="always")
def klog(q, out3):
    """Rotation vector ``angle * axis`` of ``q`` into ``out3`` (3,), shortest (``|v| <= pi``)."""
    x, y, z = log_s(q[0], q[1], q[2], q[3])
    out3[0] = x
    out3[1] = y
    out3[2] = z


@jit(inline="always")
def kexp(v3, out):
    """Unit quaternion of the rotation vector ``v3`` (3,) (inverse of :func:`klog`)."""
    w, x, y, z = exp_s(v3[0], v3[1], v3[2])
    out[0] = w
    out[1] = x
    out[2] = y
    out[3] = z


#: relative norm below which :func:`kblend` falls back to the log-map blend
#: (read when a kernel is compiled: changing it later has no effect)
BLEND_FALLBACK = 1e-6


@jit(inline="always")
def kblend(qs, w, out):
    """Weighted blend of ``m`` unit quaternions ``qs`` (m, 4) with weights ``w`` (m,).

    Every input is flipped to the hemisphere of the reference (the input
    with the largest weight; the first on ties), the four components are
    blended linearly and normalised.  When the blended norm is below
    ``BLEND_FALLBACK`` times ``sum |w|`` the rotation vectors about the
    reference, ``log(ref* ⊗ q_i)``, are blended instead (divided by
    ``sum w``, or by ``sum |w|`` when that sum vanishes) and mapped back,
    ``ref ⊗ exp(v)``: nothing divides by ~0.  All weights zero gives the
    reference; ``m == 0`` the identity.  ``out`` must not alias ``qs``.
    """
    m = qs.shape[0]
    if m == 0:
        out[0] = 1.0
        out[1] = 0.0
        out[2] = 0.0
        out[3] = 0.0
        return
    r = 0
    wmax = w[0]
    for i in range(1, m):
        if w[i] > wmax:
            wmax = w[i]
            r = i
    r0 = qs[r, 0]
    r1 = qs[r, 1]
    r2 = qs[r, 2]
    r3 = qs[r, 3]
    a0 = 0.0
    a1 = 0.0
    a2 = 0.0
    a3 = 0.0
    wabs = 0.0
    wsum = 0.0
    for i in range(m):
        wi = w[i]
        wabs += abs(wi)
        wsum += wi
        if qs[i, 0] * r0 + qs[i, 1] * r1 + qs[i, 2] * r2 + qs[i, 3] * r3 < 0.0:
            wi = -wi
        a0 += wi * qs[i, 0]
        a1 += wi * qs[i, 1]
        a2 += wi * qs[i, 2]
        a3 += wi * qs[i, 3]
    n = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2 + a3 * a3)
    if n > BLEND_FALLBACK * wabs and n > 0.0:
        inv = 1.0 / n
        out[0] = a0 * inv
        out[1] = a1 * inv
        out[2] = a2 * inv
        out[3] = a3 * inv
        return
    # fallback: blend of rotation vectors about the (normalised) reference
    rn = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2 + r3 * r3)
    if not (rn > 0.0):
        r0, r1, r2, r3, rn = 1.0, 0.0, 0.0, 0.0, 1.0
    r0 /= rn
    r1 /= rn
    r2 /= rn
    r3 /= rn
    if not (wabs > 0.0):
        out[0] = r0
        out[1] = r1
        out[2] = r2
        out[3] = r3
        return
    den = wsum
    if abs(den) <= 1e-12 * wabs:
        den = wabs
    v0 = 0.0
    v1 = 0.0
    v2 = 0.0
    for i in range(m):
        # ref* ⊗ q_i (log ignores the norm of q_i)
        d0, d1, d2, d3 = mul_s(r0, -r1, -r2, -r3, qs[i, 0], qs[i, 1], qs[i, 2], qs[i, 3])
        l0, l1, l2 = log_s(d0, d1, d2, d3)
        v0 += w[i] * l0
        v1 += w[i] * l1
        v2 += w[i] * l2
    e0, e1, e2, e3 = exp_s(v0 / den, v1 / den, v2 / den)
    b0, b1, b2, b3 = mul_s(r0, r1, r2, r3, e0, e1, e2, e3)
    inv = 1.0 / math.sqrt(b0 * b0 + b1 * b1 + b2 * b2 + b3 * b3)
    out[0] = b0 * inv
    out[1] = b1 * inv
    out[2] = b2 * inv
    out[3] = b3 * inv


# ------------------------------------------------------------------ drivers
# Loop templates: KERNEL is a global of each copy made by _many (not a closure
# variable: numba keys its disk cache on the pickled closure, and a pickled
# dispatcher differs between processes).
def _loop1(a, out):
    for n in range(out.shape[0]):
        KERNEL(a[n], out[n])  # noqa: F821


def _loop2(a, b, out):
    for n in range(out.shape[0]):
        KERNEL(a[n], b[n], out[n])  # noqa: F821


def _loop3(a, b, c, out):
    for n in range(out.shape[0]):
        KERNEL(a[n], b[n], c[n], out[n])  # noqa: F821


def _many(kernel, name: str):
    """Compiled loop ``out[n] = kernel(inputs[n]...)`` over flattened arrays.

    A copy of the template for the kernel's number of inputs, with the kernel
    bound as its global ``KERNEL`` and its own name (numba's cache files are
    named after it, so each loop keeps its own cache entry).
    """
    nin = kernel.py_func.__code__.co_argcount - 1
    template = (_loop1, _loop2, _loop3)[nin - 1]
    fn = types.FunctionType(template.__code__, dict(globals(), KERNEL=kernel), name)
    fn.__qualname__ = name
    fn.__doc__ = f"``{kernel.__name__}`` over the rows of flattened arrays."
    return jit(fn)


@jit(inline="always")
def _kaxis_angle(q, out):
    """:func:`kto_axis_angle` packed as ``(axis, angle)`` into ``out`` (4,)."""
    out[3] = kto_axis_angle(q, out[:3])


_mul_many = _many(kmul, "_mul_many")
_rotate_many = _many(krotate, "_rotate_many")
_slerp_many = _many(kslerp, "_slerp_many")
_normalize_many = _many(knormalize, "_normalize_many")
_from_axis_angle_many = _many(kfrom_axis_angle, "_from_axis_angle_many")
_axis_angle_many = _many(_kaxis_angle, "_axis_angle_many")
_from_matrix_many = _many(kfrom_matrix, "_from_matrix_many")
_to_matrix_many = _many(kto_matrix, "_to_matrix_many")
_from_two_vectors_many = _many(kfrom_two_vectors, "_from_two_vectors_many")
_log_many = _many(klog, "_log_many")
_exp_many = _many(kexp, "_exp_many")
_blend_many = _many(kblend, "_blend_many")


def _float(a, name: str) -> np.ndarray:
    try:
        return np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise GridValueError(f"{name}: expected an array of real numbers ({exc})") from None


def _q(a, name: str) -> np.ndarray:
    arr = _float(a, name)
    if arr.shape[-1:] != (4,):
        raise GridValueError(f"{name}: quaternions need a last axis of length 4 (w, x, y, z), got shape {arr.shape}")
    return arr


def _v(a, name: str) -> np.ndarray:
    arr = _float(a, name)
    if arr.shape[-1:] != (3,):
        raise GridValueError(f"{name}: vectors need a last axis of length 3, got shape {arr.shape}")
    return arr


def _flat(a, shape, tail) -> np.ndarray:
    """``a`` broadcast to ``shape + tail`` as a read-only C-contiguous ``(N,) + tail`` array.

    Read-only whether or not broadcasting made a copy (a view of ``a`` is read-only, a copy
    is made so), so a kernel sees one type and is compiled and loaded once, not once for
    each combination of its inputs' flags."""
    flat = np.ascontiguousarray(np.broadcast_to(a, shape + tail)).reshape((-1,) + tail)
    flat.flags.writeable = False
    return flat


def _bshape(*pairs) -> tuple:
    """Broadcast leading shapes; ``pairs`` are ``(name, leading_shape)``."""
    try:
        return np.broadcast_shapes(*(s for _, s in pairs))
    except ValueError:
        desc = ", ".join(f"{n} {s}" for n, s in pairs)
        raise GridValueError(f"leading shapes do not broadcast: {desc}") from None


def _drive(loop, out_tail: tuple, *inputs) -> np.ndarray:
    """Run ``loop`` over validated inputs ``(name, array, tail)``, broadcast over their
    leading shapes (a :class:`GridValueError` naming them if they do not broadcast);
    returns the output, of shape ``leading + out_tail``."""
    shape = _bshape(*((n, a.shape[:a.ndim - len(t)]) for n, a, t in inputs))
    out = np.empty((int(np.prod(shape, dtype=np.int64)),) + out_tail)
    loop(*(_flat(a, shape, t) for _, a, t in inputs), out)
    return out.reshape(shape + out_tail)


def multiply(a, b) -> np.ndarray:
    """Hamilton product ``a ⊗ b`` of quaternion arrays ``(..., 4)`` (broadcast)."""
    return _drive(_mul_many, (4,), ("a", _q(a, "a"), (4,)), ("b", _q(b, "b"), (4,)))


def conjugate(q) -> np.ndarray:
    """``q*`` of a quaternion array ``(..., 4)``."""
    q = _q(q, "q")
    out = q.copy()
    out[..., 1:] *= -1.0
    return out


def normalize(q) -> np.ndarray:
    """Unit quaternions ``q / |q|``; zero quaternions become the identity."""
    return _drive(_normalize_many, (4,), ("q", _q(q, "q"), (4,)))


def rotate(q, v) -> np.ndarray:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)`` (broadcast)."""
    return _drive(_rotate_many, (3,), ("q", _q(q, "q"), (4,)), ("v", _v(v, "v"), (3,)))


def slerp(a, b, t) -> np.ndarray:
    """Shortest-arc spherical interpolation between unit quaternions (broadcast over ``t``)."""
    return _drive(_slerp_many, (4,), ("a", _q(a, "a"), (4,)), ("b", _q(b, "b"), (4,)),
                  ("t", _float(t, "t"), ()))


def from_axis_angle(axis, angle) -> np.ndarray:
    """Unit quaternions from rotation axes and angles.

    Parameters
    ----------
    axis : array_like, shape (..., 3)
        Rotation axes (normalised here; a zero axis gives the identity).
    angle : array_like, shape (...)
        Angles in radians (right-hand rule), broadcast against ``axis``.

    Returns
    -------
    q : ndarray, shape (..., 4), float64
    """
    return _drive(_from_axis_angle_many, (4,), ("axis", _v(axis, "axis"), (3,)),
                  ("angle", _float(angle, "angle"), ()))


def to_axis_angle(q):
    """Unit axes and angles in ``[0, pi]`` of quaternions ``q (..., 4)``.

    Returns
    -------
    axis : ndarray, shape (..., 3), float64
        Unit axes; ``(1, 0, 0)`` for the identity.
    angle : ndarray, shape (...), float64
    """
    packed = _drive(_axis_angle_many, (4,), ("q", _q(q, "q"), (4,)))
    return np.ascontiguousarray(packed[..., :3]), np.ascontiguousarray(packed[..., 3])


def from_matrix(m) -> np.ndarray:
    """Unit quaternions (``w >= 0``) of rotation matrices ``m (..., 3, 3)`` (Shepperd).

    ``m @ v == rot(q, v)``.  A matrix that is not exactly orthogonal gives a
    nearby rotation (the result is normalised).
    """
    m = _float(m, "m")
    if m.shape[-2:] != (3, 3):
        raise GridValueError(f"m: rotation matrices need trailing shape (3, 3), got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise GridValueError("m: rotation matrices hold NaN or infinite values")
    return _drive(_from_matrix_many, (4,), ("m", m, (3, 3)))


def to_matrix(q) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of quaternions ``q (..., 4)``: ``R @ v == rot(q, v)``."""
    return _drive(_to_matrix_many, (3, 3), ("q", _q(q, "q"), (4,)))


def from_two_vectors(a, b) -> np.ndarray:
    """Minimal rotations taking directions ``a (..., 3)`` to ``b (..., 3)`` (broadcast).

    Parallel directions give the identity; antiparallel ones a rotation by
    pi about a perpendicular axis.  Zero vectors give the identity.

    Returns
    -------
    q : ndarray, shape (..., 4), float64, ``w >= 0``
    """
    return _drive(_from_two_vectors_many, (4,), ("a", _v(a, "a"), (3,)), ("b", _v(b, "b"), (3,)))


def log(q) -> np.ndarray:
    """Rotation vectors ``angle * axis`` (shortest, ``|v| <= pi``) of quaternions ``q (..., 4)``."""
    return _drive(_log_many, (3,), ("q", _q(q, "q"), (4,)))


def exp(v) -> np.ndarray:
    """Unit quaternions of rotation vectors ``v (..., 3)`` (inverse of :func:`log`)."""
    return _drive(_exp_many, (4,), ("v", _v(v, "v"), (3,)))


def blend(qs, weights) -> np.ndarray:
    """Weighted hemisphere-aligned blend of quaternions (see :func:`kblend`).

    Parameters
    ----------
    qs : array_like, shape (..., m, 4)
        Unit quaternions to blend, ``m >= 1`` per blend.
    weights : array_like, shape (..., m)
        Weights (may be negative, as in TFI corrections), broadcast against
        the leading shape of ``qs``.

    Returns
    -------
    q : ndarray, shape (..., 4), float64
        Unit quaternions, in the hemisphere of the largest-weight input.
    """
    qs = _q(qs, "qs")
    if qs.ndim < 2 or qs.shape[-2] < 1:
        raise GridValueError(f"qs: expected shape (..., m, 4) with m >= 1, got shape {qs.shape}")
    weights = _float(weights, "weights")
    m = qs.shape[-2]
    if weights.ndim < 1 or weights.shape[-1] != m:
        raise GridValueError(f"weights: expected shape (..., {m}) to match qs {qs.shape}, "
                             f"got shape {weights.shape}")
    if not (np.all(np.isfinite(qs)) and np.all(np.isfinite(weights))):
        raise GridValueError("qs/weights: NaN or infinite values")
    return _drive(_blend_many, (4,), ("qs", qs, (m, 4)), ("weights", weights, (m,)))
