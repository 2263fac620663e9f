"""Coincident point pairs: all ``i < j`` with ``|P[i] - P[j]| <= tol``, exactly.

:func:`close_pairs` replaces ``scipy.spatial.cKDTree(P).query_pairs(tol,
output_type="ndarray")`` for the sets this package feeds it: the boundary
points of a structured multiblock grid, most of which have no partner at all,
the rest coinciding across block interfaces and wake cuts (pairs) or at
collapsed faces and poles (many copies of one point).  For such a set and a
tolerance far below the grid spacing the pairs are found by a sweep along one
direction:

1. project every point onto a fixed generic unit direction :data:`DIRECTION`
   (cubic-irrational components, so no small-integer lattice vector of an
   axis-aligned structured grid is perpendicular to it);
2. sort the projections: a two-level bucket sort (a few thousand coarse
   equal-width buckets, then each coarse bucket by as many fine buckets as it
   has points, fine buckets by insertion or ``np.argsort``) -- about half the
   time of ``np.argsort`` on a grid boundary, and still ``O(n log n)`` on
   skewed projections;
3. for every point in sorted order compare it with the points that follow
   while their projection exceeds its own by at most ``tol`` plus a rounding
   margin (so no pair is missed because of rounding in the projections), and
   keep the pair when the squared distance passes the final test below;
4. order the pairs lexicographically with a counting sort on the first index.

Rows come out sorted by ``i``, then ``j`` (cKDTree's order is unspecified), so
the result is deterministic.  On the boundary of the 10.9 M-point wing
(527 800 points, 135 522 pairs, ``tol = 1e-10`` x diagonal) it takes ~19 ms
against ~300 ms for cKDTree on a 2-core machine (``benchmarks/bench_points.py``).

The final test is the one cKDTree makes for ``p=2``: ``dx*dx + dy*dy + dz*dz
<= tol*tol``, summed in that order in float64.  (cKDTree also accepts whole
node pairs at once from rectangle bounds, so a pair whose distance lies
within a few units in the last place of ``tol`` may be decided differently by
the two; nothing else differs.)

The sweep costs one comparison per point plus one per pair -- and one per
*false candidate*, a point close to another in projection only.  Sets with many false candidates (points much denser than
``tol`` along the direction; not a structured grid's boundary) would make it
quadratic, so failed comparisons are counted and once they exceed ``budget``
(default ``32 * n + 1024``) the routine falls back to cKDTree.  True pairs are
never counted: a pole with ``k`` copies of one point is ``k (k - 1) / 2``
pairs of output anyway (the pair arrays are then sized by a second sweep).
Coordinates so large that projections would overflow are scaled by 1/16 for
the projection (cKDTree refuses such sets).
"""

from __future__ import annotations

import numbers

import numpy as np

from ._jit import jit

__all__ = ["close_pairs", "DIRECTION"]

_RHO = 1.324717957244746025960908854478          # plastic number, rho**3 = rho + 1
#: the sweep direction: ``(rho**-1, rho**-2, rho**-3)`` normalised -- no two
#: components equal, none zero, and no integer combination of them vanishes
DIRECTION = np.array([_RHO ** -1, _RHO ** -2, _RHO ** -3])
DIRECTION = DIRECTION / np.sqrt(DIRECTION @ DIRECTION)

_EPS = np.finfo(np.float64).eps
#: absolute floor of the projection window: a pair closer than this may have a
#: squared distance that underflows to zero and passes any ``tol``
_TINY = 2.0 ** -500
#: bound on the absolute rounding error of a projection from subnormal terms
_SUB = 64 * 2.0 ** -1074
#: buckets this small are sorted by insertion, larger ones by ``np.argsort``
_SMALL = 24


