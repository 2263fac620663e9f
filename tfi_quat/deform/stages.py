"""The Deformer's compiled stages: numba kernels on the global boundary arrays.

Each kernel works on the arrays of one hierarchy level (the gaps of the
segments, the derived patches, the symmetry points, the wall halos) and
neither validates nor raises.  Below them, one thin driver per level
(:func:`vertex_stage`, :func:`segment_stage`, :func:`patch_stage`,
:func:`symmetry_stage`, :func:`wall_quaternions`, :func:`volume`) calls them
on a :class:`~.skeleton.Skeleton`; the Deformer front validates the user's
input before any of them runs.
"""

from __future__ import annotations

import math

import numpy as np

from .. import quaternion as qa
from .. import kernels, tfi
from .._jit import jit, parallel_for, serial_below, task_jit

@task_jit
def hermite_kernel(lo, hi, s):
    """``s <- 3 s^2 - 2 s^3`` in place on the items ``lo <= m < hi`` of a flat array, the sums
    of the numpy form."""
    for m in range(lo, hi):
        x = s[m]
        s[m] = (x * -2.0 + 3.0) * (x * x)


def hermite(s: np.ndarray) -> np.ndarray:
    """In place: s -> 3 s^2 - 2 s^3 (0 and 1 stay exact, zero slope at both ends)."""
    if s.flags.f_contiguous or s.flags.c_contiguous:
        flat = s.reshape(-1, order="F" if s.flags.f_contiguous else "C")
        with serial_below(flat.size):
            parallel_for(hermite_kernel, flat.size, flat)
        return s
    s2 = s * s
    s *= -2.0
    s += 3.0
    s *= s2
    return s



@jit(inline="always")
def fade_and_rebase(q, f, shift, k, r):
    """Two-level: ``q <- slerp(1, q, f)`` in place (exact at f = 0 and 1) and ``k += rot(q, shift)``
    (``k``, ``shift``: rows of K and of the re-basing shifts)."""
    if f <= 0.0:
        q[0] = 1.0
        q[1] = q[2] = q[3] = 0.0
    elif f < 1.0:
        # slerp(1, q, f) along the short arc, with the volume kernels' polynomial weights
        sg = -1.0 if q[0] < 0.0 else 1.0
        w2, sw = kernels.slerp_angle(1.0, 0.0, 0.0, 0.0, sg * q[0], sg * q[1], sg * q[2], sg * q[3])
        wa, wb = kernels.slerp_weights(f, w2, sw)
        wb *= sg
        q[0] = wa + wb * q[0]
        for c in range(1, 4):
            q[c] = wb * q[c]
    if shift[0] != 0.0 or shift[1] != 0.0 or shift[2] != 0.0:
        qa.krotate(q, shift, r)
        for c in range(3):
            k[c] += r[c]


@jit
def fill_gaps(K, gq, left, right, ptr, pts, s, use_q, damp, shift):
    """Segments, gap by gap (a gap's ends may be points of earlier gaps): K linear and Q
    slerp in the blending parameter between the known end points.

    The two-level formulation also passes ``damp`` and ``shift`` (length G; empty
    otherwise): Q is then faded towards 1 by ``damp`` and K re-based by ``rot(Q, shift)``.
    """
    local = damp.shape[0] > 0
    tmp = np.empty(4)
    r = np.empty(3)
    for g in range(left.shape[0]):
        a = left[g]
        b = right[g]
        for m in range(ptr[g], ptr[g + 1]):
            p = pts[m]
            t = s[m]
            for c in range(3):
                K[p, c] = (1.0 - t) * K[a, c] + t * K[b, c]
            if not use_q:
                continue
            qa.kslerp(gq[a], gq[b], t, tmp)
            if local:
                fade_and_rebase(tmp, damp[p], shift[p], K[p], r)
            for c in range(4):
                gq[p, c] = tmp[c]


