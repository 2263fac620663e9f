"""Grid generators: airfoils (C and O), cylinder, channel, two-block case, wing.

Every generator is deterministic and returns a :class:`tfi_quat.Grid`.  2-D
grids have ``ndim == 2``, blocks ``(ni, nj, 1, 3)`` with z = 0, ``j = 0`` on
the wall and convex cells of positive area (``(d/di x d/dj) . e_z > 0``).
3-D grids are right-handed (positive hexahedron volumes and corners).

Viscous grids (airfoil, wing) are built in two layers:

1. the first ``n_ortho`` layers are extruded straight along the discrete wall
   normal (central differences of the wall points; 3-D: the cross product of
   the central-difference surface tangents), so grid lines leave the wall
   orthogonally by construction, except where straight lines from
   neighbouring points would converge too far (concave corners: the first
   :data:`N_STRAIGHT` layers stay straight until the lines have come to half
   their wall spacing);
2. further out the grid is marched outwards layer by layer along the normal
   of the current layer, in sub-steps no longer than half the smallest
   point spacing, with limited Laplacian smoothing (an explicit, dissipative
   variant of hyperbolic grid marching; the sub-steps run in a compiled
   kernel, bit-identical to the numpy reference form).  The marching
   distances follow a geometric or a one-sided tanh stretching from
   ``first_spacing`` to ``farfield``.

C-grid wake cuts and O-grid seams share their wall points by copy, so the two
sides of a cut are bit-identical; multiblock grids are cut out of one global
point array, so block interfaces are bit-identical too.  Every generator
checks its cells (volumes and corner Jacobians) and raises
:class:`~tfi_quat.errors.GridValueError` rather than return a folded grid.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import jit
from .errors import GridValueError
from .grid import Block, Grid
from .quality import invalid_cells

__all__ = ["naca4", "airfoil", "airfoil_wall_range", "cylinder", "channel", "two_block", "wing",
           "wing_geometry", "wing_wall_range", "geometric_spacing", "tanh_spacing", "STRETCHINGS",
           "boundary_patches", "GENERATORS"]


# --------------------------------------------------------------------------- helpers
def _check_int(name: str, value, lo: int, odd: bool = False) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise GridValueError(f"{name} must be an integer, got {value!r}")
    v = int(value)
    if v < lo:
        raise GridValueError(f"{name} must be >= {lo}, got {v}")
    if odd and v % 2 == 0:
        raise GridValueError(f"{name} must be odd, got {v}")
    return v


def _check_pos(name: str, value, hi: float | None = None) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise GridValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0.0:
        raise GridValueError(f"{name} must be a positive finite number, got {value!r}")
    if hi is not None and v >= hi:
        raise GridValueError(f"{name} must be < {hi}, got {v}")
    return v


def _check_float(name: str, value, lo: float, hi: float, unit: str = "") -> float:
    """``value`` as a float in ``[lo, hi]``, else a GridValueError naming ``name``."""
    if isinstance(value, bool):
        raise GridValueError(f"{name} must be a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise GridValueError(f"{name} must be a number, got {value!r}") from None
    if not lo <= v <= hi:       # also rejects NaN
        raise GridValueError(f"{name} must be in [{lo:g}, {hi:g}]{unit}, got {value!r}")
    return v


def _check_bool(name: str, value) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise GridValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def geometric_spacing(n: int, total: float, first: float) -> np.ndarray:
    """Cumulative distances of a geometric stretching.

    Parameters
    ----------
    n : int
        Number of intervals (>= 1).
    total : float
        Total length.
    first : float
        Length of the first interval (``0 < first <= total``).

    Returns
    -------
    ndarray of float64, shape (n + 1,)
        ``0 = s[0] < s[1] < ... < s[n] = total`` with ``s[1] = first`` (to
        round-off) and a constant ratio between successive intervals.
    """
    n = _check_int("n", n, 1)
    total = _check_pos("total", total)
    first = _check_pos("first", first)
    if first > total:
        raise GridValueError(f"first spacing {first} exceeds the total length {total}")
    if n == 1:
        return np.array([0.0, total])
    k = np.arange(n)

    def length(r):
        return first * np.sum(r ** k)

    target = total
    lo, hi = 1e-6, 1.0
    if length(1.0) < target:
        lo, hi = 1.0, 2.0
        while length(hi) < target:
            hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        new = (mid, hi) if length(mid) < target else (lo, mid)
        if new == (lo, hi):             # converged: further steps change nothing
            break
        lo, hi = new
    r = 0.5 * (lo + hi)
    s = np.concatenate([[0.0], np.cumsum(first * r ** k)])
    s *= total / s[-1]
    s[-1] = total
    return s


def tanh_spacing(n: int, total: float, first: float) -> np.ndarray:
    """Cumulative distances of a one-sided hyperbolic-tangent stretching.

    ``s(x) = total (1 + tanh(d (x - 1)) / tanh(d))`` at ``x = i / n``
    (Vinokur's one-sided form), evaluated as ``total sinh(d x) / (sinh(d)
    cosh(d (x - 1)))`` (no cancellation near the wall), with ``d`` chosen
    so that the first interval is ``first``.  The ratio of successive
    intervals is largest at the wall (a little above the geometric one) and
    falls smoothly towards 1 at the far end, so the outer cells come out
    smaller than a geometric stretching's (65 points, first 1e-5, total 20:
    last interval 2.1 instead of 3.7).

    Parameters
    ----------
    n : int
        Number of intervals (>= 2).
    total : float
        Total length.
    first : float
        Length of the first interval; below the mean ``total / n`` (the
        distribution clusters at ``s = 0``).

    Returns
    -------
    ndarray of float64, shape (n + 1,)
        ``0 = s[0] < ... < s[n] = total``, ``s[1] = first`` to 1e-12.
    """
    n = _check_int("n", n, 2)
    total = _check_pos("total", total)
    first = _check_pos("first", first)
    if not first < 0.999 * total / n:
        raise GridValueError(f"first spacing {first} must be below the mean spacing {total / n:g} "
                             "for a tanh stretching")
    x = np.arange(n + 1) / n

    def first_of(d):
        return total * math.sinh(d / n) / (math.sinh(d) * math.cosh(d * (1.0 / n - 1.0)))

    lo, hi = 1e-8, 1.0
    while first_of(hi) > first:         # first_of decreases from total / n towards 0
        lo, hi = hi, 2.0 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        new = (mid, hi) if first_of(mid) > first else (lo, mid)
        if new == (lo, hi):
            break
        lo, hi = new
    d = 0.5 * (lo + hi)
    s = total * np.sinh(d * x) / (math.sinh(d) * np.cosh(d * (x - 1.0)))
    s[0], s[-1] = 0.0, total
    return s


#: wall-normal distributions of :func:`airfoil` and :func:`wing`
STRETCHINGS = {"geometric": geometric_spacing, "tanh": tanh_spacing}


def _stretching(name, n: int, total: float, first: float) -> np.ndarray:
    if name not in STRETCHINGS:
        raise GridValueError(f"stretching must be one of {', '.join(map(repr, STRETCHINGS))}, got {name!r}")
    return STRETCHINGS[name](n, total, first)


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0.0, n, 1.0)


def _rot_ccw(t: np.ndarray) -> np.ndarray:
    out = np.empty_like(t)
    out[..., 0] = -t[..., 1]
    out[..., 1] = t[..., 0]
    return out


def _curve_normals(p: np.ndarray, closed: bool) -> np.ndarray:
    """Unit normals of curves ``p`` (..., n, 2) traversed clockwise: left of +i rotated.

    Central differences ``p[i+1] - p[i-1]`` rotated by +90 degrees (one-sided
    at the ends of open curves).  At a cusp (both neighbours coincide) the
    normal points away from the neighbours.  A closed curve repeats its first
    point at the end.
    """
    if closed:
        q = p[..., :-1, :]
        t = np.roll(q, -1, axis=-2) - np.roll(q, 1, axis=-2)
        away = 2.0 * q - np.roll(q, -1, axis=-2) - np.roll(q, 1, axis=-2)
        t = np.concatenate([t, t[..., :1, :]], axis=-2)
        away = np.concatenate([away, away[..., :1, :]], axis=-2)
    else:
        t = np.empty_like(p)
        t[..., 1:-1, :] = p[..., 2:, :] - p[..., :-2, :]
        t[..., 0, :] = p[..., 1, :] - p[..., 0, :]
        t[..., -1, :] = p[..., -1, :] - p[..., -2, :]
        away = np.zeros_like(p)
        away[..., 1:-1, :] = 2.0 * p[..., 1:-1, :] - p[..., 2:, :] - p[..., :-2, :]
    tn = np.linalg.norm(t, axis=-1, keepdims=True)
    scale = np.linalg.norm(p[..., 1:, :] - p[..., :-1, :], axis=-1).max(axis=-1)[..., None, None]
    cusp = tn <= 1e-12 * np.maximum(scale, 1e-300)
    n = np.where(cusp, _unit(away), _rot_ccw(t) / np.where(cusp, 1.0, tn))
    return n


#: largest smoothing move per marching sub-step, as a fraction of the sub-step
SMOOTH_CAP = 2.0

#: march with the compiled sub-step kernel (False: the numpy reference form)
_COMPILED = True


def _limited(lap: np.ndarray, nrm: np.ndarray, eps: float, dh: float) -> np.ndarray:
    """Smoothing displacement ``eps * lap``.

    Where the smoothing pulls a point back (convex parts of the layer) it is
    limited to half the marching step, so small leading-edge radii do not
    stall the layer; where it pushes outwards (concave parts) it is not.
    """
    size = np.linalg.norm(lap, axis=-1, keepdims=True)
    back = np.einsum("...i,...i->...", lap, nrm)[..., None] < 0.0
    lim = np.where(back, np.minimum(eps, 0.5 * dh / np.maximum(size, 1e-300)), eps)
    # never more than the step itself: in thin near-wall layers an unscaled
    # smoothing move would lean the grid lines over in a single layer
    lim = np.minimum(lim, SMOOTH_CAP * dh / np.maximum(size, 1e-300))
    return lap * lim


#: layers kept on straight wall-normal lines wherever those lines stay at
#: least half their wall spacing apart (the orthogonality the tests require)
N_STRAIGHT = 10


def _safe_extrusion(wall: np.ndarray, n0: np.ndarray, closed: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per point: how far straight extrusion along the wall normal is safe.

    Returns ``(soft, hard)``, arrays of shape ``wall.shape[:2]``.  ``soft``:
    a quarter of the distance at which the straight lines from a point and a
    neighbour would cross (concave spots); on open curves (C-grids, whose
    wake junction is concave and whose wake spacing grows fast) also at most
    twice the local point spacing, so that the points round the junction
    switch to marching together.  ``hard``: half the crossing distance (the
    lines have come to half their wall spacing), on open curves at most
    eight local point spacings; the first :data:`N_STRAIGHT` layers stay
    straight up to it.  Without it, the points next to a C-grid's trailing
    edge would leave their straight lines after a few layers of a
    first_spacing of 1e-4 (257 points round the C).
    """
    e = wall[:, 1:] - wall[:, :-1]
    dn = n0[:, 1:] - n0[:, :-1]
    conv = -np.einsum("bij,bij->bi", dn, e)
    ll = np.einsum("bij,bij->bi", e, e)
    dstar = np.where(conv > 0.0, ll / np.where(conv > 0.0, conv, 1.0), np.inf)
    out = np.full(wall.shape[:2], np.inf)
    out[:, :-1] = np.minimum(out[:, :-1], dstar)
    out[:, 1:] = np.minimum(out[:, 1:], dstar)
    if closed:
        out[:, 0] = out[:, -1] = np.minimum(out[:, 0], out[:, -1])
        return 0.25 * out, 0.5 * out
    seg = np.sqrt(ll)
    loc = np.full(wall.shape[:2], np.inf)
    loc[:, :-1] = np.minimum(loc[:, :-1], seg)
    loc[:, 1:] = np.minimum(loc[:, 1:], seg)
    return np.minimum(0.25 * out, 2.0 * loc), np.minimum(0.5 * out, 8.0 * loc)