# ---------------------------------------------------------------- kernels
@jit
def _project(P, u, sc, p):
    """``p[i] = (sc P[i] - sc P[0]) @ u``; returns (ok, pmin, pmax, amax), amax = max_i sum_k |p's terms|.

    ``ok`` is 0 when a coordinate is not finite, 1 when a projection
    overflows (call again with ``sc = 1/16``), 2 when all is well.  The shift
    keeps the rounding error of the projections relative to the cloud's
    extent rather than to its distance from the origin; ``sc`` is a power of
    two, so scaling is exact (but for subnormals).
    """
    n = P.shape[0]
    u0, u1, u2 = u[0], u[1], u[2]
    a0, a1, a2 = abs(u0), abs(u1), abs(u2)
    c0 = P[0, 0] * sc
    c1 = P[0, 1] * sc
    c2 = P[0, 2] * sc
    pmin = np.inf
    pmax = -np.inf
    amax = 0.0
    bad = not (abs(c0) + abs(c1) + abs(c2) < np.inf)
    for i in range(n):
        x = P[i, 0] * sc - c0
        y = P[i, 1] * sc - c1
        z = P[i, 2] * sc - c2
        v = x * u0 + y * u1 + z * u2
        a = abs(x) * a0 + abs(y) * a1 + abs(z) * a2
        p[i] = v
        # NaN compares false everywhere, so (a < inf) is false for a NaN or
        # infinite coordinate and for an overflow
        if not (a < np.inf) or not (abs(v) < np.inf):
            bad = True
        if v < pmin:
            pmin = v
        if v > pmax:
            pmax = v
        if a > amax:
            amax = a
    if bad:
        for i in range(n):
            for k in range(3):
                if not np.isfinite(P[i, k]):
                    return 0, pmin, pmax, amax
        return 1, pmin, pmax, amax
    return 2, pmin, pmax, amax


@jit
def _insertion_sort(ps, order, s, e):
    """Sort ``ps[s:e]`` ascending in place, carrying ``order[s:e]`` along."""
    for t in range(s + 1, e):
        j = order[t]
        pj = ps[t]
        r = t - 1
        while r >= s and ps[r] > pj:
            order[r + 1] = order[r]
            ps[r + 1] = ps[r]
            r -= 1
        order[r + 1] = j
        ps[r + 1] = pj


@jit(inline="always")
def _bucket(v, lo, scale, nb):
    """Bucket ``0 .. nb - 1`` of ``v >= lo``: monotone in ``v``, also when ``scale`` is 0 or inf."""
    x = (v - lo) * scale
    if x >= nb:                          # also +inf
        return nb - 1
    if x > 0.0:
        return np.int64(x)
    return np.int64(0)                   # 0 and NaN (0 * inf, inf * 0)


@jit
def _bucket_counts(src_p, s, e, lo, scale, nb, count):
    """``count[b + 1]`` = how many of ``src_p[s:e]`` fall in bucket ``b``, then prefix sums."""
    for b in range(nb + 1):
        count[b] = 0
    for t in range(s, e):
        count[_bucket(src_p[t], lo, scale, nb) + 1] += 1
    for b in range(nb):
        count[b + 1] += count[b]