@jit
def merge_quaternions(gid, q, acc, count):
    """Hemisphere-aligned sum of the quaternions given for each global point."""
    for n in range(gid.shape[0]):
        g = gid[n]
        if count[g] == 0:
            for c in range(4):
                acc[g, c] = q[n, c]
        else:
            d = acc[g, 0] * q[n, 0] + acc[g, 1] * q[n, 1] + acc[g, 2] * q[n, 2] + acc[g, 3] * q[n, 3]
            sg = 1.0 if d >= 0.0 else -1.0
            for c in range(4):
                acc[g, c] += sg * q[n, c]
        count[g] += 1


@jit
def rebase_gaps(c, left, right, ptr, pts, s, target, shift):
    """Set-up twin of the two-level :func:`fill_gaps` for the centres: interpolate, then re-base."""
    for g in range(left.shape[0]):
        a = left[g]
        b = right[g]
        for m in range(ptr[g], ptr[g + 1]):
            p = pts[m]
            t = s[m]
            for k in range(3):
                ci = (1.0 - t) * c[a, k] + t * c[b, k]
                shift[p, k] = target[p, k] - ci
                c[p, k] = target[p, k]


@jit
def positions_local(K, gq, A, idx, pos):
    """``pos[p] = K[p] + rot(q[p], A[p])`` for the listed points."""
    r = np.empty(3)
    for m in range(idx.shape[0]):
        p = idx[m]
        qa.krotate(gq[p], A[p], r)
        for c in range(3):
            pos[p, c] = K[p, c] + r[c]


@jit
def positions_global(gdelta, gq, centre, idx, pos):
    """In place, for the listed points: ``pos = c + Δ + rot(q, pos - c)``."""
    v = np.empty(3)
    r = np.empty(3)
    for m in range(idx.shape[0]):
        p = idx[m]
        for c in range(3):
            v[c] = pos[p, c] - centre[c]
        qa.krotate(gq[p], v, r)
        for c in range(3):
            pos[p, c] = centre[c] + gdelta[p, c] + r[c]


@jit
def blend_rows(P, foot, w, out):
    """``out[p] = w[p] P[foot[p]] + (1 - w[p]) P[p]`` (the sums of the numpy form)."""
    for p in range(P.shape[0]):
        f = foot[p]
        for c in range(3):
            out[p, c] = w[p] * P[f, c] + (1.0 - w[p]) * P[p, c]


@jit
def halo_points(X, hidx, mirror, po, pn, out):
    """``out[h] = X[hidx[h]]``, mirrored across plane ``mirror[h]`` (``po``, ``pn``: plane
    points and unit normals) where that is >= 0, NaN where ``hidx[h] < 0``."""
    for h in range(hidx.shape[0]):
        g = hidx[h]
        if g < 0:
            for c in range(3):
                out[h, c] = np.nan
            continue
        for c in range(3):
            out[h, c] = X[g, c]
        s = mirror[h]
        if s >= 0:
            d = 0.0
            for c in range(3):
                d += (out[h, c] - po[s, c]) * pn[s, c]
            for c in range(3):
                out[h, c] -= 2.0 * d * pn[s, c]


@jit
def scatter_rows(src, gid, local, dst):
    """``dst[local[m]] = src[gid[m]]`` (dst: a block's points as (n, 3), any layout)."""
    for m in range(gid.shape[0]):
        g = gid[m]
        r = local[m]
        for c in range(3):
            dst[r, c] = src[g, c]


@jit(inline="always")
def lm_flat(lead, nb, l, m):
    """Flat (C order) position in an (na, nb) patch of the point ``l`` along the leading
    direction on line ``m``."""
    if lead == 0:
        return l * nb + m
    return m * nb + l


