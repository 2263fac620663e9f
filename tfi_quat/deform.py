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
   vertices, the gaps of each segment with their arclength parameters, the
   arclength parameters and leading direction of each derived patch, and the
   arclength parameters and direction order of each block.

A step (:meth:`Deformer.deform`): wall quaternions and translations
(:func:`tfi_quat.boundary.boundary_motion`, DESIGN 3.1), vertices (decayed
inverse-distance blend), segments (translation linear, quaternion slerp in
arclength), patches (2-D Soni TFI), symmetry (put back on the plane), then
each block by the fused 3-D (or 2-D) TFI kernel, whose boundary points are
finally overwritten by the global values so walls are exact and interfaces
bit-identical.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np

from . import quaternion as qa
from . import tfi
from ._jit import jit
from .errors import CaseError, DeformationError
from .grid import FACES, Block, Grid
from .spec import PatchSpec, as_patch_specs, parse_patch_spec

__all__ = ["Deformer", "rigid_motion", "StepTimings"]

WALL, FIXED, SYMMETRY, DERIVED = 3, 2, 1, 0
_ORIGIN = np.zeros(3)


def _hermite(s: np.ndarray) -> np.ndarray:
    """In place: s -> 3 s^2 - 2 s^3 (0 and 1 stay exact, zero slope at both ends)."""
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


def _as_specs(items, what: str) -> list[PatchSpec]:
    return as_patch_specs(items, what)


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
    """Seconds spent in each stage of the last :meth:`Deformer.deform` call."""

    walls: float = 0.0
    skeleton: float = 0.0
    faces: float = 0.0
    volumes: float = 0.0

    @property
    def total(self) -> float:
        return self.walls + self.skeleton + self.faces + self.volumes


# ------------------------------------------------------------- kernels
@jit
def _fill_gaps(gdelta, gq, left, right, ptr, pts, s, use_q):
    """Segments: delta linear, q slerp in arclength between known end points."""
    tmp = np.empty(4)
    for g in range(left.shape[0]):
        a = left[g]
        b = right[g]
        for m in range(ptr[g], ptr[g + 1]):
            p = pts[m]
            t = s[m]
            for c in range(3):
                gdelta[p, c] = (1.0 - t) * gdelta[a, c] + t * gdelta[b, c]
            if use_q:
                qa.kslerp(gq[a], gq[b], t, tmp)
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


