"""Connectivity search: coincident boundary points -> maximal rectangular interfaces -> patches.

Only boundary points are touched (O(surface)).  Steps:

1. Gather the points of every boundary face (six per block, four in 2-D)
   with a matching tolerance scaled by the local spacing.
2. Contract points that coincide with an in-face neighbour (collapsed faces,
   poles) and the copies of one block point on two or three faces, so that the
   coincidence search over the remaining representatives sees small cliques only.
3. Coincident representatives (:func:`tfi_quat._points.close_pairs`, a sweep
   along a generic direction) give every boundary point a geometric node label.
4. Pairs of coincident, non-degenerate points on faces ``F1 <= F2`` vote for an
   affine map of face indices (one of eight signed permutations plus an
   offset) that their index neighbours confirm.
5. Each distinct map is checked on every point of ``F1``; the matching cells
   are split into maximal rectangles, which become interfaces (master: the
   lower ``(block, face)``).
6. What is left of each face becomes patches, with the user's kinds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._jit import jit
from .._points import close_pairs
from ..errors import CaseError, ConnectivityError, GridValueError
from ..grid import face_axes, face_axis, face_ijk, face_index, faces_of
from ..spec import PatchSpec, parse_patch_spec
from .graph import connected_components
from .model import KINDS, Connectivity, Interface, Patch

__all__ = ["connect", "classify", "node_labels", "interface_mismatches", "check_interfaces", "DEFAULT_RTOL",
           "PLANE_RTOL"]

#: default matching tolerance relative to the smallest adjacent edge
DEFAULT_RTOL = 1e-6
#: a patch is planar (a straight side in 2-D) when no point is farther from its best plane
#: than this fraction of the patch's extent -- the test the Deformer applies to symmetry patches
PLANE_RTOL = 1e-6

# the eight signed permutations of two face axes: q = M @ p + off
_MS = [np.array(m, dtype=np.int64) for m in (
    [[1, 0], [0, 1]], [[-1, 0], [0, 1]], [[1, 0], [0, -1]], [[-1, 0], [0, -1]],
    [[0, 1], [1, 0]], [[0, -1], [1, 0]], [[0, 1], [-1, 0]], [[0, -1], [-1, 0]])]


# ---------------------------------------------------------------- kernels
@jit
def _largest_rectangle(mask):
    """Largest all-True rectangle of a 2-D bool array: (area, r0, r1, c0, c1), inclusive."""
    nr, nc = mask.shape
    h = np.zeros(nc + 1, dtype=np.int64)
    stack = np.zeros(nc + 1, dtype=np.int64)
    best = 0
    br0 = br1 = bc0 = bc1 = -1
    for r in range(nr):
        for c in range(nc):
            h[c] = h[c] + 1 if mask[r, c] else 0
        h[nc] = 0
        top = 0
        for c in range(nc + 1):
            while top > 0 and h[stack[top - 1]] >= h[c]:
                height = h[stack[top - 1]]
                top -= 1
                left = stack[top - 1] + 1 if top > 0 else 0
                area = height * (c - left)
                if area > best:
                    best = area
                    br0, br1, bc0, bc1 = r - height + 1, r, left, c - 1
            stack[top] = c
            top += 1
    return best, br0, br1, bc0, bc1


#: cells of a mask below which :func:`_rectangles` runs :func:`_largest_rectangle` as Python
_RECT_PYTHON_BELOW = 1 << 12


def _rectangles(mask: np.ndarray) -> list[tuple[int, int, int, int]]:
    """Split a bool array into maximal rectangles, largest first: ``(r0, r1, c0, c1)`` inclusive."""
    m = np.array(mask, dtype=np.bool_, copy=True)
    out = []
    while m.any():
        rows = np.flatnonzero(m.any(axis=1))
        cols = np.flatnonzero(m.any(axis=0))
        r0, c0 = rows[0], cols[0]
        sub = m[r0:rows[-1] + 1, c0:cols[-1] + 1]
        if sub.all():
            rect = (int(r0), int(rows[-1]), int(c0), int(cols[-1]))
        else:
            # small masks: the same code uncompiled (a run that meets only those, as the
            # demo, compiles no kernel for them)
            kern = _largest_rectangle.py_func if sub.size < _RECT_PYTHON_BELOW else _largest_rectangle
            area, a0, a1, b0, b1 = kern(np.ascontiguousarray(sub))
            rect = (int(r0 + a0), int(r0 + a1), int(c0 + b0), int(c0 + b1))
        out.append(rect)
        m[rect[0]:rect[1] + 1, rect[2]:rect[3] + 1] = False
    return out


# --------------------------------------------------------------- geometry
@dataclass
class _Face:
    block: int
    face: str
    na: int
    nb: int
    off: int           # first point in the global arrays; point (a, b) at off + a + na * b
    dims: tuple

    @property
    def size(self) -> int:
        return self.na * self.nb

    @property
    def cells(self) -> tuple[int, int]:
        return max(self.na - 1, 1), max(self.nb - 1, 1)

    @property
    def active(self) -> tuple[bool, bool]:
        return self.na >= 2, self.nb >= 2

    def sl(self) -> slice:
        return slice(self.off, self.off + self.size)


class _Geometry:
    """Boundary points of a grid with tolerances and coincidence labels."""

    def __init__(self, grid, tol=None, rtol=DEFAULT_RTOL):
        if tol is not None and not (np.isfinite(tol) and tol >= 0):
            raise ConnectivityError(f"tol must be a finite distance >= 0, got {tol!r}")
        if not (np.isfinite(rtol) and rtol > 0):
            raise ConnectivityError(f"rtol must be > 0, got {rtol!r}")
        self.grid = grid
        self.ndim = grid.ndim
        self.faces: list[_Face] = []
        self.index = {}
        xyz, hs, bps, edges = [], [], [], []
        off = 0
        boff = 0
        for b, blk in enumerate(grid):
            dims = blk.dims
            ext = float(np.linalg.norm(np.subtract(*blk.bbox()[::-1])))
            tiny = 1e-10 * ext if ext > 0 else 0.0
            fallback = ext if ext > 0 else 1.0
            for f in faces_of(grid.ndim):
                d, _ = face_axis(f)
                pts = blk.face(f)  # (na, nb, 3)
                na, nb = pts.shape[:2]
                if not np.isfinite(pts).all():
                    raise GridValueError(f"block {b + 1} face {f}: non-finite (NaN or infinite) "
                                         "coordinates; no connectivity can be found")
                h = np.full((na, nb), np.inf)
                # the edge lengths along a and b, kept for the labels (:meth:`_label`)
                ea = np.linalg.norm(np.diff(pts, axis=0), axis=-1) if na >= 2 else None
                eb = np.linalg.norm(np.diff(pts, axis=1), axis=-1) if nb >= 2 else None
                if ea is not None:
                    e = np.where(ea > tiny, ea, np.inf)
                    h[:-1] = np.minimum(h[:-1], e)
                    h[1:] = np.minimum(h[1:], e)
                if eb is not None:
                    e = np.where(eb > tiny, eb, np.inf)
                    h[:, :-1] = np.minimum(h[:, :-1], e)
                    h[:, 1:] = np.minimum(h[:, 1:], e)
                edges.append((ea, eb))
                if dims[d] >= 2:
                    e = np.linalg.norm(blk.face(f, 1) - pts, axis=-1)
                    h = np.minimum(h, np.where(e > tiny, e, np.inf))
                h[~np.isfinite(h)] = fallback
                fc = _Face(b, f, na, nb, off, dims)
                self.index[(b, f)] = len(self.faces)
                self.faces.append(fc)
                xyz.append(pts.reshape(-1, 3, order="F"))
                hs.append(h.reshape(-1, order="F"))
                ijk = face_ijk(dims, f).reshape(-1, 3, order="F")
                bps.append(boff + ijk[:, 0] + dims[0] * (ijk[:, 1] + dims[1] * ijk[:, 2]))
                off += na * nb
            boff += blk.npoints
        self.xyz = np.concatenate(xyz)
        if tol is not None:
            self.tol = np.full(off, float(tol))
        else:
            # rtol x local spacing, but never below the round-off of the coordinates
            # (16 units in the last place of the file's precision) nor above h / 4
            h = np.concatenate(hs)
            single = getattr(grid.source_format, "precision", 8) == 4
            eps = float(np.finfo(np.float32 if single else np.float64).eps)
            floor = 16 * eps * np.abs(self.xyz).max(axis=1)
            self.tol = np.minimum(np.maximum(rtol * h, floor), 0.25 * h)
        self.bp = np.concatenate(bps)
        self.fid = np.concatenate([np.full(fc.size, n, dtype=np.int64) for n, fc in enumerate(self.faces)])
        self.a = np.concatenate([np.tile(np.arange(fc.na), fc.nb) for fc in self.faces])
        self.b = np.concatenate([np.repeat(np.arange(fc.nb), fc.na) for fc in self.faces])
        self.n = off
        self._label(edges)

    # ------------------------------------------------------------ labels
    def _label(self, edges) -> None:
        """Labels of the points: ``cface`` (coincident within a face), ``degenerate``, ``g``
        (coincident anywhere); ``edges``: per face its edge lengths along a ``(na - 1, nb)`` and
        along b ``(na, nb - 1)`` (None where the face has one point that way)."""
        n = self.n
        ei, ej = [], []
        for fc, (ea, eb) in zip(self.faces, edges):
            # views (nb, na) of the face's rows: point (a, b) is row off + a + na * b
            ids = np.arange(fc.off, fc.off + fc.size).reshape(fc.nb, fc.na)
            tol = self.tol[fc.sl()].reshape(fc.nb, fc.na)
            for lo, hi, e in (((slice(None), slice(None, -1)), (slice(None), slice(1, None)), ea),
                              ((slice(None, -1), slice(None)), (slice(1, None), slice(None)), eb)):
                if ids[lo].size:
                    d = e.T             # (nb, na - 1) or (nb - 1, na), as ids[lo]
                    close = d <= np.minimum(tol[lo], tol[hi])
                    ei.append(ids[lo][close])
                    ej.append(ids[hi][close])
        ei = np.concatenate(ei) if ei else np.zeros(0, np.int64)
        ej = np.concatenate(ej) if ej else np.zeros(0, np.int64)
        _, self.cface = _components(n, ei, ej)
        self.degenerate = np.bincount(self.cface, minlength=n)[self.cface] > 1
        # copies of one block point on several faces
        order = np.argsort(self.bp, kind="stable")
        same = self.bp[order[1:]] == self.bp[order[:-1]]
        pi, pj = order[1:][same], order[:-1][same]
        # labels are 0..ncomp-1: representative of label c is its first point
        _, cpre = _components(n, np.concatenate([ei, pi]), np.concatenate([ej, pj]))
        reps = np.unique(cpre, return_index=True)[1]
        rtol = np.full(reps.size, np.inf)
        np.minimum.at(rtol, cpre, self.tol)
        ri, rj = _close_pairs(self.xyz[reps], rtol)
        _, grep = _components(reps.size, ri, rj)
        self.g = grep[cpre]

    # ----------------------------------------------------------- helpers
    def ids(self, fc: _Face) -> np.ndarray:
        return np.arange(fc.off, fc.off + fc.size).reshape(fc.na, fc.nb, order="F")

    def degenerate_cells(self, fc: _Face) -> np.ndarray:
        """Cells of a face with no area (corners in at most two in-face clusters; one in 2-D)."""
        c = self.cface[fc.sl()].reshape(fc.na, fc.nb, order="F")
        act_a, act_b = fc.active
        if act_a and act_b:
            p, q, r, s = c[:-1, :-1], c[1:, :-1], c[:-1, 1:], c[1:, 1:]
            # each corner that differs from every corner before it is one more cluster
            distinct = (1 + (q != p) + ((r != p) & (r != q)) + ((s != p) & (s != q) & (s != r)))
            return distinct <= 2
        if act_a:
            return (c[:-1, :] == c[1:, :])
        if act_b:
            return (c[:, :-1] == c[:, 1:])
        return np.ones((1, 1), dtype=bool)


def _components(n, i, j):
    if len(i) == 0:
        return n, np.arange(n)
    return connected_components(n, i, j)


def _close_pairs(xyz: np.ndarray, tol: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``i < j`` with ``|x_i - x_j| <= min(tol_i, tol_j)``."""
    if len(xyz) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    bound = float(tol.max()) * (1 + 1e-12) + 1e-300
    # no pair is farther apart than the points' extent (a huge user tol would overflow tol**2)
    extent = float(np.sqrt(np.sum(np.ptp(xyz, axis=0) ** 2)))
    pairs = close_pairs(xyz, min(bound, extent * (1 + 1e-12) + 1e-300))
    i, j = pairs[:, 0], pairs[:, 1]
    d = xyz[i] - xyz[j]
    dist = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
    ok = dist <= np.minimum(tol[i], tol[j])
    return i[ok], j[ok]