@jit
def _sort_by_projection(p, pmin, pmax):
    """``(order, ps)``: the permutation sorting ``p`` ascending and ``p[order]``.

    Two-level bucket sort, most significant first, each level with a bucket
    index monotone in the key: a few thousand coarse buckets over
    ``[pmin, pmax]`` (a cache-friendly scatter of the whole set), then each
    coarse bucket through a small scratch buffer by as many fine buckets as it
    has points over its own range; fine buckets are sorted by insertion, or by
    ``np.argsort`` when large.  Memory: the two output arrays and scratch the
    size of the largest coarse bucket (``~n / 4096`` unless skewed).
    """
    n = p.size
    order = np.empty(n, dtype=np.int64)
    ps = np.empty(n)
    if not (pmax > pmin):
        for i in range(n):
            order[i] = i
            ps[i] = p[i]
        return order, ps
    k1 = min(max(n // 64, 1), 4096)
    start1 = np.empty(k1 + 1, dtype=np.int64)
    scale = k1 / (pmax - pmin)
    _bucket_counts(p, 0, n, pmin, scale, k1, start1)
    big = 0
    for b in range(k1):
        big = max(big, start1[b + 1] - start1[b])
    for i in range(n):
        v = p[i]
        b = _bucket(v, pmin, scale, k1)
        r = start1[b]
        ps[r] = v
        order[r] = i
        start1[b] = r + 1
    # start1[b] is now the end of coarse bucket b
    count = np.empty(big + 1, dtype=np.int64)
    tp = np.empty(big)
    to = np.empty(big, dtype=np.int64)
    s = 0
    for b in range(k1):
        e = start1[b]
        c = e - s
        if c > _SMALL:
            lo = np.inf
            hi = -np.inf
            for t in range(s, e):
                v = ps[t]
                if v < lo:
                    lo = v
                if v > hi:
                    hi = v
            if hi > lo:
                sc = c / (hi - lo)
                _bucket_counts(ps, s, e, lo, sc, c, count)
                for t in range(s, e):
                    v = ps[t]
                    f = _bucket(v, lo, sc, c)
                    r = count[f]
                    tp[r] = v
                    to[r] = order[t]
                    count[f] = r + 1
                for t in range(c):
                    ps[s + t] = tp[t]
                    order[s + t] = to[t]
                r0 = s
                for f in range(c):
                    r1 = s + count[f]
                    if r1 - r0 > _SMALL:
                        srt = np.argsort(ps[r0:r1])
                        seg = order[r0:r1][srt]
                        key = ps[r0:r1][srt]
                        order[r0:r1] = seg
                        ps[r0:r1] = key
                    elif r1 - r0 > 1:
                        _insertion_sort(ps, order, r0, r1)
                    r0 = r1
        elif c > 1:
            _insertion_sort(ps, order, s, e)
        s = e
    return order, ps


@jit
def _sweep(P, order, ps, window, tol2, budget, first, second):
    """Pairs ``(min, max)`` of original indices found by the sweep, unordered.

    The pairs go to ``first[:m]``, ``second[:m]`` while they fit (``m`` is
    counted on regardless: call again with arrays of size ``m`` when it
    exceeds theirs).  Returns ``(m, ok)``; ``ok`` is False when more than
    ``budget`` comparisons failed the distance test (``m`` is then meaningless).
    """
    n = ps.size
    cap = first.size
    m = 0
    fails = 0
    for s in range(n - 1):
        lim = ps[s] + window
        t = s + 1
        if t < n and ps[t] <= lim:
            i = order[s]
            x = P[i, 0]
            y = P[i, 1]
            z = P[i, 2]
            while t < n and ps[t] <= lim:
                j = order[t]
                dx = x - P[j, 0]
                dy = y - P[j, 1]
                dz = z - P[j, 2]
                d2 = dx * dx + dy * dy + dz * dz
                if d2 <= tol2:
                    if m < cap:
                        if i < j:
                            first[m] = i
                            second[m] = j
                        else:
                            first[m] = j
                            second[m] = i
                    m += 1
                else:
                    fails += 1
                    if fails > budget:
                        return m, False
                t += 1
    return m, True


@jit
def _lexsorted(first, second, m, n):
    """The ``m`` pairs as an ``(m, 2)`` array sorted by first, then second index."""
    start = np.zeros(n + 1, dtype=np.int64)
    for k in range(m):
        start[first[k] + 1] += 1
    for i in range(n):
        start[i + 1] += start[i]
    out = np.empty((m, 2), dtype=np.int64)
    fill = start[:n].copy()
    col = np.empty(m, dtype=np.int64)
    for k in range(m):
        i = first[k]
        col[fill[i]] = second[k]
        fill[i] += 1
    for i in range(n):
        s = start[i]
        e = start[i + 1]
        if e - s > _SMALL:
            col[s:e] = np.sort(col[s:e])
        elif e - s > 1:
            for t in range(s + 1, e):
                v = col[t]
                r = t - 1
                while r >= s and col[r] > v:
                    col[r + 1] = col[r]
                    r -= 1
                col[r + 1] = v
        for t in range(s, e):
            out[t, 0] = i
            out[t, 1] = col[t]
    return out


# ---------------------------------------------------------------- public
def _kdtree_pairs(P: np.ndarray, tol: float) -> np.ndarray:
    """The fallback: cKDTree's pairs, sorted lexicographically."""
    from scipy.spatial import cKDTree

    pairs = cKDTree(P).query_pairs(tol, output_type="ndarray").astype(np.int64, copy=False)
    if len(pairs) == 0:
        return np.empty((0, 2), dtype=np.int64)
    return np.ascontiguousarray(pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))])


