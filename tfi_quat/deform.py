"""The multiblock Deformer: the skeleton hierarchy of DESIGN 3.3.

Set-up (once per grid, :class:`Deformer`):

1. Every boundary point of every block is numbered; points that coincide
   (point-matched interfaces, self-matching cuts, collapsed faces and poles)
   are merged into one **global boundary point**.  All derived data lives on
   global points, so it is computed once and every copy of a point, on any
   block, gets bit-identical values (DESIGN 3.7).
2. Each global point gets a kind from the patches on it: wall beats fixed
   beats symmetry beats derived.
3. The faces are cut into rectangles: the patches and the interface ranges
   (the master of each interface; its slave is the same global points).
   Their corners are the **vertices**, their sides the **segments**.
4. What every level needs is precomputed: inverse-distance weights of the free
   vertices, the gaps of each segment with their blending parameters, the
   parameters and leading direction of each derived patch, the parameters and
   direction order of each block and, for the two-level formulation, the
   rotation arms of every level (in the volumes as O(surface) tables the
   kernel evaluates them from) and the weights of each wall body's rigid
   motion on the derived boundary points.

Formulations (``docs/deformer.md`` has the derivation and the measurements):

``"two-level"`` (default)
    The wall motion of each wall body is split into the rigid motion that
    fits it best and a residual deformation.  The residual moves the grid by
    ``R_d = K(x) + rot(Q(x), A(x))`` with ``K``, ``Q`` interpolated from the
    boundaries and ``A`` the arm of each point from an interpolated centre
    field that sits on the wall next to walls and on the point itself away
    from them; the blending is flat over a wall layer of thickness
    ``rotation_length``, so the residual rotations act only there.  The rigid
    part is then applied to the whole field in Samareh's form with uniform
    wall data.  Rigid motions are reproduced exactly, near-wall grid lines
    turn with the wall, and small irregularities of the fitted wall rotations
    are not carried over long lever arms into thin far-field cells.
``"samareh"``
    The memo's update ``R_d = c + Δ(x) + rot(Q(x), R_u - c)``, Δ and Q
    interpolated from the boundaries (Hermite blending by default).

``method="tfi"`` is the classic baseline: the same hierarchy with Q ≡ 1 and Δ
the displacement.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np

from . import quaternion as qa
from . import kernels, tfi
from ._jit import jit, pjit, prange, serial_below
from .blending import wall_layer_arclength, wall_layer_line
from .errors import CaseError, DeformationError
from .fit import constrain_to_planes, fit_rigid
from .grid import FACES, Block, Grid
from .spec import PatchSpec, as_patch_specs, parse_patch_spec

__all__ = ["Deformer", "rigid_motion", "StepTimings", "deformer_from_case", "FORMULATIONS"]

WALL, FIXED, SYMMETRY, DERIVED = 3, 2, 1, 0
_ORIGIN = np.zeros(3)
_IDENT = np.array([1.0, 0.0, 0.0, 0.0])
_NONE = np.zeros(0)                 # "no damping" for _fill_gaps
_NONE3 = np.zeros((0, 3))           # "no re-basing" for _fill_gaps
#: a derived patch point costs about as much as this many volume points (the patch
#: level runs on all threads when that work reaches tfi_quat._jit.SERIAL_BELOW)
_PATCH_WORK = 8

#: formulations of the quaternion method
FORMULATIONS = ("two-level", "samareh")

#: default rotation length (wall-layer thickness) as a fraction of the walls'
#: size, twice the largest distance of a wall point from the walls' centroid
#: (docs/deformer.md, "The wall layer")
ROTATION_LENGTH_FRACTION = 0.01
#: derived boundary points measure their arms from the nearest wall point with
#: weight exp(-d / (REBASE_FRACTION * rotation_length)), from themselves otherwise
REBASE_FRACTION = 0.1
#: residual rotations of derived boundary points are damped by
#: exp(-(d / (DAMP_FRACTION * rotation_length))^2) (d: distance to the walls)
DAMP_FRACTION = 4.0


@pjit
def _hermite_kernel(s):
    """``s <- 3 s^2 - 2 s^3`` in place on a flat array, the sums of the numpy form."""
    for m in prange(s.shape[0]):
        x = s[m]
        s[m] = (x * -2.0 + 3.0) * (x * x)


def _hermite(s: np.ndarray) -> np.ndarray:
    """In place: s -> 3 s^2 - 2 s^3 (0 and 1 stay exact, zero slope at both ends)."""
    if s.flags.f_contiguous or s.flags.c_contiguous:
        flat = s.reshape(-1, order="F" if s.flags.f_contiguous else "C")
        with serial_below(flat.size):
            _hermite_kernel(flat)
        return s
    s2 = s * s
    s *= -2.0
    s += 3.0
    s *= s2
    return s


_BLENDINGS = {"hermite": _hermite, "linear": lambda s: s}
_KIND_CODE = {"wall": WALL, "fixed": FIXED, "symmetry": SYMMETRY}


# ---------------------------------------------------------------- helpers
def rigid_motion(rotate_deg: float = 0.0, axis=(0.0, 0.0, 1.0), about=(0.0, 0.0, 0.0),
                 translate=(0.0, 0.0, 0.0)) -> Callable[[np.ndarray], np.ndarray]:
    """A callable moving points ``(n, 3)`` by a rotation about a point, then a translation.

    ``x -> about + rot(axis, angle)(x - about) + translate``.
    """
    axis = np.asarray(axis, dtype=np.float64)
    n = np.linalg.norm(axis)
    if not np.isfinite(n) or n == 0.0:
        raise CaseError(f"rotation axis {tuple(axis)} has no direction")
    half = math.radians(float(rotate_deg)) / 2.0
    q = np.concatenate([[math.cos(half)], axis / n * math.sin(half)])
    about = np.asarray(about, dtype=np.float64)
    translate = np.asarray(translate, dtype=np.float64)

    def move(points: np.ndarray) -> np.ndarray:
        return about + qa.rotate(q, np.asarray(points, dtype=np.float64) - about) + translate

    return move


def _face_ijk(dims, face: str, rng) -> np.ndarray:
    """Block indices (na, nb, 3) int64 of a face range ((a0, a1), (b0, b1))."""
    d, side = divmod(FACES.index(face), 2)
    (a0, a1), (b0, b1) = rng
    others = [m for m in range(3) if m != d]
    a = np.arange(a0, a1 + 1)
    b = np.arange(b0, b1 + 1)
    out = np.empty((a.size, b.size, 3), dtype=np.int64)
    out[..., d] = dims[d] - 1 if side else 0
    out[..., others[0]] = a[:, None]
    out[..., others[1]] = b[None, :]
    return out


def _flat(dims, ijk: np.ndarray) -> np.ndarray:
    ni, nj, _ = dims
    return ijk[..., 0] + ni * (ijk[..., 1] + nj * ijk[..., 2])


def _faces_of(ndim: int) -> tuple[str, ...]:
    return FACES if ndim == 3 else FACES[:4]


@dataclass
class StepTimings:
    """Seconds spent in each stage of the last :meth:`Deformer.deform` call.

    ``walls``: wall targets, rigid fits, wall quaternions; ``skeleton``:
    vertices and segments; ``faces``: patches, symmetry and boundary
    positions; ``volumes``: the block kernels and the copy of boundary points.
    """

    walls: float = 0.0
    skeleton: float = 0.0
    faces: float = 0.0
    volumes: float = 0.0

    @property
    def total(self) -> float:
        return self.walls + self.skeleton + self.faces + self.volumes


# ------------------------------------------------------------- kernels
@jit(inline="always")
def _fade_and_rebase(q, f, shift, k, one, tmp2, r):
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
def _fill_gaps(K, gq, left, right, ptr, pts, s, use_q, damp, shift):
    """Segments, gap by gap (a gap's ends may be points of earlier gaps): K linear and Q
    slerp in the blending parameter between the known end points.

    The two-level formulation also passes ``damp`` and ``shift`` (length G; empty
    otherwise): Q is then faded towards 1 by ``damp`` and K re-based by ``rot(Q, shift)``.
    """
    one = np.array([1.0, 0.0, 0.0, 0.0])
    local = damp.shape[0] > 0
    tmp = np.empty(4)
    tmp2 = np.empty(4)
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
                _fade_and_rebase(tmp, damp[p], shift[p], K[p], one, tmp2, r)
            for c in range(4):
                gq[p, c] = tmp[c]


@jit
def _merge_quaternions(gid, q, acc, count):
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
def _rebase_gaps(c, left, right, ptr, pts, s, target, shift):
    """Set-up twin of the two-level :func:`_fill_gaps` for the centres: interpolate, then re-base."""
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
def _positions_local(K, gq, A, idx, pos):
    """``pos[p] = K[p] + rot(q[p], A[p])`` for the listed points."""
    r = np.empty(3)
    for m in range(idx.shape[0]):
        p = idx[m]
        qa.krotate(gq[p], A[p], r)
        for c in range(3):
            pos[p, c] = K[p, c] + r[c]


@jit
def _positions_global(gdelta, gq, centre, idx, pos):
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
def _blend_rows(P, foot, w, out):
    """``out[p] = w[p] P[foot[p]] + (1 - w[p]) P[p]`` (the sums of the numpy form)."""
    for p in range(P.shape[0]):
        f = foot[p]
        for c in range(3):
            out[p, c] = w[p] * P[f, c] + (1.0 - w[p]) * P[p, c]


@jit
def _halo_points(X, hidx, mirror, po, pn, out):
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
def _scatter_rows(src, gid, local, dst):
    """``dst[local[m]] = src[gid[m]]`` (dst: a block's points as (n, 3), any layout)."""
    for m in range(gid.shape[0]):
        g = gid[m]
        r = local[m]
        for c in range(3):
            dst[r, c] = src[g, c]


@jit(inline="always")
def _lm_flat(lead, nb, l, m):
    """Flat (C order) position in an (na, nb) patch of the point ``l`` along the leading
    direction on line ``m``."""
    if lead == 0:
        return l * nb + m
    return m * nb + l


@jit(inline="always")
def _patch_tables(gd, gq, use_q, off, nb, lead, nl, nm, gidf, sf, lineD, lineQ, resD, resQ, fb):
    """One patch's tables: per line of the leading direction its end values, aligned end
    quaternions and slerp angle; per point of the two other sides the residuals F - U."""
    for m in range(nm):
        g0 = gidf[off + _lm_flat(lead, nb, 0, m)]
        g1 = gidf[off + _lm_flat(lead, nb, nl - 1, m)]
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
            f = off + _lm_flat(lead, nb, l, m)
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


@pjit
def _patch_level(gd, gq, use_q, meta, gidf, sf, wf, tasks, work, damp, shift):
    """Every derived patch of one level: 2-D Soni TFI of (Δ, Q) from the patch's four
    sides, read from and written to the global arrays ``gd`` (G, 3), ``gq`` (G, 4).

    ``meta[p] = (offset, na, nb, lead, line offset, side offset)``; ``gidf``, ``sf``
    (n, 2), ``wf``: the patches' global ids, blending parameters and write flags, flat
    in C order; ``tasks`` (T, 2): (patch, line) of every interior line; ``work``: the
    tables (:func:`_level_pack`).  The formulas are
    :func:`tfi_quat.tfi.tfi_patch_fast`'s (slerp along the leading direction,
    hemisphere-aligned residuals of the two other sides, normalised; the
    rotation-vector blend where the norm falls below ``QNORM_MIN``).  Patches only read
    their sides, which earlier levels define, so the tables come first (serially,
    O(perimeter)) and then the interior lines in parallel.  ``damp``/``shift``
    (two-level, length G; else empty): Q is faded and K re-based as in :func:`_fill_gaps`.
    """
    lineD, lineQ, resD, resQ, fb = work
    for p in range(meta.shape[0]):
        off, na, nb, lead, lo, ro = meta[p, 0], meta[p, 1], meta[p, 2], meta[p, 3], meta[p, 4], \
            meta[p, 5]
        nl, nm = (na, nb) if lead == 0 else (nb, na)
        _patch_tables(gd, gq, use_q, off, nb, lead, nl, nm, gidf, sf, lineD[lo:lo + nm],
                      lineQ[lo:lo + nm], resD[ro:ro + nl], resQ[ro:ro + nl], fb[ro:ro + nl])
    local = damp.shape[0] > 0
    qmin = tfi.QNORM_MIN
    for tk in prange(tasks.shape[0]):
        p = tasks[tk, 0]
        m = tasks[tk, 1]
        off, na, nb, lead, lo, ro = meta[p, 0], meta[p, 1], meta[p, 2], meta[p, 3], meta[p, 4], \
            meta[p, 5]
        nl, nm = (na, nb) if lead == 0 else (nb, na)
        lD = lineD[lo:lo + nm]
        lQ = lineQ[lo:lo + nm]
        rD = resD[ro:ro + nl]
        rQ = resQ[ro:ro + nl]
        fbp = fb[ro:ro + nl]
        one = np.array([1.0, 0.0, 0.0, 0.0])
        tmp2 = np.empty(4)
        r = np.empty(3)
        q = np.empty(4)
        nofb = np.zeros((1, 1, 16))
        for l in range(1, nl - 1):
            f = off + _lm_flat(lead, nb, l, m)
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
            if n < qmin:
                qw, qx, qy, qz = kernels.fallback_q(lQ, m, 0, t, fbp, l, 0, sm, nofb, 0, 0, 0.0, False)
                n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            q[0] = qw / n
            q[1] = qx / n
            q[2] = qy / n
            q[3] = qz / n
            if local:
                _fade_and_rebase(q, damp[g], shift[g], gd[g], one, tmp2, r)
            for c in range(4):
                gq[g, c] = q[c]


def _level_pack(patches) -> tuple:
    """Pack ``(gid (na, nb), s (na, nb, 2), lead, write (na, nb))`` patches for
    :func:`_patch_level`: ``(meta, gidf, sf, wf, tasks, work)``."""
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
def _rigid_blend(phi, idx, Db, Rb, gd, gq):
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
def _onto_planes(pos, idx, point, normal):
    """``pos[idx[m]]`` projected onto the plane (``point[m]``, unit ``normal[m]``), in place."""
    for m in range(idx.shape[0]):
        p = idx[m]
        d = 0.0
        for c in range(3):
            d += (pos[p, c] - point[m, c]) * normal[m, c]
        for c in range(3):
            pos[p, c] -= d * normal[m, c]


@jit
def _symmetry_fix(F, gq, use_q, X, carm, idx, point, normal):
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
            u = gq[p, 1] * normal[m, 0] + gq[p, 2] * normal[m, 1] + gq[p, 3] * normal[m, 2]
            tw[0] = gq[p, 0]
            for c in range(3):
                tw[1 + c] = u * normal[m, c]
            n = math.sqrt(tw[0] * tw[0] + tw[1] * tw[1] + tw[2] * tw[2] + tw[3] * tw[3])
            if n == 0.0:
                tw[0] = 1.0
                tw[1] = tw[2] = tw[3] = 0.0
            else:
                for c in range(4):
                    tw[c] /= n
            for c in range(4):
                gq[p, c] = tw[c]
            qa.krotate(tw, arm, r)
        for c in range(3):
            F[p, c] = pos[c] - carm[c] - r[c]


# ------------------------------------------------------------- set-up data
@dataclass
class _Rect:
    block: int
    face: str
    gid: np.ndarray            # (na, nb) global point ids
    kind: str                  # patch kind, or "interface"
    slave: bool = False


@dataclass
class _PatchTFI:
    gid: np.ndarray            # (na, nb)
    s: np.ndarray              # (na, nb, 2) blending parameters
    lead: int
    write: np.ndarray          # bool (na, nb): interior points this patch defines
    block: int = 0
    face: str = ""


@dataclass
class _Wall:
    spec: PatchSpec
    gid: np.ndarray            # (na, nb) or (n,) for 2-D curves
    halo: np.ndarray           # (na+2, nb+2) or (n+2,), C order, -1 where no neighbour
    mirror: np.ndarray         # same shape: symmetry plane whose mirror image of halo is used, or -1
    pu: np.ndarray | None = None   # undeformed halo points as boundary_motion takes them:
                                   # (na+2, nb+2, 3) or (n+2, 1, 3), NaN where no neighbour


@dataclass
class _BlockPlan:
    s: np.ndarray                       # blending parameters (ni, nj, nk, 3)
    order: tuple[int, ...]
    face_gid: list[np.ndarray] = field(default_factory=list)   # per face (na, nb)
    face_s: tuple | None = None         # tfi.face_params(s)
    base: tuple | None = None           # two-level: tables of TFI(-c), the arms A = R_u - TFI(c)
    gather: object = None               # tfi.gather_plan: faces read from the global arrays


@dataclass
class _Body:
    """A connected set of wall points and the rigid motions it may take."""

    gids: np.ndarray
    axis: np.ndarray | None            # allowed rotation axis (None: any; zero: none)
    tproj: np.ndarray                  # translation projection


class Deformer:
    """Deform a multiblock volume grid when its walls move.

    Parameters
    ----------
    grid : Grid
        The reference (undeformed) grid.  It is kept by reference and never
        modified; do not modify it while the Deformer is in use.
    walls, symmetry, fixed : sequence of PatchSpec or "BLOCK:FACE[:A1-A2,B1-B2]"
        Boundary patches by kind (1-based text, 0-based PatchSpec).  A whole
        face given as a wall is reduced by the interfaces on it.  Faces not
        given are ``fixed``.
    connectivity : tfi_quat.topology.Connectivity, optional
        Interfaces and patches (e.g. loaded from JSON or an ``.nmf``); found
        with :func:`tfi_quat.topology.connect` when omitted.  When given with
        ``walls``/``symmetry``/``fixed``, those kinds are applied to it.
    method : {"quaternion", "tfi"}
        ``quaternion``: interpolate translations and rotations;
        ``tfi``: the classic baseline, displacements only.
    formulation : {"two-level", "samareh"}
        How rotations act on positions (``method="quaternion"`` only); see the
        module docstring and ``docs/deformer.md``.
    centre : array_like (3,), optional
        Rotation centre ``c`` of the Samareh update (the whole update for
        ``"samareh"``, the rigid part for ``"two-level"``).  Default: the
        centroid of the undeformed wall points (it moves with the problem,
        DESIGN 3.6).
    tol : float, optional
        Coincidence tolerance for merging boundary points; default
        1e-10 x the grid's bounding-box diagonal.
    blending : {"hermite", "linear"}, optional
        Blending function of ``"samareh"`` and ``method="tfi"`` applied to the
        normalised arclength ``s``: ``hermite`` (default) ``3 s^2 - 2 s^3``,
        ``linear`` Soni's original.  The two-level formulation always uses its
        wall-layer blending (:mod:`tfi_quat.blending`).
    rotation_length : float, optional
        Two-level formulation: thickness of the wall layer in which residual
        (non-rigid) wall rotations act.  Default:
        ``ROTATION_LENGTH_FRACTION`` x the walls' size (twice the largest
        distance of a wall point from their centroid).
    idw_power : float
        Exponent of the inverse-distance weights of free vertices.
    max_idw_sources : int
        At most this many (evenly sampled) wall points serve as sources of the
        vertex blend.
    """

    def __init__(self, grid: Grid, walls=(), symmetry=(), fixed=(), connectivity=None,
                 method: str = "quaternion", formulation: str = "two-level", centre=None,
                 tol: float | None = None, blending: str | None = None,
                 rotation_length: float | None = None, idw_power: float = 3.0,
                 max_idw_sources: int = 2000):
        if not isinstance(grid, Grid):
            raise CaseError(f"grid must be a tfi_quat.Grid, got {type(grid).__name__}")
        if method not in ("quaternion", "tfi"):
            raise CaseError(f"method must be 'quaternion' or 'tfi', got {method!r}")
        if formulation not in FORMULATIONS:
            raise CaseError(f"formulation must be one of {', '.join(map(repr, FORMULATIONS))}, "
                            f"got {formulation!r}")
        two = method == "quaternion" and formulation == "two-level"
        if blending is not None and blending not in _BLENDINGS:
            raise CaseError(f"blending must be one of {', '.join(_BLENDINGS)}, got {blending!r}")
        if blending is not None and two:
            raise CaseError("blending applies to formulation='samareh' and method='tfi'; the "
                            "two-level formulation blends with its wall layer (rotation_length)")
        if rotation_length is not None:
            try:
                rotation_length = float(rotation_length)
            except (TypeError, ValueError):
                raise CaseError(f"rotation_length must be a positive number, got "
                                f"{rotation_length!r}") from None
            if not (rotation_length > 0.0 and math.isfinite(rotation_length)):
                raise CaseError(f"rotation_length must be a positive number, got {rotation_length!r}")
            if not two:
                raise CaseError("rotation_length applies to the two-level formulation only")
        t0 = time.perf_counter()
        self.grid = grid
        self.ndim = grid.ndim
        self.method = method
        self.formulation = formulation if method == "quaternion" else None
        self._use_q = method == "quaternion"
        self._two = two
        self.blending = None if two else (blending or "hermite")
        self._psi = None if two else _BLENDINGS[self.blending]
        if grid.ndim == 3:
            for b, blk in enumerate(grid):
                if min(blk.dims) < 2:
                    raise CaseError(f"block {b + 1}: a 3-D volume block needs at least 2 points in "
                                    f"each direction, got {blk.dims}")
        else:
            for b, blk in enumerate(grid):
                if min(blk.dims[:2]) < 2:
                    raise CaseError(f"block {b + 1}: a 2-D block needs at least 2 points in i and j, "
                                    f"got {blk.dims[:2]}")
        walls = as_patch_specs(walls, "walls")
        symmetry = as_patch_specs(symmetry, "symmetry")
        fixed = as_patch_specs(fixed, "fixed")
        from . import topology
        if connectivity is None:
            connectivity = topology.connect(grid, walls=walls, symmetry=symmetry, fixed=fixed)
        elif walls or symmetry or fixed:
            connectivity = topology.classify(connectivity, grid, walls=walls, symmetry=symmetry,
                                             fixed=fixed)
        self.connectivity = connectivity
        lo, hi = grid.bbox()
        diag = float(np.linalg.norm(hi - lo)) or 1.0
        self._scale = diag
        self.tol = float(tol) if tol is not None else 1e-10 * diag
        if not (math.isfinite(self.tol) and self.tol >= 0.0):
            raise CaseError(f"tol must be a finite number >= 0, got {tol!r}")
        self._number_boundary_points()
        self._classify_points()
        if not np.any(self._kind == WALL):
            raise CaseError("no wall points: give at least one wall patch")
        self.centre = self._choose_centre(centre)
        self._build_walls()
        self._build_rects()
        self.rotation_length = None
        if two:
            self._build_wall_distances(rotation_length)
        self._build_vertices(idw_power, max_idw_sources)
        self._build_segments_and_patches()
        self._build_symmetry()
        self._build_blocks()
        if two:
            self._build_bodies()
            self._build_rigid_weights()
            self._build_arms()
        self._buffers = None
        self._rd = self._y = None
        self._lock = threading.Lock()
        self.setup_seconds = time.perf_counter() - t0
        self.timings = StepTimings()

    # ------------------------------------------------------------------ set-up
    def _number_boundary_points(self) -> None:
        grid = self.grid
        keys, offsets = [], [0]
        for blk in grid:
            offsets.append(offsets[-1] + blk.npoints)
        self._offsets = np.array(offsets, dtype=np.int64)
        faces = _faces_of(self.ndim)
        full = {}
        for b, blk in enumerate(grid):
            for f in faces:
                d = FACES.index(f) // 2
                dims = blk.dims
                others = [m for m in range(3) if m != d]
                rng = ((0, dims[others[0]] - 1), (0, dims[others[1]] - 1))
                ijk = _face_ijk(dims, f, rng)
                key = self._offsets[b] + _flat(dims, ijk)
                full[(b, f)] = key
                keys.append(key.ravel())
        allkeys = np.concatenate(keys)
        total = int(self._offsets[-1])
        if total <= 32 * allkeys.size:
            # a marker per grid point beats sorting the keys (the copies of edge points)
            mark = np.zeros(total, dtype=bool)
            mark[allkeys] = True
            ukeys = np.flatnonzero(mark)
            del mark
        else:
            ukeys = np.unique(allkeys)
        nb = ukeys.size
        # coordinates of each boundary point
        P = np.empty((nb, 3))
        blk_of = np.searchsorted(self._offsets, ukeys, side="right") - 1
        for b, blk in enumerate(grid):
            sel = blk_of == b
            local = ukeys[sel] - self._offsets[b]
            P[sel] = blk.xyz.reshape(-1, 3, order="F")[local]
        # merge coincident points (interfaces, cuts, collapsed faces) ...
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components
        from ._points import close_pairs
        pairs = close_pairs(P, self.tol)
        rows = [pairs[:, 0]] if len(pairs) else []
        cols = [pairs[:, 1]] if len(pairs) else []
        # ... and the connectivity's interfaces, which are authoritative
        for itf in self.connectivity.interfaces:
            m = itf.master
            mi = _face_ijk(grid[m.block].dims, m.face, m.range).reshape(-1, 3)
            si = np.asarray(itf.slave_index(mi), dtype=np.int64).reshape(-1, 3)
            km = self._offsets[m.block] + _flat(grid[m.block].dims, mi)
            ks = self._offsets[itf.slave.block] + _flat(grid[itf.slave.block].dims, si)
            rows.append(np.searchsorted(ukeys, km))
            cols.append(np.searchsorted(ukeys, ks))
        if rows:
            r = np.concatenate(rows)
            c = np.concatenate(cols)
            graph = coo_matrix((np.ones(r.size, dtype=np.int8), (r, c)), shape=(nb, nb))
            ncomp, comp = connected_components(graph, directed=False)
        else:
            ncomp, comp = nb, np.arange(nb)
        # global ids numbered by first appearance, representatives = first member
        first = np.full(ncomp, -1, dtype=np.int64)
        order = np.arange(nb)[::-1]
        first[comp[order]] = order
        self._P = P[first]                                 # (G, 3) undeformed
        self._rep_key = ukeys[first]                       # flat key of a representative
        self.n_global = int(ncomp)
        bid_to_gid = comp.astype(np.int64)
        self._face_gid = {k: bid_to_gid[np.searchsorted(ukeys, v)] for k, v in full.items()}
        # every (block, key) copy of every global point, for the final scatter
        self._copies_key = ukeys
        self._copies_gid = bid_to_gid

    def _classify_points(self) -> None:
        G = self.n_global
        kind = np.zeros(G, dtype=np.int8)
        sym_of = np.full(G, -1, dtype=np.int64)
        self._sym_planes: list[tuple[np.ndarray, np.ndarray]] = []
        for p in self.connectivity.patches:
            code = _KIND_CODE.get(p.kind, DERIVED)
            gid = self._rect_gid(p.spec)
            if code == SYMMETRY:
                pts = self._P[gid.ravel()]
                centroid = pts.mean(axis=0)
                if self.ndim == 2:
                    # a 2-D symmetry "plane" is a line: its normal lies in the x-y plane
                    t = pts[-1] - pts[0]
                    normal = np.array([t[1], -t[0], 0.0])
                else:
                    _, _, vt = np.linalg.svd(pts - centroid, full_matrices=False)
                    normal = vt[-1]
                nn = np.linalg.norm(normal)
                if nn == 0.0:
                    raise CaseError(f"symmetry patch {p.spec}: its points do not span a plane")
                normal = normal / nn
                dev = np.abs((pts - centroid) @ normal).max()
                size = np.ptp(pts, axis=0).max() or 1.0
                if dev > 1e-6 * size:
                    raise CaseError(f"symmetry patch {p.spec} is not planar "
                                    f"(points up to {dev:.3g} off the best plane)")
                sym_of[gid.ravel()] = len(self._sym_planes)
                self._sym_planes.append((centroid, normal))
            kind[gid.ravel()] = np.maximum(kind[gid.ravel()], code)
        self._kind = kind
        self._sym_of = sym_of

    def _rect_gid(self, spec: PatchSpec) -> np.ndarray:
        (a0, a1), (b0, b1) = spec.range
        return self._face_gid[(spec.block, spec.face)][a0:a1 + 1, b0:b1 + 1]

    def _choose_centre(self, centre) -> np.ndarray:
        if centre is None:
            return self._P[self._kind == WALL].mean(axis=0)
        c = np.asarray(centre, dtype=np.float64).reshape(-1)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise CaseError(f"centre must be 3 finite numbers, got {centre!r}")
        return c

    def _build_walls(self) -> None:
        """Wall patches with their halos (neighbours across the patch edges)."""
        walls = [p for p in self.connectivity.patches if p.kind == "wall"]
        self._walls: list[_Wall] = []
        curve = self.ndim == 2
        # wall-surface graph: in-patch neighbours, in global ids
        edges = []
        for p in walls:
            g = self._rect_gid(p.spec)
            if g.shape[0] > 1:
                edges.append(np.stack([g[:-1].ravel(), g[1:].ravel()], 1))
            if g.shape[1] > 1 and not curve:
                edges.append(np.stack([g[:, :-1].ravel(), g[:, 1:].ravel()], 1))
        E = np.concatenate(edges) if edges else np.empty((0, 2), dtype=np.int64)
        E = E[E[:, 0] != E[:, 1]]
        E = np.sort(E, axis=1)
        G = np.int64(self.n_global)
        key = np.unique(E[:, 0] * G + E[:, 1])
        E = np.stack([key // G, key % G], axis=1)
        self._wall_edges = E
        # neighbour sets of the points on the patches' edges (the only ones `across` asks for)
        on_edge = np.zeros(self.n_global, dtype=bool)
        for p in walls:
            g = self._rect_gid(p.spec)
            for side in (g[0], g[-1], g[:, 0], g[:, -1]):
                on_edge[side] = True
        nbr: dict[int, set[int]] = {}
        for a, b in E[on_edge[E[:, 0]] | on_edge[E[:, 1]]].tolist():
            nbr.setdefault(a, set()).add(b)
            nbr.setdefault(b, set()).add(a)
        P = self._P

        def across(p: int, inner: int, exclude) -> int:
            """The wall neighbour of p on the other side from `inner` (most negative cosine), or -1.

            "Other side" is an angle beyond ~96 deg (cosine < -0.1, clear of the
            round-off at a right-angled corner): the continuation of the surface into
            another patch, or the opposite surface across a collapsed edge (wing-tip
            cap); a sharp trailing edge's other surface (acute angle) is not taken.
            """
            best, best_cos = -1, -0.1
            d_in = P[inner] - P[p]
            n_in = np.linalg.norm(d_in)
            for x in nbr.get(p, ()):
                if x == inner or x in exclude:
                    continue
                d = P[x] - P[p]
                nd = np.linalg.norm(d)
                if nd == 0.0 or n_in == 0.0:
                    continue
                c = float(d @ d_in) / (nd * n_in)
                if c < best_cos:
                    best, best_cos = x, c
            return best

        sym_of = self._sym_of

        def fill(halo, mirror, at, p: int, inner: int, exclude) -> None:
            """Halo entry `at` for edge point p: the wall neighbour across the edge, or,
            where the wall ends on a symmetry plane, the mirror image of `inner`."""
            x = across(p, inner, exclude)
            if x >= 0:
                halo[at] = x
            elif sym_of[p] >= 0 and inner != p:
                halo[at] = inner
                mirror[at] = sym_of[p]

        for p in walls:
            g = self._rect_gid(p.spec)
            if curve:
                g = g[:, :1]
            na, nb = g.shape
            halo = np.full((na + 2, nb + 2), -1, dtype=np.int64)
            mirror = np.full((na + 2, nb + 2), -1, dtype=np.int64)
            halo[1:-1, 1:-1] = g
            for bb in range(nb):
                for row, inner_row, at in ((0, 1, 0), (na - 1, na - 2, na + 1)):
                    if na < 2:
                        continue
                    side = {int(g[row, x]) for x in (bb - 1, bb + 1) if 0 <= x < nb}
                    fill(halo, mirror, (at, bb + 1), int(g[row, bb]), int(g[inner_row, bb]), side)
            for aa in range(na):
                for col, inner_col, at in ((0, 1, 0), (nb - 1, nb - 2, nb + 1)):
                    if nb < 2:
                        continue
                    side = {int(g[x, col]) for x in (aa - 1, aa + 1) if 0 <= x < na}
                    fill(halo, mirror, (aa + 1, at), int(g[aa, col]), int(g[aa, inner_col]), side)
            if curve:
                self._walls.append(_Wall(p.spec, g[:, 0], np.ascontiguousarray(halo[:, 1]),
                                         np.ascontiguousarray(mirror[:, 1])))
            else:
                self._walls.append(_Wall(p.spec, g, halo, mirror))
        self._wall_gids = np.flatnonzero(self._kind == WALL)
        where = np.full(self.n_global, -1, dtype=np.int64)
        where[self._wall_gids] = np.arange(self._wall_gids.size)
        # each wall patch's points as indices into the merged wall arrays
        self._wall_local = [np.ascontiguousarray(where[w.gid].ravel()) for w in self._walls]
        # the halos as boundary_motion takes them (padded, NaN where no neighbour, mirror
        # images across symmetry planes), undeformed ones built here, deformed ones per step
        npl = len(self._sym_planes)
        self._plane_o = np.array([o for o, _ in self._sym_planes]).reshape(npl, 3)
        self._plane_n = np.array([n for _, n in self._sym_planes]).reshape(npl, 3)
        for w in self._walls:
            w.pu = np.empty((w.halo.shape[0], 1, 3) if curve else w.halo.shape + (3,))
            _halo_points(P, w.halo.ravel(), w.mirror.ravel(), self._plane_o, self._plane_n,
                         w.pu.reshape(-1, 3))

    def _build_rects(self) -> None:
        rects: list[_Rect] = []
        for p in self.connectivity.patches:
            rects.append(_Rect(p.spec.block, p.spec.face, self._rect_gid(p.spec), p.kind))
        for itf in self.connectivity.interfaces:
            rects.append(_Rect(itf.master.block, itf.master.face, self._rect_gid(itf.master), "interface"))
            rects.append(_Rect(itf.slave.block, itf.slave.face, self._rect_gid(itf.slave), "interface",
                               slave=True))
        # every face point must be covered
        covered = {k: np.zeros(v.shape, dtype=bool) for k, v in self._face_gid.items()}
        specs = [p.spec for p in self.connectivity.patches]
        specs += [i.master for i in self.connectivity.interfaces] + [i.slave for i in self.connectivity.interfaces]
        for s in specs:
            (a0, a1), (b0, b1) = s.range
            covered[(s.block, s.face)][a0:a1 + 1, b0:b1 + 1] = True
        for (b, f), cov in covered.items():
            if not cov.all():
                a, bb = np.argwhere(~cov)[0]
                raise CaseError(f"block {b + 1} face {f}: point ({a + 1}, {bb + 1}) of the face is "
                                "covered by no patch or interface of the connectivity")
        self._rects = rects

    # ----------------------------------------------------- blending parameters
    def _build_wall_distances(self, rotation_length) -> None:
        """Two-level: distance of every boundary point to the walls, its nearest wall point,
        the rotation length and the end weights ``omega = exp(-d / ell)``."""
        from ._points import nearest_within
        P = self._P
        wall = self._wall_gids
        W = P[wall]
        if rotation_length is None:
            # twice the largest distance from the walls' centroid: a size that rotates with them
            size = 2.0 * float(np.sqrt(np.max(np.sum((W - W.mean(axis=0)) ** 2, axis=1))))
            rotation_length = ROTATION_LENGTH_FRACTION * size
            if not rotation_length > 0.0:
                rotation_length = ROTATION_LENGTH_FRACTION * self._scale
        ell = float(rotation_length)
        self.rotation_length = ell
        # every weight built from d is below 1e-8 beyond 20 ell (omega = exp(-d / ell)): a
        # bounded query; points farther away get d = inf, weight 0
        d, near = nearest_within(W, P, 20.0 * ell)
        far = ~np.isfinite(d)
        d[self._kind == WALL] = 0.0
        near[far] = 0
        self._dwall = d
        self._foot = np.where(far, np.arange(P.shape[0]), wall[near])
        self._omega = np.exp(-d / ell)

    def _line_params(self, s: np.ndarray, length: float, g0: int, g1: int) -> np.ndarray:
        """Blending parameters of one chain of points between the known ends g0, g1
        (``s``: normalised arclength including both ends)."""
        if not self._two:
            return self._psi(np.array(s, dtype=np.float64))
        ell = self.rotation_length
        return wall_layer_line(s, length, ell * self._omega[g0], ell * self._omega[g1])

    def _patch_params(self, g: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(self._P[g])
        if not self._two:
            return self._psi(tfi.arclength_surface(x))
        ell = self.rotation_length
        om = self._omega
        x4 = np.asfortranarray(x[:, :, None, :])
        lam = [ell * om[g[0, :]], ell * om[g[-1, :]], ell * om[g[:, 0]], ell * om[g[:, -1]]]
        return np.ascontiguousarray(wall_layer_arclength(x4, lam, ndim=2)[:, :, 0, :2])

    def _block_params(self, b: int, blk: Block) -> np.ndarray:
        if not self._two:
            return self._psi(tfi.arclength(blk.xyz))
        ell = self.rotation_length
        lam = [ell * self._omega[self._face_gid[(b, f)]] for f in _faces_of(self.ndim)]
        return wall_layer_arclength(blk.xyz, lam, ndim=self.ndim)

    # --------------------------------------------------------------- skeleton
    def _build_vertices(self, power: float, max_sources: int) -> None:
        known = self._kind >= FIXED
        corners = set()
        for r in self._rects:
            g = r.gid
            corners.update(int(x) for x in (g[0, 0], g[-1, 0], g[0, -1], g[-1, -1]))
        free = np.array(sorted(c for c in corners if not known[c]), dtype=np.int64)
        self._free_vertices = free
        self._vertex_corners = np.array(sorted(corners), dtype=np.int64)
        if free.size == 0:
            self._idw = None
            return
        wall = self._wall_gids
        step = max(1, int(math.ceil(wall.size / max_sources)))
        src = wall[::step]
        d = np.linalg.norm(self._P[free][:, None, :] - self._P[src][None, :, :], axis=-1)
        dmin = d.min(axis=1)
        w = 1.0 / np.maximum(d, 1e-300) ** power
        exact = d <= self.tol
        rows = exact.any(axis=1)
        w[rows] = exact[rows].astype(float)
        w /= w.sum(axis=1, keepdims=True)
        fixed = np.flatnonzero(self._kind == FIXED)
        if fixed.size:
            from scipy.spatial import cKDTree
            dfix, _ = cKDTree(self._P[fixed]).query(self._P[free])
            decay = dfix / (dmin + dfix)
            decay[(dmin + dfix) == 0.0] = 1.0
        else:
            decay = np.ones(free.size)
        ref = np.argmax(w, axis=1)
        self._idw = (src, w, decay, ref)

    def _chain_gaps(self, chain: np.ndarray, known: np.ndarray, gaps: list) -> None:
        """Record the runs of unknown points of one side, between known points."""
        n = chain.size
        m = 0
        while m < n:
            if known[chain[m]]:
                m += 1
                continue
            start = m
            while m < n and not known[chain[m]]:
                m += 1
            left, right = chain[start - 1], chain[m]        # chain ends are vertices: known
            run = chain[start:m]
            pts = self._P[chain[start - 1:m + 1]]
            arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
            if arc[-1] > 0.0:
                s = arc / arc[-1]
            else:
                s = np.arange(run.size + 2) / (run.size + 1.0)
            s[0], s[-1] = 0.0, 1.0
            t = self._line_params(s, arc[-1], int(left), int(right))[1:-1]
            # a point may repeat along a side (collapsed): keep its first occurrence
            _, keep = np.unique(run, return_index=True)
            keep.sort()
            gaps.append((int(left), int(right), run[keep], t[keep]))
            known[run] = True

    def _build_segments_and_patches(self) -> None:
        known = self._kind >= FIXED
        known[self._vertex_corners] = True
        gaps: list = []
        for r in self._rects:
            g = r.gid
            if g.shape[0] == 1 or g.shape[1] == 1:
                self._chain_gaps(g.ravel(), known, gaps)
            else:
                for chain in (g[:, 0], g[:, -1], g[0, :], g[-1, :]):
                    self._chain_gaps(chain, known, gaps)
        if gaps:
            self._gaps = (np.array([x[0] for x in gaps], dtype=np.int64),
                          np.array([x[1] for x in gaps], dtype=np.int64),
                          np.concatenate([[0], np.cumsum([x[2].size for x in gaps])]).astype(np.int64),
                          np.concatenate([x[2] for x in gaps]).astype(np.int64),
                          np.concatenate([x[3] for x in gaps]).astype(np.float64))
        else:
            self._gaps = None
        patches: list[_PatchTFI] = []
        prescribed = self._kind >= FIXED
        for r in self._rects:
            g = r.gid
            if r.slave or g.shape[0] < 3 or g.shape[1] < 3:
                continue
            inner = np.zeros(g.shape, dtype=bool)
            inner[1:-1, 1:-1] = ~known[g[1:-1, 1:-1]]
            if not inner.any():
                continue
            s = self._patch_params(g)
            ends = [prescribed[g[0, :]].sum() + prescribed[g[-1, :]].sum(),
                    prescribed[g[:, 0]].sum() + prescribed[g[:, -1]].sum()]
            lead = 0 if ends[0] >= ends[1] else 1
            # a point that repeats inside the patch is written once
            flat = g[inner]
            _, first = np.unique(flat, return_index=True)
            write = np.zeros(g.shape, dtype=bool)
            idx = np.argwhere(inner)[np.sort(first)]
            write[idx[:, 0], idx[:, 1]] = True
            patches.append(_PatchTFI(g, s, lead, write, r.block, r.face))
            known[flat] = True
        self._patches = patches
        # the patches packed for _patch_level (one compiled call per level)
        self._plevel = _level_pack([(p.gid, p.s, p.lead, p.write) for p in patches])
        self._plevel_points = int(sum(p.gid.size for p in patches))
        self._derived = np.flatnonzero(self._kind < FIXED)
        if not known.all():
            g = int(np.flatnonzero(~known)[0])
            raise CaseError(f"boundary point at {tuple(np.round(self._P[g], 6))} is reached by no "
                            "patch, segment or vertex of the skeleton (inconsistent connectivity)")

    def _build_symmetry(self) -> None:
        sym = np.flatnonzero((self._sym_of >= 0) & (self._kind == SYMMETRY))
        self._sym_gids = sym
        planes = self._sym_of[sym]
        self._sym_point = np.zeros((sym.size, 3))
        self._sym_normal = np.zeros((sym.size, 3))
        for m, pl in enumerate(self._sym_planes):
            sel = planes == m
            self._sym_point[sel] = pl[0]
            self._sym_normal[sel] = pl[1]

    def _onto_symmetry(self, pos: np.ndarray) -> None:
        """The symmetry points of the global array ``pos`` (G, 3) projected onto their planes,
        in place."""
        _onto_planes(pos, self._sym_gids, self._sym_point, self._sym_normal)

    def _build_blocks(self) -> None:
        plans = []
        prescribed = self._kind >= FIXED
        faces = _faces_of(self.ndim)
        for b, blk in enumerate(self.grid):
            with serial_below(blk.npoints):
                s = self._block_params(b, blk)
            fg = [self._face_gid[(b, f)] for f in faces]
            counts = [int(prescribed[g].sum()) for g in fg]
            order = tuple(int(x) for x in tfi.lead_order(counts))
            plan = _BlockPlan(s, order, fg, tfi.face_params(s))
            plan.gather = tfi.gather_plan(fg, s, order, face_s=plan.face_s)
            plans.append(plan)
        self._blocks = plans
        # where each block's boundary points live, for the final scatter
        blk_of = np.searchsorted(self._offsets, self._copies_key, side="right") - 1
        self._scatter = []
        for b in range(len(self.grid)):
            sel = blk_of == b
            self._scatter.append((self._copies_key[sel] - self._offsets[b], self._copies_gid[sel]))

    # ------------------------------------------------------- two-level set-up
    def _build_bodies(self) -> None:
        """Connected wall bodies, each with the rigid motions its symmetry planes allow."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components
        wall = self._wall_gids
        pos = np.full(self.n_global, -1, dtype=np.int64)
        pos[wall] = np.arange(wall.size)
        E = self._wall_edges
        r, c = pos[E[:, 0]], pos[E[:, 1]]
        ok = (r >= 0) & (c >= 0)
        graph = coo_matrix((np.ones(int(ok.sum()), dtype=np.int8), (r[ok], c[ok])),
                           shape=(wall.size, wall.size))
        _, label = connected_components(graph, directed=False)
        bodies = []
        for lab in np.unique(label):
            gids = wall[label == lab]
            planes = sorted({int(p) for p in self._sym_of[gids] if p >= 0})
            normals = [self._sym_planes[p][1] for p in planes]
            if self.ndim == 2:
                normals.append(np.array([0.0, 0.0, 1.0]))
            axis, tproj = constrain_to_planes(normals)
            bodies.append(_Body(gids, axis, tproj))
        self._bodies = bodies

    def _build_rigid_weights(self) -> None:
        """Two-level: the weight ``φ_b`` of each wall body's rigid motion on every derived point.

        ``φ_b`` is Samareh's hierarchy (vertices, segments, patches) applied to the
        scalar that is 1 on the walls of body ``b`` and 0 on every other prescribed
        point.  A step blends the bodies' fitted motions with it in closed form
        (:func:`_rigid_blend`): ``Δ = Σ φ_b Δ_b`` is exactly what the hierarchy gives
        for uniform ``Δ_b``, and ``Q = exp(Σ φ_b v_b)`` blends the rotations the same
        way, so the rigid part costs no interpolation per step.
        """
        G = self.n_global
        der = self._derived
        nb = len(self._bodies)
        phi = np.empty((der.size, nb))
        for b0 in range(0, nb, 3):
            F = np.zeros((G, 3))
            chunk = self._bodies[b0:b0 + 3]
            for k, body in enumerate(chunk):
                F[body.gids, k] = 1.0
            self._vertex_stage(F, None)
            self._segment_stage(F, None)
            self._patch_stage(F, None)
            phi[:, b0:b0 + len(chunk)] = F[der, :len(chunk)]
        self._phi = phi

    def _build_arms(self) -> None:
        """Two-level: the centre field ``c`` on boundary points and the arms ``A = R_u - c``.

        Walls: ``c`` is the point itself.  Fixed points on the side faces of a
        block (faces that are not ends of its leading direction), near walls:
        ``c`` is the interpolant along the leading direction between the face's
        end edges (weight ``exp(-(d / 2 ell)^2)`` against the point itself), so
        the side faces' own offsets from their edges do not become
        interpolation residuals that would carry un-rotated wall-layer
        offsets into the block.  Derived points (vertices, segments, patches):
        ``c`` is interpolated like every other field, then re-based to
        ``w foot + (1 - w) x`` (``foot``: the nearest wall point, ``w`` =
        ``exp(-d / (REBASE_FRACTION * rotation_length))``), and the shift
        ``c_rebased - c_interpolated`` is kept: a step adds ``rot(Q, shift)``
        to the interpolated ``K`` so the position is unchanged and rigid
        motions stay exact.  Volumes: ``A = R_u - TFI(c on the faces)``.
        """
        P = self._P
        kind = self._kind
        c = P.copy()
        # fixed points of side faces: the leading-direction interpolant of the face's end edges
        for b, plan in enumerate(self._blocks):
            L = plan.order[0]
            dims = self.grid[b].dims
            for d in plan.order[1:]:
                others = [m for m in range(3) if m != d]
                if L not in others:
                    continue
                ax = others.index(L)
                for side in (0, 1):
                    g = plan.face_gid[2 * d + side]
                    fx = kind[g] == FIXED
                    if not fx.any():
                        continue
                    sl = [slice(None)] * 3
                    sl[d] = dims[d] - 1 if side else 0
                    sL = plan.s[tuple(sl)][..., L]
                    e0 = np.take(P[g], [0], axis=ax)
                    e1 = np.take(P[g], [-1], axis=ax)
                    u = (1.0 - sL)[..., None] * e0 + sL[..., None] * e1
                    # near walls only: far away Q is 1 and the offsets carry no rotation, and
                    # a point on the side faces of several blocks keeps one value there
                    gf = g[fx]
                    om = np.exp(-(self._dwall[gf] / (2.0 * self.rotation_length)) ** 2)[:, None]
                    c[gf] = om * u[fx] + (1.0 - om) * P[gf]
        shift = np.zeros_like(P)
        lr = REBASE_FRACTION * self.rotation_length
        w_r = np.exp(-self._dwall / lr)
        target = np.empty_like(P)                # re-based centres w foot + (1 - w) x
        _blend_rows(P, self._foot, w_r, target)

        def rebase(idx, c_interp):
            shift[idx] = target[idx] - c_interp
            c[idx] = target[idx]

        # same order as a step: vertices, segments (gap by gap), patches
        if self._idw is not None:
            src, w, decay, _ = self._idw
            free = self._free_vertices
            rebase(free, decay[:, None] * (w @ c[src]) + (1.0 - decay)[:, None] * P[free])
        if self._gaps is not None:
            _rebase_gaps(c, *self._gaps, target, shift)
        if self._patches:
            self._patch_stage(c, None)
            wg = self._plevel[1][self._plevel[3]]
            rebase(wg, c[wg].copy())
        self._c = c
        self._cshift = shift
        self._arm = P - c
        damp = np.ones(self.n_global)
        der = self._derived
        damp[der] = np.exp(-(self._dwall[der] / (DAMP_FRACTION * self.rotation_length)) ** 2)
        self._dampf = damp
        np.negative(c, out=c)                    # -c for the tables (negation is exact)
        for plan in self._blocks:
            # A = R_u - TFI(c), evaluated inside the volume kernel from these O(surface) tables
            plan.base = plan.gather.base_tables(c)
        np.negative(c, out=c)

    # -------------------------------------------------------------- a step
    def wall_points(self) -> np.ndarray:
        """Undeformed positions ``(n, 3)`` of the (distinct) wall points, in the order
        :meth:`deform` passes them to a motion callable."""
        return self._P[self._wall_gids].copy()

    def _wall_targets(self, moved) -> np.ndarray:
        """Deformed positions of every global point (only wall rows are meaningful)."""
        G = self.n_global
        if self._rd is None:
            self._rd = self._P.copy()      # only the wall rows change (a step holds the lock)
        rd = self._rd
        wall = self._wall_gids
        if callable(moved):
            new = np.asarray(moved(self._P[wall].copy()), dtype=np.float64)
            if new.shape != (wall.size, 3):
                raise DeformationError(f"the motion callable returned shape {new.shape}, expected "
                                       f"({wall.size}, 3) for the {wall.size} wall points")
            rd[wall] = new
        elif isinstance(moved, Grid):
            if moved.dims != self.grid.dims:
                raise DeformationError(f"moved grid dimensions {moved.dims} differ from the "
                                       f"reference {self.grid.dims}")
            key = self._rep_key[wall]
            blk_of = np.searchsorted(self._offsets, key, side="right") - 1
            for b, blk in enumerate(moved):
                sel = blk_of == b
                rd[wall[sel]] = blk.xyz.reshape(-1, 3, order="F")[key[sel] - self._offsets[b]]
        elif isinstance(moved, Mapping):
            seen = np.zeros(G, dtype=bool)
            for k, arr in moved.items():
                spec = k if isinstance(k, PatchSpec) else parse_patch_spec(str(k))
                spec = spec.resolve(self.grid)
                gid = self._rect_gid(spec)
                a = np.asarray(arr, dtype=np.float64)
                if a.shape[:-1] != gid.shape and a.shape[:-1] != (gid.size,):
                    raise DeformationError(f"moved patch {spec}: array shape {a.shape}, expected "
                                           f"{gid.shape + (3,)}")
                rd[gid.ravel()] = a.reshape(-1, 3)
                seen[gid.ravel()] = True
            missing = wall[~seen[wall]]
            if missing.size:
                raise DeformationError(f"{missing.size} wall point(s) have no new position in the "
                                       f"mapping, e.g. at {tuple(np.round(self._P[missing[0]], 6))}")
        else:
            raise DeformationError("moved must be a callable, a Grid, or a mapping patch -> array")
        bad = ~np.isfinite(rd[wall])
        if bad.any():
            raise DeformationError(f"{int(bad.any(axis=1).sum())} moved wall point(s) are not finite")
        if self.ndim == 2 and np.any(rd[wall, 2] != 0.0):
            raise DeformationError("moved wall points of a 2-D grid must have z = 0")
        return rd

    def _wall_quaternions(self, rd: np.ndarray) -> np.ndarray:
        """Merged boundary quaternions ``(n_wall, 4)`` of the wall points moved to ``rd``."""
        with serial_below(self._wall_gids.size):
            return self._wall_quaternions_now(rd)

    def _wall_quaternions_now(self, rd: np.ndarray) -> np.ndarray:
        from .boundary import motion_padded
        nw = self._wall_gids.size
        acc = np.zeros((nw, 4))
        count = np.zeros(nw, dtype=np.int64)
        curve = self.ndim == 2
        e = np.array([0.0, 0.0, 1.0]) if curve else np.zeros(3)
        for w, lid in zip(self._walls, self._wall_local):
            pd = np.empty_like(w.pu)
            _halo_points(rd, w.halo.ravel(), w.mirror.ravel(), self._plane_o, self._plane_n,
                         pd.reshape(-1, 3))
            na = pd.shape[0] - 2
            nb = 1 if curve else pd.shape[1] - 2
            q, _ = motion_padded(w.pu, pd, 1, 0 if curve else 1, curve, e, self.centre, na, nb)
            _merge_quaternions(lid, q.reshape(-1, 4), acc, count)
        acc /= np.linalg.norm(acc, axis=1, keepdims=True)
        return acc

    # -- the Samareh hierarchy (formulation "samareh", the rigid part of "two-level", "tfi")
    def _vertex_stage(self, gdelta, gq) -> None:
        if self._idw is None:
            return
        src, w, decay, ref = self._idw
        free = self._free_vertices
        gdelta[free] = decay[:, None] * (w @ gdelta[src])
        if gq is not None:
            gq[free] = self._vertex_q(gq, decay)

    def _vertex_q(self, gq, decay) -> np.ndarray:
        src, w, _, ref = self._idw
        qs = gq[src]                                         # (ns, 4)
        qref = qs[ref]                                       # (nv, 4)
        sign = np.where(qref @ qs.T >= 0.0, 1.0, -1.0)       # (nv, ns)
        qbar = (w * sign) @ qs
        norm = np.linalg.norm(qbar, axis=1)
        small = norm < 1e-6
        qbar[small] = qref[small]
        qbar[~small] /= norm[~small, None]
        ident = np.zeros_like(qbar)
        ident[:, 0] = 1.0
        return qa.slerp(ident, qbar, decay)

    def _segment_stage(self, gdelta, gq) -> None:
        if self._gaps is None:
            return
        left, right, ptr, pts, s = self._gaps
        _fill_gaps(gdelta, gq if gq is not None else np.empty((1, 4)), left, right, ptr, pts, s,
                   gq is not None, _NONE, _NONE3)

    def _patch_stage(self, gdelta, gq, damp=_NONE, shift=_NONE3) -> None:
        """The derived patches (:func:`_patch_level`); ``gq`` None: translations only;
        ``damp``/``shift``: the two-level fade and re-basing."""
        use_q = gq is not None
        gqa = gq if use_q else np.empty((1, 4))
        with serial_below(_PATCH_WORK * self._plevel_points):
            _patch_level(gdelta, gqa, use_q, *self._plevel, damp, shift)

    def _symmetry_stage(self, gdelta, gq) -> None:
        """Symmetry points of Samareh's fields (:func:`_symmetry_fix`): on their plane,
        rotating about its normal only."""
        if self._sym_gids.size:
            use_q = gq is not None
            _symmetry_fix(gdelta, gq if use_q else np.empty((1, 4)), use_q, self._P,
                          self.centre if use_q else _ORIGIN, self._sym_gids, self._sym_point,
                          self._sym_normal)

    def _finish_boundary(self, pos, rd) -> np.ndarray:
        """Boundary positions: symmetry points on their plane, walls exact (fixed points are
        never written: they keep the buffer's undeformed position)."""
        self._onto_symmetry(pos)
        wall = self._wall_gids
        pos[wall] = rd[wall]
        return pos

    def _samareh_fields(self, gdelta, gq):
        """Vertices, segments, patches and symmetry of the Samareh hierarchy, in place."""
        t1 = time.perf_counter()
        self._vertex_stage(gdelta, gq)
        self._segment_stage(gdelta, gq)
        t2 = time.perf_counter()
        self._patch_stage(gdelta, gq)
        self._symmetry_stage(gdelta, gq)
        return t2 - t1, time.perf_counter() - t2

    def _volumes(self, bases, gdelta, gq, centre, outs, callback=None, done0=0, total=None,
                 based=False):
        """Fused TFI kernel per block: ``out = centre + Δ + rot(Q, base - centre)``.

        The face values are read from the global boundary arrays through each block's
        :func:`tfi.gather_plan` (no per-face copies).  ``based``: the base point is
        ``bases[b] + TFI(-c)`` (the two-level arms, from the block's base tables).
        """
        nblk = len(self.grid)
        total = total or nblk
        for b, plan in enumerate(self._blocks):
            with serial_below(self.grid[b].npoints):
                tfi.deform_block_gathered(bases[b], plan.s, gdelta, gq, plan.gather, centre,
                                          out=outs[b], base=plan.base if based else None)
            if callback is not None:
                callback(done0 + b + 1, total)

    # -- the two-level step
    def _fits(self, rd):
        """Per wall body: (q, t) of the best rigid motion and the pulled-back residual targets."""
        P = self._P
        if self._y is None:
            self._y = P.copy()             # only the wall rows change
        y = self._y
        fits = []
        for body in self._bodies:
            g = body.gids
            q, t = fit_rigid(P[g], rd[g], body.axis, body.tproj)
            fits.append((q, t))
            # rot(q)^-1 (rd - t)
            y[g] = qa.rotate(qa.conjugate(q), rd[g] - t)
        return fits, y

    def _work(self):
        """Buffers reused by every two-level step (boundary-sized; a step is not re-entrant,
        :meth:`deform` holds a lock).  Fixed points' entries are constant and set here."""
        if self._buffers is None:
            G = self.n_global
            P = self._P
            # two-level: fixed points have K = c (Q = 1: position c + A = P)
            K = self._c.copy() if self._two else None
            ql = np.zeros((G, 4))
            ql[:, 0] = 1.0
            gd = np.zeros((G, 3))
            qg = ql.copy()
            pos = P.copy()
            self._buffers = (K, ql, gd, qg, pos)
        return self._buffers

    def _local_fields(self, y, qwall):
        """The residual motion: K and Q on every boundary point (``qwall``: the wall
        quaternions of the residual targets ``y``), positions in the work buffer."""
        P = self._P
        A = self._arm
        wall = self._wall_gids
        K, gq, _, _, pos = self._work()
        gq[wall] = qwall
        K[wall] = y[wall]                   # walls: A = 0
        damp = self._dampf
        shift = self._cshift
        t1 = time.perf_counter()
        # each level: interpolate, fade the residual rotation out away from the walls, add
        # the re-basing shift of the centres (the position K + rot(Q, A) is unchanged by it)
        if self._idw is not None:
            src, w, decay, _ = self._idw
            free = self._free_vertices
            K[free] = decay[:, None] * (w @ K[src]) + (1.0 - decay)[:, None] * P[free]
            gq[free] = self._vertex_q(gq, decay)
            K[free] += qa.rotate(gq[free], shift[free])
        if self._gaps is not None:
            _fill_gaps(K, gq, *self._gaps, True, damp, shift)
        t2 = time.perf_counter()
        self._patch_stage(K, gq, damp, shift)
        if self._sym_gids.size:
            _symmetry_fix(K, gq, True, A, _ORIGIN, self._sym_gids, self._sym_point,
                          self._sym_normal)
        _positions_local(K, gq, A, self._derived, pos)
        pos[wall] = y[wall]
        return K, gq, pos, t2 - t1, time.perf_counter() - t2

    def _global_fields(self, fits):
        """The rigid part: each body's (Δ_b, Q_b) on its walls, blended in closed form on the
        derived points with the weights of :meth:`_build_rigid_weights`."""
        c = self.centre
        _, _, gdelta, gq, _ = self._work()
        nb = len(self._bodies)
        Db = np.empty((nb, 3))
        Qb = np.empty((nb, 4))
        for b, (body, (q, t)) in enumerate(zip(self._bodies, fits)):
            # c + Δ + rot(q, x - c) = rot(q, x) + t
            Db[b] = t + qa.rotate(q, c) - c
            Qb[b] = q
            gdelta[body.gids] = Db[b]
            gq[body.gids] = q
        t1 = time.perf_counter()
        _rigid_blend(self._phi, self._derived, Db, qa.log(Qb), gdelta, gq)
        self._symmetry_stage(gdelta, gq)
        return gdelta, gq, 0.0, time.perf_counter() - t1

    def deform(self, moved, *, callback: Callable[[int, int], None] | None = None) -> Grid:
        """Deform the grid for new wall positions.

        Parameters
        ----------
        moved : callable, Grid or mapping
            * a callable ``f(points (n, 3)) -> (n, 3)`` giving the new
              position of each wall point (see :meth:`wall_points`);
            * a Grid with the reference's dimensions whose wall points hold
              the new positions (other points are ignored);
            * a mapping ``PatchSpec or "B:FACE[:range]" -> array (na, nb, 3)``
              covering every wall point.
        callback : callable(done, total), optional
            Called after each block kernel (progress reporting).

        Returns
        -------
        Grid
            A new grid; the reference is not modified.  Every call starts from
            the reference, so repeated steps do not drift.
        """
        with self._lock:
            t0 = time.perf_counter()
            rd = self._wall_targets(moved)
            if self._two:
                return self._deform_two_level(rd, callback, t0)
            return self._deform_samareh(rd, callback, t0)

    def _assemble(self, outs, pos) -> Grid:
        blocks = []
        for b, (blk, out) in enumerate(zip(self.grid, outs)):
            local, gid = self._scatter[b]
            _scatter_rows(pos, gid, local, out.reshape(-1, 3, order="F"))
            if self.ndim == 2:
                out[..., 2] = 0.0
            blocks.append(Block(out, blk.iblank, blk.name, allow_nonfinite=True))
        return Grid(blocks, self.ndim, source_format=self.grid.source_format)

    def _deform_samareh(self, rd, callback, t0) -> Grid:
        wall = self._wall_gids
        c = self.centre
        P = self._P
        # persistent buffers: walls and derived points are written every step, fixed points
        # keep Δ = 0, Q = 1 and their position
        _, _, gdelta, gq, pos = self._work()
        if self._use_q:
            qw = self._wall_quaternions(rd)
            gq[wall] = qw
            # the translation follows from the merged rotation: c + delta + rot(q, ru - c) = rd
            gdelta[wall] = rd[wall] - c - qa.rotate(qw, P[wall] - c)
        else:
            gq = None
            gdelta[wall] = rd[wall] - P[wall]
        t1 = time.perf_counter()
        ts, tf = self._samareh_fields(gdelta, gq)
        der = self._derived
        if gq is not None:
            pos[der] = P[der]
            _positions_global(gdelta, gq, c, der, pos)
        else:
            pos[der] = P[der] + gdelta[der]
        pos = self._finish_boundary(pos, rd)
        t3 = time.perf_counter()
        outs = [np.empty_like(blk.xyz, order="F") for blk in self.grid]
        self._volumes([blk.xyz for blk in self.grid], gdelta, gq, c, outs, callback)
        grid = self._assemble(outs, pos)
        t4 = time.perf_counter()
        self.timings = StepTimings(walls=t1 - t0, skeleton=ts, faces=tf + (t3 - t1 - ts - tf),
                                   volumes=t4 - t3)
        return grid

    def _deform_two_level(self, rd, callback, t0) -> Grid:
        wall = self._wall_gids
        P = self._P
        fits, y = self._fits(rd)
        tiny = 1e-14 * self._scale
        local = bool(np.max(np.abs(y[wall] - P[wall]), initial=0.0) > tiny)
        rigid = any(np.max(np.abs(q - _IDENT)) > 1e-15 or np.max(np.abs(t)) > tiny for q, t in fits)
        qwall = self._wall_quaternions(y) if local else None
        t1 = time.perf_counter()
        ts = tf = 0.0
        pos = self._work()[4]
        if local:
            K, gql, pos, a, b = self._local_fields(y, qwall)
            ts += a
            tf += b
        else:
            pos[self._derived] = P[self._derived]
        if rigid:
            gdelta, gq, a, b = self._global_fields(fits)
            ts += a
            tf += b
            _positions_global(gdelta, gq, self.centre, self._derived, pos)
        self._onto_symmetry(pos)
        pos[wall] = rd[wall]
        t3 = time.perf_counter()
        outs = [np.empty_like(blk.xyz, order="F") for blk in self.grid]
        total = len(self.grid) * (int(local) + int(rigid))
        if local:
            self._volumes([blk.xyz for blk in self.grid], K, gql, _ORIGIN, outs, callback, 0,
                          total, based=True)
        else:
            for out, blk in zip(outs, self.grid):
                np.copyto(out, blk.xyz)
        if rigid:
            self._volumes(outs, gdelta, gq, self.centre, outs, callback,
                          len(self.grid) * int(local), total)
        grid = self._assemble(outs, pos)
        t4 = time.perf_counter()
        self.timings = StepTimings(walls=t1 - t0, skeleton=ts, faces=tf + (t3 - t1 - ts - tf),
                                   volumes=t4 - t3)
        return grid

    # ------------------------------------------------------------ reporting
    def summary(self) -> str:
        """A few lines describing the skeleton (for the CLI and logs)."""
        k = self._kind
        if self.method == "tfi":
            head = f"method tfi (plain TFI), {self.blending} blending"
        elif self._two:
            head = (f"method quaternion, formulation two-level, rotation length "
                    f"{self.rotation_length:.6g}, {len(self._bodies)} wall bod"
                    f"{'y' if len(self._bodies) == 1 else 'ies'}")
        else:
            head = f"method quaternion, formulation samareh, {self.blending} blending"
        lines = [
            head + f", centre ({', '.join(f'{v:.6g}' for v in self.centre)})",
            f"{self.n_global} boundary points: {int((k == WALL).sum())} wall, "
            f"{int((k == FIXED).sum())} fixed, {int((self._sym_of >= 0).sum())} symmetry",
            f"{len(self._vertex_corners)} vertices ({len(self._free_vertices)} free), "
            f"{0 if self._gaps is None else len(self._gaps[0])} derived segments, "
            f"{len(self._patches)} derived patches, {len(self._blocks)} blocks",
        ]
        return "\n".join(lines)


def deformer_from_case(case, grid: Grid | None = None, **kw) -> Deformer:
    """Build a :class:`Deformer` from a :class:`tfi_quat.case.Case` (walls, symmetry, fixed)."""
    from . import io
    if grid is None:
        grid = io.read(case.grid)
    return Deformer(grid, walls=case.walls, symmetry=case.symmetry, fixed=case.fixed, **kw)