@jit(inline="always")
def patch_tables(gd, gq, use_q, off, nb, lead, nl, nm, gidf, sf, lineD, lineQ, resD, resQ, fb):
    """One patch's tables: per line of the leading direction its end values, aligned end
    quaternions and slerp angle; per point of the two other sides the residuals F - U."""
    for m in range(nm):
        g0 = gidf[off + lm_flat(lead, nb, 0, m)]
        g1 = gidf[off + lm_flat(lead, nb, nl - 1, m)]
        for c in range(3):
            lineD[m, 0, c] = gd[g0, c]
            lineD[m, 0, 3 + c] = gd[g1, c]
        if use_q:
            lq = lineQ[m, 0]
            # the lines' first ends in one hemisphere, neighbour to neighbour (as tfi's
            # _coherent does for the leading face), then each second end aligned to its first
            s0 = 1.0
            if m > 0:
                d = lineQ[m - 1, 0, 0] * gq[g0, 0] + lineQ[m - 1, 0, 1] * gq[g0, 1] + \
                    lineQ[m - 1, 0, 2] * gq[g0, 2] + lineQ[m - 1, 0, 3] * gq[g0, 3]
                if d < 0.0:
                    s0 = -1.0
            for c in range(4):
                lq[c] = s0 * gq[g0, c]
            d = lq[0] * gq[g1, 0] + lq[1] * gq[g1, 1] + lq[2] * gq[g1, 2] + lq[3] * gq[g1, 3]
            sg = -1.0 if d < 0.0 else 1.0
            for c in range(4):
                lq[4 + c] = sg * gq[g1, c]
            w2, sw = kernels.slerp_angle(lq[0], lq[1], lq[2], lq[3], lq[4], lq[5], lq[6], lq[7])
            lq[8] = w2
            lq[9] = sw
    for side in range(2):
        m = 0 if side == 0 else nm - 1
        for l in range(nl):
            f = off + lm_flat(lead, nb, l, m)
            g = gidf[f]
            t = sf[f, lead]
            x, y, z = kernels.u_d(lineD, m, 0, t)
            rd = resD[l, 0]
            rd[3 * side] = gd[g, 0] - x
            rd[3 * side + 1] = gd[g, 1] - y
            rd[3 * side + 2] = gd[g, 2] - z
            if use_q:
                qw, qx, qy, qz = kernels.u_q(lineQ, m, 0, t)
                d = qw * gq[g, 0] + qx * gq[g, 1] + qy * gq[g, 2] + qz * gq[g, 3]
                sg = -1.0 if d < 0.0 else 1.0
                rq = resQ[l, 0]
                o = 4 * side
                rq[o] = sg * gq[g, 0] - qw
                rq[o + 1] = sg * gq[g, 1] - qx
                rq[o + 2] = sg * gq[g, 2] - qy
                rq[o + 3] = sg * gq[g, 3] - qz
                n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
                fl = fb[l, 0]
                o = 8 * side
                fl[o] = qw / n
                fl[o + 1] = qx / n
                fl[o + 2] = qy / n
                fl[o + 3] = qz / n
                for c in range(4):
                    fl[o + 4 + c] = sg * gq[g, c]


def patch_level(gd, gq, use_q, meta, gidf, sf, wf, tasks, work, damp, shift):
    """Every derived patch of one level: 2-D Soni TFI of (Δ, Q) from the patch's four
    sides, read from and written to the global arrays ``gd`` (G, 3), ``gq`` (G, 4).

    ``meta[p] = (offset, na, nb, lead, line offset, side offset)``; ``gidf``, ``sf``
    (n, 2), ``wf``: the patches' global ids, blending parameters and write flags, flat
    in C order; ``tasks`` (T, 2): (patch, line) of every interior line; ``work``: the
    tables (:func:`level_pack`).  The formulas are
    :func:`tfi_quat.tfi.tfi_patch_fast`'s (slerp along the leading direction,
    hemisphere-aligned residuals of the two other sides, normalised; the
    rotation-vector blend where the norm falls below ``QNORM_MIN``).  Patches only read
    their sides, which earlier levels define, so the tables come first (serially,
    O(perimeter): :func:`level_tables`) and then the interior lines on the threads
    (:func:`patch_lines`).  ``damp``/``shift`` (two-level, length G; else empty): Q is
    faded and K re-based as in :func:`fill_gaps`.
    """
    level_tables(gd, gq, use_q, meta, gidf, sf, work)
    parallel_for(patch_lines, tasks.shape[0], gd, gq, use_q, meta, gidf, sf, wf, tasks, work,
                 damp, shift)


