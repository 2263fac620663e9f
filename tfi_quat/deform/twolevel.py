"""The two-level formulation's parts (docs/deformer.md): wall layer, bodies, rigid fits, arms.

The wall motion of each wall body is split into the rigid motion that fits it
best and a residual deformation.  The residual moves the grid by
``R_d = K(x) + rot(Q(x), A(x))`` with ``K``, ``Q`` interpolated from the
boundaries and ``A`` the arm of each point from an interpolated centre field
that sits on the wall next to walls and on the point itself away from them
(:func:`local_fields`); the blending is flat over a wall layer of thickness
``rotation_length`` (:class:`WallLayer`), so the residual rotations act only
there.  The rigid part is then applied to the whole field in Samareh's form
with uniform wall data, blended between bodies in closed form
(:func:`rigid_fields`).

Set-up: :func:`wall_layer` (before the skeleton: its blending parameters are
the skeleton's), then :func:`build_two_level` on the skeleton (bodies, the
weights of their rigid motions, the centre field and its arms).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .. import quaternion as qa
from ..blending import wall_layer_arclength, wall_layer_line
from ..fit import constrain_to_planes, rigid_from_moments
from ..grid import face_axes
from ..topology.graph import connected_components
from . import stages
from .skeleton import FIXED, WALL, BoundaryPoints, Skeleton

__all__ = ["ROTATION_LENGTH_FRACTION", "REBASE_FRACTION", "DAMP_FRACTION", "WallLayer", "Body",
           "TwoLevel", "wall_layer", "build_two_level", "fit_parts", "fit_sums", "fit_centroids",
           "fit_moments", "fit_bodies", "local_fields", "rigid_fields"]

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


# ------------------------------------------------------------------ the wall layer
@dataclass(frozen=True)
class WallLayer:
    """The wall layer: its thickness ``ell`` (the rotation length), every boundary point's
    distance ``dwall`` to the walls (inf beyond 20 ``ell``), nearest wall point ``foot``
    (itself when far) and end weight ``omega = exp(-dwall / ell)``.

    Also the blending parameters of the skeleton (:mod:`.skeleton`'s *params*):
    :func:`tfi_quat.blending.wall_layer_line` and ``wall_layer_arclength``.
    """

    ell: float
    dwall: np.ndarray
    foot: np.ndarray
    omega: np.ndarray

    def line(self, s: np.ndarray, length: float, g0: int, g1: int) -> np.ndarray:
        ell = self.ell
        return wall_layer_line(s, length, ell * self.omega[g0], ell * self.omega[g1])

    def patch(self, g: np.ndarray, x: np.ndarray) -> np.ndarray:
        ell = self.ell
        om = self.omega
        x4 = np.asfortranarray(x[:, :, None, :])
        lam = [ell * om[g[0, :]], ell * om[g[-1, :]], ell * om[g[:, 0]], ell * om[g[:, -1]]]
        return np.ascontiguousarray(wall_layer_arclength(x4, lam, ndim=2)[:, :, 0, :2])

    def block(self, xyz: np.ndarray, face_gid: list) -> np.ndarray:
        lam = [self.ell * self.omega[g] for g in face_gid]
        return wall_layer_arclength(xyz, lam, ndim=len(face_gid) // 2)


def wall_layer(pts: BoundaryPoints, rotation_length: float | None, scale: float) -> WallLayer:
    """The wall layer of the boundary points ``pts``; ``rotation_length`` None: the default,
    ``ROTATION_LENGTH_FRACTION`` x the walls' size (``scale``: the grid's size, where the
    walls have none)."""
    from .._points import nearest_within
    P = pts.P
    wall = pts.wall
    W = P[wall]
    if rotation_length is None:
        # twice the largest distance from the walls' centroid: a size that rotates with them
        size = 2.0 * float(np.sqrt(np.max(np.sum((W - W.mean(axis=0)) ** 2, axis=1))))
        rotation_length = ROTATION_LENGTH_FRACTION * size
        if not rotation_length > 0.0:
            rotation_length = ROTATION_LENGTH_FRACTION * scale
    ell = float(rotation_length)
    # every weight built from d is below 1e-8 beyond 20 ell (omega = exp(-d / ell)): a
    # bounded query; points farther away get d = inf, weight 0
    d, near = nearest_within(W, P, 20.0 * ell)
    far = ~np.isfinite(d)
    d[pts.kind == WALL] = 0.0
    near[far] = 0
    return WallLayer(ell, d, np.where(far, np.arange(P.shape[0]), wall[near]), np.exp(-d / ell))


# ------------------------------------------------------------------ bodies, weights, arms
@dataclass(frozen=True)
class Body:
    """A connected set of wall points and the rigid motions it may take."""

    gids: np.ndarray
    axis: np.ndarray | None            # allowed rotation axis (None: any; zero: none)
    tproj: np.ndarray                  # translation projection


@dataclass(frozen=True)
class TwoLevel:
    """What a two-level step reads besides the skeleton.

    ``phi`` (n_derived, n_bodies): the weight of each body's rigid motion on the derived
    points; ``c`` (G, 3): the centre field, ``arm = P - c``; ``shift`` (G, 3): the
    re-basing shift of the derived points' centres; ``damp`` (G,): the fade of their
    residual rotations; ``base``: per block, the tables of ``TFI(-c)`` its kernel adds to
    the block's points (the volume arms ``A = R_u - TFI(c)``).
    """

    layer: WallLayer
    bodies: tuple[Body, ...]
    phi: np.ndarray
    c: np.ndarray
    shift: np.ndarray
    arm: np.ndarray
    damp: np.ndarray
    base: tuple
    part_ptr: np.ndarray
    part_gids: np.ndarray
    part_body: np.ndarray
    part_patch: np.ndarray
    wall_body: np.ndarray


def _bodies(sk: Skeleton) -> tuple[Body, ...]:
    """Connected wall bodies, each with the rigid motions its symmetry planes allow."""
    pts = sk.points
    wall = pts.wall
    pos = np.full(pts.n_global, -1, dtype=np.int64)
    pos[wall] = np.arange(wall.size)
    E = sk.walls.edges
    r, c = pos[E[:, 0]], pos[E[:, 1]]
    ok = (r >= 0) & (c >= 0)
    _, label = connected_components(wall.size, r[ok], c[ok])
    bodies = []
    for lab in np.unique(label):
        gids = wall[label == lab]
        planes = sorted({int(p) for p in pts.sym_of[gids] if p >= 0})
        normals = [pts.plane_n[p] for p in planes]
        if sk.ndim == 2:
            normals.append(np.array([0.0, 0.0, 1.0]))
        axis, tproj = constrain_to_planes(normals)
        bodies.append(Body(gids, axis, tproj))
    return tuple(bodies)


def fit_parts(sk: Skeleton, bodies) -> tuple:
    """The partition of the wall points the rigid fits sum over: each wall point in the
    first wall patch (global patch order) that holds it, split by body; parts in patch
    order, then body order.  It does not depend on how the blocks are spread over MPI
    ranks, so every rank count sums the same parts in the same order.  Returns ``(ptr,
    gids, body, patch)``."""
    wall = sk.points.wall
    body_of = np.full(sk.n_global, -1, dtype=np.int64)
    for b, body in enumerate(bodies):
        body_of[body.gids] = b
    seen = np.zeros(wall.size, dtype=bool)
    sizes, gids, pbody, ppatch = [], [], [], []
    for m, lid in enumerate(sk.walls.local):
        lid = np.asarray(lid, dtype=np.int64).ravel()
        lid = lid[~seen[lid]]
        _, first = np.unique(lid, return_index=True)
        lid = lid[np.sort(first)]
        seen[lid] = True
        g = wall[lid]
        for b in np.unique(body_of[g]):
            sizes.append(int(np.count_nonzero(body_of[g] == b)))
            gids.append(g[body_of[g] == b])
            pbody.append(int(b))
            ppatch.append(m)
    ptr = np.concatenate([[0], np.cumsum(sizes, dtype=np.int64)]).astype(np.int64)
    return (ptr, np.concatenate(gids).astype(np.int64) if gids else np.zeros(0, np.int64),
            np.array(pbody, dtype=np.int64), np.array(ppatch, dtype=np.int64))


def _rigid_weights(sk: Skeleton, bodies) -> np.ndarray:
    """The weight ``φ_b`` of each wall body's rigid motion on every derived point.

    ``φ_b`` is Samareh's hierarchy (vertices, segments, patches) applied to the
    scalar that is 1 on the walls of body ``b`` and 0 on every other prescribed
    point.  A step blends the bodies' fitted motions with it in closed form
    (:func:`stages.rigid_blend`): ``Δ = Σ φ_b Δ_b`` is exactly what the hierarchy
    gives for uniform ``Δ_b``, and ``Q = exp(Σ φ_b v_b)`` blends the rotations the
    same way, so the rigid part costs no interpolation per step.
    """
    G = sk.n_global
    der = sk.derived
    nb = len(bodies)
    phi = np.empty((der.size, nb))
    for b0 in range(0, nb, 3):
        F = np.zeros((G, 3))
        chunk = bodies[b0:b0 + 3]
        for k, body in enumerate(chunk):
            F[body.gids, k] = 1.0
        stages.vertex_stage(sk, F, None)
        stages.segment_stage(sk, F, None)
        stages.patch_stage(sk, F, None)
        phi[:, b0:b0 + len(chunk)] = F[der, :len(chunk)]
    return phi


def _centres(sk: Skeleton, layer: WallLayer):
    """The centre field ``c`` on boundary points and the re-basing shifts ``(c, shift)``.

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
    motions stay exact.
    """
    P = sk.points.P
    kind = sk.points.kind
    c = P.copy()
    # fixed points of side faces: the leading-direction interpolant of the face's end edges
    for plan in sk.blocks:
        L = plan.order[0]
        for d in plan.order[1:]:
            others = face_axes(2 * d)[1:]
            if L not in others:
                continue
            ax = others.index(L)
            for side in (0, 1):
                g = plan.face_gid[2 * d + side]
                fx = kind[g] == FIXED
                if not fx.any():
                    continue
                sL = plan.face_s[2 * d + side][..., L]
                e0 = np.take(P[g], [0], axis=ax)
                e1 = np.take(P[g], [-1], axis=ax)
                u = (1.0 - sL)[..., None] * e0 + sL[..., None] * e1
                # near walls only: far away Q is 1 and the offsets carry no rotation, and
                # a point on the side faces of several blocks keeps one value there
                gf = g[fx]
                om = np.exp(-(layer.dwall[gf] / (2.0 * layer.ell)) ** 2)[:, None]
                c[gf] = om * u[fx] + (1.0 - om) * P[gf]
    shift = np.zeros_like(P)
    lr = REBASE_FRACTION * layer.ell
    w_r = np.exp(-layer.dwall / lr)
    target = np.empty_like(P)                # re-based centres w foot + (1 - w) x
    stages.blend_rows(P, layer.foot, w_r, target)

    def rebase(idx, c_interp):
        shift[idx] = target[idx] - c_interp
        c[idx] = target[idx]

    # same order as a step: vertices, segments (gap by gap), patches
    vx = sk.vertices
    if vx.idw is not None:
        decay = vx.idw[2]
        free = vx.free
        rebase(free, decay[:, None] * stages.vertex_blend(vx, c) + (1.0 - decay)[:, None] * P[free])
    if sk.segments is not None:
        stages.rebase_gaps(c, *sk.segments.arrays(), target, shift)
    if sk.patches.items:
        stages.patch_stage(sk, c, None)
        wg = sk.patches.written
        rebase(wg, c[wg].copy())
    return c, shift


def build_two_level(sk: Skeleton, layer: WallLayer) -> TwoLevel:
    """The bodies, their weights, the centre field and its arms on the skeleton ``sk`` (built
    with ``layer`` as its blending parameters)."""
    bodies = _bodies(sk)
    phi = _rigid_weights(sk, bodies)
    c, shift = _centres(sk, layer)
    P = sk.points.P
    damp = np.ones(sk.n_global)
    der = sk.derived
    damp[der] = np.exp(-(layer.dwall[der] / (DAMP_FRACTION * layer.ell)) ** 2)
    np.negative(c, out=c)                    # -c for the tables (negation is exact)
    # A = R_u - TFI(c), evaluated inside the volume kernel from these O(surface) tables
    base = tuple(None if plan.gather is None else plan.gather.base_tables(c) for plan in sk.blocks)
    np.negative(c, out=c)
    wall_body = np.empty(sk.points.wall.size, dtype=np.int64)
    pos = np.full(sk.n_global, -1, dtype=np.int64)
    pos[sk.points.wall] = np.arange(sk.points.wall.size)
    for b, body in enumerate(bodies):
        wall_body[pos[body.gids]] = b
    return TwoLevel(layer, bodies, phi, c, shift, P - c, damp, base, *fit_parts(sk, bodies),
                    wall_body)


# ------------------------------------------------------------------ a step
def fit_sums(sk: Skeleton, two: TwoLevel, rd: np.ndarray, which) -> np.ndarray:
    """The first pass of the rigid fits on the parts ``which`` (indices into the parts,
    :func:`fit_parts`): per part, the sums of its points' reference and target positions
    ``(len(which), 6)``."""
    which = np.asarray(which, dtype=np.int64)
    out = np.empty((which.size, 6))
    stages.part_sums(sk.points.P, rd, which, two.part_ptr, two.part_gids, out)
    return out


def fit_centroids(two: TwoLevel, sums: np.ndarray) -> tuple:
    """Per body, the centroids ``(cu, cd)`` (nb, 3) of its reference and target wall points
    from every part's sums (:func:`fit_sums`, all parts in order), added in part order."""
    nb = len(two.bodies)
    acc = np.zeros((nb, 6))
    stages.add_parts(sums, two.part_body, acc)
    n = np.array([body.gids.size for body in two.bodies], dtype=np.float64)[:, None]
    return np.ascontiguousarray(acc[:, :3] / n), np.ascontiguousarray(acc[:, 3:] / n)


