"""Quaternion algebra: numba kernels on single quaternions, and array drivers.

Kernel contract
---------------
* A quaternion is a float64 array of 4 values, **scalar first** ``(w, x, y, z)``.
* Kernels act on one quaternion (or one vector): inputs first, the output
  array last; they write the output and return nothing (or a scalar), never
  allocate, never raise.  Output may alias an input unless stated.
* Rotations are unit quaternions; ``q`` and ``-q`` are the same rotation.
  The rotation of a vector ``v`` is ``q [0, v] q*``.
* The composition "first ``a``, then ``b``" is ``b ⊗ a`` (:func:`qmul` (b, a)).

Array drivers (no leading ``k``) take arrays of any leading shape
``(..., 4)`` / ``(..., 3)`` and return new arrays.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import jit

__all__ = [
    # kernels
    "kmul", "kconj", "knormalize", "krotate", "kslerp", "kdot",
    # drivers
    "multiply", "conjugate", "normalize", "rotate", "slerp",
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
    """``out = a / |a|``; returns ``|a|``.  A zero quaternion gives the identity."""
    n = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2] + a[3] * a[3])
    if n > 0.0:
        inv = 1.0 / n
        out[0] = a[0] * inv
        out[1] = a[1] * inv
        out[2] = a[2] * inv
        out[3] = a[3] * inv
    else:
        out[0] = 1.0
        out[1] = 0.0
        out[2] = 0.0
        out[3] = 0.0
    return n


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


# ------------------------------------------------------------------ drivers
@jit
def _mul_many(a, b, out):
    for n in range(out.shape[0]):
        kmul(a[n], b[n], out[n])


@jit
def _rotate_many(q, v, out):
    for n in range(out.shape[0]):
        krotate(q[n], v[n], out[n])


@jit
def _slerp_many(a, b, t, out):
    for n in range(out.shape[0]):
        kslerp(a[n], b[n], t[n], out[n])


@jit
def _normalize_many(a, out):
    for n in range(out.shape[0]):
        knormalize(a[n], out[n])


def _q(a, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.shape[-1:] != (4,):
        raise ValueError(f"{name}: quaternions need a last axis of length 4 (w, x, y, z), got shape {arr.shape}")
    return arr


def _v(a, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.shape[-1:] != (3,):
        raise ValueError(f"{name}: vectors need a last axis of length 3, got shape {arr.shape}")
    return arr


def multiply(a, b) -> np.ndarray:
    """Hamilton product ``a ⊗ b`` of quaternion arrays ``(..., 4)`` (broadcast)."""
    a, b = np.broadcast_arrays(_q(a, "a"), _q(b, "b"))
    shape = a.shape
    out = np.empty((int(np.prod(shape[:-1], dtype=np.int64)), 4))
    _mul_many(np.ascontiguousarray(a).reshape(-1, 4), np.ascontiguousarray(b).reshape(-1, 4), out)
    return out.reshape(shape)


def conjugate(q) -> np.ndarray:
    """``q*`` of a quaternion array ``(..., 4)``."""
    q = _q(q, "q")
    out = q.copy()
    out[..., 1:] *= -1.0
    return out


def normalize(q) -> np.ndarray:
    """Unit quaternions ``q / |q|``; zero quaternions become the identity."""
    q = _q(q, "q")
    out = np.empty((int(np.prod(q.shape[:-1], dtype=np.int64)), 4))
    _normalize_many(np.ascontiguousarray(q).reshape(-1, 4), out)
    return out.reshape(q.shape)


def rotate(q, v) -> np.ndarray:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)`` (broadcast)."""
    q, v = _q(q, "q"), _v(v, "v")
    shape = np.broadcast_shapes(q.shape[:-1], v.shape[:-1])
    qb = np.ascontiguousarray(np.broadcast_to(q, shape + (4,))).reshape(-1, 4)
    vb = np.ascontiguousarray(np.broadcast_to(v, shape + (3,))).reshape(-1, 3)
    out = np.empty_like(vb)
    _rotate_many(qb, vb, out)
    return out.reshape(shape + (3,))


def slerp(a, b, t) -> np.ndarray:
    """Shortest-arc spherical interpolation between unit quaternions (broadcast over ``t``)."""
    a, b = _q(a, "a"), _q(b, "b")
    t = np.asarray(t, dtype=np.float64)
    shape = np.broadcast_shapes(a.shape[:-1], b.shape[:-1], t.shape)
    ab = np.ascontiguousarray(np.broadcast_to(a, shape + (4,))).reshape(-1, 4)
    bb = np.ascontiguousarray(np.broadcast_to(b, shape + (4,))).reshape(-1, 4)
    tb = np.ascontiguousarray(np.broadcast_to(t, shape)).reshape(-1)
    out = np.empty_like(ab)
    _slerp_many(ab, bb, tb, out)
    return out.reshape(shape + (4,))
