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
is the driver for a block (or a patch given as a ``(na, nb, 1, 3)`` block), and
:func:`wall_layer_arclength` the same fused with :func:`tfi_quat.tfi.arclength`
(one pass over the block instead of two).  The block kernels skip the lines
without a layer (their parameters are ``s``), sum each line's length as
``arclength`` does, and process the lines of directions j and k in tiles of
:data:`tfi_quat.kernels.TILE` lines, i innermost, so memory is read along i as it lies; the
result is bit for bit that of :func:`wall_layer_line` applied line by line.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import jit, task_jit
from .errors import GridValueError
from .kernels import TILE, arc_line_i, arc_tile, at, by_direction, dist, line_point
from .tfi import S_DTYPE, ZERO_LENGTH_RTOL, check_xyz

__all__ = ["wall_layer_line", "wall_layer_block", "wall_layer_arclength", "AMAX"]

#: a layer thicker than AMAX line lengths is treated as AMAX (the line is far
#: shorter than the layer: the parameter tends to s^2 or a Hermite-like cubic)
AMAX = 1.0e3
#: beyond EXP_CUT layer thicknesses f_a(t) is 1 to double precision
EXP_CUT = 6.5


@jit(forceinline=True)
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
    length, lam0, lam1 = float(length), float(lam0), float(lam1)
    if s.shape[0] >= 2 and length > 0.0 and not (lam0 <= 0.0 and lam1 <= 0.0) \
            and lam0 == lam0 and lam1 == lam1 and s.shape[0] < _ARC_NUMPY_BELOW:
        # numpy (the same bits): a run that only meets short lines compiles no _layer_line
        out[:] = _layer_numpy(s[:, None], np.array([length]), np.array([lam0]),
                              np.array([lam1]))[:, 0]
    else:
        _layer_line(s, length, lam0, lam1, out)
    return out




@jit(forceinline=True)
def _needs_layer(lam0, lam1):
    """False where :func:`_layer_line` returns ``s`` whatever the length (lines of >= 2 points)."""
    return not (lam0 <= 0.0 and lam1 <= 0.0)


@jit(inline="always")
def _layer_tile(col, nw, ln, lam0, lam1, act, a0, a1, acc, gpp, sp):
    """:func:`_layer_line` on the columns ``w < nw`` of ``col`` (n, TILE) where ``act[w]``, in place.

    Column ``w`` holds a line's normalised arclength on entry and its
    parameters on return, computed with the operations of ``_layer_line`` in
    the same order (lines interleaved, i innermost).  ``act[w]`` must be
    False unless the line needs a layer and ``ln[w] > 0``; it is cleared
    where ``_layer_line`` returns ``s`` (zero integral), the column then
    holding garbage.  ``a0 .. sp`` are work arrays of at least ``nw``.
    """
    n = col.shape[0]
    for w in range(nw):
        if act[w]:
            a0[w] = min(lam0[w] / ln[w], AMAX)
            a1[w] = min(lam1[w] / ln[w], AMAX)
            s0 = col[0, w]
            gpp[w] = _f(s0, a0[w]) * _f(1.0 - s0, a1[w])
            sp[w] = s0
            col[0, w] = 0.0
            acc[w] = 0.0
    for m in range(1, n):
        for w in range(nw):
            if act[w]:
                sm = col[m, w]
                gp = _f(sm, a0[w]) * _f(1.0 - sm, a1[w])
                acc[w] += 0.5 * (gp + gpp[w]) * (sm - sp[w])
                col[m, w] = acc[w]
                gpp[w] = gp
                sp[w] = sm
    for w in range(nw):
        if act[w]:
            if acc[w] > 0.0:
                a0[w] = 1.0 / acc[w]
            else:
                act[w] = False
    for m in range(1, n - 1):
        for w in range(nw):
            if act[w]:
                col[m, w] *= a0[w]
    for w in range(nw):
        if act[w]:
            col[n - 1, w] = 1.0