# ------------------------------------------------------------- interfaces
def _candidate_pairs(geo: _Geometry) -> tuple[np.ndarray, np.ndarray]:
    """Coincident pairs of non-degenerate points on different block points, ``fid[p] <= fid[q]``."""
    nd = np.flatnonzero(~geo.degenerate)
    order = nd[np.argsort(geo.g[nd], kind="stable")]
    gs = geo.g[order]
    ps, qs = [], []
    r = 1
    while r < len(order):
        m = gs[:-r] == gs[r:]
        if not m.any():
            break
        ps.append(order[:-r][m])
        qs.append(order[r:][m])
        r += 1
    if not ps:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    p, q = np.concatenate(ps), np.concatenate(qs)
    keep = geo.bp[p] != geo.bp[q]
    p, q = p[keep], q[keep]
    swap = geo.fid[p] > geo.fid[q]
    p, q = np.where(swap, q, p), np.where(swap, p, q)
    return p, q


def _find_interfaces(geo: _Geometry) -> list[Interface]:
    p, q = _candidate_pairs(geo)
    faces = geo.faces
    na = np.array([f.na for f in faces])
    nb = np.array([f.nb for f in faces])
    offs = np.array([f.off for f in faces])
    f1, f2 = geo.fid[p], geo.fid[q]
    n1 = np.stack([na[f1], nb[f1]], axis=1)
    n2 = np.stack([na[f2], nb[f2]], axis=1)
    act1, act2 = n1 >= 2, n2 >= 2
    P = np.stack([geo.a[p], geo.b[p]], axis=1)
    Q = np.stack([geo.a[q], geo.b[q]], axis=1)
    # conf[u, v, s]: a neighbour of p along master axis u coincides with the neighbour of q
    # along slave axis v in direction (+1, -1)[s] (checked on both sides where they exist)
    conf = {}
    base1 = offs[f1] + P[:, 0] + n1[:, 0] * P[:, 1]
    base2 = offs[f2] + Q[:, 0] + n2[:, 0] * Q[:, 1]
    stride1 = np.stack([np.ones_like(f1), n1[:, 0]], axis=1)
    stride2 = np.stack([np.ones_like(f2), n2[:, 0]], axis=1)
    for u in range(2):
        for v in range(2):
            for s, sgn in enumerate((1, -1)):
                c = np.zeros(len(p), dtype=bool)
                for step in (1, -1):
                    pa = P[:, u] + step
                    qa = Q[:, v] + sgn * step
                    inr = (pa >= 0) & (pa < n1[:, u]) & (qa >= 0) & (qa < n2[:, v])
                    ip = np.where(inr, base1 + step * stride1[:, u], 0)
                    iq = np.where(inr, base2 + sgn * step * stride2[:, v], 0)
                    c |= inr & (geo.g[ip] == geo.g[iq])
                conf[u, v, s] = c
    same_count = act1.sum(axis=1) == act2.sum(axis=1)
    keys = []
    for mid, M in enumerate(_MS):
        good = same_count.copy()
        for u in range(2):
            v = int(np.abs(M[:, u]).argmax())
            sgn = int(M[v, u])
            # active axes map to active axes; inactive ones to inactive ones, unflipped
            good &= np.where(act1[:, u], act2[:, v] & conf[u, v, 0 if sgn > 0 else 1], ~act2[:, v] & (sgn > 0))
        if good.any():
            off = Q[good] - P[good] @ M.T
            keys.append(np.column_stack([f1[good], f2[good], np.full(good.sum(), mid), off]))
    if not keys:
        return []
    keys = _unique_rows(np.concatenate(keys))

    claimed = [np.zeros(f.cells, dtype=bool) for f in faces]
    found = []
    for fa, fb, mid, o0, o1 in keys:
        F1, F2, M, off = faces[fa], faces[fb], _MS[mid], np.array([o0, o1])
        for rect in _group_rectangles(geo, F1, F2, M, off):
            m_rng, s_rng, Mx, offx = rect
            if fa == fb and (s_rng[0][0], s_rng[1][0]) < (m_rng[0][0], m_rng[1][0]):
                m_rng, s_rng = s_rng, m_rng
                Mx = Mx.T.copy()
                offx = -(Mx @ offx)
            cm, cs = _cells_of(F1, m_rng), _cells_of(F2, s_rng)
            if claimed[fa][cm].any() or claimed[fb][cs].any():
                continue
            if fa == fb and all(x.start < y.stop and y.start < x.stop for x, y in zip(cm, cs)):
                continue      # a face that matches itself shifted (a block wound round more than once)
            claimed[fa][cm] = True
            claimed[fb][cs] = True
            master = PatchSpec(F1.block, F1.face, m_rng)
            found.append(Interface.from_face_map(master, F2.face, Mx, offx, F1.dims, F2.dims, F2.block))
    found.sort(key=lambda i: (i.master.block, face_index(i.master.face), i.master.range,
                              i.slave.block, face_index(i.slave.face), i.slave.range))
    return found