def close_pairs(points, tol: float, *, budget: int | None = None) -> np.ndarray:
    """All pairs ``i < j`` of rows of ``points`` with Euclidean distance ``<= tol``.

    Parameters
    ----------
    points : (n, 3) array_like of float
        The points (converted to C-ordered float64).  Every coordinate must be
        finite.
    tol : float
        Distance bound, finite and ``>= 0``; ``0`` finds exact duplicates.
    budget : int, optional
        How many candidate comparisons may fail the distance test before the
        sweep gives up and cKDTree answers instead (default ``32 * n + 1024``;
        ``0`` falls back at the first false candidate).  The answer is the
        same either way.

    Returns
    -------
    (m, 2) int64 array
        Row ``(i, j)`` with ``i < j`` per pair, rows in lexicographic order
        (by ``i``, then ``j``): the set ``cKDTree(points).query_pairs(tol,
        output_type="ndarray")`` returns, whose row order is unspecified.
        The distance test is cKDTree's: ``dx*dx + dy*dy + dz*dz <= tol*tol``
        in float64.

    Raises
    ------
    ValueError
        ``points`` is not ``(n, 3)`` or has a NaN or infinite coordinate;
        ``tol`` is negative, NaN or infinite, or so large (> 1.3e154) that
        ``tol**2`` overflows; ``budget`` is negative.
    """
    P = np.ascontiguousarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"close_pairs: points must have shape (n, 3), got {P.shape}")
    if isinstance(tol, np.ndarray) and tol.ndim == 0:
        tol = tol[()]
    if isinstance(tol, (bool, np.bool_)) or not isinstance(tol, numbers.Real):
        raise ValueError(f"close_pairs: tol must be a real number, got {tol!r}")
    tol = float(tol)
    if not np.isfinite(tol):
        raise ValueError(f"close_pairs: tol must be finite, got {tol!r}")
    if tol < 0.0:
        raise ValueError(f"close_pairs: tol must be >= 0, got {tol!r}")
    if not tol * tol < np.inf:
        raise ValueError(f"close_pairs: tol too large (tol**2 overflows float64), got {tol!r}")
    n = P.shape[0]
    if budget is None:
        budget = 32 * n + 1024
    elif int(budget) < 0:
        raise ValueError(f"close_pairs: budget must be >= 0, got {budget!r}")
    budget = int(budget)
    if n < 2:
        if n == 1 and not np.isfinite(P).all():
            raise ValueError("close_pairs: points contain a non-finite (NaN or infinite) coordinate")
        return np.empty((0, 2), dtype=np.int64)
    p = np.empty(n)
    sc = 1.0
    ok, pmin, pmax, amax = _project(P, DIRECTION, sc, p)
    if ok == 1:                          # |coordinates| near the float64 limit: scale the projections
        sc = 1.0 / 16.0
        ok, pmin, pmax, amax = _project(P, DIRECTION, sc, p)
    if ok == 0:
        bad = np.flatnonzero(~np.isfinite(P).all(axis=1))
        raise ValueError(f"close_pairs: points contain a non-finite (NaN or infinite) coordinate "
                         f"({bad.size} row(s), first row {int(bad[0])})")
    # projection window (in units scaled by sc): |u.(a-b)| <= |a-b| for a unit
    # u; each computed projection is off by at most 4 eps sum_k |(x_k - c_k)
    # u_k| <= 4 eps amax (shift, products, two sums), u's norm by 2 eps, and a
    # pair passing the final test may be (1 + 3 eps) tol apart -- 16 eps covers
    # it with room to spare.  _TINY keeps pairs whose squared distance
    # underflows, _SUB the absolute error of subnormal terms.
    ts = tol * sc
    window = ts + 16.0 * _EPS * (ts + amax) + _TINY * sc + _SUB
    order, ps = _sort_by_projection(p, pmin, pmax)
    cap = n
    while True:
        first = np.empty(cap, dtype=np.int64)
        second = np.empty(cap, dtype=np.int64)
        m, done = _sweep(P, order, ps, window, tol * tol, budget, first, second)
        if not done:
            return _kdtree_pairs(P, tol)
        if m <= cap:
            return _lexsorted(first, second, m, n)
        cap = m                          # big clusters: more pairs than points; sweep again
