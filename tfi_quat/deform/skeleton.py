"""The skeleton of a multiblock grid's boundaries (docs/method.md §3.3), built once.

1. Every boundary point of every block is numbered; points that coincide
   (point-matched interfaces, self-matching cuts, collapsed faces and poles)
   are merged into one **global boundary point** (:func:`boundary_points`).
   All derived data lives on global points, so it is computed once and every
   copy of a point, on any block, gets bit-identical values (docs/method.md §3.7).
2. Each global point gets a kind from the patches on it: wall beats fixed
   beats symmetry beats derived.
3. The faces are cut into rectangles: the patches and the interface ranges
   (the master of each interface; its slave is the same global points).
   Their corners are the **vertices**, their sides the **segments**.
4. What every level needs is precomputed (:func:`build_skeleton`): the wall
   patches' halos, inverse-distance weights of the free vertices, the gaps of
   each segment with their blending parameters, the parameters and leading
   direction of each derived patch, the parameters and direction order of each
   block, the symmetry planes of the symmetry points.

The blending parameters come from a *params* object with three methods:
``line(s, length, g0, g1)`` (a chain of points between known ends),
``patch(g, x)`` (a derived patch) and ``block(xyz, face_gid)`` (a block).
:class:`ArclengthParams` is the normalised arclength through a blending
function (``"samareh"``, ``"tfi"``); :class:`tfi_quat.deform.twolevel.WallLayer`
the two-level formulation's wall-layer parameters.

Everything here is a frozen dataclass: a step reads the skeleton and never
changes it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .. import tfi
from .._jit import serial_below
from ..errors import CaseError
from ..grid import Grid, face_ijk, faces_of
from ..spec import PatchSpec
from ..topology.graph import connected_components
from . import stages

__all__ = ["WALL", "FIXED", "SYMMETRY", "DERIVED", "BLENDINGS", "ArclengthParams", "BoundaryPoints",
           "WallPatch", "Walls", "Rect", "Vertices", "Segments", "Patch", "Patches", "Symmetry",
           "BlockPlan", "Skeleton", "boundary_points", "build_skeleton"]

# point kinds, in the order they win where patches meet
#: kind of a wall point (its motion is prescribed by the walls)
WALL = 3
#: kind of a fixed point (it stays where it is)
FIXED = 2
#: kind of a symmetry point (it slides on its plane)
SYMMETRY = 1
#: kind of a derived point (interpolated from the levels below)
DERIVED = 0
_KIND_CODE = {"wall": WALL, "fixed": FIXED, "symmetry": SYMMETRY}

#: blending functions of the normalised arclength (``"samareh"`` and ``"tfi"``)
BLENDINGS: dict[str, Callable[[np.ndarray], np.ndarray]] = {"hermite": stages.hermite,
                                                             "linear": lambda s: s}


def _flat(dims, ijk: np.ndarray) -> np.ndarray:
    ni, nj, _ = dims
    return ijk[..., 0] + ni * (ijk[..., 1] + nj * ijk[..., 2])


# ------------------------------------------------------------------ blending parameters
@dataclass(frozen=True)
class ArclengthParams:
    """Blending parameters ``psi(s)`` of the normalised arclength ``s`` (``"samareh"``, ``"tfi"``)."""

    psi: Callable[[np.ndarray], np.ndarray]

    def line(self, s: np.ndarray, length: float, g0: int, g1: int) -> np.ndarray:
        """A chain of points between known ends (``s``: normalised arclength, both ends included)."""
        return self.psi(np.array(s, dtype=np.float64))

    def patch(self, g: np.ndarray, x: np.ndarray) -> np.ndarray:
        """A derived patch ``(na, nb, 2)`` of global ids ``g`` at points ``x`` (na, nb, 3)."""
        return self.psi(tfi.arclength_surface(x))

    def block(self, xyz: np.ndarray, face_gid: list) -> np.ndarray:
        """A block ``(ni, nj, nk, 3)``."""
        return self.psi(tfi.arclength(xyz))


# ------------------------------------------------------------------ global boundary points
@dataclass(frozen=True)
class BoundaryPoints:
    """The distinct boundary points of a grid and their kinds.

    ``P`` (G, 3): undeformed positions; ``rep_key`` (G,): the flat key (block
    offset + point index) of a representative copy; ``offsets`` (nblk + 1,):
    each block's first key; ``face_gid``: ``(block, face) -> (na, nb)`` global
    ids of the whole face; ``copies_key``, ``copies_gid``: every copy of every
    global point; ``kind`` (G,) int8: WALL, FIXED, SYMMETRY or DERIVED;
    ``sym_of`` (G,): the symmetry plane of each point, or -1; ``plane_o``,
    ``plane_n`` (npl, 3): the planes' centroids and unit normals; ``wall``:
    the wall points' global ids, ascending.
    """

    P: np.ndarray
    rep_key: np.ndarray
    offsets: np.ndarray
    face_gid: dict
    copies_key: np.ndarray
    copies_gid: np.ndarray
    kind: np.ndarray
    sym_of: np.ndarray
    plane_o: np.ndarray
    plane_n: np.ndarray
    wall: np.ndarray

    @property
    def n_global(self) -> int:
        return self.P.shape[0]

    def rect_gid(self, spec: PatchSpec) -> np.ndarray:
        """Global ids ``(na, nb)`` of a face range."""
        (a0, a1), (b0, b1) = spec.range
        return self.face_gid[(spec.block, spec.face)][a0:a1 + 1, b0:b1 + 1]


def _number(grid: Grid, connectivity, tol: float, marker: bool = True):
    """Global ids of every boundary point: ``(offsets, P, rep_key, face_gid, copies_key, copies_gid)``.

    Reads the blocks' faces only (``grid`` may be a :class:`.shell.ShellGrid`); ``marker``:
    allow a marker array over all grid points where it beats sorting the keys."""
    keys, offsets = [], [0]
    for blk in grid:
        offsets.append(offsets[-1] + blk.npoints)
    offsets = np.array(offsets, dtype=np.int64)
    full = {}
    for b, blk in enumerate(grid):
        for f in faces_of(grid.ndim):
            dims = blk.dims
            ijk = face_ijk(dims, f)
            key = offsets[b] + _flat(dims, ijk)
            full[(b, f)] = key
            keys.append(key.ravel())
    allkeys = np.concatenate(keys)
    total = int(offsets[-1])
    if marker and total <= 32 * allkeys.size:
        # a marker per grid point beats sorting the keys (the copies of edge points)
        mark = np.zeros(total, dtype=bool)
        mark[allkeys] = True
        ukeys = np.flatnonzero(mark)
        del mark
    else:
        ukeys = np.unique(allkeys)
    nb = ukeys.size
    # coordinates of each boundary point, from the faces (a point on several faces of its
    # block is written once per face, with the same value)
    P = np.empty((nb, 3))
    for b, blk in enumerate(grid):
        for f in faces_of(grid.ndim):
            P[np.searchsorted(ukeys, full[(b, f)])] = blk.face(f)
    # merge coincident points (interfaces, cuts, collapsed faces) ...
    from .._points import close_pairs
    pairs = close_pairs(P, tol)
    rows = [pairs[:, 0]] if len(pairs) else []
    cols = [pairs[:, 1]] if len(pairs) else []
    # ... and the connectivity's interfaces, which are authoritative
    for itf in connectivity.interfaces:
        m = itf.master
        mi = face_ijk(grid[m.block].dims, m.face, m.range).reshape(-1, 3)
        si = np.asarray(itf.slave_index(mi), dtype=np.int64).reshape(-1, 3)
        km = offsets[m.block] + _flat(grid[m.block].dims, mi)
        ks = offsets[itf.slave.block] + _flat(grid[itf.slave.block].dims, si)
        rows.append(np.searchsorted(ukeys, km))
        cols.append(np.searchsorted(ukeys, ks))
    if rows:
        r = np.concatenate(rows)
        c = np.concatenate(cols)
        ncomp, comp = connected_components(nb, r, c)
    else:
        ncomp, comp = nb, np.arange(nb)
    # global ids numbered by first appearance, representatives = first member
    first = np.full(ncomp, -1, dtype=np.int64)
    order = np.arange(nb)[::-1]
    first[comp[order]] = order
    bid_to_gid = comp.astype(np.int64)
    face_gid = {k: bid_to_gid[np.searchsorted(ukeys, v)] for k, v in full.items()}
    # every (block, key) copy of every global point, for the final scatter
    return offsets, P[first], ukeys[first], face_gid, ukeys, bid_to_gid


def _classify(P, face_gid, connectivity, ndim: int):
    """``(kind, sym_of, planes)``: each point's kind and symmetry plane, the planes (centroid, normal)."""
    G = P.shape[0]
    kind = np.zeros(G, dtype=np.int8)
    sym_of = np.full(G, -1, dtype=np.int64)
    planes: list[tuple[np.ndarray, np.ndarray]] = []
    for p in connectivity.patches:
        code = _KIND_CODE.get(p.kind, DERIVED)
        (a0, a1), (b0, b1) = p.spec.range
        gid = face_gid[(p.spec.block, p.spec.face)][a0:a1 + 1, b0:b1 + 1]
        if code == SYMMETRY:
            pts = P[gid.ravel()]
            centroid = pts.mean(axis=0)
            if ndim == 2:
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
            sym_of[gid.ravel()] = len(planes)
            planes.append((centroid, normal))
        kind[gid.ravel()] = np.maximum(kind[gid.ravel()], code)
    return kind, sym_of, planes