# ------------------------------------------------------------- set-up data
def _twist_about(q: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The rotation of each ``q`` about the unit axis ``n`` (swing-twist split)."""
    tw = np.empty_like(q)
    tw[:, 0] = q[:, 0]
    tw[:, 1:] = n * np.sum(q[:, 1:] * n, axis=1, keepdims=True)
    norm = np.linalg.norm(tw, axis=1)
    tw[norm == 0.0] = [1.0, 0.0, 0.0, 0.0]
    norm[norm == 0.0] = 1.0
    return tw / norm[:, None]


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
    s: np.ndarray              # (na, nb, 2)
    lead: int
    write: np.ndarray          # bool (na, nb): interior points this patch defines
    block: int = 0
    face: str = ""
    e: np.ndarray | None = None   # local formulation: P - TFI(P on the sides), written points
    params: tuple | None = None   # tfi.patch_params(s), for the compiled patch kernel


@dataclass
class _Wall:
    spec: PatchSpec
    gid: np.ndarray            # (na, nb) or (n,) for 2-D curves
    halo: np.ndarray           # (na+2, nb+2) or (n+2,), -1 where no neighbour
    mirror: np.ndarray         # same shape: symmetry plane whose mirror image of halo is used, or -1


@dataclass
class _BlockPlan:
    s: np.ndarray                       # arclength parameters (ni, nj, nk, 3)
    order: tuple[int, ...]
    face_gid: list[np.ndarray] = field(default_factory=list)   # per face (na, nb)
    e: np.ndarray | None = None         # local formulation: R_u - TFI(R_u on the faces)


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
        ``quaternion``: interpolate translations and rotations (Samareh);
        ``tfi``: the classic baseline, displacements only.
    centre : array_like (3,), optional
        Rotation centre ``c`` of the field update.  Default: the centroid of
        the undeformed wall points (it moves with the problem, DESIGN 3.6).
    tol : float, optional
        Coincidence tolerance for merging boundary points; default
        1e-10 x the grid's bounding-box diagonal.
    blending : {"hermite", "linear"}
        Blending function applied to the normalised arclength ``s`` of every
        interpolation (segments, patches, volumes).  ``linear`` is Soni's
        original ``s``; ``hermite`` (default) is ``3 s^2 - 2 s^3``, which has
        zero slope at both ends, so the layers next to a wall move with the
        wall's own rotation and translation and keep their angle to it (the
        linear form shears them by about ``|delta| / L``, a few degrees for
        large motions).  Both reproduce the boundaries exactly.
    idw_power : float
        Exponent of the inverse-distance weights of free vertices.
    formulation : {"samareh", "local"}
        How rotations act on positions (``method="quaternion"`` only).
        ``samareh`` (default, the memo): ``R_d = c + Δ + rot(Q, R_u - c)``
        with Δ and Q interpolated, arms measured from the centre ``c``.
        ``local``: ``R_d = TFI(boundary R_d) + rot(Q, E)`` with
        ``E = R_u - TFI(boundary R_u)``, the grid's offset from the
        interpolant of its own boundary: no centre, arms only as long as
        that offset (see ``docs/deformer.md`` for when each is better).
    """

    def __init__(self, grid: Grid, walls=(), symmetry=(), fixed=(), connectivity=None,
                 method: str = "quaternion", centre=None, tol: float | None = None,
                 blending: str = "hermite", idw_power: float = 3.0, max_idw_sources: int = 2000,
                 formulation: str = "samareh"):
        if not isinstance(grid, Grid):
            raise CaseError(f"grid must be a tfi_quat.Grid, got {type(grid).__name__}")
        if method not in ("quaternion", "tfi"):
            raise CaseError(f"method must be 'quaternion' or 'tfi', got {method!r}")
        if formulation not in ("local", "samareh"):
            raise CaseError(f"formulation must be 'local' or 'samareh', got {formulation!r}")
        if blending not in _BLENDINGS:
            raise CaseError(f"blending must be one of {', '.join(_BLENDINGS)}, got {blending!r}")
        t0 = time.perf_counter()
        self.blending = blending
        self._psi = _BLENDINGS[blending]
        self.grid = grid
        self.ndim = grid.ndim
        self.method = method
        self._use_q = method == "quaternion"
        self.formulation = formulation
        self._local = self._use_q and formulation == "local"
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
        walls = _as_specs(walls, "walls")
        symmetry = _as_specs(symmetry, "symmetry")
        fixed = _as_specs(fixed, "fixed")
        from . import topology
        if connectivity is None:
            connectivity = topology.connect(grid, walls=walls, symmetry=symmetry, fixed=fixed)
        elif walls or symmetry or fixed:
            connectivity = topology.classify(connectivity, grid, walls=walls, symmetry=symmetry,
                                             fixed=fixed)
        self.connectivity = connectivity
        lo, hi = grid.bbox()
        diag = float(np.linalg.norm(hi - lo)) or 1.0
        self.tol = float(tol) if tol is not None else 1e-10 * diag
        self._number_boundary_points()
        self._classify_points()
        if not np.any(self._kind == WALL):
            raise CaseError("no wall points: give at least one wall patch")
        self.centre = self._choose_centre(centre)
        self._build_walls()
        self._build_rects()
        self._build_vertices(idw_power, max_idw_sources)
        self._build_segments_and_patches()
        self._build_symmetry()
        self._build_blocks()
        if self._local:
            self._build_local_arms()
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
        ukeys, inv = np.unique(allkeys, return_inverse=True)
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
        from scipy.spatial import cKDTree
        pairs = cKDTree(P).query_pairs(self.tol, output_type="ndarray")
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
        E = np.unique(np.sort(E, axis=1), axis=0)
        nbr: dict[int, set[int]] = {}
        for a, b in E:
            nbr.setdefault(int(a), set()).add(int(b))
            nbr.setdefault(int(b), set()).add(int(a))
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
                self._walls.append(_Wall(p.spec, g[:, 0], halo[:, 1], mirror[:, 1]))
            else:
                self._walls.append(_Wall(p.spec, g, halo, mirror))
        self._wall_gids = np.flatnonzero(self._kind == WALL)

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
                s = arc[1:-1] / arc[-1]
            else:
                s = np.arange(1, run.size + 1) / (run.size + 1.0)
            # a point may repeat along a side (collapsed): keep its first occurrence
            _, keep = np.unique(run, return_index=True)
            keep.sort()
            gaps.append((int(left), int(right), run[keep], self._psi(s[keep])))
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
            s = self._psi(tfi.arclength_surface(np.ascontiguousarray(self._P[g])))
            ends = [prescribed[g[0, :]].sum() + prescribed[g[-1, :]].sum(),
                    prescribed[g[:, 0]].sum() + prescribed[g[:, -1]].sum()]
            lead = 0 if ends[0] >= ends[1] else 1
            # a point that repeats inside the patch is written once
            flat = g[inner]
            _, first = np.unique(flat, return_index=True)
            write = np.zeros(g.shape, dtype=bool)
            idx = np.argwhere(inner)[np.sort(first)]
            write[idx[:, 0], idx[:, 1]] = True
            patches.append(_PatchTFI(g, s, lead, write, r.block, r.face, params=tfi.patch_params(s)))
            known[flat] = True
        self._patches = patches
        if not known.all():
            g = int(np.flatnonzero(~known)[0])
            raise CaseError(f"boundary point at {tuple(np.round(self._P[g], 6))} is reached by no "
                            "patch, segment or vertex of the skeleton (inconsistent connectivity)")

    def _build_symmetry(self) -> None:
        sym = np.flatnonzero((self._sym_of >= 0) & (self._kind == SYMMETRY))
        self._sym_gids = sym
        if sym.size:
            planes = self._sym_of[sym]
            self._sym_point = np.array([self._sym_planes[p][0] for p in planes])
            self._sym_normal = np.array([self._sym_planes[p][1] for p in planes])

    def _build_blocks(self) -> None:
        plans = []
        prescribed = self._kind >= FIXED
        faces = _faces_of(self.ndim)
        for b, blk in enumerate(self.grid):
            s = self._psi(tfi.arclength(blk.xyz))
            fg = [self._face_gid[(b, f)] for f in faces]
            counts = [int(prescribed[g].sum()) for g in fg]
            order = tuple(int(x) for x in tfi.lead_order(counts))
            plans.append(_BlockPlan(s, order, fg))
        self._blocks = plans
        # where each block's boundary points live, for the final scatter
        blk_of = np.searchsorted(self._offsets, self._copies_key, side="right") - 1
        self._scatter = []
        for b in range(len(self.grid)):
            sel = blk_of == b
            self._scatter.append((self._copies_key[sel] - self._offsets[b], self._copies_gid[sel]))

    def _build_local_arms(self) -> None:
        """The local formulation's arms ``E = R_u - TFI(R_u from the boundary)``.

        Segments: the offset from the chord between the known end points;
        patches: from the 2-D TFI of the patch's sides; blocks: from the 3-D
        (2-D) TFI of the block's faces (sides), all with the same parameters
        and leading directions as the step uses.
        """
        P = self._P
        if self._gaps is not None:
            left, right, ptr, pts, t = self._gaps
            lo = np.repeat(left, np.diff(ptr))
            hi = np.repeat(right, np.diff(ptr))
            self._gap_e = P[pts] - ((1.0 - t)[:, None] * P[lo] + t[:, None] * P[hi])
        for p in self._patches:
            d = np.ascontiguousarray(P[p.gid])
            tfi.tfi_patch(d, None, p.s, p.lead)
            p.e = np.ascontiguousarray(P[p.gid][p.write] - d[p.write])
        zero = np.zeros(3)
        for blk, plan in zip(self.grid, self._blocks):
            fd = tuple(np.ascontiguousarray(P[g]) for g in plan.face_gid)
            base = np.zeros_like(blk.xyz, order="F")
            interp = np.empty_like(blk.xyz, order="F")
            if self.ndim == 3:
                tfi.deform_block(base, plan.s, fd, None, zero, plan.order, out=interp)
            else:
                tfi.deform_block_2d(base, plan.s, tuple(d[:, 0] for d in fd), None, zero, plan.order,
                                    out=interp)
            np.subtract(blk.xyz, interp, out=interp)
            plan.e = interp

    # -------------------------------------------------------------- a step
    def wall_points(self) -> np.ndarray:
        """Undeformed positions ``(n, 3)`` of the (distinct) wall points, in the order
        :meth:`deform` passes them to a motion callable."""
        return self._P[self._wall_gids].copy()

    def _wall_targets(self, moved) -> np.ndarray:
        """Deformed positions of every global point (only wall rows are meaningful)."""
        G = self.n_global
        rd = self._P.copy()
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
        return rd

    def _wall_stage(self, rd: np.ndarray):
        G = self.n_global
        gdelta = np.zeros((G, 3))
        gq = np.zeros((G, 4))
        gq[:, 0] = 1.0
        wall = self._wall_gids
        c = self.centre
        if not self._use_q:
            gdelta[wall] = rd[wall] - self._P[wall]
            return gdelta, None
        from .boundary import boundary_motion
        acc = np.zeros((G, 4))
        count = np.zeros(G, dtype=np.int64)
        plane = np.array([0.0, 0.0, 1.0]) if self.ndim == 2 else None
        nan3 = np.full(3, np.nan)
        for w in self._walls:
            ru = self._P[w.gid]
            rdw = rd[w.gid]
            hu = np.where((w.halo >= 0)[..., None], self._P[np.maximum(w.halo, 0)], nan3)
            hd = np.where((w.halo >= 0)[..., None], rd[np.maximum(w.halo, 0)], nan3)
            m = w.mirror >= 0
            if m.any():
                for sp in np.unique(w.mirror[m]):
                    o, n = self._sym_planes[sp]
                    sel = w.mirror == sp
                    hu[sel] -= 2.0 * ((hu[sel] - o) @ n)[:, None] * n
                    hd[sel] -= 2.0 * ((hd[sel] - o) @ n)[:, None] * n
            q, _ = boundary_motion(ru, rdw, c, plane_normal=plane, halo_u=hu, halo_d=hd)
            _merge_quaternions(w.gid.ravel(), np.ascontiguousarray(q.reshape(-1, 4)), acc, count)
        qw = acc[wall]
        qw /= np.linalg.norm(qw, axis=1, keepdims=True)
        gq[wall] = qw
        if self._local:
            # the local formulation carries deformed positions, not translations
            gdelta[:] = self._P
            gdelta[wall] = rd[wall]
            return gdelta, gq
        # the translation follows from the merged rotation: c + delta + rot(q, ru - c) = rd
        gdelta[wall] = rd[wall] - c - qa.rotate(qw, self._P[wall] - c)
        return gdelta, gq

    def _vertex_stage(self, gdelta, gq) -> None:
        if self._idw is None:
            return
        src, w, decay, ref = self._idw
        free = self._free_vertices
        if not self._local:
            gdelta[free] = decay[:, None] * (w @ gdelta[src])
        if gq is None:
            return
        qs = gq[src]                                         # (ns, 4)
        if self._local:
            # each wall source predicts the vertex by its own rigid motion,
            # rd_s + rot(q_s, P_v - P_s); the predictions are blended and decayed
            pv = self._P[free]
            pred = np.empty((free.size, 3))
            for a in range(0, free.size, 64):
                arm = pv[a:a + 64, None, :] - self._P[src][None, :, :]
                moved = gdelta[src][None] + qa.rotate(np.broadcast_to(qs, arm.shape[:2] + (4,)), arm)
                pred[a:a + 64] = np.einsum("vs,vsc->vc", w[a:a + 64], moved)
            gdelta[free] = pv + decay[:, None] * (pred - pv)
        qref = qs[ref]                                       # (nv, 4)
        sign = np.where(qref @ qs.T >= 0.0, 1.0, -1.0)       # (nv, ns)
        qbar = (w * sign) @ qs
        norm = np.linalg.norm(qbar, axis=1)
        small = norm < 1e-6
        qbar[small] = qref[small]
        qbar[~small] /= norm[~small, None]
        ident = np.zeros_like(qbar)
        ident[:, 0] = 1.0
        gq[free] = qa.slerp(ident, qbar, decay)

    def _segment_stage(self, gdelta, gq) -> None:
        if self._gaps is None:
            return
        left, right, ptr, pts, s = self._gaps
        _fill_gaps(gdelta, gq if gq is not None else np.empty((1, 4)), left, right, ptr, pts, s,
                   gq is not None)
        if self._local:
            gdelta[pts] += qa.rotate(gq[pts], self._gap_e)

    def _patch_stage(self, gdelta, gq) -> None:
        for p in self._patches:
            d = np.ascontiguousarray(gdelta[p.gid])
            q = np.ascontiguousarray(gq[p.gid]) if gq is not None else None
            tfi.tfi_patch_fast(d, q, p.params, p.lead)
            if p.e is not None:
                gdelta[p.gid[p.write]] = d[p.write] + qa.rotate(q[p.write], p.e)
            else:
                gdelta[p.gid[p.write]] = d[p.write]
            if q is not None:
                gq[p.gid[p.write]] = q[p.write]

    def _symmetry_stage(self, gdelta, gq) -> None:
        """Symmetry points: on their plane, rotating about its normal only.

        The position from the interpolated (delta, q) is projected onto the
        plane; then q is reduced to its rotation about the plane normal (its
        "twist") and delta recomputed so that the projected position is kept.
        Dropping part of the rotation without recomputing delta would move the
        point by (dropped angle) x (distance to the centre).
        """
        sym = self._sym_gids
        if sym.size == 0:
            return
        n = self._sym_normal
        c = self.centre
        arm = self._P[sym] - c
        if self._local:
            pos = gdelta[sym]
            gdelta[sym] = pos - np.sum((pos - self._sym_point) * n, axis=1, keepdims=True) * n
            gq[sym] = _twist_about(gq[sym], n)
            return
        if gq is not None:
            pos = c + gdelta[sym] + qa.rotate(gq[sym], arm)
        else:
            pos = self._P[sym] + gdelta[sym]
        pos -= np.sum((pos - self._sym_point) * n, axis=1, keepdims=True) * n
        if gq is None:
            gdelta[sym] = pos - self._P[sym]
            return
        tw = _twist_about(gq[sym], n)
        gq[sym] = tw
        gdelta[sym] = pos - c - qa.rotate(tw, arm)

    def _boundary_positions(self, gdelta, gq, rd) -> np.ndarray:
        c = self.centre
        if self._local:
            pos = gdelta.copy()
        elif gq is not None:
            pos = c + gdelta + qa.rotate(gq, self._P - c)
        else:
            pos = self._P + gdelta
        sym = self._sym_gids
        if sym.size:
            off = np.sum((pos[sym] - self._sym_point) * self._sym_normal, axis=1)
            pos[sym] -= off[:, None] * self._sym_normal
        fixed = self._kind == FIXED
        pos[fixed] = self._P[fixed]
        wall = self._wall_gids
        pos[wall] = rd[wall]
        return pos

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
            Called after each block (progress reporting).

        Returns
        -------
        Grid
            A new grid; the reference is not modified.  Every call starts from
            the reference, so repeated steps do not drift.
        """
        t0 = time.perf_counter()
        rd = self._wall_targets(moved)
        gdelta, gq = self._wall_stage(rd)
        t1 = time.perf_counter()
        self._vertex_stage(gdelta, gq)
        self._segment_stage(gdelta, gq)
        t2 = time.perf_counter()
        self._patch_stage(gdelta, gq)
        self._symmetry_stage(gdelta, gq)
        pos = self._boundary_positions(gdelta, gq, rd)
        t3 = time.perf_counter()
        out_blocks = []
        nblk = len(self.grid)
        for b, (blk, plan) in enumerate(zip(self.grid, self._blocks)):
            fd = tuple(np.ascontiguousarray(gdelta[g]) for g in plan.face_gid)
            fq = tuple(np.ascontiguousarray(gq[g]) for g in plan.face_gid) if gq is not None else None
            out = np.empty_like(blk.xyz, order="F")
            # local: TFI(boundary positions) + rot(Q, E); samareh: c + Δ + rot(Q, R_u - c)
            base, c = (plan.e, _ORIGIN) if self._local else (blk.xyz, self.centre)
            if self.ndim == 3:
                tfi.deform_block(base, plan.s, fd, fq, c, plan.order, out=out)
            else:
                sd = tuple(d[:, 0] for d in fd)
                sq = tuple(q[:, 0] for q in fq) if fq is not None else None
                tfi.deform_block_2d(base, plan.s, sd, sq, c, plan.order, out=out)
            local, gid = self._scatter[b]
            out.reshape(-1, 3, order="F")[local] = pos[gid]
            if self.ndim == 2:
                out[..., 2] = 0.0
            out_blocks.append(Block(out, blk.iblank, blk.name, allow_nonfinite=True))
            if callback is not None:
                callback(b + 1, nblk)
        t4 = time.perf_counter()
        self.timings = StepTimings(walls=t1 - t0, skeleton=t2 - t1, faces=t3 - t2, volumes=t4 - t3)
        return Grid(out_blocks, self.ndim, source_format=self.grid.source_format)

    # ------------------------------------------------------------ reporting
    def summary(self) -> str:
        """A few lines describing the skeleton (for the CLI and logs)."""
        k = self._kind
        lines = [
            f"method {self.method}, centre ({', '.join(f'{v:.6g}' for v in self.centre)})",
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