def _unique_rows(k: np.ndarray) -> np.ndarray:
    """Distinct rows of an int array (n, 5), sorted; faster than ``np.unique(axis=0)``."""
    order = np.lexsort(k.T[::-1])
    k = k[order]
    new = np.ones(len(k), dtype=bool)
    new[1:] = (k[1:] != k[:-1]).any(axis=1)
    return k[new]


def _cells_of(fc: _Face, rng) -> tuple[slice, slice]:
    (a0, a1), (b0, b1) = rng
    sa = slice(a0, max(a1, a0 + 1)) if fc.na >= 2 else slice(0, 1)
    sb = slice(b0, max(b1, b0 + 1)) if fc.nb >= 2 else slice(0, 1)
    return sa, sb


def _group_rectangles(geo, F1: _Face, F2: _Face, M, off):
    """Maximal rectangles of F1 whose points coincide with F2 under ``q = M p + off``."""
    ids1 = geo.ids(F1)
    A, B = np.meshgrid(np.arange(F1.na), np.arange(F1.nb), indexing="ij")
    QA = M[0, 0] * A + M[0, 1] * B + off[0]
    QB = M[1, 0] * A + M[1, 1] * B + off[1]
    inr = (QA >= 0) & (QA < F2.na) & (QB >= 0) & (QB < F2.nb)
    ids2 = F2.off + np.where(inr, QA + F2.na * QB, 0)
    ok = inr & (geo.g[ids1] == geo.g[ids2])
    if F1 is F2:
        # a point of a face matching itself, or an in-face neighbour, is a fold: no interface
        ok &= (geo.bp[ids1] != geo.bp[ids2]) & (geo.cface[ids1] != geo.cface[ids2])
    # on two faces of one block, a block point the map sends to itself (their common edge,
    # e.g. the centre of a block wrapped round a point) belongs to both sides
    act_a, act_b = F1.active
    cell = ok
    if act_a:
        cell = cell[:-1, :] & cell[1:, :]
    if act_b:
        cell = cell[:, :-1] & cell[:, 1:]
    if not cell.any():
        return []
    deg = geo.degenerate_cells(F1)
    out = []
    for r0, r1, c0, c1 in _rectangles(cell):
        if deg[r0:r1 + 1, c0:c1 + 1].all():
            continue
        a_rng = (r0, r1 + 1) if act_a else (0, 0)
        b_rng = (c0, c1 + 1) if act_b else (0, 0)
        p0 = np.array([a_rng[0], b_rng[0]])
        p1 = np.array([a_rng[1], b_rng[1]])
        q0, q1 = M @ p0 + off, M @ p1 + off
        s_rng = ((int(min(q0[0], q1[0])), int(max(q0[0], q1[0]))),
                 (int(min(q0[1], q1[1])), int(max(q0[1], q1[1]))))
        out.append(((a_rng, b_rng), s_rng, M, off))
    return out