def boundary_points(grid: Grid, connectivity, tol: float, *, marker: bool = True) -> BoundaryPoints:
    """Number, merge (within ``tol`` and across the connectivity's interfaces) and classify the
    boundary points of ``grid`` (its faces only; ``marker`` False: nothing the size of the
    whole grid is allocated, for a distributed set-up)."""
    offsets, P, rep_key, face_gid, copies_key, copies_gid = _number(grid, connectivity, tol, marker)
    kind, sym_of, planes = _classify(P, face_gid, connectivity, grid.ndim)
    npl = len(planes)
    return BoundaryPoints(P=P, rep_key=rep_key, offsets=offsets, face_gid=face_gid,
                          copies_key=copies_key, copies_gid=copies_gid, kind=kind, sym_of=sym_of,
                          plane_o=np.array([o for o, _ in planes]).reshape(npl, 3),
                          plane_n=np.array([n for _, n in planes]).reshape(npl, 3),
                          wall=np.flatnonzero(kind == WALL))


# ------------------------------------------------------------------ the levels
@dataclass(frozen=True)
class WallPatch:
    """A wall patch and its halo (its neighbours across the patch edges).

    ``gid`` (na, nb), or (n,) for 2-D curves; ``halo``: (na+2, nb+2) or (n+2,),
    C order, -1 where no neighbour; ``mirror``: same shape, the symmetry plane
    whose mirror image of the halo point is used, or -1; ``pu``: the undeformed
    halo points as :func:`tfi_quat.boundary.boundary_motion` takes them:
    (na+2, nb+2, 3) or (n+2, 1, 3), NaN where no neighbour.
    """

    spec: PatchSpec
    gid: np.ndarray
    halo: np.ndarray
    mirror: np.ndarray
    pu: np.ndarray