def fit_moments(sk: Skeleton, two: TwoLevel, rd: np.ndarray, cents: tuple, which) -> np.ndarray:
    """The second pass of the rigid fits on the parts ``which``: per part, the
    cross-covariance ``sum (P - cu)(rd - cd)^T`` of its points about its body's centroids
    ``cents`` (:func:`fit_centroids`), row major ``(len(which), 9)``."""
    which = np.asarray(which, dtype=np.int64)
    out = np.empty((which.size, 9))
    stages.part_moments(sk.points.P, rd, which, two.part_ptr, two.part_gids, two.part_body,
                        cents[0], cents[1], out)
    return out


def _all_parts(fn, nparts: int) -> np.ndarray:
    return fn(np.arange(nparts))


def fit_bodies(sk: Skeleton, two: TwoLevel, rd: np.ndarray, y: np.ndarray, gather=None,
               rows=None) -> list:
    """Per wall body: ``(q, t)`` of the best rigid motion of its walls to ``rd`` (G, 3); the
    pulled-back residual targets ``rot(q)^-1 (rd - t)`` are written to the wall rows of ``y``.

    The fit's sums are taken per part of the fixed partition :func:`fit_parts`, then added
    in part order (:func:`fit_centroids`, then the covariances).  ``gather(fn, nparts)``
    returns ``fn(parts)`` for every part in order (default: computes them all; under MPI
    each rank computes its wall patches' parts and the ranks exchange them,
    :mod:`.distributed`): the same bits for any rank count.  ``rows``: per body, the
    points of ``y`` to write (default: all its wall points).
    """
    gather = _all_parts if gather is None else gather
    nparts = two.part_body.size
    cents = fit_centroids(two, gather(lambda which: fit_sums(sk, two, rd, which), nparts))
    mom = gather(lambda which: fit_moments(sk, two, rd, cents, which), nparts)
    nb = len(two.bodies)
    h = np.zeros((nb, 9))
    stages.add_parts(mom, two.part_body, h)
    fits = []
    for b, body in enumerate(two.bodies):
        q, t = rigid_from_moments(cents[0][b], cents[1][b], h[b].reshape(3, 3), body.axis,
                                  body.tproj)
        fits.append((q, t))
        g = body.gids if rows is None else rows[b]
        y[g] = qa.rotate(qa.conjugate(q), rd[g] - t)
    return fits