@jit(inline="always")
def _limited_1(l0, l1, n0, n1, eps, dh, cap):
    """One point of :func:`_limited`; returns the smoothing move (x, y)."""
    size = math.sqrt(l0 * l0 + l1 * l1)
    s = max(size, 1e-300)
    lim = eps
    if l0 * n0 + l1 * n1 < 0.0:
        lim = min(eps, 0.5 * dh / s)
    lim = min(lim, cap * dh / s)
    return l0 * lim, l1 * lim


@jit
def _march_substeps(p, n0, free, end0, end1, has_end, closed, m, dh, eps, keep, has_keep, cap):
    """``m`` marching sub-steps of every curve of ``p`` (nb, n, 2), in place.

    The compiled form of the sub-step loop of :func:`_march2d`, operation
    for operation (the results are bit-identical to the numpy form): move
    each free point along the normal of the current curve (frozen points
    along ``n0``, open ends along ``end0``/``end1``), then smooth the free
    points (:func:`_limited`; open curves blend in the spacing-keeping
    smoothing with weight ``keep``).  Serial: it runs once per layer, too
    short for threads to pay on a loaded machine.
    """
    nb, n, _ = p.shape
    nrm = np.empty((n, 2))
    lap = np.empty((n, 2))
    for b in range(nb):
        nq = n - 1 if closed else n
        for _ in range(m):
            scale = 0.0
            for i in range(n - 1):
                d0 = p[b, i + 1, 0] - p[b, i, 0]
                d1 = p[b, i + 1, 1] - p[b, i, 1]
                scale = max(scale, math.sqrt(d0 * d0 + d1 * d1))
            thr = 1e-12 * max(scale, 1e-300)
            for i in range(nq):
                if closed:
                    ip = i + 1 if i + 1 < nq else 0
                    im = i - 1 if i > 0 else nq - 1
                elif i == 0:
                    ip, im = 1, 0
                elif i == n - 1:
                    ip, im = n - 1, n - 2
                else:
                    ip, im = i + 1, i - 1
                t0 = p[b, ip, 0] - p[b, im, 0]
                t1 = p[b, ip, 1] - p[b, im, 1]
                tn = math.sqrt(t0 * t0 + t1 * t1)
                if tn <= thr:
                    if closed or 0 < i < n - 1:
                        a0 = 2.0 * p[b, i, 0] - p[b, ip, 0] - p[b, im, 0]
                        a1 = 2.0 * p[b, i, 1] - p[b, ip, 1] - p[b, im, 1]
                    else:
                        a0 = 0.0
                        a1 = 0.0
                    an = math.sqrt(a0 * a0 + a1 * a1)
                    if not an > 0.0:
                        an = 1.0
                    nrm[i, 0] = a0 / an
                    nrm[i, 1] = a1 / an
                else:
                    nrm[i, 0] = -t1 / tn
                    nrm[i, 1] = t0 / tn
            if closed:
                nrm[n - 1, 0] = nrm[0, 0]
                nrm[n - 1, 1] = nrm[0, 1]
            for i in range(n):
                if not free[b, i]:
                    nrm[i, 0] = n0[b, i, 0]
                    nrm[i, 1] = n0[b, i, 1]
            if has_end:
                nrm[0, 0], nrm[0, 1] = end0[0], end0[1]
                nrm[n - 1, 0], nrm[n - 1, 1] = end1[0], end1[1]
            for i in range(n):
                p[b, i, 0] = p[b, i, 0] + dh * nrm[i, 0]
                p[b, i, 1] = p[b, i, 1] + dh * nrm[i, 1]
            if eps > 0.0:
                lo, hi = (0, nq) if closed else (1, n - 1)
                for i in range(lo, hi):
                    if closed:
                        ip = i + 1 if i + 1 < nq else 0
                        im = i - 1 if i > 0 else nq - 1
                    else:
                        ip, im = i + 1, i - 1
                    l0 = 0.5 * (p[b, im, 0] + p[b, ip, 0]) - p[b, i, 0]
                    l1 = 0.5 * (p[b, im, 1] + p[b, ip, 1]) - p[b, i, 1]
                    if has_keep and not closed:
                        e0 = p[b, i, 0] - p[b, im, 0]
                        e1 = p[b, i, 1] - p[b, im, 1]
                        hl = math.sqrt(e0 * e0 + e1 * e1)
                        e0 = p[b, ip, 0] - p[b, i, 0]
                        e1 = p[b, ip, 1] - p[b, i, 1]
                        hr = math.sqrt(e0 * e0 + e1 * e1)
                        w = max(hl + hr, 1e-300)
                        w0 = (hr * p[b, im, 0] + hl * p[b, ip, 0]) / w - p[b, i, 0]
                        w1 = (hr * p[b, im, 1] + hl * p[b, ip, 1]) / w - p[b, i, 1]
                        a = keep[b, i]
                        l0 = (1.0 - a) * l0 + a * w0
                        l1 = (1.0 - a) * l1 + a * w1
                    lap[i, 0], lap[i, 1] = _limited_1(l0, l1, nrm[i, 0], nrm[i, 1], eps, dh, cap)
                for i in range(lo, hi):
                    f = 1.0 if free[b, i] else 0.0
                    p[b, i, 0] = p[b, i, 0] + f * lap[i, 0]
                    p[b, i, 1] = p[b, i, 1] + f * lap[i, 1]
                if closed:
                    p[b, n - 1, 0] = p[b, 0, 0]
                    p[b, n - 1, 1] = p[b, 0, 1]