@jit
def level_tables(gd, gq, use_q, meta, gidf, sf, work):
    """The tables of every patch of a level (:func:`patch_tables`), serially."""
    lineD, lineQ, resD, resQ, fb = work
    for p in range(meta.shape[0]):
        off, na, nb, lead, lo, ro = meta[p, 0], meta[p, 1], meta[p, 2], meta[p, 3], meta[p, 4], \
            meta[p, 5]
        nl, nm = (na, nb) if lead == 0 else (nb, na)
        patch_tables(gd, gq, use_q, off, nb, lead, nl, nm, gidf, sf, lineD[lo:lo + nm],
                      lineQ[lo:lo + nm], resD[ro:ro + nl], resQ[ro:ro + nl], fb[ro:ro + nl])


@task_jit
def patch_lines(lo, hi, gd, gq, use_q, meta, gidf, sf, wf, tasks, work, damp, shift):
    """The interior lines ``tasks[lo:hi]`` (patch, line) of :func:`patch_level`."""
    for tk in range(lo, hi):
        patch_line(gd, gq, use_q, meta, gidf, sf, wf, work, damp, shift, tasks[tk, 0], tasks[tk, 1])


@jit
def patch_line(gd, gq, use_q, meta, gidf, sf, wf, work, damp, shift, p, m):
    """Interior line ``m`` of patch ``p`` for :func:`patch_lines`."""
    lineD, lineQ, resD, resQ, fb = work
    local = damp.shape[0] > 0
    off, na, nb, lead, lo, ro = meta[p, 0], meta[p, 1], meta[p, 2], meta[p, 3], meta[p, 4], \
        meta[p, 5]
    nl, nm = (na, nb) if lead == 0 else (nb, na)
    lD = lineD[lo:lo + nm]
    lQ = lineQ[lo:lo + nm]
    rD = resD[ro:ro + nl]
    rQ = resQ[ro:ro + nl]
    fbp = fb[ro:ro + nl]
    r = np.empty(3)
    q = np.empty(4)
    nofb = np.zeros((1, 1, 16))
    for l in range(1, nl - 1):
        f = off + lm_flat(lead, nb, l, m)
        if not wf[f]:
            continue
        g = gidf[f]
        t = sf[f, lead]
        sm = sf[f, 1 - lead]
        dx, dy, dz = kernels.v_d(lD, m, 0, t, rD, l, 0, sm)
        gd[g, 0] = dx
        gd[g, 1] = dy
        gd[g, 2] = dz
        if not use_q:
            continue
        qw, qx, qy, qz = kernels.v_q(lQ, m, 0, t, rQ, l, 0, sm)
        n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if n < tfi.QNORM_MIN:
            qw, qx, qy, qz = kernels.fallback_q(lQ, m, 0, t, fbp, l, 0, sm, nofb, 0, 0, 0.0, False)
            n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        q[0] = qw / n
        q[1] = qx / n
        q[2] = qy / n
        q[3] = qz / n
        if local:
            fade_and_rebase(q, damp[g], shift[g], gd[g], r)
        for c in range(4):
            gq[g, c] = q[c]


def level_pack(patches) -> tuple:
    """Pack ``(gid (na, nb), s (na, nb, 2), lead, write (na, nb))`` patches for
    :func:`patch_level`: ``(meta, gidf, sf, wf, tasks, work)``."""
    meta = np.zeros((len(patches), 6), dtype=np.int64)
    off = lo = ro = 0
    tasks = []
    for m, (g, s, lead, w) in enumerate(patches):
        na, nb = g.shape
        nl, nm = (na, nb) if lead == 0 else (nb, na)
        meta[m] = (off, na, nb, lead, lo, ro)
        tasks += [(m, k) for k in range(1, nm - 1)]
        off += g.size
        lo += nm
        ro += nl
    cat = lambda xs, sh, dt: np.ascontiguousarray(np.concatenate(xs) if xs else np.zeros(sh, dt))  # noqa: E731
    work = (np.zeros((lo, 1, 6)), np.zeros((lo, 1, 10)), np.zeros((ro, 1, 6)), np.zeros((ro, 1, 8)),
            np.zeros((ro, 1, 16)))
    return (meta,
            cat([p[0].ravel() for p in patches], (0,), np.int64),
            cat([np.reshape(p[1], (-1, 2)) for p in patches], (0, 2), np.float64),
            cat([p[3].ravel() for p in patches], (0,), bool),
            np.array(tasks, dtype=np.int64).reshape(-1, 2), work)