@task_jit
def _layer_dir_i(lo, hi, xyz, s, lam0, lam1, out):
    """Direction i of :func:`wall_layer_block`: the lines ``lo <= jk < hi`` (j, k), contiguous
    in memory (:func:`tfi_quat.kernels.by_direction`)."""
    ni, nj = xyz.shape[0], xyz.shape[1]
    line = np.empty(ni)
    res = np.empty(ni)
    for jk in range(lo, hi):
        j = jk % nj
        k = jk // nj
        l0 = lam0[j, k]
        l1 = lam1[j, k]
        if ni == 1:
            out[0, j, k, 0] = 0.0
            continue
        if not _needs_layer(l0, l1):
            continue                        # out already holds s
        length = 0.0
        for i in range(1, ni):
            length += dist(xyz, i - 1, j, k, i, j, k)
        for i in range(ni):
            line[i] = s[i, j, k, 0]
        _layer_line(line, length, l0, l1, res)
        for i in range(ni):
            out[i, j, k, 0] = res[i]


@jit
def _layer_task_jk(xyz, s, lam0, lam1, out, t, nt, kdir):
    """Task ``t`` of direction j (``kdir`` None) or k (``kdir`` True) of
    :func:`wall_layer_block`: the plane ``t // nt`` of the third direction and tile
    ``t % nt`` of TILE lines i; compiled once per direction, with the direction a
    constant, so the index arithmetic folds away (a separate compiled function: inlined
    into the task kernel, the kernel compiled more slowly)."""
    ni = xyz.shape[0]
    axis = 2 if kdir is not None else 1
    n = xyz.shape[axis]
    c = t // nt
    i0 = (t % nt) * TILE
    nw = min(TILE, ni - i0)
    u0 = np.uint64(i0)
    if n == 1:
        for w in range(nw):
            i, j, k = line_point(axis, at(u0, w), n - 1, c)
            out[i, j, k, axis] = 0.0
        return
    l0 = np.empty(nw)
    l1 = np.empty(nw)
    act = np.empty(nw, dtype=np.bool_)
    some = False
    for w in range(nw):
        l0[w] = lam0[at(u0, w), c]
        l1[w] = lam1[at(u0, w), c]
        act[w] = _needs_layer(l0[w], l1[w])
        some = some or act[w]
    if not some:
        return                            # out already holds s
    ln = np.zeros(nw)
    for m in range(1, n):
        for w in range(nw):
            ia, ja, ka = line_point(axis, at(u0, w), m - 1, c)
            ib, jb, kb = line_point(axis, at(u0, w), m, c)
            ln[w] += dist(xyz, ia, ja, ka, ib, jb, kb)
    col = np.empty((n, nw))
    for m in range(n):
        for w in range(nw):
            i, j, k = line_point(axis, at(u0, w), m, c)
            col[m, w] = s[i, j, k, axis]
    for w in range(nw):
        act[w] = act[w] and ln[w] > 0.0
    work = np.empty((5, nw))
    _layer_tile(col, nw, ln, l0, l1, act, work[0], work[1], work[2], work[3], work[4])
    for m in range(n):
        for w in range(nw):
            if act[w]:
                i, j, k = line_point(axis, at(u0, w), m, c)
                out[i, j, k, axis] = col[m, w]


@task_jit
def _layer_dir_jk(lo, hi, xyz, s, lam0, lam1, out, kdir):
    """Direction j (``kdir`` None) or k (``kdir`` True) of :func:`wall_layer_block`: the tiles
    ``lo <= t < hi`` (:func:`tfi_quat.kernels.by_direction`); compiled once per direction,
    with the direction a constant, so the index arithmetic folds away."""
    nt = (xyz.shape[0] + TILE - 1) // TILE
    for t in range(lo, hi):
        _layer_task_jk(xyz, s, lam0, lam1, out, t, nt, kdir)