@dataclass(frozen=True)
class Walls:
    """The wall patches; ``local``: each patch's points as indices into the wall points
    (``BoundaryPoints.wall``); ``edges`` (E, 2): the wall-surface graph in global ids."""

    patches: tuple[WallPatch, ...]
    local: tuple[np.ndarray, ...]
    edges: np.ndarray


@dataclass(frozen=True)
class Rect:
    """A rectangle of a face: a patch, or one side of an interface (``kind`` "interface")."""

    block: int
    face: str
    gid: np.ndarray            # (na, nb) global point ids
    kind: str
    slave: bool = False


@dataclass(frozen=True)
class Vertices:
    """The rectangles' corners and the free ones' inverse-distance weights: ``idw`` =
    ``(src, w, decay, ref)`` (source wall points, weights (nv, ns), decay towards fixed
    points, the strongest source of each vertex), None without free vertices."""

    corners: np.ndarray
    free: np.ndarray
    idw: tuple | None


@dataclass(frozen=True)
class Segments:
    """The gaps of the rectangles' sides, gap by gap: ends ``left``, ``right`` (G,);
    points ``pts[ptr[g]:ptr[g + 1]]`` with blending parameters ``s``."""

    left: np.ndarray
    right: np.ndarray
    ptr: np.ndarray
    pts: np.ndarray
    s: np.ndarray

    def arrays(self) -> tuple:
        return self.left, self.right, self.ptr, self.pts, self.s