@jit
def part_sums(P, rd, which, ptr, gids, out):
    """Per part ``m = which[k]`` (its points ``gids[ptr[m]:ptr[m + 1]]``): ``out[k] =
    (sum P, sum rd)`` over its points, in order (the first pass of the rigid fits)."""
    for k in range(which.shape[0]):
        m = which[k]
        for c in range(6):
            out[k, c] = 0.0
        for n in range(ptr[m], ptr[m + 1]):
            g = gids[n]
            for c in range(3):
                out[k, c] += P[g, c]
                out[k, 3 + c] += rd[g, c]


@jit
def part_moments(P, rd, which, ptr, gids, body, cu, cd, out):
    """Per part ``m = which[k]``: ``out[k] = sum (P - cu_b)(rd - cd_b)^T`` (row major, 9)
    over its points, in order (``b = body[m]``: the part's body, its centroids ``cu[b]``,
    ``cd[b]``; the second pass of the rigid fits)."""
    a = np.empty(3)
    for k in range(which.shape[0]):
        m = which[k]
        b = body[m]
        for c in range(9):
            out[k, c] = 0.0
        for n in range(ptr[m], ptr[m + 1]):
            g = gids[n]
            for c in range(3):
                a[c] = P[g, c] - cu[b, c]
            for i in range(3):
                for j in range(3):
                    out[k, 3 * i + j] += a[i] * (rd[g, j] - cd[b, j])


@jit
def add_parts(vals, body, out):
    """``out[body[m]] += vals[m]`` for the parts in order (the fits' fixed-order reduction)."""
    for m in range(vals.shape[0]):
        b = body[m]
        for c in range(vals.shape[1]):
            out[b, c] += vals[m, c]


@jit
def rigid_blend(phi, idx, Db, Rb, gd, gq):
    """The rigid part of the two-level formulation on the listed points (rows of ``phi``):
    ``Δ = Σ_b φ_b Δ_b`` and ``Q = exp(Σ_b φ_b v_b)`` (``v_b``: the rotation vector of body
    ``b``'s fitted rotation, ``Δ_b`` its translation in Samareh's form)."""
    nb = Db.shape[0]
    for m in range(idx.shape[0]):
        p = idx[m]
        dx = dy = dz = 0.0
        vx = vy = vz = 0.0
        for b in range(nb):
            f = phi[m, b]
            dx += f * Db[b, 0]
            dy += f * Db[b, 1]
            dz += f * Db[b, 2]
            vx += f * Rb[b, 0]
            vy += f * Rb[b, 1]
            vz += f * Rb[b, 2]
        gd[p, 0] = dx
        gd[p, 1] = dy
        gd[p, 2] = dz
        th = math.sqrt(vx * vx + vy * vy + vz * vz)
        h = 0.5 * th
        if th > 1e-8:
            f = math.sin(h) / th
        else:
            f = 0.5 - th * th / 48.0
        gq[p, 0] = math.cos(h)
        gq[p, 1] = f * vx
        gq[p, 2] = f * vy
        gq[p, 3] = f * vz


@jit
def onto_planes(pos, idx, point, normal):
    """``pos[idx[m]]`` projected onto the plane (``point[m]``, unit ``normal[m]``), in place."""
    for m in range(idx.shape[0]):
        p = idx[m]
        d = 0.0
        for c in range(3):
            d += (pos[p, c] - point[m, c]) * normal[m, c]
        for c in range(3):
            pos[p, c] -= d * normal[m, c]