# ---------------------------------------------------------------- patches
def _as_specs(items, what: str, grid) -> list[PatchSpec]:
    if items is None:
        return []
    if isinstance(items, (str, PatchSpec)):
        items = [items]
    out = []
    for it in items:
        try:
            s = parse_patch_spec(it) if isinstance(it, str) else it
            if not isinstance(s, PatchSpec):
                raise ConnectivityError(f"{what} {it!r}: expected a PatchSpec or 'BLOCK:FACE[:range]'")
            r = s.resolve(grid)
        except CaseError as exc:
            raise ConnectivityError(f"{what} {it}: {exc}") from None
        out.append(r)
    return out


def _plane(points: np.ndarray, ndim: int):
    """Best plane ``(origin, normal, deviation)``: normal None when the points span no plane.

    ``deviation`` is the largest distance of a point from the plane relative to
    the points' extent (the largest side of their bounding box).  In 2-D the
    points are a side, in order, and the plane is the line through its two
    ends (and the z axis).
    """
    c = points.mean(axis=0)
    x = points - c
    size = float(np.ptp(points, axis=0).max()) if len(points) else 0.0
    if ndim == 2:
        # the chord between the side's end points (as the Deformer measures it)
        t = points[-1, :2] - points[0, :2]
        if not np.any(t):
            return c, None, np.inf
        n = np.array([-t[1], t[0], 0.0]) / np.hypot(t[0], t[1])
    else:
        if len(points) < 3:
            return c, None, np.inf
        _, s, vt = np.linalg.svd(x, full_matrices=False)
        if len(s) < 3 or s[1] <= 0:
            return c, None, np.inf
        n = vt[2]
    # a reproducible sign: largest component positive; no negative zeros
    if n[np.argmax(np.abs(n))] < 0:
        n = -n
    n = n + 0.0
    return c, n, float(np.max(np.abs(x @ n))) / size