@dataclass(frozen=True)
class Patch:
    """A derived patch: global ids, blending parameters (na, nb, 2), leading direction and
    the interior points it writes (bool (na, nb); a point repeated inside it is written once)."""

    gid: np.ndarray
    s: np.ndarray
    lead: int
    write: np.ndarray
    block: int = 0
    face: str = ""


@dataclass(frozen=True)
class Patches:
    """The derived patches and their packing for :func:`stages.patch_level` (one call)."""

    items: tuple[Patch, ...]
    pack: tuple
    npoints: int

    @property
    def written(self) -> np.ndarray:
        """Global ids of the points the patches write, in the packing's order."""
        return self.pack[1][self.pack[3]]


@dataclass(frozen=True)
class Symmetry:
    """The symmetry points (``gids``) with a point and unit normal of their plane each."""

    gids: np.ndarray
    point: np.ndarray
    normal: np.ndarray


@dataclass(frozen=True)
class BlockPlan:
    """A block: blending parameters (ni, nj, nk, 3), direction order, global ids of its faces,
    :func:`tfi.face_params` and the :func:`tfi.gather_plan` its kernel reads the faces through."""

    s: np.ndarray
    order: tuple[int, ...]
    face_gid: list
    face_s: tuple
    gather: object


@dataclass(frozen=True)
class Skeleton:
    """Everything a step reads: the boundary points, the hierarchy levels, the blocks.

    ``derived``: the derived points' global ids; ``scatter``: per block, the local flat
    indices of its boundary points and their global ids (the result's boundary copies);
    ``wall_rows``: the wall points a step fills (indices into ``points.wall``; None: all,
    an MPI rank's part: those it reads, :mod:`.distributed`).
    """

    ndim: int
    tol: float
    points: BoundaryPoints
    walls: Walls
    rects: tuple[Rect, ...]
    vertices: Vertices
    segments: Segments | None
    patches: Patches
    derived: np.ndarray
    symmetry: Symmetry
    blocks: tuple[BlockPlan, ...]
    scatter: tuple
    wall_rows: np.ndarray | None = None

    @property
    def n_global(self) -> int:
        return self.points.n_global

    def step_walls(self) -> tuple:
        """``(gids, rows)``: the wall points a step fills, as global ids and as indices into
        ``points.wall`` (all of them: ``rows`` is ``slice(None)``)."""
        if self.wall_rows is None:
            return self.points.wall, slice(None)
        return self.points.wall[self.wall_rows], self.wall_rows