@jit(forceinline=True)
def symmetry_twist(qw, qx, qy, qz, n0, n1, n2, tw):
    """The twist of Q = (qw, qx, qy, qz) about the unit normal n (its rotation about n
    only), normalised into ``tw`` (4); returns the norm before normalising (0: no twist,
    ``tw`` the identity).  The symmetry fix (:func:`symmetry_fix`) and its derivative
    (:mod:`.dskeleton`) share it."""
    u = qx * n0 + qy * n1 + qz * n2
    tw[0] = qw
    tw[1] = u * n0
    tw[2] = u * n1
    tw[3] = u * n2
    nr = math.sqrt(tw[0] * tw[0] + tw[1] * tw[1] + tw[2] * tw[2] + tw[3] * tw[3])
    if nr == 0.0:
        tw[0] = 1.0
        tw[1] = tw[2] = tw[3] = 0.0
    else:
        for c in range(4):
            tw[c] /= nr
    return nr


@jit
def symmetry_fix(F, gq, use_q, X, carm, idx, point, normal):
    """Symmetry points: on their plane, rotating about its normal only.

    The position ``carm + F + rot(q, X - carm)`` is projected onto the plane; ``q``
    is reduced to its rotation about the normal (its twist; 1 if it has none) and
    ``F`` recomputed so that the projected position is kept.  (Local fields:
    ``F = K``, ``X = A``, ``carm = 0``; Samareh's: ``F = Δ``, ``X = R_u``, ``carm = c``;
    ``use_q`` False: Q ≡ 1.)
    """
    arm = np.empty(3)
    r = np.empty(3)
    pos = np.empty(3)
    tw = np.empty(4)
    for m in range(idx.shape[0]):
        p = idx[m]
        for c in range(3):
            arm[c] = X[p, c] - carm[c]
        if use_q:
            qa.krotate(gq[p], arm, r)
        else:
            for c in range(3):
                r[c] = arm[c]
        d = 0.0
        for c in range(3):
            pos[c] = carm[c] + F[p, c] + r[c]
            d += (pos[c] - point[m, c]) * normal[m, c]
        for c in range(3):
            pos[c] -= d * normal[m, c]
        if use_q:
            symmetry_twist(gq[p, 0], gq[p, 1], gq[p, 2], gq[p, 3],
                           normal[m, 0], normal[m, 1], normal[m, 2], tw)
            for c in range(4):
                gq[p, c] = tw[c]
            qa.krotate(tw, arm, r)
        for c in range(3):
            F[p, c] = pos[c] - carm[c] - r[c]


# ----------------------------------------------------------------------------- drivers
# One call per hierarchy level on the global boundary arrays of a Skeleton
# (tfi_quat.deform.skeleton): Δ or K (G, 3) and Q (G, 4), ``gq`` None for
# translations only.

#: "no damping" / "no re-basing" for fill_gaps and patch_level
NONE = np.zeros(0)
NONE3 = np.zeros((0, 3))
_ORIGIN = np.zeros(3)
#: a derived patch point costs about as much as this many volume points (the patch
#: level runs on all threads when that work reaches tfi_quat._jit.SERIAL_BELOW)
PATCH_WORK = 8


@task_jit
def idw_rows(lo, hi, w, X, out):
    """``out[i] = sum_j w[i, j] X[j]`` for the rows ``lo <= i < hi`` (``X``: the sources'
    values, (ns, 3)), each row summed in source order: a row's bits do not depend on
    which other rows are computed (a BLAS product's do)."""
    ns = X.shape[0]
    for i in range(lo, hi):
        a0 = a1 = a2 = 0.0
        for j in range(ns):
            f = w[i, j]
            a0 += f * X[j, 0]
            a1 += f * X[j, 1]
            a2 += f * X[j, 2]
        out[i, 0] = a0
        out[i, 1] = a1
        out[i, 2] = a2


@task_jit
def idw_quaternion_rows(lo, hi, w, qs, ref, out):
    """Rows ``lo <= i < hi``: the weighted mean of the sources' quaternions ``qs`` (ns, 4),
    each aligned to the hemisphere of the row's strongest source ``qs[ref[i]]``, summed in
    source order and normalised (that source where the mean vanishes)."""
    ns = qs.shape[0]
    for i in range(lo, hi):
        r = ref[i]
        a0 = a1 = a2 = a3 = 0.0
        for j in range(ns):
            d = qs[r, 0] * qs[j, 0] + qs[r, 1] * qs[j, 1] + qs[r, 2] * qs[j, 2] + qs[r, 3] * qs[j, 3]
            f = w[i, j] if d >= 0.0 else -w[i, j]
            a0 += f * qs[j, 0]
            a1 += f * qs[j, 1]
            a2 += f * qs[j, 2]
            a3 += f * qs[j, 3]
        n = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2 + a3 * a3)
        if n < 1e-6:
            for c in range(4):
                out[i, c] = qs[r, c]
        else:
            out[i, 0] = a0 / n
            out[i, 1] = a1 / n
            out[i, 2] = a2 / n
            out[i, 3] = a3 / n