@jit(inline="always")
def _arc_tile_norm(col, cum, den, w):
    """Column ``w`` of ``col``: the normalised arclength ``cum[:, w] / den[w]``, exactly 1 at the end."""
    n = col.shape[0]
    for m in range(n - 1):
        col[m, w] = cum[m, w] / den[w]
    col[n - 1, w] = 1.0


@jit(inline="always")
def _arc_tile_layer(col, cum, den, nw, ln, lam0, lam1, u0, c):
    """Parameters of a tile of :func:`wall_layer_arclength` into ``col`` (n, nw): lines ``i = u0 + w``
    with arclength ``cum / den`` and length ``ln`` (:func:`tfi_quat.kernels.arc_tile`), thicknesses
    ``lam0[i, c]`` and ``lam1[i, c]``."""
    n = col.shape[0]
    for m in range(n - 1):
        for w in range(nw):
            col[m, w] = cum[m, w] / den[w]
    for w in range(nw):
        col[n - 1, w] = 1.0
    l0 = np.empty(nw)
    l1 = np.empty(nw)
    need = np.empty(nw, dtype=np.bool_)
    act = np.empty(nw, dtype=np.bool_)
    some = False
    for w in range(nw):
        l0[w] = lam0[at(u0, w), c]
        l1[w] = lam1[at(u0, w), c]
        need[w] = _needs_layer(l0[w], l1[w])
        act[w] = need[w] and ln[w] > 0.0
        some = some or act[w]
    if not some:
        return
    work = np.empty((5, nw))
    _layer_tile(col, nw, ln, l0, l1, act, work[0], work[1], work[2], work[3], work[4])
    for w in range(nw):
        if need[w] and not act[w]:              # zero integral: the parameters are s
            _arc_tile_norm(col, cum, den, w)


@task_jit
def _arc_layer_i(lo, hi, xyz, rtol, lam0, lam1, out):
    """Direction i of :func:`wall_layer_arclength`, the lines ``lo <= jk < hi`` (j, k): each
    line's arclength, then its layer (:func:`tfi_quat.kernels.by_direction`)."""
    ni, nj = xyz.shape[0], xyz.shape[1]
    buf = np.empty(ni)
    line = np.empty(ni)
    res = np.empty(ni)
    for jk in range(lo, hi):
        j = jk % nj
        k = jk // nj
        if ni == 1:
            out[0, j, k, 0] = 0.0
            continue
        length, a = arc_line_i(xyz, rtol, j, k, buf)
        l0 = lam0[j, k]
        l1 = lam1[j, k]
        if _needs_layer(l0, l1):
            for i in range(ni - 1):
                line[i] = buf[i] / a
            line[ni - 1] = 1.0
            _layer_line(line, length, l0, l1, res)
            for i in range(ni):
                out[i, j, k, 0] = res[i]
        else:
            for i in range(ni - 1):
                out[i, j, k, 0] = buf[i] / a
            out[ni - 1, j, k, 0] = 1.0