def _walls(pts: BoundaryPoints, connectivity, ndim: int) -> Walls:
    """Wall patches with their halos (neighbours across the patch edges)."""
    walls = [p for p in connectivity.patches if p.kind == "wall"]
    curve = ndim == 2
    # wall-surface graph: in-patch neighbours, in global ids
    edges = []
    for p in walls:
        g = pts.rect_gid(p.spec)
        if g.shape[0] > 1:
            edges.append(np.stack([g[:-1].ravel(), g[1:].ravel()], 1))
        if g.shape[1] > 1 and not curve:
            edges.append(np.stack([g[:, :-1].ravel(), g[:, 1:].ravel()], 1))
    E = np.concatenate(edges) if edges else np.empty((0, 2), dtype=np.int64)
    E = E[E[:, 0] != E[:, 1]]
    E = np.sort(E, axis=1)
    G = np.int64(pts.n_global)
    key = np.unique(E[:, 0] * G + E[:, 1])
    E = np.stack([key // G, key % G], axis=1)
    # neighbour sets of the points on the patches' edges (the only ones `across` asks for)
    on_edge = np.zeros(pts.n_global, dtype=bool)
    for p in walls:
        g = pts.rect_gid(p.spec)
        for side in (g[0], g[-1], g[:, 0], g[:, -1]):
            on_edge[side] = True
    nbr: dict[int, set[int]] = {}
    for a, b in E[on_edge[E[:, 0]] | on_edge[E[:, 1]]].tolist():
        nbr.setdefault(a, set()).add(b)
        nbr.setdefault(b, set()).add(a)
    P = pts.P

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

    sym_of = pts.sym_of

    def fill(halo, mirror, at, p: int, inner: int, exclude) -> None:
        """Halo entry `at` for edge point p: the wall neighbour across the edge, or,
        where the wall ends on a symmetry plane, the mirror image of `inner`."""
        x = across(p, inner, exclude)
        if x >= 0:
            halo[at] = x
        elif sym_of[p] >= 0 and inner != p:
            halo[at] = inner
            mirror[at] = sym_of[p]

    out = []
    for p in walls:
        g = pts.rect_gid(p.spec)
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
            g, halo, mirror = g[:, 0], np.ascontiguousarray(halo[:, 1]), np.ascontiguousarray(mirror[:, 1])
        # the halo as boundary_motion takes it (padded, NaN where no neighbour, mirror
        # images across symmetry planes); the deformed one is gathered per step
        pu = np.empty((halo.shape[0], 1, 3) if curve else halo.shape + (3,))
        stages.halo_points(P, halo.ravel(), mirror.ravel(), pts.plane_o, pts.plane_n, pu.reshape(-1, 3))
        out.append(WallPatch(p.spec, g, halo, mirror, pu))
    where = np.full(pts.n_global, -1, dtype=np.int64)
    where[pts.wall] = np.arange(pts.wall.size)
    # each wall patch's points as indices into the merged wall arrays
    local = tuple(np.ascontiguousarray(where[w.gid].ravel()) for w in out)
    return Walls(tuple(out), local, E)


def _rects(pts: BoundaryPoints, connectivity) -> tuple[Rect, ...]:
    """The patches and both sides of every interface; every face point must be covered."""
    rects: list[Rect] = []
    for p in connectivity.patches:
        rects.append(Rect(p.spec.block, p.spec.face, pts.rect_gid(p.spec), p.kind))
    for itf in connectivity.interfaces:
        rects.append(Rect(itf.master.block, itf.master.face, pts.rect_gid(itf.master), "interface"))
        rects.append(Rect(itf.slave.block, itf.slave.face, pts.rect_gid(itf.slave), "interface",
                          slave=True))
    covered = {k: np.zeros(v.shape, dtype=bool) for k, v in pts.face_gid.items()}
    specs = [p.spec for p in connectivity.patches]
    specs += [i.master for i in connectivity.interfaces] + [i.slave for i in connectivity.interfaces]
    for s in specs:
        (a0, a1), (b0, b1) = s.range
        covered[(s.block, s.face)][a0:a1 + 1, b0:b1 + 1] = True
    for (b, f), cov in covered.items():
        if not cov.all():
            a, bb = np.argwhere(~cov)[0]
            raise CaseError(f"block {b + 1} face {f}: point ({a + 1}, {bb + 1}) of the face is "
                            "covered by no patch or interface of the connectivity")
    return tuple(rects)


def _vertices(pts: BoundaryPoints, rects, tol: float, power: float, max_sources: int) -> Vertices:
    """The rectangles' corners; inverse-distance weights of the free ones from (at most
    ``max_sources`` evenly sampled) wall points, decaying towards the fixed points."""
    known = pts.kind >= FIXED
    corners = set()
    for r in rects:
        g = r.gid
        corners.update(int(x) for x in (g[0, 0], g[-1, 0], g[0, -1], g[-1, -1]))
    free = np.array(sorted(c for c in corners if not known[c]), dtype=np.int64)
    all_corners = np.array(sorted(corners), dtype=np.int64)
    if free.size == 0:
        return Vertices(all_corners, free, None)
    P = pts.P
    wall = pts.wall
    step = max(1, int(math.ceil(wall.size / max_sources)))
    src = wall[::step]
    d = np.linalg.norm(P[free][:, None, :] - P[src][None, :, :], axis=-1)
    dmin = d.min(axis=1)
    w = 1.0 / np.maximum(d, 1e-300) ** power
    exact = d <= tol
    rows = exact.any(axis=1)
    w[rows] = exact[rows].astype(float)
    w /= w.sum(axis=1, keepdims=True)
    fixed = np.flatnonzero(pts.kind == FIXED)
    if fixed.size:
        from .._points import nearest_within
        dfix, _ = nearest_within(P[fixed], P[free], np.inf)
        decay = dfix / (dmin + dfix)
        decay[(dmin + dfix) == 0.0] = 1.0
    else:
        decay = np.ones(free.size)
    ref = np.argmax(w, axis=1)
    return Vertices(all_corners, free, (src, w, decay, ref))


def _chain_gaps(P, params, chain: np.ndarray, known: np.ndarray, gaps: list) -> None:
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
        pts = P[chain[start - 1:m + 1]]
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        if arc[-1] > 0.0:
            s = arc / arc[-1]
        else:
            s = np.arange(run.size + 2) / (run.size + 1.0)
        s[0], s[-1] = 0.0, 1.0
        t = params.line(s, arc[-1], int(left), int(right))[1:-1]
        # a point may repeat along a side (collapsed): keep its first occurrence
        _, keep = np.unique(run, return_index=True)
        keep.sort()
        gaps.append((int(left), int(right), run[keep], t[keep]))
        known[run] = True


def _segments_and_patches(pts: BoundaryPoints, rects, corners, params):
    """The gaps of the rectangles' sides, then the derived patches (sides first: a patch's
    sides are known before its interior)."""
    P = pts.P
    known = pts.kind >= FIXED
    known[corners] = True
    gaps: list = []
    for r in rects:
        g = r.gid
        if g.shape[0] == 1 or g.shape[1] == 1:
            _chain_gaps(P, params, g.ravel(), known, gaps)
        else:
            for chain in (g[:, 0], g[:, -1], g[0, :], g[-1, :]):
                _chain_gaps(P, params, chain, known, gaps)
    segments = None
    if gaps:
        segments = Segments(np.array([x[0] for x in gaps], dtype=np.int64),
                            np.array([x[1] for x in gaps], dtype=np.int64),
                            np.concatenate([[0], np.cumsum([x[2].size for x in gaps])]).astype(np.int64),
                            np.concatenate([x[2] for x in gaps]).astype(np.int64),
                            np.concatenate([x[3] for x in gaps]).astype(np.float64))
    patches: list[Patch] = []
    prescribed = pts.kind >= FIXED
    for r in rects:
        g = r.gid
        if r.slave or g.shape[0] < 3 or g.shape[1] < 3:
            continue
        inner = np.zeros(g.shape, dtype=bool)
        inner[1:-1, 1:-1] = ~known[g[1:-1, 1:-1]]
        if not inner.any():
            continue
        s = params.patch(g, np.ascontiguousarray(P[g]))
        ends = [prescribed[g[0, :]].sum() + prescribed[g[-1, :]].sum(),
                prescribed[g[:, 0]].sum() + prescribed[g[:, -1]].sum()]
        lead = 0 if ends[0] >= ends[1] else 1
        # a point that repeats inside the patch is written once
        flat = g[inner]
        _, first = np.unique(flat, return_index=True)
        write = np.zeros(g.shape, dtype=bool)
        idx = np.argwhere(inner)[np.sort(first)]
        write[idx[:, 0], idx[:, 1]] = True
        patches.append(Patch(g, s, lead, write, r.block, r.face))
        known[flat] = True
    if not known.all():
        g = int(np.flatnonzero(~known)[0])
        raise CaseError(f"boundary point at {tuple(np.round(P[g], 6))} is reached by no "
                        "patch, segment or vertex of the skeleton (inconsistent connectivity)")
    pack = stages.level_pack([(p.gid, p.s, p.lead, p.write) for p in patches])
    return segments, Patches(tuple(patches), pack, int(sum(p.gid.size for p in patches)))


def _symmetry(pts: BoundaryPoints) -> Symmetry:
    sym = np.flatnonzero((pts.sym_of >= 0) & (pts.kind == SYMMETRY))
    planes = pts.sym_of[sym]
    point = np.zeros((sym.size, 3))
    normal = np.zeros((sym.size, 3))
    for m in range(pts.plane_o.shape[0]):
        sel = planes == m
        point[sel] = pts.plane_o[m]
        normal[sel] = pts.plane_n[m]
    return Symmetry(sym, point, normal)


def _blocks(grid: Grid, pts: BoundaryPoints, params, own, exchange) -> tuple[BlockPlan, ...]:
    """The plans of the blocks ``own`` (all: None); the others' face parameters from
    ``exchange(plans, error)`` (a collective: the plans with every block's ``face_s``, or the
    first rank's error raised), their plans without ``s`` and ``gather``."""
    plans = []
    prescribed = pts.kind >= FIXED
    faces = faces_of(grid.ndim)
    mine = None if own is None else set(own)
    error = None
    for b, blk in enumerate(grid):
        fg = [pts.face_gid[(b, f)] for f in faces]
        counts = [int(prescribed[g].sum()) for g in fg]
        order = tuple(int(x) for x in tfi.lead_order(counts))
        plan = BlockPlan(None, order, fg, None, None)
        if (mine is None or b in mine) and error is None:
            try:
                with serial_below(blk.npoints):
                    s = params.block(blk.xyz, fg)
                face_s = tfi.face_params(s)
                plan = BlockPlan(s, order, fg, face_s, tfi.gather_plan(fg, s, order, face_s=face_s))
            except Exception as exc:    # noqa: BLE001  (every rank raises it in the exchange)
                if exchange is None:
                    raise
                error = exc
        plans.append(plan)
    if exchange is not None:
        plans = exchange(plans, error)
    return tuple(plans)


def _scatter(grid: Grid, pts: BoundaryPoints) -> tuple:
    """Where each block's boundary points live, for the final scatter."""
    blk_of = np.searchsorted(pts.offsets, pts.copies_key, side="right") - 1
    out = []
    for b in range(len(grid)):
        sel = blk_of == b
        out.append((pts.copies_key[sel] - pts.offsets[b], pts.copies_gid[sel]))
    return tuple(out)


def build_skeleton(grid: Grid, connectivity, pts: BoundaryPoints, params, *, tol: float,
                   idw_power: float, max_idw_sources: int, own=None, exchange=None) -> Skeleton:
    """The skeleton of ``grid`` on its boundary points ``pts`` with the blending parameters of
    ``params`` (see the module docstring).

    ``own``: the blocks whose volume plans are made here (None: all); the others get their
    face parameters from ``exchange`` (a distributed set-up, :mod:`.distributed`)."""
    walls = _walls(pts, connectivity, grid.ndim)
    rects = _rects(pts, connectivity)
    vertices = _vertices(pts, rects, tol, idw_power, max_idw_sources)
    segments, patches = _segments_and_patches(pts, rects, vertices.corners, params)
    return Skeleton(ndim=grid.ndim, tol=tol, points=pts, walls=walls, rects=rects,
                    vertices=vertices, segments=segments, patches=patches,
                    derived=np.flatnonzero(pts.kind < FIXED), symmetry=_symmetry(pts),
                    blocks=_blocks(grid, pts, params, own, exchange), scatter=_scatter(grid, pts))