def _classify(geo: _Geometry, interfaces, base_patches, walls, symmetry, fixed, default,
              auto_symmetry: bool, notes: list[str]) -> list[Patch]:
    grid = geo.grid
    if default not in KINDS:
        raise ConnectivityError(f"default kind {default!r} is not one of {', '.join(KINDS)}")
    user = [(s, "wall") for s in _as_specs(walls, "wall", grid)] + \
           [(s, "symmetry") for s in _as_specs(symmetry, "symmetry", grid)] + \
           [(s, "fixed") for s in _as_specs(fixed, "fixed", grid)]
    covered = [np.zeros(f.cells, dtype=bool) for f in geo.faces]
    for itf in interfaces:
        for s in (itf.master, itf.slave):
            fc = geo.faces[geo.index[(s.block, s.face)]]
            covered[geo.index[(s.block, s.face)]][_cells_of(fc, s.range)] = True
    # source label per cell: -1 unassigned, else index into sources
    sources: list[tuple[str, Patch | PatchSpec, str]] = []   # (origin, object, kind)
    label = [np.full(f.cells, -1, dtype=np.int64) for f in geo.faces]
    for p in base_patches:
        if p.origin not in ("user", "file"):
            continue
        k = geo.index.get((p.spec.block, p.spec.face))
        if k is None:
            raise ConnectivityError(f"patch {p.spec}: no such boundary face in the grid")
        label[k][_cells_of(geo.faces[k], p.spec.range)] = len(sources)
        sources.append((p.origin, p, p.kind))
    owner = [np.full(f.cells, -1, dtype=np.int64) for f in geo.faces]
    for n, (s, kind) in enumerate(user):
        k = geo.index[(s.block, s.face)]
        fc = geo.faces[k]
        (a0, a1), (b0, b1) = s.range
        if (fc.na >= 2 and a1 == a0) or (fc.nb >= 2 and b1 == b0):
            raise ConnectivityError(f"{kind} {s}: the range has no area (a line of points); "
                                    "give at least two points in each direction")
        cs = _cells_of(fc, s.range)
        prev = owner[k][cs]
        if (prev >= 0).any():
            other, okind = user[int(prev[prev >= 0][0])]
            raise ConnectivityError(f"{kind} {s} overlaps {okind} {other} on block {s.block + 1} face {s.face}")
        owner[k][cs] = n
        if covered[k][cs].all():
            notes.append(f"{kind} {s} lies entirely on interfaces: ignored")
        elif covered[k][cs].any() and s.range != ((0, fc.na - 1), (0, fc.nb - 1)):
            # a whole face is reduced silently (that is what it means); a given range is reported
            notes.append(f"{kind} {s} is partly on interfaces: only its part off them is {kind}")
        label[k][cs] = len(sources)
        sources.append(("user", s, kind))

    patches: list[Patch] = []
    for k, fc in enumerate(geo.faces):
        deg = geo.degenerate_cells(fc)
        key = np.where(covered[k], -1, (label[k] + 1) * 2 + deg)
        for v in np.unique(key):
            if v < 0:
                continue
            src, isdeg = int(v) // 2 - 1, bool(int(v) % 2)
            for r0, r1, c0, c1 in _rectangles(key == v):
                rng = ((r0, r1 + 1) if fc.na >= 2 else (0, 0), (c0, c1 + 1) if fc.nb >= 2 else (0, 0))
                spec = PatchSpec(fc.block, fc.face, rng)
                if src >= 0:
                    origin, obj, kind = sources[src]
                    name = obj.name if isinstance(obj, Patch) else None
                    patches.append(Patch(spec, kind, name, isdeg, origin))
                elif isdeg:
                    patches.append(Patch(spec, "free", None, True, "collapsed"))
                    notes.append(f"collapsed {spec}: its points coincide (a pole or a line), kind free")
                else:
                    patches.append(Patch(spec, default, None, False, "default"))

    # symmetry planes; automatic symmetry for planar unclassified patches next to walls
    wall_nodes = np.unique(np.concatenate(
        [geo.g[_patch_ids(geo, p.spec)] for p in patches if p.kind == "wall"] or [np.zeros(0, np.int64)]))
    out = []
    for p in patches:
        if p.collapsed:
            out.append(p)
            continue
        ids = _patch_ids(geo, p.spec)
        if p.kind == "symmetry":
            c, n, dev = _plane(geo.xyz[ids], geo.ndim)
            if n is None or dev > PLANE_RTOL:
                notes.append(f"symmetry {p.spec} is not planar (points up to {dev:.3g} of its size "
                             f"off the best plane, more than {PLANE_RTOL:g})")
                out.append(p)
            else:
                out.append(Patch(p.spec, p.kind, p.name, False, p.origin, (tuple(c.tolist()), tuple(n.tolist()))))
            continue
        if auto_symmetry and p.origin == "default" and wall_nodes.size and np.isin(geo.g[ids], wall_nodes).any():
            c, n, dev = _plane(geo.xyz[ids], geo.ndim)
            if n is not None and dev <= PLANE_RTOL:
                nn = ", ".join(f"{v:.6g}" for v in n)
                what = "straight" if geo.ndim == 2 else "planar"
                notes.append(f"symmetry (auto) {p.spec}: {what}, touches a wall, not classified; normal ({nn})")
                out.append(Patch(p.spec, "symmetry", p.name, False, "auto", (tuple(c.tolist()), tuple(n.tolist()))))
                continue
        out.append(p)
    out.sort(key=lambda p: (p.spec.block, face_index(p.spec.face), p.spec.range))
    return out