def _march2d(wall: np.ndarray, dist: np.ndarray, closed: bool, n_ortho: int,
             smoothing: float = 0.3, end_normals=None, keep_spacing=None) -> np.ndarray:
    """March curves outwards.

    Each point moves straight along its wall normal while the distance is
    within the first ``n_ortho`` layers and short of the distance at which
    straight lines from neighbouring points would cross (concave corners;
    see :func:`_safe_extrusion`); otherwise along the normal of the current
    layer, in sub-steps of at most half the smallest point spacing, with
    limited Laplacian smoothing.

    Parameters
    ----------
    wall : ndarray, shape (nb, n, 2)
        ``nb`` wall curves (clockwise; closed ones repeat the first point).
    dist : ndarray, shape (nj,)
        Cumulative marching distances, ``dist[0] = 0``.
    closed : bool
    n_ortho : int
        Layers extruded straight along the wall normals.
    smoothing : float
        Final Laplacian smoothing coefficient per sub-step (0..0.5).
    end_normals : (ndarray (2,), ndarray (2,)), optional
        Fixed marching directions of the two ends of open curves.
    keep_spacing : ndarray of float, shape (n,) or (nb, n), optional
        Open curves, per point in [0, 1]: how much of the smoothing only
        straightens the layer and keeps its point distribution (neighbours
        averaged with weights inverse to their distances, which leaves a
        point on a straight layer in place) instead of evening the spacing.
        C-grid wakes: their geometric stretching would otherwise be smoothed
        out layer after layer, leaning the wake-normal lines over until,
        near the outflow, they run almost parallel to the cut (cells a
        deformation folds at once).  Near the trailing edge the even
        smoothing is kept: the layers must turn round the junction.

    Returns
    -------
    ndarray, shape (nb, n, nj, 2)
    """
    nb, n, _ = wall.shape
    nj = dist.shape[0]
    out = np.empty((nb, n, nj, 2))
    out[:, :, 0] = wall
    n0 = _curve_normals(wall, closed)
    if end_normals is not None:
        n0[:, 0] = end_normals[0]
        n0[:, -1] = end_normals[1]
    dsafe, dhard = _safe_extrusion(wall, n0, closed)
    d_orth = dist[min(n_ortho, nj - 1)]
    p = wall.copy()
    for j in range(1, nj):
        # once a point marches it never returns to its straight line: the
        # conditions only get stricter as j grows
        safe = (dist[j] <= dsafe) | ((j <= N_STRAIGHT) & (dist[j] <= dhard))
        frozen = (dist[j] <= d_orth) & safe
        if frozen.all():
            p = wall + dist[j] * n0
            out[:, :, j] = p
            continue
        free = (~frozen)[..., None]
        h = dist[j] - dist[j - 1]
        eps = smoothing
        seg = np.linalg.norm(p[:, 1:] - p[:, :-1], axis=-1)
        spacing = float(seg[seg > 0].min()) if np.any(seg > 0) else h
        m = int(min(400, max(1, math.ceil(h / (0.5 * spacing)))))
        dh = h / m
        if _COMPILED:
            p = np.ascontiguousarray(p)
            ends = (np.zeros(2), np.zeros(2)) if end_normals is None else end_normals
            keep = (np.zeros((nb, n)) if keep_spacing is None else
                    np.array(np.broadcast_to(keep_spacing, (nb, n)), dtype=np.float64))
            _march_substeps(p, n0, np.ascontiguousarray(free[..., 0]), np.asarray(ends[0], np.float64),
                            np.asarray(ends[1], np.float64), end_normals is not None, closed, m, dh,
                            float(eps), keep, keep_spacing is not None, SMOOTH_CAP)
            p = np.where(free, p, wall + dist[j] * n0)
            out[:, :, j] = p
            continue
        for _ in range(m):
            nrm = _curve_normals(p, closed)
            nrm = np.where(free, nrm, n0)
            if end_normals is not None:
                nrm[:, 0] = end_normals[0]
                nrm[:, -1] = end_normals[1]
            p = p + dh * nrm
            if eps > 0.0:
                if closed:
                    q = p[:, :-1]
                    lap = 0.5 * (np.roll(q, 1, axis=1) + np.roll(q, -1, axis=1)) - q
                    q = q + free[:, :-1] * _limited(lap, nrm[:, :-1], eps, dh)
                    p = np.concatenate([q, q[:, :1]], axis=1)
                else:
                    lap = 0.5 * (p[:, :-2] + p[:, 2:]) - p[:, 1:-1]
                    if keep_spacing is not None:
                        hl = np.linalg.norm(p[:, 1:-1] - p[:, :-2], axis=-1)[..., None]
                        hr = np.linalg.norm(p[:, 2:] - p[:, 1:-1], axis=-1)[..., None]
                        lap_w = (hr * p[:, :-2] + hl * p[:, 2:]) / np.maximum(hl + hr, 1e-300) - p[:, 1:-1]
                        a = np.broadcast_to(keep_spacing, p.shape[:2])[:, 1:-1, None]
                        lap = (1.0 - a) * lap + a * lap_w
                    p[:, 1:-1] += free[:, 1:-1] * _limited(lap, nrm[:, 1:-1], eps, dh)
        p = np.where(free, p, wall + dist[j] * n0)
        out[:, :, j] = p
    if closed:
        out[:, -1] = out[:, 0]
    return out