@task_jit
def _arc_layer_jk(lo, hi, xyz, rtol, lam0, lam1, out, kdir):
    """Direction j (``kdir`` None) or k (``kdir`` True) of :func:`wall_layer_arclength`: the
    tiles ``lo <= t < hi``, tile ``t``: the plane ``t // nt`` of the third direction and the
    tile ``t % nt`` of TILE lines i (as :func:`_layer_dir_jk`); compiled once per direction,
    with the direction a constant, so the index arithmetic folds away.  (The tile is a loop
    of this kernel, not a compiled function of its own: one compiled level fewer.)"""
    ni = xyz.shape[0]
    nt = (ni + TILE - 1) // TILE
    axis = 2 if kdir is not None else 1
    n = xyz.shape[axis]
    for t in range(lo, hi):
        c = t // nt
        i0 = (t % nt) * TILE
        nw = min(TILE, ni - i0)
        u0 = np.uint64(i0)
        if n == 1:
            for w in range(nw):
                i, j, k = line_point(axis, at(u0, w), n - 1, c)
                out[i, j, k, axis] = 0.0
            continue
        cum = np.empty((n, nw))
        col = np.empty((n, nw))
        ln = np.empty(nw)
        den = np.empty(nw)
        arc_tile(xyz, rtol, axis, u0, nw, c, cum, ln, den)
        _arc_tile_layer(col, cum, den, nw, ln, lam0, lam1, u0, c)
        for m in range(n):
            for w in range(nw):
                i, j, k = line_point(axis, at(u0, w), m, c)
                out[i, j, k, axis] = col[m, w]


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
        itself (each line is read before it is written).  Lines whose two
        thicknesses are <= 0 keep ``s`` and are not computed.

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
        if dims[d] == 1:                        # no lines to walk: compile nothing for them
            out[..., d] = 0.0
            continue
        others = tuple(dims[m] for m in range(3) if m != d)
        l0 = np.ascontiguousarray(lam[2 * d], dtype=np.float64).reshape(others)
        l1 = np.ascontiguousarray(lam[2 * d + 1], dtype=np.float64).reshape(others)
        by_direction(_layer_dir_i, _layer_dir_jk, d, xyz, s, l0, l1, out)
    return out


#: points of a 2-D block (nk = 1) below which :func:`wall_layer_arclength` (and so
#: :func:`tfi_quat.tfi.arclength`) computes with numpy (:func:`_arc_layer_numpy`, the same
#: values bit for bit; ~10x slower, once per block at set-up) rather than the compiled
#: kernels: a run that only meets small 2-D blocks, as the demo, does not compile them
_ARC_NUMPY_BELOW = 1 << 15


def _f_numpy(t, a):
    """:func:`_f` on arrays (``a`` > 0 where it matters); ``expm1`` is the C library's, as
    the compiled kernel's (numpy's may be a vectorised variant with other rounding)."""
    with np.errstate(all="ignore"):
        u = t / np.where(a > 0.0, a, 1.0)
    out = np.ones(np.broadcast(t, a).shape)
    far = (a <= 0.0) | (u >= EXP_CUT)
    out[~far] = [-math.expm1(-v * v) for v in np.broadcast_to(u, out.shape)[~far].tolist()]
    return out


def _arc_layer_numpy(xyz, d, rtol, lam0, lam1, out) -> None:
    """The lines of direction ``d`` (>= 2 points) of :func:`wall_layer_arclength` with numpy:
    the operations of :func:`tfi_quat.kernels.arc_line_i` and :func:`_layer_line` in the same
    order on every line at once (sums along the line sequential, as ``np.cumsum``)."""
    X = np.moveaxis(xyz, d, 0)                              # (n, A, B, 3), lam: (A, B)
    n = X.shape[0]
    dx = X[1:, :, :, 0] - X[:-1, :, :, 0]
    dy = X[1:, :, :, 1] - X[:-1, :, :, 1]
    dz = X[1:, :, :, 2] - X[:-1, :, :, 2]
    with np.errstate(all="ignore"):
        seg = np.sqrt(dx * dx + dy * dy + dz * dz)
        cum = np.cumsum(np.concatenate([np.zeros((1,) + seg.shape[1:]), seg]), axis=0)
        length = cum[n - 1].copy()
        scale = np.abs(np.concatenate([X[0], X[n - 1]], axis=-1)).max(axis=-1)
        zero = ~(length > rtol * scale)                     # NaN: zero-length, as the kernel
        cum[:, zero] = np.arange(n, dtype=np.float64)[:, None]
        s = cum / np.where(zero, n - 1.0, length)
        s[n - 1] = 1.0
    act = ~((lam0 <= 0.0) & (lam1 <= 0.0)) & (length > 0.0)
    if act.any():
        s[:, act] = _layer_numpy(s[:, act], length[act], lam0[act], lam1[act])
    np.moveaxis(out[..., d], d, 0)[...] = s


