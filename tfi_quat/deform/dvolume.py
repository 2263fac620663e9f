"""Derivatives of a Deformer step: the work behind :meth:`Deformer.jvp` and :meth:`Deformer.vjp`.

A step maps the wall targets ``rd`` (the boundary level, :mod:`.dskeleton`) to the
volume passes ``(Δ or K, Q, centre, base tables)`` and the boundary positions ``pos``,
then each block through its passes (:func:`tfi_quat.tfi.deform_block_gathered`) and
the scatter of ``pos`` into every boundary copy.  Here: the user's inputs mapped to and
from the tangent ``drd`` of ``rd`` (:meth:`Deformer.surface_ids` order or ``ids``; only
the first copy of a point counts, as in :meth:`Deformer.deform`), and the volume level
block by block with the kernels of :mod:`tfi_quat.dtfi`.

Memory: the linearisation keeps O(surface) arrays (the passes and the boundary level's
chain); a block's first pass is recomputed when its second one needs it, in one scratch
array the size of the block, so nothing the size of the grid is kept.
"""

from __future__ import annotations

import numpy as np

from .. import dtfi, tfi
from .._jit import jit, serial_below
from ..errors import DeformationError
from . import buffers

__all__ = ["tangent_targets", "surface_bar", "volume_jvp", "volume_vjp"]