def _patch_ids(geo: _Geometry, spec: PatchSpec) -> np.ndarray:
    fc = geo.faces[geo.index[(spec.block, spec.face)]]
    (a0, a1), (b0, b1) = spec.range
    return geo.ids(fc)[a0:a1 + 1, b0:b1 + 1].ravel()


# ------------------------------------------------------------ file checks
def interface_mismatches(conn: Connectivity, grid, *, fraction: float = 0.25) -> list[tuple]:
    """Interfaces whose master and slave points do not coincide.

    A point pair is a mismatch when its distance exceeds ``fraction`` of the
    smallest non-zero edge next to the master point on its face (and 16 units
    in the last place of the coordinates): a wrong Transform, offset or swap
    flag moves points by at least a cell, while tolerances that bridge small
    gaps between blocks stay well below.

    Parameters
    ----------
    conn : Connectivity
        Checked against the grid's dimensions first.
    grid : Grid

    Returns
    -------
    list of tuple
        ``(index, master_ijk, slave_ijk, distance, spacing)`` for the worst
        point of each bad interface (0-based block indices).
    """
    conn.check(grid)
    out = []
    for n, it in enumerate(conn.interfaces):
        s = it.master
        blk = grid[s.block]
        pts = blk.face(s.face)
        (a0, a1), (b0, b1) = s.range
        pts = pts[a0:a1 + 1, b0:b1 + 1]
        ext = float(np.linalg.norm(np.subtract(*blk.bbox()[::-1]))) or 1.0
        h = np.full(pts.shape[:2], np.inf)
        for ax in (0, 1):
            if pts.shape[ax] > 1:
                e = np.linalg.norm(np.diff(pts, axis=ax), axis=-1)
                e = np.where(e > 1e-10 * ext, e, np.inf)
                lo = [slice(None)] * 2
                hi = [slice(None)] * 2
                lo[ax], hi[ax] = slice(None, -1), slice(1, None)
                h[tuple(lo)] = np.minimum(h[tuple(lo)], e)
                h[tuple(hi)] = np.minimum(h[tuple(hi)], e)
        h[~np.isfinite(h)] = ext
        lo, hi = it.point_range
        ii = np.stack(np.meshgrid(*[np.arange(u, v + 1) for u, v in zip(lo, hi)], indexing="ij"), -1)
        # (points of the range in face order a, b)
        d_, ax_a, ax_b = face_axes(s.face)
        ii = np.moveaxis(ii, (ax_a, ax_b), (0, 1)).reshape(pts.shape[:2] + (3,))
        jj = it.slave_index(ii)
        xm = blk.xyz[ii[..., 0], ii[..., 1], ii[..., 2]]
        xs = grid[it.slave.block].xyz[jj[..., 0], jj[..., 1], jj[..., 2]]
        dist = np.linalg.norm(xm - xs, axis=-1)
        floor = 16 * np.finfo(np.float64).eps * np.maximum(np.abs(xm).max(axis=-1), np.abs(xs).max(axis=-1))
        ratio = dist / np.maximum(fraction * h, floor)
        if ratio.max() > 1:
            w = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
            out.append((n, tuple(int(v) for v in ii[w]), tuple(int(v) for v in jj[w]), float(dist[w]),
                        float(h[w])))
    return out