def _layer_numpy(s, length, lam0, lam1):
    """:func:`_layer_line` on the columns of ``s`` (n >= 2, L) with numpy, lines of length > 0
    with a layer (``length``, ``lam0``, ``lam1``: (L,), not NaN): the same operations in the
    same order (the trapezoid sums sequential, as ``np.cumsum``); returns the (n, L) parameters."""
    n = s.shape[0]
    with np.errstate(all="ignore"):
        a0 = np.minimum(lam0 / length, AMAX)
        a1 = np.minimum(lam1 / length, AMAX)
        gp = _f_numpy(s, a0) * _f_numpy(1.0 - s, a1)
        terms = 0.5 * (gp[1:] + gp[:-1]) * (s[1:] - s[:-1])
        acc = np.cumsum(np.concatenate([np.zeros((1,) + terms.shape[1:]), terms]), axis=0)
        pos = acc[n - 1] > 0.0
        acc[1:n - 1] *= 1.0 / np.where(pos, acc[n - 1], 1.0)
        acc[n - 1] = 1.0
        return np.where(pos, acc, s)


def wall_layer_arclength(xyz, lam, ndim: int = 3, *, rtol: float = ZERO_LENGTH_RTOL, out=None) -> np.ndarray:
    """:func:`tfi_quat.tfi.arclength` and :func:`wall_layer_block` in one pass over the block.

    Bit for bit ``wall_layer_block(xyz, s, lam, ndim, out=s)`` with
    ``s = tfi.arclength(xyz, rtol=rtol)``, without storing ``s`` or reading
    ``xyz`` again for the line lengths: each line's arclength is computed as
    ``arclength`` computes it and its wall-layer parameters are taken from it
    while it is in cache.

    Parameters
    ----------
    xyz : ndarray, shape (ni, nj, nk, 3), float64, Fortran order
        Undeformed coordinates (``Block.xyz``; a patch as ``(na, nb, 1, 3)`` with ``ndim=2``).
    lam : sequence of ``2 * ndim`` arrays
        Layer thicknesses, as for :func:`wall_layer_block`.
    ndim : {2, 3}
        Directions that get a layer (the others keep the arclength).
    rtol : float
        Zero-length tolerance of :func:`tfi_quat.tfi.arclength`.
    out : ndarray, optional
        Receives the result (float64, Fortran order, the shape of ``xyz``).

    Returns
    -------
    ndarray, shape (ni, nj, nk, 3), float64, Fortran order
    """
    check_xyz(xyz, "xyz")
    if len(lam) != 2 * ndim:
        raise GridValueError(f"lam: expected {2 * ndim} face arrays, got {len(lam)}")
    if out is None:
        out = np.empty(xyz.shape, dtype=S_DTYPE, order="F")
    elif out.shape != xyz.shape or out.dtype != S_DTYPE or not out.flags.f_contiguous:
        raise GridValueError(f"out: expected a float64 Fortran-order array of shape {xyz.shape}")
    dims = xyz.shape[:3]
    small = (dims[2] == 1 and dims[0] * dims[1] < _ARC_NUMPY_BELOW
             and not any(np.isnan(a).any() for a in lam[:2 * ndim]))
    for d in range(3):
        if dims[d] == 1:                        # one point per line: the parameter is 0, and
            out[..., d] = 0.0                   # a 2-D run compiles no kernel for it
            continue
        others = tuple(dims[m] for m in range(3) if m != d)
        if d < ndim:
            l0 = np.ascontiguousarray(lam[2 * d], dtype=np.float64).reshape(others)
            l1 = np.ascontiguousarray(lam[2 * d + 1], dtype=np.float64).reshape(others)
        else:                                   # no layer: the arclength itself
            l0 = l1 = np.zeros(others)
        if small:
            _arc_layer_numpy(xyz, d, float(rtol), l0, l1, out)
        else:
            by_direction(_arc_layer_i, _arc_layer_jk, d, xyz, float(rtol), l0, l1, out)
    return out