def tangent_targets(deformer, dxs, ids) -> np.ndarray:
    """The tangent ``drd`` (G, 3) of the global wall targets for the rows ``dxs`` (n, 3)."""
    a = np.asarray(dxs)
    if a.ndim != 2 or a.shape[1] != 3:
        raise DeformationError(f"dxs must have shape (n, 3), got {a.shape}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise DeformationError(f"dxs must hold real numbers, got dtype {a.dtype}")
    a = np.asarray(a, dtype=np.float64)
    walls = deformer.walls
    _, gid = walls.rows(ids, a.shape[0], "dxs")
    bad = ~np.isfinite(a)
    if bad.any():
        r = int(np.flatnonzero(bad.any(axis=1))[0])
        raise DeformationError(f"dxs row {r} is not finite ({int(bad.any(axis=1).sum())} such "
                               f"row(s))")
    first = walls.first_rows(gid)
    walls.check_covered(gid[first], "dxs")
    drd = np.zeros((deformer.n_global, 3))
    drd[gid[first]] = a[first]
    if deformer.ndim == 2 and np.any(drd[:, 2] != 0.0):
        raise DeformationError("the tangents of a 2-D grid's wall points must have z = 0")
    return drd


def surface_bar(deformer, rd_bar: np.ndarray) -> np.ndarray:
    """``rd_bar`` (G, 3) as rows in :meth:`Deformer.surface_ids` order: the first copy of a
    point gets its value, the other copies 0."""
    _, gid = deformer.walls.surface()
    first = deformer.walls.first_rows(gid)
    out = np.zeros((gid.shape[0], 3))
    out[first] = rd_bar[gid[first]]
    if deformer.ndim == 2:
        out[:, 2] = 0.0
    return out


def _fail_fallback(b: int, n: int):
    raise DeformationError(
        f"block {b} (0-based): {n} point(s) where the blended rotation takes the rotation-vector "
        f"fallback (|Q| < QNORM_MIN, rotations near 180 degrees apart): the derivatives do not "
        f"cover that path")


def volume_jvp(deformer, passes, tangents, dpos, out) -> list:
    """The volume level's tangent: per block its passes' tangents, then ``dpos`` into every
    boundary copy.  ``out``: :func:`buffers.check_out` buffers, or None (new arrays)."""
    sk = deformer.skeleton
    grid = deformer.grid
    dests = None if out is None else buffers.check_out(grid, out)
    npass = len(passes)
    scratch = None
    if npass > 1:
        scratch = np.empty(3 * max(blk.npoints for blk in grid))
    result = []
    for b, blk in enumerate(grid):
        dest = None if dests is None else dests[b]
        if dest is not None and buffers.is_kernel_array(dest):
            dst = dest
        else:
            dst = np.empty_like(blk.xyz, order="F")
        plan = sk.blocks[b]
        # the passes' results in one scratch (each pass in place on the previous one), their
        # tangents in dst (likewise in place): both point for point
        cur = dst if scratch is None else \
            scratch[:3 * blk.npoints].reshape(blk.xyz.shape, order="F")
        base, dbase = blk.xyz, None
        with serial_below(blk.npoints):
            for (gd, gq, c, tables), (dgd, dgq) in zip(passes, tangents):
                nbad = dtfi.volume_jvp(plan.gather, base, plan.s, gd, gq, dgd, dgq, c, cur, dst,
                                       base=None if tables is None else tables[b], dxyz=dbase)
                if nbad:
                    _fail_fallback(b, nbad)
                base, dbase = cur, dst
        local, gid = sk.scatter[b]
        dst.reshape(-1, 3, order="F")[local] = dpos[gid]
        if sk.ndim == 2:
            dst[..., 2] = 0.0
        if dest is not None and dst is not dest:
            buffers.copy_out(dst, dest)
        result.append(dst if dest is None else dest)
    return result


@jit
def _copy_tiled(src, dst):
    """``dst[...] = src`` for 3-D arrays of one shape, ``dst`` Fortran-ordered and ``src`` of any
    layout, in tiles of 32 x 32 points of each (i, k) plane: a bar in C order (a solver's
    own arrays) copied by numpy ran at a sixth of the speed of a Fortran one."""
    ni, nj, nk = src.shape
    for j in range(nj):
        for k0 in range(0, nk, 32):
            k1 = min(k0 + 32, nk)
            for i0 in range(0, ni, 32):
                i1 = min(i0 + 32, ni)
                for k in range(k0, k1):
                    for i in range(i0, i1):
                        dst[i, j, k] = src[i, j, k]


def _copy_part(part, dst):
    """One component of a bar into the kernel's Fortran buffer ``dst``."""
    if part.flags.f_contiguous:
        dst[...] = part
    else:
        _copy_tiled(np.asarray(part, dtype=np.float64), dst)


def volume_vjp(deformer, passes, dxv) -> tuple:
    """The volume level's adjoint: for the bars ``dxv`` of every block (any layout
    :meth:`Deformer.deform` writes), the bars of the passes ``[(D_bar, Q_bar), ...]`` and of
    the boundary positions ``pos_bar`` (G, 3)."""
    sk = deformer.skeleton
    grid = deformer.grid
    bars_in = buffers.layout(grid, dxv, "dxv")
    G = deformer.n_global
    pass_bars = [(np.zeros((G, 3)), None if gq is None else np.zeros((G, 4)))
                 for _, gq, _, _ in passes]
    pos_bar = np.zeros((G, 3))
    nmax = 3 * max(blk.npoints for blk in grid)
    buf_o = np.empty(nmax)
    buf_r = np.empty(nmax) if len(passes) > 1 else None
    for b, blk in enumerate(grid):
        shape = blk.xyz.shape
        ob = buf_o[:3 * blk.npoints].reshape(shape, order="F")
        src = bars_in[b]
        for c, part in enumerate(buffers.parts(src)):
            _copy_part(part, ob[..., c])
        if not np.isfinite(np.sum(ob)) and not np.all(np.isfinite(ob)):    # (sum: no temporary)
            raise DeformationError(f"dxv[{b}] holds non-finite values")
        if sk.ndim == 2:
            ob[..., 2] = 0.0
        flat = ob.reshape(-1, 3, order="F")
        local, gid = sk.scatter[b]
        np.add.at(pos_bar, gid, flat[local])
        flat[local] = 0.0
        plan = sk.blocks[b]
        with serial_below(blk.npoints):
            # the bases of the passes: the reference, then (two passes) the first one's result
            bases = [blk.xyz]
            if len(passes) > 1:
                gd, gq, c, tables = passes[0]
                r1 = buf_r[:3 * blk.npoints].reshape(shape, order="F")
                tfi.deform_block_gathered(blk.xyz, plan.s, gd, gq, plan.gather, c, out=r1,
                                          base=None if tables is None else tables[b])
                bases.append(r1)
            for p in range(len(passes) - 1, -1, -1):
                gd, gq, c, tables = passes[p]
                db, qb = pass_bars[p]
                nbad = dtfi.volume_vjp(plan.gather, bases[p], plan.s, gd, gq, c, ob, db, qb,
                                       base=None if tables is None else tables[b],
                                       xbar=ob if p > 0 else None)
                if nbad:
                    _fail_fallback(b, nbad)
    return pass_bars, pos_bar