def _wake_keep_spacing(s_wake: np.ndarray, n: int) -> np.ndarray:
    """``keep_spacing`` of a C curve: 0 on the section, rising smoothly from 0
    at 2 chords behind the trailing edge to 1 at 6 chords along each wake
    (``s_wake``: distances of the wake points from the trailing edge, in
    chords, trailing edge excluded; the curve runs outflow -> wake ->
    section -> wake -> outflow).  Even smoothing stays where the layers must
    turn round the junction."""
    nw = s_wake.shape[0]
    t = np.clip((s_wake - 2.0) / 4.0, 0.0, 1.0)
    ramp = t * t * (3.0 - 2.0 * t)
    out = np.zeros(n)
    out[n - nw:] = ramp
    out[:nw] = ramp[::-1]
    return out


def _block2d(xy: np.ndarray, name: str) -> Block:
    ni, nj, _ = xy.shape
    xyz = np.zeros((ni, nj, 1, 3), order="F")
    xyz[:, :, 0, :2] = xy
    return Block(xyz, name=name)


#: a hexahedron corner counts as inside out below this scaled Jacobian
#: (round-off on the 180-degree corners of a wing's collapsed edges)
CORNER_TOL = 1e-9


def _checked(grid: Grid, what: str) -> Grid:
    """Return ``grid`` if every cell is valid, else raise naming the first bad cell.

    Valid (:func:`tfi_quat.quality.invalid_cells`): positive area or volume
    and positive scaled corner Jacobians, 2-D quads strictly convex.  A
    hexahedron may have a zero corner (to :data:`CORNER_TOL`): on a wing's
    collapsed edge (the leading edge of the zero-thickness sheet beyond the
    tip cap) the C wraps round a line, and the grid lines meet there at 180
    degrees.
    """
    tol = 0.0 if grid.ndim == 2 else CORNER_TOL
    for n, b in enumerate(grid):
        count, first = invalid_cells(b, grid.ndim, tol)
        if count:
            i, j, k = first
            idx = (i + 1, j + 1) if grid.ndim == 2 else (i + 1, j + 1, k + 1)
            raise GridValueError(
                f"{what}: {int(count)} folded or degenerate cell(s) in block {n + 1}, first at "
                f"cell {idx} (1-based); the parameters ask too much of the marcher: use more points "
                "(ni, nj) or a gentler wall-normal stretching")
    return grid


# --------------------------------------------------------------------------- NACA
def _naca_digits(naca) -> tuple[float, float, float]:
    s = str(naca).strip()
    if s.upper().startswith("NACA"):
        s = s[4:].strip()
    if len(s) != 4 or not s.isdigit():
        raise GridValueError(f"naca must be a 4-digit NACA code such as '0012', got {naca!r}")
    m, p, t = int(s[0]) / 100.0, int(s[1]) / 10.0, int(s[2:]) / 100.0
    if t <= 0.0:
        raise GridValueError(f"naca {naca!r}: thickness must be > 0")
    if (m > 0.0) != (p > 0.0):
        raise GridValueError(f"naca {naca!r}: camber and camber position must both be zero or both non-zero")
    return m, p, t


def naca4(naca, x, blunt_te: bool = False, thickness_scale=1.0):
    """NACA 4-digit section coordinates (unit chord).

    Parameters
    ----------
    naca : str
        Four digits, e.g. ``"0012"``, ``"4412"``.
    x : array_like, shape (n,)
        Chordwise stations in [0, 1].
    blunt_te : bool
        Use the original thickness polynomial (trailing edge thickness about
        0.21 t); default: the closed-trailing-edge variant (last coefficient
        -0.1036), whose thickness at x = 1 is set exactly to zero.
    thickness_scale : float or array_like
        Factor on the thickness (broadcast against ``x``; the wing tip cap
        shrinks the section with it).

    Returns
    -------
    xu, yu, xl, yl : ndarray of float64, shape (n,)
        Upper and lower surface points (thickness applied normal to the
        camber line).
    """
    m, p, t = _naca_digits(naca)
    x = np.asarray(x, dtype=np.float64)
    a4 = -0.1015 if blunt_te else -0.1036
    yt = 5.0 * t * (0.2969 * np.sqrt(x) - 0.1260 * x - 0.3516 * x ** 2 + 0.2843 * x ** 3 + a4 * x ** 4)
    if not blunt_te:
        yt = np.where(x >= 1.0, 0.0, yt)
    yt = yt * thickness_scale
    if m > 0.0:
        yc = np.where(x < p, m / p ** 2 * (2 * p * x - x ** 2),
                      m / (1 - p) ** 2 * ((1 - 2 * p) + 2 * p * x - x ** 2))
        dyc = np.where(x < p, 2 * m / p ** 2 * (p - x), 2 * m / (1 - p) ** 2 * (p - x))
        yc = np.where(x >= 1.0, 0.0, yc)
        th = np.arctan(dyc)
        s, c = np.sin(th), np.cos(th)
    else:
        yc = np.zeros_like(x)
        s, c = np.zeros_like(x), np.ones_like(x)
    return x - yt * s, yc + yt * c, x + yt * s, yc - yt * c


def _section_curve(naca, n_side, blunt_te, n_base, thickness_scale=1.0):
    """Clockwise wall curve of one section, TE (or base middle) to TE.

    Returns (curve (n, 2), spacing at the trailing edge).  Sharp: lower TE ->
    LE -> upper TE, first and last point equal.  Blunt: base middle -> lower
    corner -> LE -> upper corner -> base middle.
    """
    beta = np.linspace(0.0, np.pi, n_side + 1)
    x = 0.5 * (1.0 - np.cos(beta))
    x[0], x[-1] = 0.0, 1.0
    xu, yu, xl, yl = naca4(naca, x, blunt_te, thickness_scale)
    lower = np.stack([xl[::-1], yl[::-1]], axis=-1)   # TE -> LE
    upper = np.stack([xu[1:], yu[1:]], axis=-1)       # after LE -> TE
    surf = np.concatenate([lower, upper])
    ds_te = float(np.hypot(*(surf[1] - surf[0])))
    if not blunt_te:
        surf[-1] = surf[0]
        return surf, ds_te
    mid = 0.5 * (surf[0] + surf[-1])
    w = np.linspace(0.0, 1.0, n_base + 1)[:, None]
    down_l = mid + w * (surf[0] - mid)                # mid -> lower corner
    down_u = surf[-1] + w * (mid - surf[-1])          # upper corner -> mid
    curve = np.concatenate([down_l[:-1], surf, down_u[1:]])
    curve[-1] = curve[0]
    return curve, ds_te