def check_interfaces(conn: Connectivity, grid, where=None) -> None:
    """Raise :class:`ConnectivityError` for the first interface whose points do not coincide.

    ``where(n)`` gives the message prefix for interface ``n`` (a file and line).
    """
    bad = interface_mismatches(conn, grid)
    if bad:
        n, mi, si, dist, h = bad[0]
        it = conn.interfaces[n]
        head = where(n) if where is not None else f"interface {n + 1}"
        one = ", ".join(str(v + 1) for v in mi)
        two = ", ".join(str(v + 1) for v in si)
        raise ConnectivityError(
            f"{head}: {it} does not match the grid: point ({one}) of block {it.master.block + 1} is "
            f"{dist:.3g} from its partner ({two}) of block {it.slave.block + 1}, the spacing there is "
            f"{h:.3g} (a wrong Transform, range or swap flag?)")


# ------------------------------------------------------------------ public
def connect(grid, *, tol=None, rtol=DEFAULT_RTOL, walls=(), symmetry=(), fixed=(), default="fixed",
            auto_symmetry: bool = True) -> Connectivity:
    """Find the point-matched interfaces of a grid and classify the rest of its boundary.

    Parameters
    ----------
    grid : Grid
    tol : float, optional
        Absolute matching distance.  Default: ``rtol`` times the smallest
        adjacent edge length at each point, at least 16 units in the last
        place of the coordinates and at most a quarter of that edge (both
        points of a pair must agree).
    rtol : float
        Relative matching tolerance used when ``tol`` is None (default 1e-6).
    walls, symmetry, fixed : sequence of PatchSpec or str
        User kinds: whole faces or sub-ranges (``"1:jmin"``, ``"2:imax:1-9,1-5"``).
        Interfaces on them take precedence (a whole-face wall is reduced by
        the interfaces on it).
    default : {"fixed", "free", "wall", "symmetry"}
        Kind of the unclassified rest (default ``"fixed"``).
    auto_symmetry : bool
        Make unclassified planar patches (straight in 2-D) that touch a wall
        ``symmetry``, with a note.

    Returns
    -------
    Connectivity
        Interfaces (master -> slave with a CGNS Transform), patches with
        kinds, and notes.

    Raises
    ------
    ConnectivityError
        Unknown blocks or faces, ranges out of bounds or without area,
        overlapping user patches.
    """
    geo = _Geometry(grid, tol, rtol)
    # validate user input before the search
    for items, what in ((walls, "wall"), (symmetry, "symmetry"), (fixed, "fixed")):
        _as_specs(items, what, grid)
    interfaces = _find_interfaces(geo)
    notes: list[str] = []
    patches = _classify(geo, interfaces, [], walls, symmetry, fixed, default, auto_symmetry, notes)
    return Connectivity(interfaces, patches, grid.ndim, grid.dims, notes)