def vertex_blend(vertices, X: np.ndarray) -> np.ndarray:
    """``w @ X[src]`` (nv, 3) of the free vertices' inverse-distance weights, row by row
    (:func:`idw_rows`)."""
    src, w, _, _ = vertices.idw
    out = np.empty((w.shape[0], 3))
    with serial_below(w.size):
        parallel_for(idw_rows, w.shape[0], w, np.ascontiguousarray(X[src]), out)
    return out


def vertex_q(vertices, gq: np.ndarray, decay: np.ndarray) -> np.ndarray:
    """Quaternions of the free vertices: the hemisphere-aligned weighted mean of the sources,
    normalised (the strongest source where it vanishes), slerped from 1 by ``decay``
    (:func:`idw_quaternion_rows`: each row's bits independent of the other rows)."""
    src, w, _, ref = vertices.idw
    qbar = np.empty((w.shape[0], 4))
    with serial_below(w.size):
        parallel_for(idw_quaternion_rows, w.shape[0], w, np.ascontiguousarray(gq[src]), ref, qbar)
    ident = np.zeros_like(qbar)
    ident[:, 0] = 1.0
    return qa.slerp(ident, qbar, decay)


def vertex_stage(sk, gdelta: np.ndarray, gq: np.ndarray | None) -> None:
    """The free vertices: inverse-distance blend of the wall sources, decaying to fixed points."""
    if sk.vertices.idw is None:
        return
    _, _, decay, _ = sk.vertices.idw
    free = sk.vertices.free
    gdelta[free] = decay[:, None] * vertex_blend(sk.vertices, gdelta)
    if gq is not None:
        gq[free] = vertex_q(sk.vertices, gq, decay)


def segment_stage(sk, gdelta: np.ndarray, gq: np.ndarray | None) -> None:
    """The segments' gaps (:func:`fill_gaps`)."""
    if sk.segments is None:
        return
    fill_gaps(gdelta, gq if gq is not None else np.empty((1, 4)), *sk.segments.arrays(),
              gq is not None, NONE, NONE3)


def patch_stage(sk, gdelta: np.ndarray, gq: np.ndarray | None, damp: np.ndarray = NONE,
                shift: np.ndarray = NONE3) -> None:
    """The derived patches (:func:`patch_level`); ``damp``/``shift``: the two-level fade and
    re-basing."""
    meta, gidf, sf, wf, tasks, work = sk.patches.pack
    if tasks.shape[0] == 0:                 # no interior lines (a 2-D grid): nothing is written,
        return                              # and patch_level is not compiled for nothing
    use_q = gq is not None
    gqa = gq if use_q else np.empty((1, 4))
    with serial_below(PATCH_WORK * sk.patches.npoints):
        patch_level(gdelta, gqa, use_q, *sk.patches.pack, damp, shift)


def symmetry_stage(sk, gdelta: np.ndarray, gq: np.ndarray | None, centre: np.ndarray) -> None:
    """Symmetry points of Samareh's fields (:func:`symmetry_fix`): on their plane, rotating
    about its normal only."""
    sym = sk.symmetry
    if sym.gids.size:
        use_q = gq is not None
        symmetry_fix(gdelta, gq if use_q else np.empty((1, 4)), use_q, sk.points.P,
                     centre if use_q else _ORIGIN, sym.gids, sym.point, sym.normal)


def onto_symmetry(sk, pos: np.ndarray) -> None:
    """The symmetry points of the global array ``pos`` (G, 3) projected onto their planes,
    in place."""
    onto_planes(pos, sk.symmetry.gids, sk.symmetry.point, sk.symmetry.normal)