# --------------------------------------------------------------------------- airfoil
def airfoil(naca="0012", topology="C", ni: int = 257, nj: int = 65, first_spacing: float = 1e-5,
            farfield: float = 20.0, wake_length: float | None = None, blunt_te: bool = False,
            n_wake: int | None = None, n_base: int = 4, n_ortho: int = 12,
            smoothing: float = 0.3, stretching: str = "geometric") -> Grid:
    """Viscous 2-D grid around a NACA 4-digit airfoil (unit chord, LE at the origin).

    Parameters
    ----------
    naca : str
        Four-digit NACA code.
    topology : {"C", "O"}
        C-grid: i runs from the lower end of the wake cut (outflow) along the
        wake, clockwise round the airfoil and back along the wake; the wake cut
        ``jmin[0:n_wake+1]`` matches ``jmin[ni-n_wake-1:]`` reversed, bit for bit.
        O-grid: i runs clockwise from the trailing edge (base middle when
        blunt); ``imin`` and ``imax`` are the same line (periodic seam).
    ni, nj : int
        Points round (odd) and outwards.
    first_spacing : float
        Wall-normal size of the first cell (chords), 1e-7 .. 1e-2.
    farfield : float
        Marching distance to the outer boundary (chords).
    wake_length : float, optional
        C-grid: length of the wake cut behind the trailing edge (default:
        ``farfield``).
    blunt_te : bool
        Blunt trailing edge (original NACA thickness polynomial, base closed
        by a straight segment with ``2 * n_base`` intervals).  O-grid only:
        the wake cut of a one-block C-grid would meet the base in two
        right-angle corners of the domain, where cells cannot be both valid
        and wall-orthogonal.
    n_wake : int, optional
        C-grid: intervals along each side of the wake (default ``(ni-1)//4``).
    n_base : int
        Intervals on each half of a blunt base (O-grid).
    n_ortho : int
        Layers extruded straight along the wall normal (orthogonal lines).
    smoothing : float
        Laplacian smoothing of the outer marching, 0 .. 0.5.
    stretching : {"geometric", "tanh"}
        Wall-normal distribution from ``first_spacing`` to ``farfield``:
        constant ratio (:func:`geometric_spacing`) or one-sided tanh
        (:func:`tanh_spacing`: the ratio falls off away from the wall, the
        outer cells are smaller).

    Returns
    -------
    Grid
        ``ndim = 2``, one block ``(ni, nj, 1, 3)``, wall on ``jmin``: the
        whole face for the O-grid, i (0-based) in ``airfoil_wall_range(...)``
        for the C-grid.
    """
    topo = str(topology).upper()
    if topo not in ("C", "O"):
        raise GridValueError(f"topology must be 'C' or 'O', got {topology!r}")
    _naca_digits(naca)
    ni = _check_int("ni", ni, 9, odd=True)
    nj = _check_int("nj", nj, 3)
    first_spacing = _check_float("first_spacing", first_spacing, 1e-7, 1e-2, " chords")
    farfield = _check_float("farfield", farfield, 2.0, 1e4, " chords")
    n_ortho = _check_int("n_ortho", n_ortho, 0)
    smoothing = _check_float("smoothing", smoothing, 0.0, 0.5)
    blunt = _check_bool("blunt_te", blunt_te)
    nb = _check_int("n_base", n_base, 1) if blunt else 0
    if topo == "O":
        for name, value in (("wake_length", wake_length), ("n_wake", n_wake)):
            if value is not None:
                raise GridValueError(f"{name} applies to C-grids only (topology 'C'), got {name} = "
                                     f"{value!r} with topology 'O'")
    elif blunt:
        raise GridValueError("blunt_te=True needs topology 'O': a one-block C-grid's wake cut would "
                             "meet the blunt base in right-angle corners, where cells cannot be both "
                             "valid and orthogonal to the wall")
    dist = _stretching(stretching, nj - 1, farfield, first_spacing)
    if topo == "O":
        n_side, rem = divmod(ni - 1 - 2 * nb, 2)
        if n_side < 4:
            raise GridValueError(f"ni = {ni} is too small for an O-grid (need >= {9 + 2 * nb})")
        curve, _ = _section_curve(naca, n_side, blunt, nb)
        xy = _march2d(curve[None], dist, True, n_ortho, smoothing)[0]
        xy[-1] = xy[0]
        return _checked(Grid([_block2d(xy, "airfoil_O")], ndim=2), f"airfoil {naca} O-grid")
    wl = farfield if wake_length is None else _check_float("wake_length", wake_length, 1.0, 1e4, " chords")
    nw = (ni - 1) // 4 if n_wake is None else _check_int("n_wake", n_wake, 1)
    n_side2 = ni - 1 - 2 * nw
    if n_side2 < 8 or n_side2 % 2:
        raise GridValueError(f"ni = {ni}, n_wake = {nw}: the airfoil needs an even number >= 8 of "
                             f"intervals, got ni - 1 - 2*n_wake = {n_side2}")
    curve, ds_te = _section_curve(naca, n_side2 // 2, False, 0)
    te = curve[0]
    s = geometric_spacing(nw, wl, min(ds_te, wl / nw))
    wake = np.stack([te[0] + s[1:], np.full(nw, te[1])], axis=-1)   # TE -> outflow
    c_curve = np.concatenate([wake[::-1], curve, wake])
    xy = _march2d(c_curve[None], dist, False, n_ortho, smoothing,
                  end_normals=(np.array([0.0, -1.0]), np.array([0.0, 1.0])),
                  keep_spacing=_wake_keep_spacing(s[1:], c_curve.shape[0]))[0]
    return _checked(Grid([_block2d(xy, "airfoil_C")], ndim=2), f"airfoil {naca} C-grid")


def airfoil_wall_range(ni: int, topology="C", n_wake: int | None = None) -> tuple[int, int]:
    """0-based inclusive i range of the wall on ``jmin`` of :func:`airfoil`'s grid."""
    if str(topology).upper() == "O":
        return 0, ni - 1
    nw = (ni - 1) // 4 if n_wake is None else int(n_wake)
    return nw, ni - 1 - nw


# --------------------------------------------------------------------------- cylinder
def cylinder(ni: int = 129, nj: int = 65, radius: float = 0.5, first_spacing: float = 1e-4,
             farfield: float = 20.0) -> Grid:
    """Analytic 2-D O-grid around a circular cylinder centred at the origin.

    Parameters
    ----------
    ni, nj : int
        Points round (the last i line repeats the first: periodic seam) and
        outwards.
    radius : float
        Cylinder radius.
    first_spacing : float
        Radial size of the first cell.
    farfield : float
        Outer radius.

    Returns
    -------
    Grid
        ``ndim = 2``, one block ``(ni, nj, 1, 3)``; i runs clockwise from
        (radius, 0), wall on ``jmin``; radial lines are exactly orthogonal
        to the wall.
    """
    ni = _check_int("ni", ni, 5)
    nj = _check_int("nj", nj, 2)
    radius = _check_pos("radius", radius)
    farfield = _check_pos("farfield", farfield)
    if farfield <= radius:
        raise GridValueError(f"farfield ({farfield}) must exceed the radius ({radius})")
    first_spacing = _check_pos("first_spacing", first_spacing, hi=farfield - radius)
    r = radius + geometric_spacing(nj - 1, farfield - radius, first_spacing)
    th = -2.0 * np.pi * np.arange(ni) / (ni - 1)
    xy = np.empty((ni, nj, 2))
    xy[:, :, 0] = np.cos(th)[:, None] * r[None, :]
    xy[:, :, 1] = np.sin(th)[:, None] * r[None, :]
    xy[-1] = xy[0]
    return Grid([_block2d(xy, "cylinder")], ndim=2)


# --------------------------------------------------------------------------- channel
def _bump(x, x0, x1, height):
    t = np.clip((x - x0) / (x1 - x0), 0.0, 1.0)
    return height * np.sin(np.pi * t) ** 2


def _channel_points(ni, nj, length, height, bump_height, bump_start, bump_end, first_spacing,
                    n_ortho=10):
    x = np.linspace(0.0, length, ni)
    yw = _bump(x, bump_start, bump_end, bump_height)
    wall = np.stack([x, yw], axis=-1)
    # discrete wall normal (central differences), as for the airfoils
    t = np.gradient(wall, axis=0)
    nrm = np.stack([-t[:, 1], t[:, 0]], axis=-1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    eta = geometric_spacing(nj - 1, 1.0, first_spacing / height)
    hloc = height - yw
    ext = wall[:, None, :] + (eta[None, :, None] * hloc[:, None, None]) * nrm[:, None, :]
    vert = np.stack([np.broadcast_to(x[:, None], (ni, nj)),
                     yw[:, None] + eta[None, :] * hloc[:, None]], axis=-1)
    # straight wall-normal lines for the first n_ortho layers, then a smooth
    # blend into vertical lines, reached at mid-height
    e0 = eta[min(n_ortho, nj - 1)]
    s = np.clip((eta - e0) / max(0.5 - e0, 1e-12), 0.0, 1.0)
    beta = (s * s * (3.0 - 2.0 * s))[None, :, None]
    xy = (1.0 - beta) * ext + beta * vert
    xy[:, 0] = wall
    xy[:, -1, 1] = height
    return xy


def channel(ni: int = 129, nj: int = 49, length: float = 3.0, height: float = 1.0,
            bump_height: float = 0.1, bump_start: float = 1.0, bump_end: float = 2.0,
            first_spacing: float = 1e-3) -> Grid:
    """2-D H-grid of a channel with a smooth bump on the lower wall.

    The lower wall is ``y = h sin^2(pi (x - x0)/(x1 - x0))`` on
    ``[bump_start, bump_end]`` and ``y = 0`` elsewhere; the upper wall is
    ``y = height``.  j-lines leave the lower wall along its normal and turn
    into vertical lines by mid-height (straight along the discrete wall normal
    for the first 10 layers).

    Parameters
    ----------
    ni, nj : int
        Points along and across the channel.
    length, height : float
    bump_height : float
        Bump height (``0 <= bump_height < height / 2``).
    bump_start, bump_end : float
        Bump extent, ``0 < bump_start < bump_end < length``.
    first_spacing : float
        Size of the first cell off the lower wall.

    Returns
    -------
    Grid
        ``ndim = 2``, one block ``(ni, nj, 1, 3)``; lower wall ``jmin``,
        upper wall ``jmax``, inflow ``imin``, outflow ``imax``.
    """
    ni = _check_int("ni", ni, 3)
    nj = _check_int("nj", nj, 3)
    length = _check_pos("length", length)
    height = _check_pos("height", height)
    bump_height = _check_float("bump_height", bump_height, 0.0, 0.5 * height)
    if bump_height == 0.5 * height:
        raise GridValueError(f"bump_height must be in [0, height/2), got {bump_height}")
    bump_start = _check_float("bump_start", bump_start, 0.0, length)
    bump_end = _check_float("bump_end", bump_end, 0.0, length)
    if not 0.0 < bump_start < bump_end < length:
        raise GridValueError(f"need 0 < bump_start < bump_end < length, "
                             f"got {bump_start}, {bump_end}, {length}")
    first_spacing = _check_pos("first_spacing", first_spacing, hi=0.5 * height)
    xy = _channel_points(ni, nj, length, height, bump_height, bump_start, bump_end, first_spacing)
    return _checked(Grid([_block2d(xy, "channel")], ndim=2), "channel")


def two_block(ni: int = 65, nj: int = 33, length: float = 3.0, height: float = 1.0,
              bump_height: float = 0.1, first_spacing: float = 2e-3) -> Grid:
    """2-D two-block channel: a walled lower block and an upper block turned by 90 degrees.

    The channel of :func:`channel` (bump on ``[length/3, 2 length/3]``) is
    cut at mid-height of its index range.  Block 1 is the lower part as
    generated (wall on ``jmin``); block 2 is the upper part with its index
    axes turned (its i runs downwards, its j along the channel), so the
    interface ``1:jmax`` <-> ``2:imax`` has swapped axes.  Points on the
    interface are bit-identical.

    Parameters
    ----------
    ni : int
        Points along the channel.
    nj : int
        Points across the whole channel (odd: the cut is at ``(nj-1)/2``).
    length, height, bump_height, first_spacing : float
        As in :func:`channel`.

    Returns
    -------
    Grid
        ``ndim = 2``, blocks ``(ni, (nj+1)/2, 1, 3)`` and ``((nj+1)/2, ni, 1, 3)``.
    """
    ni = _check_int("ni", ni, 3)
    nj = _check_int("nj", nj, 5, odd=True)
    length = _check_pos("length", length)
    height = _check_pos("height", height)
    bump_height = _check_float("bump_height", bump_height, 0.0, 0.5 * height)
    if bump_height == 0.5 * height:
        raise GridValueError(f"bump_height must be in [0, height/2), got {bump_height}")
    first_spacing = _check_pos("first_spacing", first_spacing, hi=0.5 * height)
    xy = _channel_points(ni, nj, length, height, bump_height, length / 3.0, 2.0 * length / 3.0,
                         first_spacing)
    jc = (nj - 1) // 2
    lower = xy[:, :jc + 1]
    upper = xy[:, jc:]                       # (ni, nu): i along, j up
    turned = upper[:, ::-1].transpose(1, 0, 2)   # i' = down (j reversed), j' = along (i)
    return _checked(Grid([_block2d(lower, "lower"), _block2d(np.ascontiguousarray(turned), "upper")],
                         ndim=2), "two_block")


# --------------------------------------------------------------------------- wing
def _smooth_ramp(y, yb):
    """``sqrt(y^2 + yb^2) - yb``: zero value and slope at y = 0, slope -> 1."""
    return np.sqrt(y * y + yb * yb) - yb


def wing_geometry(aspect_ratio: float = 4.0, taper: float = 0.5, sweep: float = 30.0,
                  root_chord: float = 1.0):
    """Semi-span, tip chord, and the leading-edge and chord laws of :func:`wing`.

    Returns
    -------
    semispan : float
    x_le : callable
        ``x_le(y)``: leading-edge x at span station y (0 <= y <= semispan).
    chord : callable
        ``chord(y)``.

    Notes
    -----
    Both laws have zero slope at the root (a fairing over the first
    ``0.2 * root_chord`` of span), so the wing meets the symmetry plane at
    right angles, and reach ``tan(sweep)`` and the linear taper slope
    outboard.
    """
    c_tip = taper * root_chord
    semispan = 0.25 * aspect_ratio * (root_chord + c_tip)
    yb = 0.2 * root_chord
    tan_l = math.tan(math.radians(sweep))
    gb = float(_smooth_ramp(semispan, yb))

    def x_le(y):
        return tan_l * _smooth_ramp(np.asarray(y, dtype=np.float64), yb) * semispan / gb

    def chord(y):
        return root_chord - (root_chord - c_tip) * _smooth_ramp(np.asarray(y, dtype=np.float64), yb) / gb

    return semispan, x_le, chord


def _stations(n, a, b, first_at_b=None, first_at_a=None):
    """``n`` points from a to b, geometric from the given end spacing (else uniform)."""
    if first_at_b is not None:
        s = geometric_spacing(n - 1, b - a, min(first_at_b, (b - a) / (n - 1)))
        out = b - s[::-1]
        out[0] = a
        return out
    if first_at_a is not None:
        s = geometric_spacing(n - 1, b - a, min(first_at_a, (b - a) / (n - 1)))
        out = a + s
        out[-1] = b
        return out
    return np.linspace(a, b, n)


def wing(naca="0012", aspect_ratio: float = 4.0, taper: float = 0.5, sweep: float = 30.0,
         ni: int = 129, nj: int = 49, nk_wing: int = 45, nk_cap: int = 9, nk_out: int = 25,
         first_spacing: float = 2e-5, farfield: float = 15.0, span_farfield: float = 10.0,
         wake_length: float = 15.0, n_wake: int | None = None, n_ortho: int = 12,
         smoothing: float = 0.3, stretching: str = "geometric") -> Grid:
    """3-D C-H multiblock grid around a swept, tapered half wing (root chord 1).

    x runs downstream, y along the span (the root, ``y = 0``, is a symmetry
    plane), z up.  Sections are NACA 4-digit airfoils with a sharp trailing
    edge.  Beyond the tip the section thickness shrinks to zero over a
    rounded cap (``0.5 t c_tip`` long), and further out the C-grid continues
    round a zero-thickness sheet (collapsed section) to the spanwise far
    field.

    Blocks (1-based as in case files); i runs from the upper end of the wake
    cut (outflow, z > 0) upstream, over the upper surface, round the leading
    edge and back along the lower surface and wake; j outwards; k (blocks
    1-3) along +y.

    1. ``wing``: ``(ni, nj, nk_wing)``, root to tip.  Wall: ``jmin``, i in
       the airfoil range; wake cut: ``jmin`` i in ``1..n_wake+1`` matches
       ``ni-n_wake..ni`` reversed; symmetry: ``kmin``.
    2. ``cap``: ``(ni, nj, nk_cap)``, tip cap.  Wall: ``jmin`` airfoil range
       (its last k line is the collapsed edge); wake cut as block 1;
       ``kmin`` = block 1 ``kmax``.
    3. ``outer_upper``: ``(ni_half, nj, nk_out)`` beyond the cap, the half
       of the C on the upper side (``ni_half = (ni+1)/2``).
    4. ``outer_lower``: the lower half with its axes permuted cyclically,
       ``(nk_out, ni_half, nj)``: its i runs along the span, j round the
       C, k outwards.  Its ``imin`` face is part of block 2's ``kmax``
       (swapped axes); block 3's ``jmin`` matches block 4's ``kmin`` with
       the running index reversed; block 3's ``imax`` matches block 4's
       ``jmin``.

    Parameters
    ----------
    naca : str
        Four-digit NACA section (the same at every station).
    aspect_ratio : float
        Full-span aspect ratio ``(2 b)^2 / S``, 1 .. 20.
    taper : float
        Tip chord / root chord, 0.1 .. 1.
    sweep : float
        Leading-edge sweep outboard of the root fairing, degrees, 0 .. 60.
    ni : int
        Points round the C (odd, ``(ni - 1) % 4 == 0``).
    nj : int
        Points outwards.
    nk_wing, nk_cap, nk_out : int
        Span stations on the wing, the cap and beyond (shared stations
        counted in both blocks).
    first_spacing : float
        Wall-normal first cell (root chords).
    farfield : float
        Marching distance to the outer boundary (root chords).
    span_farfield : float
        Distance of the spanwise far field beyond the tip (root chords).
    wake_length : float
        Outflow plane at ``x = max trailing edge x + wake_length``.
    n_wake : int, optional
        Intervals along each side of the wake (default ``(ni - 1) // 4``).
    n_ortho : int
        Layers extruded along the 3-D wall normal.
    smoothing : float
        Laplacian smoothing of the outer marching.
    stretching : {"geometric", "tanh"}
        Wall-normal distribution, as in :func:`airfoil`.

    Returns
    -------
    Grid
        ``ndim = 3``, four blocks, right-handed.
    """
    ni = _check_int("ni", ni, 17, odd=True)
    if (ni - 1) % 4:
        raise GridValueError(f"ni - 1 must be a multiple of 4, got ni = {ni}")
    nj = _check_int("nj", nj, 5)
    nk_wing = _check_int("nk_wing", nk_wing, 3)
    nk_cap = _check_int("nk_cap", nk_cap, 3)
    nk_out = _check_int("nk_out", nk_out, 3)
    ar = _check_float("aspect_ratio", aspect_ratio, 1.0, 20.0)
    taper = _check_float("taper", taper, 0.1, 1.0)
    sweep = _check_float("sweep", sweep, 0.0, 60.0, " degrees")
    first_spacing = _check_float("first_spacing", first_spacing, 1e-7, 1e-2, " root chords")
    farfield = _check_float("farfield", farfield, 2.0, 1e4, " root chords")
    span_farfield = _check_float("span_farfield", span_farfield, 1.0, 1e4, " root chords")
    wake_length = _check_float("wake_length", wake_length, 1.0, 1e4, " root chords")
    n_ortho = _check_int("n_ortho", n_ortho, 0)
    smoothing = _check_float("smoothing", smoothing, 0.0, 0.5)
    t = _naca_digits(naca)[2]
    nw = (ni - 1) // 4 if n_wake is None else _check_int("n_wake", n_wake, 1)
    n_side2 = ni - 1 - 2 * nw
    if n_side2 < 8 or n_side2 % 2:
        raise GridValueError(f"ni = {ni}, n_wake = {nw}: ni - 1 - 2*n_wake must be even and >= 8")
    n_side = n_side2 // 2

    semispan, x_le, chord = wing_geometry(ar, taper, sweep)
    c_tip = float(chord(semispan))
    r_cap = 0.5 * t * c_tip
    # span stations: wing (clustered towards the tip), cap (uniform), beyond (stretched)
    dy_cap = r_cap / (nk_cap - 1)
    y_w = _stations(nk_wing, 0.0, semispan, first_at_b=dy_cap)
    y_c = np.linspace(semispan, semispan + r_cap, nk_cap)
    y_o = _stations(nk_out, semispan + r_cap, semispan + span_farfield, first_at_a=dy_cap)
    y = np.concatenate([y_w, y_c[1:], y_o[1:]])
    kt, kc = nk_wing - 1, nk_wing + nk_cap - 2
    nk = y.size
    # the cap continues the planform (sweep, taper), so the wall has no crease
    # at the tip; beyond the cap the collapsed section stays as it ends
    ys = np.minimum(y, semispan + r_cap)
    scale = np.ones(nk)
    scale[kt:kc + 1] = np.cos(0.5 * np.pi * (y[kt:kc + 1] - semispan) / r_cap)
    scale[kc:] = 0.0
    xle, ch = x_le(ys), chord(ys)

    x_out = float(np.max(xle + ch)) + wake_length
    curves = np.empty((nk, ni, 2))
    keep = np.empty((nk, ni))
    for k in range(nk):
        sec, ds_te = _section_curve(naca, n_side, False, 0, thickness_scale=scale[k])
        sec = sec * ch[k]
        sec[:, 0] += xle[k]
        te = sec[0]
        ds_te *= ch[k]
        s = geometric_spacing(nw, x_out - te[0], min(ds_te, (x_out - te[0]) / nw))
        wake = np.stack([te[0] + s[1:], np.full(nw, te[1])], axis=-1)
        wake[-1, 0] = x_out
        curves[k] = np.concatenate([wake[::-1], sec, wake])
        keep[k] = _wake_keep_spacing(s[1:] / ch[k], ni)
    dist = _stretching(stretching, nj - 1, farfield, first_spacing)
    sec2d = _march2d(curves, dist, False, n_ortho, smoothing,
                     end_normals=(np.array([0.0, -1.0]), np.array([0.0, 1.0])), keep_spacing=keep)
    # global array (i, j, k, xyz); i reversed so that (i, j, k) is right-handed
    g = np.empty((ni, nj, nk, 3))
    g[..., 0] = sec2d[:, ::-1, :, 0].transpose(1, 2, 0)
    g[..., 1] = y[None, None, :]
    g[..., 2] = sec2d[:, ::-1, :, 1].transpose(1, 2, 0)

    # 3-D wall normals; lines near the wall leave along them
    w = g[:, 0]                                       # (ni, nk, 3)
    ti = np.empty_like(w)
    ti[1:-1] = w[2:] - w[:-2]
    ti[0], ti[-1] = w[1] - w[0], w[-1] - w[-2]
    tk = np.empty_like(w)
    tk[:, 1:-1] = w[:, 2:] - w[:, :-2]
    tk[:, 0] = -3.0 * w[:, 0] + 4.0 * w[:, 1] - w[:, 2]
    tk[:, -1] = w[:, -1] - w[:, -2]
    n2 = np.zeros_like(w)
    n2d = _curve_normals(curves, False)[:, ::-1].transpose(1, 0, 2)   # (ni, nk, 2)
    n2d[0], n2d[-1] = [0.0, 1.0], [0.0, -1.0]
    n2[..., 0], n2[..., 2] = n2d[..., 0], n2d[..., 1]
    c = np.cross(ti, tk)
    cn = np.linalg.norm(c, axis=-1, keepdims=True)
    ok = cn[..., 0] > 1e-12 * np.max(cn)
    n3 = np.where(ok[..., None], c / np.where(cn > 0, cn, 1.0), n2)
    n3 = np.where((np.einsum("ikc,ikc->ik", n3, n2) < 0.0)[..., None], -n3, n3)
    # where the wall has no tangent plane (the collapsed leading edge at the
    # cap's last station) the line stays in the section plane, along the
    # sheet: the grid lines meet there at 180 degrees, and any lean out of
    # the sheet would turn one of the two cells there inside out
    n3[:, 0, 1] = 0.0                                 # root: in the symmetry plane
    n3[:, 0] = _unit(n3[:, 0])
    jb = np.arange(nj)
    fade = np.clip((jb - n_ortho) / 8.0, 0.0, 1.0)
    bj = 0.5 * (1.0 + np.cos(np.pi * fade))
    # beyond n_ortho the correction never grows past its size at n_ortho
    bj = bj * np.minimum(1.0, dist[min(n_ortho, nj - 1)] / np.maximum(dist, 1e-300))
    corr = (bj * dist)[None, :, None, None] * (n3 - n2)[:, None, :, :]
    corr[:, 0] = 0.0
    # beyond the cap (no wall) the correction of the collapsed edge fades
    # out over four times its size, a change of at most a quarter of the
    # span spacing per station
    c_end = corr[:, :, kc]
    reach = np.maximum(4.0 * np.linalg.norm(c_end, axis=-1), 1e-300)
    corr[:, :, kc + 1:] = c_end[:, :, None, :] * np.clip(
        1.0 - (y[kc + 1:] - y[kc])[None, None, :] / reach[..., None], 0.0, 1.0)[..., None]
    # neighbouring stations' corrections never differ by more than half
    # their span spacing, or hexahedra twist: where they would (first layers
    # thick compared with the span spacing at the cap) the correction of the
    # whole spanwise line is scaled down, at the cost of orthogonality there
    dc = np.linalg.norm(np.diff(corr, axis=2), axis=-1) / (0.5 * np.diff(y))[None, None, :]
    corr *= np.minimum(1.0, 1.0 / np.maximum(dc.max(axis=2), 1e-300))[:, :, None, None]
    g += corr

    ih = (ni - 1) // 2
    b1 = g[:, :, :kt + 1]
    b2 = g[:, :, kt:kc + 1]
    b3 = g[:ih + 1, :, kc:]
    b4 = g[ih:, :, kc:].transpose(2, 0, 1, 3)
    blocks = [Block(np.asfortranarray(b), name=nm) for b, nm in
              ((b1, "wing"), (b2, "cap"), (b3, "outer_upper"), (b4, "outer_lower"))]
    return _checked(Grid(blocks, ndim=3), "wing")


def wing_wall_range(ni: int, n_wake: int | None = None) -> tuple[int, int]:
    """0-based inclusive i range of the wall on ``jmin`` of blocks 1 and 2 of :func:`wing`."""
    nw = (ni - 1) // 4 if n_wake is None else int(n_wake)
    return nw, ni - 1 - nw


#: generator name (CLI subcommand argument) -> function
GENERATORS = {
    "airfoil": airfoil,
    "cylinder": cylinder,
    "channel": channel,
    "two-block": two_block,
    "wing": wing,
}


# --------------------------------------------------------------------------- boundaries
def boundary_patches(kind: str, grid: Grid, n_wake: int | None = None, topology: str = "C") -> dict:
    """Walls, symmetry planes and fixed (far-field) patches of a generated grid.

    Parameters
    ----------
    kind : {"airfoil", "cylinder", "channel", "two-block", "wing"}
        The generator that made ``grid``.
    grid : Grid
        Its output.
    n_wake : int, optional
        The ``n_wake`` given to :func:`airfoil` or :func:`wing`.
    topology : {"C", "O"}
        The airfoil topology.

    Returns
    -------
    dict
        ``{"walls": [...], "symmetry": [...], "fixed": [...]}``, lists of
        :class:`tfi_quat.spec.PatchSpec` (0-based, explicit wall ranges).
    """
    from .spec import PatchSpec

    def whole(b, *faces):
        return [PatchSpec(b, f) for f in faces]

    if kind not in GENERATORS:
        raise GridValueError(f"unknown generator {kind!r}: expected one of {', '.join(GENERATORS)}")
    if kind == "airfoil":
        ni = grid[0].dims[0]
        if str(topology).upper() == "O":
            return {"walls": whole(0, "jmin"), "symmetry": [], "fixed": whole(0, "jmax")}
        lo, hi = airfoil_wall_range(ni, "C", n_wake)
        return {"walls": [PatchSpec(0, "jmin", ((lo, hi), (0, 0)))], "symmetry": [],
                "fixed": whole(0, "jmax", "imin", "imax")}
    if kind == "cylinder":
        return {"walls": whole(0, "jmin"), "symmetry": [], "fixed": whole(0, "jmax")}
    if kind == "channel":
        return {"walls": whole(0, "jmin"), "symmetry": [], "fixed": whole(0, "jmax", "imin", "imax")}
    if kind == "two-block":
        return {"walls": whole(0, "jmin"), "symmetry": [],
                "fixed": whole(0, "imin", "imax") + whole(1, "imin", "jmin", "jmax")}
    ni, _, nk1 = grid[0].dims
    nk2 = grid[1].dims[2]
    lo, hi = wing_wall_range(ni, n_wake)
    return {"walls": [PatchSpec(0, "jmin", ((lo, hi), (0, nk1 - 1))),
                      PatchSpec(1, "jmin", ((lo, hi), (0, nk2 - 1)))],
            "symmetry": whole(0, "kmin"),
            "fixed": whole(0, "imin", "imax", "jmax") + whole(1, "imin", "imax", "jmax") +
            whole(2, "imin", "jmax", "kmax") + whole(3, "imax", "jmax", "kmax")}