def local_fields(sk: Skeleton, two: TwoLevel, y, qwall, K, gq, pos):
    """The residual motion: K and Q on every boundary point (``qwall``: the wall quaternions
    of the residual targets ``y``) and the positions ``pos``, in the given buffers (fixed
    points' entries are never written: ``K = c``, ``Q = 1``).  Returns the seconds spent
    on vertices and segments."""
    P = sk.points.P
    A = two.arm
    wall, rows = sk.step_walls()
    gq[wall] = qwall[rows]
    K[wall] = y[wall]                   # walls: A = 0
    damp = two.damp
    shift = two.shift
    t1 = time.perf_counter()
    # each level: interpolate, fade the residual rotation out away from the walls, add
    # the re-basing shift of the centres (the position K + rot(Q, A) is unchanged by it)
    vx = sk.vertices
    if vx.idw is not None:
        decay = vx.idw[2]
        free = vx.free
        K[free] = decay[:, None] * stages.vertex_blend(vx, K) + (1.0 - decay)[:, None] * P[free]
        gq[free] = stages.vertex_q(vx, gq, decay)
        K[free] += qa.rotate(gq[free], shift[free])
    if sk.segments is not None:
        stages.fill_gaps(K, gq, *sk.segments.arrays(), True, damp, shift)
    t2 = time.perf_counter()
    stages.patch_stage(sk, K, gq, damp, shift)
    sym = sk.symmetry
    if sym.gids.size:
        stages.symmetry_fix(K, gq, True, A, np.zeros(3), sym.gids, sym.point, sym.normal)
    stages.positions_local(K, gq, A, sk.derived, pos)
    pos[wall] = y[wall]
    return t2 - t1


def rigid_fields(sk: Skeleton, two: TwoLevel, fits, centre, gdelta, gq) -> None:
    """The rigid part: each body's (Δ_b, Q_b) on its walls, blended in closed form on the
    derived points with the weights ``two.phi`` (Samareh's form about ``centre``), then
    the symmetry points; in the buffers ``gdelta``, ``gq``."""
    c = centre
    nb = len(two.bodies)
    Db = np.empty((nb, 3))
    Qb = np.empty((nb, 4))
    for b, (q, t) in enumerate(fits):
        # c + Δ + rot(q, x - c) = rot(q, x) + t
        Db[b] = t + qa.rotate(q, c) - c
        Qb[b] = q
    wall, rows = sk.step_walls()
    body = two.wall_body[rows]
    gdelta[wall] = Db[body]
    gq[wall] = Qb[body]
    stages.rigid_blend(two.phi, sk.derived, Db, qa.log(Qb), gdelta, gq)
    stages.symmetry_stage(sk, gdelta, gq, c)