def wall_quaternions(sk, rd: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Merged boundary quaternions ``(n_wall, 4)`` of the wall points moved to ``rd`` (G, 3)."""
    with serial_below(sk.points.wall.size):
        return _wall_quaternions(sk, rd, centre)


def _wall_quaternions(sk, rd, centre):
    return merge_wall_quaternions(sk, patch_quaternions(sk, rd, centre, range(len(sk.walls.patches))))


def patch_quaternions(sk, rd: np.ndarray, centre: np.ndarray, which) -> list:
    """The boundary quaternions ``(n, 4)`` of the wall patches ``which`` (indices into
    ``sk.walls.patches``) moved to ``rd`` (G, 3), each patch's own (not merged)."""
    from ..boundary import motion_padded
    curve = sk.ndim == 2
    e = np.array([0.0, 0.0, 1.0]) if curve else np.zeros(3)
    out = []
    for m in which:
        w = sk.walls.patches[m]
        pd = np.empty_like(w.pu)
        halo_points(rd, w.halo.ravel(), w.mirror.ravel(), sk.points.plane_o, sk.points.plane_n,
                    pd.reshape(-1, 3))
        na = pd.shape[0] - 2
        nb = 1 if curve else pd.shape[1] - 2
        q, _ = motion_padded(w.pu, pd, 1, 0 if curve else 1, curve, e, centre, na, nb)
        out.append(q.reshape(-1, 4))
    return out


def merge_wall_quaternions(sk, qs) -> np.ndarray:
    """The merged wall quaternions ``(n_wall, 4)`` from every wall patch's own (``qs``, in the
    order of ``sk.walls.patches``)."""
    nw = sk.points.wall.size
    acc = np.zeros((nw, 4))
    count = np.zeros(nw, dtype=np.int64)
    for q, lid in zip(qs, sk.walls.local):
        merge_quaternions(lid, q, acc, count)
    acc /= np.linalg.norm(acc, axis=1, keepdims=True)
    return acc


def merge_plan(sk, rows) -> tuple:
    """What :func:`merge_wall_rows` needs to merge the wall quaternions at the wall points
    ``rows`` only (indices into the wall points): ``(rows, [(patch, positions in it, their
    wall indices)])`` for the patches holding one of them."""
    rows = np.asarray(rows, dtype=np.int64)
    mask = np.zeros(sk.points.wall.size, dtype=bool)
    mask[rows] = True
    plan = []
    for m, lid in enumerate(sk.walls.local):
        pos = np.flatnonzero(mask[lid])
        if pos.size:
            plan.append((m, pos, np.ascontiguousarray(lid[pos])))
    return rows, plan


def merge_wall_rows(plan, qs, acc, count) -> np.ndarray:
    """:func:`merge_wall_quaternions` at the rows of ``plan`` (:func:`merge_plan`) only, into
    the buffers ``acc`` (n_wall, 4; its other rows are left as they are) and ``count``.  A
    point's merge runs over the patches in order whatever the other points, so its bits are
    those of the whole merge."""
    rows, parts = plan
    count[rows] = 0
    for m, pos, lid in parts:
        merge_quaternions(lid, np.ascontiguousarray(qs[m][pos]), acc, count)
    acc[rows] /= np.linalg.norm(acc[rows], axis=1, keepdims=True)
    return acc


def volume(sk, grid, b, base, gdelta, gq, centre, out, base_tables=None) -> None:
    """Fused TFI kernel of block ``b``: ``out = centre + Δ + rot(Q, base - centre)`` (``out``:
    a Fortran-ordered (ni, nj, nk, 3) array; it may be ``base``).

    The face values are read from the global boundary arrays through the block's
    :func:`tfi.gather_plan` (no per-face copies).  ``base_tables``: the base point is
    ``base + TFI(-c)`` (the two-level arms).
    """
    plan = sk.blocks[b]
    with serial_below(grid[b].npoints):
        tfi.deform_block_gathered(base, plan.s, gdelta, gq, plan.gather, centre, out=out,
                                  base=base_tables)