def classify(conn: Connectivity, grid, walls=(), symmetry=(), fixed=(), default="fixed", *,
             tol=None, rtol=DEFAULT_RTOL, auto_symmetry: bool = True) -> Connectivity:
    """Apply user kinds to a connectivity: rebuild its patches around its interfaces.

    Patches that came from the user or a file keep their kinds unless a new
    user patch overrides them; the rest gets ``default`` (collapsed parts:
    ``free``) and planar parts next to walls become ``symmetry``.

    Parameters
    ----------
    conn : Connectivity
        From :func:`connect`, :meth:`Connectivity.from_json` or
        :meth:`Connectivity.from_nmf`.
    grid : Grid
        The grid it describes (checked).
    walls, symmetry, fixed, default, tol, rtol, auto_symmetry
        As for :func:`connect`.

    Returns
    -------
    Connectivity
        Same interfaces, new patches and notes.
    """
    conn.check(grid)
    overlaps = conn.overlaps()
    if overlaps:
        first, second = overlaps[0]
        raise ConnectivityError(f"{second[0]} {conn.item_spec(second)} overlaps {first[0]} "
                                f"{conn.item_spec(first)}: "
                                "every boundary cell must belong to one patch or interface side")
    geo = _Geometry(grid, tol, rtol)
    notes: list[str] = []
    patches = _classify(geo, conn.interfaces, conn.patches, walls, symmetry, fixed, default,
                        auto_symmetry, notes)
    return Connectivity(conn.interfaces, patches, grid.ndim, grid.dims, notes)


def node_labels(grid, *, tol=None, rtol=DEFAULT_RTOL) -> dict:
    """Geometric node labels of every boundary point: equal labels = coincident points.

    Points coincide when they are within the matching tolerance of
    :func:`connect`, across faces, blocks and within a face (poles,
    collapsed faces, wake cuts).  This identifies the vertices and segments
    shared by several blocks, including those where blocks only touch along
    an edge or at a corner.

    Parameters
    ----------
    grid : Grid
    tol, rtol
        As for :func:`connect`.

    Returns
    -------
    dict
        ``(block, face) -> ndarray of int64, shape (na, nb)`` for every
        boundary face (four per block in 2-D, six in 3-D); labels run from 0
        to the number of distinct boundary points - 1.
    """
    geo = _Geometry(grid, tol, rtol)
    _, dense = np.unique(geo.g, return_inverse=True)
    return {(fc.block, fc.face): dense[fc.sl()].reshape(fc.na, fc.nb, order="F") for fc in geo.faces}
