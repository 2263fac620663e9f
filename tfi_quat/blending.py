"""Wall-layer blending parameters for the two-level Deformer.

Soni's blending uses the normalised arclength ``s`` of each grid line.  The
two-level formulation (``docs/deformer.md``) replaces it, line by line, by a
*wall-layer* parameter ``chi(s)`` that is

* exactly 0 and 1 at the ends of the line and non-decreasing, so TFI with it
  reproduces every boundary and every constant field (rigid motions);
* flat (zero slope) over a layer of thickness ``lam = ell * omega`` next to
  an end that lies on or near a wall, so the first grid layers move with the
  wall's own rotation and translation and keep their angle to it;
* equal to ``s`` up to a shift of at most about ``lam`` elsewhere, so the grid's
  offset from the interpolant of its own boundary (the arm that rotations act
  on) stays of the order of ``lam`` instead of growing with the line length
  (Hermite blending, ``3 s^2 - 2 s^3``, leaves offsets of ``0.1 L``).

Definition: with ``a_e = lam_e / L`` (``L`` the line's length) and
``f_a(t) = 1 - exp(-(t / a)^2)`` (``f = 1`` where ``a = 0``)::

    g'(t) = f_{a_0}(t) * f_{a_1}(1 - t),     chi(s) = int_0^s g' / int_0^1 g'

integrated by the trapezoid rule over the line's own points, so neighbouring
lines with the same point distribution get the same parameters.  The end
weight ``omega`` is 1 on walls and decays as ``exp(-d / ell)`` with the
distance ``d`` to the nearest wall point, so the layer thins out smoothly along
a wake cut or a symmetry plane that leaves a wall.

Kernels are numba functions (:mod:`tfi_quat._jit`); :func:`wall_layer_block`
is the driver for a block (or a patch given as a ``(na, nb, 1, 3)`` block).
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import jit, pjit, prange
from .errors import GridValueError

__all__ = ["wall_layer_line", "wall_layer_block", "AMAX"]

#: a layer thicker than AMAX line lengths is treated as AMAX (the line is far
#: shorter than the layer: the parameter tends to s^2 or a Hermite-like cubic)
AMAX = 1.0e3
#: beyond EXP_CUT layer thicknesses f_a(t) is 1 to double precision
EXP_CUT = 6.5


@jit(inline="always")
def _f(t, a):
    if a <= 0.0:
        return 1.0
    u = t / a
    if u >= EXP_CUT:
        return 1.0
    return -math.expm1(-u * u)


@jit
def _layer_line(s, length, lam0, lam1, out):
    """Wall-layer parameters of one line: ``s`` (n,) normalised arclength in, ``out`` (n,)."""
    n = s.shape[0]
    if n == 1:
        out[0] = 0.0
        return
    if not length > 0.0 or (lam0 <= 0.0 and lam1 <= 0.0):
        for m in range(n):
            out[m] = s[m]
        return
    a0 = min(lam0 / length, AMAX)
    a1 = min(lam1 / length, AMAX)
    gp_prev = _f(s[0], a0) * _f(1.0 - s[0], a1)
    out[0] = 0.0
    acc = 0.0
    for m in range(1, n):
        gp = _f(s[m], a0) * _f(1.0 - s[m], a1)
        acc += 0.5 * (gp + gp_prev) * (s[m] - s[m - 1])
        out[m] = acc
        gp_prev = gp
    if acc > 0.0:
        inv = 1.0 / acc
        for m in range(1, n - 1):
            out[m] *= inv
        out[n - 1] = 1.0
    else:
        for m in range(n):
            out[m] = s[m]


def wall_layer_line(s, length, lam0, lam1) -> np.ndarray:
    """Wall-layer parameters of one grid line.

    Parameters
    ----------
    s : array_like, shape (n,)
        Normalised arclength of the line's points (0 first, 1 last, non-decreasing).
    length : float
        The line's length.
    lam0, lam1 : float
        Layer thicknesses (lengths) at the first and last end; 0 for none.

    Returns
    -------
    ndarray, shape (n,), float64
        ``chi``: exactly 0 and 1 at the ends, non-decreasing.
    """
    s = np.ascontiguousarray(s, dtype=np.float64)
    if s.ndim != 1:
        raise GridValueError(f"s: expected a 1-D array, got shape {s.shape}")
    out = np.empty_like(s)
    _layer_line(s, float(length), float(lam0), float(lam1), out)
    return out


@pjit
def _layer_block_dir(xyz, s, d, lam0, lam1, out):
    """Direction ``d`` of a block: per line, length from ``xyz``, parameters from ``s[..., d]``."""
    ni, nj, nk = xyz.shape[0], xyz.shape[1], xyz.shape[2]
    dims = (ni, nj, nk)
    n = dims[d]
    if d == 0:
        na, nb = nj, nk
    elif d == 1:
        na, nb = ni, nk
    else:
        na, nb = ni, nj
    for ab in prange(na * nb):
        a = ab % na
        b = ab // na
        line = np.empty(n)
        res = np.empty(n)
        length = 0.0
        px = py = pz = 0.0
        for m in range(n):
            if d == 0:
                i, j, k = m, a, b
            elif d == 1:
                i, j, k = a, m, b
            else:
                i, j, k = a, b, m
            line[m] = s[i, j, k, d]
            x = xyz[i, j, k, 0]
            y = xyz[i, j, k, 1]
            z = xyz[i, j, k, 2]
            if m > 0:
                length += math.sqrt((x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2)
            px, py, pz = x, y, z
        _layer_line(line, length, lam0[a, b], lam1[a, b], res)
        for m in range(n):
            if d == 0:
                out[m, a, b, d] = res[m]
            elif d == 1:
                out[a, m, b, d] = res[m]
            else:
                out[a, b, m, d] = res[m]


def wall_layer_block(xyz, s, lam, ndim: int = 3, out=None) -> np.ndarray:
    """Wall-layer parameters of every grid line of a block.

    Parameters
    ----------
    xyz : ndarray, shape (ni, nj, nk, 3), float64
        Undeformed coordinates (a patch as ``(na, nb, 1, 3)`` with ``ndim=2``).
    s : ndarray, shape (ni, nj, nk, 3), float64
        Its normalised arclength parameters (:func:`tfi_quat.tfi.arclength`).
    lam : sequence of ``2 * ndim`` arrays
        Layer thickness at the low and high end of every line of each
        direction: ``lam[2 d]`` and ``lam[2 d + 1]`` have the shape of the
        block's faces normal to ``d`` (faces imin, imax, jmin, jmax, kmin, kmax).
    ndim : {2, 3}
        Directions to process (the third parameter of a 2-D block is copied).
    out : ndarray, optional
        Receives the result (Fortran order, the shape of ``s``); may be ``s``
        itself (each line is read before it is written).

    Returns
    -------
    ndarray, shape (ni, nj, nk, 3), float64, Fortran order
    """
    xyz = np.asarray(xyz)
    if xyz.ndim != 4 or xyz.shape[-1] != 3 or s.shape != xyz.shape:
        raise GridValueError(f"xyz and s: expected equal shapes (ni, nj, nk, 3), got "
                             f"{xyz.shape} and {getattr(s, 'shape', None)}")
    if len(lam) != 2 * ndim:
        raise GridValueError(f"lam: expected {2 * ndim} face arrays, got {len(lam)}")
    if out is None:
        out = np.array(s, dtype=np.float64, order="F")
    elif out.shape != s.shape or out.dtype != np.float64 or not out.flags.f_contiguous:
        raise GridValueError(f"out: expected a float64 Fortran-order array of shape {s.shape}")
    elif out is not s:
        out[...] = s
    dims = xyz.shape[:3]
    for d in range(ndim):
        others = tuple(dims[m] for m in range(3) if m != d)
        l0 = np.ascontiguousarray(lam[2 * d], dtype=np.float64).reshape(others)
        l1 = np.ascontiguousarray(lam[2 * d + 1], dtype=np.float64).reshape(others)
        _layer_block_dir(xyz, s, d, l0, l1, out)
    return out
