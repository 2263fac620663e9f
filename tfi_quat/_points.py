"""Exact point queries: coincident pairs and bounded nearest neighbours.

* :func:`close_pairs`: all ``i < j`` with ``|P[i] - P[j]| <= tol``
  (``cKDTree.query_pairs``), by a sweep along a generic direction;
* :func:`nearest_within`: for each query point the nearest reference point
  closer than a bound (``cKDTree.query(..., distance_upper_bound=bound)``), by
  a compiled kd-tree (section *Bounded nearest neighbours* below).

Coincident pairs
----------------
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
   has points, fine buckets by insertion or heapsort) -- about half the
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

Bounded nearest neighbours
--------------------------
:func:`nearest_within` replaces ``cKDTree(ref).query(query,
distance_upper_bound=bound)`` for the Deformer's wall distances: ref = the
wall points of a wing (tens of thousands, strongly clustered at the leading
and trailing edges and at a collapsed tip edge), query = the boundary points
next to the walls (symmetry plane, wake cut, tip cap), many of them up to the
bound away from every wall point.

*Why a kd-tree and not a uniform cell hash.*  The ref points lie on a
surface and crowd at the edges, while a quarter of the queries are 0.1 to
0.6 chord from it.  On the wing below, cells of 0.005 leave 99 % of the
cells empty (still 24 points in the fullest), and a query 0.3 from the
surface must look at every cell of the ball of that radius, ~10**6 of them;
cells of 0.02 still mean ~27 000 per such query and put up to 129 points in
a cell; cells of 0.1 put up to 1 625.  A tree adapts to both.

*The tree.*  A complete binary tree over the ref points, built once per call
(a few ms for 27 k points): each node splits its points by count at the
median of the widest extent of their bounding box (quickselect, falling back
to a sort on a bad pivot sequence), down to leaves of at most about
:data:`LEAF` points; the points are stored leaf by leaf (coordinates as
three contiguous arrays) and every node keeps the *tight* bounding box of its
points.  The tree is implicit (children of node ``k`` are ``2k + 1`` and
``2k + 2``), so the only tables are the boxes, the leaf offsets and the
permutation.  Any partition gives a valid tree with tight boxes, so repeated
points, points on a plane or a line, or one point repeated ``m`` times need
no special case.

*The search*, for each query ``q``: depth first, nearer child first, a node
visited only while the squared distance from ``q`` to its box does not
exceed the best squared distance found so far (initially ``bound**2``);
the first test is the root's box, so a query far outside the ref points'
box costs one box distance.  Consecutive queries are usually close (the
points of a grid face), so each query starts with the previous query's
answer as a candidate, within chunks of :data:`CHUNK` queries.  The chunks
run on the threads (:func:`tfi_quat._jit.parallel_for`), taken in interleaved
runs of consecutive chunks so that each thread gets costly and cheap
stretches of the queries alike (:func:`_chunk_order`); fewer than
``SERIAL_BELOW / _QUERY_WORK`` queries run on one thread.  The answer does not depend on the start nor on
the order.

Small sets
----------
Below :data:`DIRECT_BELOW` point pairs both functions compute every distance
with numpy instead (the same float64 tests and the same answer): for a 2-D
grid's boundary this is faster than loading the compiled searches from
numba's cache, and a run that only meets small sets compiles none of them.

*Exactness.*  The distance test is cKDTree's: with ``dx = r_x - q_x`` etc.
in float64, a ref point is a candidate when ``dx*dx + dy*dy + dz*dz <
bound*bound`` (strictly: a point exactly at ``bound`` is not returned, as in
cKDTree, whose ``distance_upper_bound`` is squared in float64 and compared
with ``<``), and the answer is the candidate with the smallest such sum,
the smallest index among equal sums; the distance returned is its
``sqrt``.  The pruning cannot lose it: the box distance is computed with
the same operations on the box's per-axis gaps, each gap no larger than the
corresponding ``|dx|`` of any point in the box, and float64 rounding is
monotone, so the computed box distance never exceeds the computed distance
of a point inside (with any rounding, underflow or overflow); a node is
skipped only when its box distance is *larger* than the best so far, so
ties are never skipped.  cKDTree visits nodes in another order and keeps the
first of equal distances it meets, so among ties its index may differ (the
distance is the same); its node bounds are updated incrementally, so a ref
point within a few units in the last place of the bound or of another
candidate's distance may, in principle, be decided differently.

On the 2.8-scale wing (26 731 wall points, 129 973 queries, bound 0.61),
tree included, it takes ~25 ms on the 2-core machine (~34 ms on one
thread), against ~163 ms for the best cKDTree variant (``balanced_tree=False,
compact_nodes=False``; ~400 ms for the default tree), with the same
distances and indices; with all 393 228 boundary points as queries ~29 ms
against ~190 ms (``benchmarks/bench_points.py``).
"""

from __future__ import annotations

import math
import numbers

import numpy as np

from ._jit import jit, parallel_for, serial_below, task_jit, threads

__all__ = ["close_pairs", "nearest_within", "DIRECTION"]

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
#: buckets this small are sorted by insertion, larger ones by heapsort (:func:`_argsort`)
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
def _sift(key, s, idx, root, n):
    """Restore the max-heap of ``key[s + idx[:n]]`` below ``root``."""
    while True:
        c = 2 * root + 1
        if c >= n:
            return
        if c + 1 < n and key[s + idx[c]] < key[s + idx[c + 1]]:
            c += 1
        if key[s + idx[root]] < key[s + idx[c]]:
            t = idx[root]
            idx[root] = idx[c]
            idx[c] = t
            root = c
        else:
            return


@jit
def _argsort(key, s, e, idx):
    """``idx[:e - s]``: a permutation sorting ``key[s:e]`` ascending (heapsort: O(c log c)
    on any input of ``c`` finite keys; equal keys in no particular order).

    Used instead of ``np.argsort`` and slice assignments, whose compiled forms
    (quicksort, shape-mismatch messages) take seconds to compile on a first run.
    """
    n = e - s
    for t in range(n):
        idx[t] = t
    for root in range(n // 2 - 1, -1, -1):
        _sift(key, s, idx, root, n)
    for end in range(n - 1, 0, -1):
        t = idx[0]
        idx[0] = idx[end]
        idx[end] = t
        _sift(key, s, idx, 0, end)


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
    :func:`_argsort` when large (equal keys may come in any order: the pairs
    found do not depend on it).  Memory: the two output arrays and scratch the
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
    ix = np.empty(big, dtype=np.int64)
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
                        _argsort(ps, r0, r1, ix)
                        for t in range(r1 - r0):
                            tp[t] = ps[r0 + ix[t]]
                            to[t] = order[r0 + ix[t]]
                        for t in range(r1 - r0):
                            ps[r0 + t] = tp[t]
                            order[r0 + t] = to[t]
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
    ix = np.empty(0, dtype=np.int64)            # sort scratch, grown as needed
    tmp = np.empty(0, dtype=np.int64)
    for k in range(m):
        i = first[k]
        col[fill[i]] = second[k]
        fill[i] += 1
    for i in range(n):
        s = start[i]
        e = start[i + 1]
        if e - s > _SMALL:
            if ix.size < e - s:
                ix = np.empty(e - s, dtype=np.int64)
                tmp = np.empty(e - s, dtype=np.int64)
            _argsort(col, s, e, ix)
            for t in range(e - s):
                tmp[t] = col[s + ix[t]]
            for t in range(e - s):
                col[s + t] = tmp[t]
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


# ---------------------------------------------------------------- small sets
#: sets with fewer point pairs than this (``n (n - 1) / 2`` for :func:`close_pairs`,
#: ``m n`` for :func:`nearest_within`) are answered by computing every distance with
#: numpy (:func:`_direct_pairs`, :func:`_direct_nearest`), the same float64 test and
#: the same answer as the compiled searches, with nothing to compile: a 2-D grid's
#: boundary (the demo's 640 points) takes ~2 ms, where compiling the sweep and the
#: kd-tree took ~7 s and loading them from numba's cache ~0.8 s
DIRECT_BELOW = 1 << 20
#: distances computed per numpy pass of the direct answers (bounds their memory: ~4 MB)
_DIRECT_CHUNK = 1 << 16


def _direct_pairs(P: np.ndarray, tol: float) -> np.ndarray:
    """:func:`close_pairs` of a small set by all pairwise distances: rows of ``i`` against
    every ``j > i``, cKDTree's test ``dx*dx + dy*dy + dz*dz <= tol*tol`` in float64
    (``(-d)**2 == d**2`` exactly: the direction of the difference does not matter)."""
    n = P.shape[0]
    t2 = tol * tol
    step = max(1, _DIRECT_CHUNK // n)
    cols = np.arange(n)
    parts = []
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        for a in range(0, n - 1, step):
            b = min(n - 1, a + step)
            dx = P[a:b, None, 0] - P[None, :, 0]
            dy = P[a:b, None, 1] - P[None, :, 1]
            dz = P[a:b, None, 2] - P[None, :, 2]
            hit = dx * dx + dy * dy + dz * dz <= t2
            hit &= cols[None, :] > np.arange(a, b)[:, None]
            i, j = np.nonzero(hit)                   # row-major: lexicographic
            if i.size:
                parts.append(np.stack([i + a, j], axis=1))
    if not parts:
        return np.empty((0, 2), dtype=np.int64)
    return np.ascontiguousarray(np.concatenate(parts).astype(np.int64, copy=False))


def _direct_nearest(R: np.ndarray, Q: np.ndarray, bound2: float, dist: np.ndarray,
                    idx: np.ndarray) -> None:
    """:func:`nearest_within` of a small problem by all distances, into ``dist``, ``idx``:
    ``d2 = dx*dx + dy*dy + dz*dz`` (``dx = r_x - q_x``), candidates ``d2 < bound2``, the
    first of the smallest (``np.argmin``: the smallest row among equal sums)."""
    m = R.shape[0]
    step = max(1, _DIRECT_CHUNK // m)
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        for a in range(0, Q.shape[0], step):
            b = min(Q.shape[0], a + step)
            dx = R[None, :, 0] - Q[a:b, 0, None]
            dy = R[None, :, 1] - Q[a:b, 1, None]
            dz = R[None, :, 2] - Q[a:b, 2, None]
            d2 = dx * dx + dy * dy + dz * dz
            d2[~(d2 < bound2)] = np.inf
            k = np.argmin(d2, axis=1)
            best = d2[np.arange(b - a), k]
            has = best < np.inf
            dist[a:b] = np.where(has, np.sqrt(best), np.inf)
            idx[a:b] = np.where(has, k, m)


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
        same either way.  Sets of fewer than :data:`DIRECT_BELOW` pairs are
        answered by computing every distance (no sweep, no budget).

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
    if n * (n - 1) // 2 < DIRECT_BELOW:
        bad = np.flatnonzero(~np.isfinite(P).all(axis=1))
        if bad.size:
            raise ValueError(f"close_pairs: points contain a non-finite (NaN or infinite) "
                             f"coordinate ({bad.size} row(s), first row {int(bad[0])})")
        return _direct_pairs(P, tol)
    p = np.empty(n)
    sc = 1.0
    # overflow and NaN are detected by _project itself (errstate: for the uncompiled kernel)
    with np.errstate(over="ignore", invalid="ignore"):
        ok, pmin, pmax, amax = _project(P, DIRECTION, sc, p)
        if ok == 1:                      # |coordinates| near the float64 limit: scale the projections
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


# ================================================================ bounded nearest neighbours
#: target leaf size of the kd-tree: leaves hold at most about this many points
LEAF = 16
#: queries per warm-started chunk: each query of a chunk starts from the previous answer
CHUNK = 512
#: a query costs about as much as this many points of the other parallel kernels (the
#: queries run on all threads when ``_QUERY_WORK * n`` reaches ``SERIAL_BELOW``)
_QUERY_WORK = 32
#: the chunks are taken in this many runs of consecutive chunks, interleaved (:func:`_chunk_order`)
_RUNS = 16
#: stack entries for the tree search: one per level and the root (depth <= 62)
_STACK = 64


@jit(inline="always")
def _swap4(a, b, c, p, i, j):
    t = a[i]
    a[i] = a[j]
    a[j] = t
    t = b[i]
    b[i] = b[j]
    b[j] = t
    t = c[i]
    c[i] = c[j]
    c[j] = t
    u = p[i]
    p[i] = p[j]
    p[j] = u


@jit(inline="always")
def _select_rounds(c):
    """Partition rounds :func:`_select` may take on ``c`` keys before it sorts: ``2 floor(log2 c) + 8``."""
    rounds = 8
    while c > 1:
        rounds += 2
        c >>= 1
    return rounds


@jit
def _select(key, o1, o2, perm, s, e, k, rounds):
    """Reorder ``key[s:e]`` (carrying ``o1``, ``o2``, ``perm`` along) so that ``key[k]`` has rank ``k - s``.

    Afterwards ``key[s:k] <= key[k] <= key[k + 1:e]``.  Quickselect with a
    median-of-three pivot and Hoare partitioning (equal keys are split
    evenly); after ``rounds`` partitions (:func:`_select_rounds`) whatever
    range is left is sorted instead, so the cost stays ``O(c log c)`` on any
    input of ``c = e - s`` keys.
    """
    lo = s
    hi = e - 1
    while hi > lo:
        rounds -= 1
        if rounds < 0:
            c = hi + 1 - lo
            srt = np.empty(c, dtype=np.int64)
            _argsort(key, lo, hi + 1, srt)
            tmp = np.empty(c)
            for arr in (key, o1, o2):
                for t in range(c):
                    tmp[t] = arr[lo + srt[t]]
                for t in range(c):
                    arr[lo + t] = tmp[t]
            tp = np.empty(c, dtype=np.int64)
            for t in range(c):
                tp[t] = perm[lo + srt[t]]
            for t in range(c):
                perm[lo + t] = tp[t]
            return
        a = key[lo]
        b = key[(lo + hi) // 2]
        c = key[hi]
        piv = max(min(a, b), min(max(a, b), c))
        i = lo
        j = hi
        while i <= j:
            while key[i] < piv:
                i += 1
            while key[j] > piv:
                j -= 1
            if i <= j:
                _swap4(key, o1, o2, perm, i, j)
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return


@jit
def _range_box(xs, ys, zs, s, e, box, nd):
    """``box[nd] = (xlo, xhi, ylo, yhi, zlo, zhi)`` of the points ``s:e`` (empty: lo = inf, hi = -inf)."""
    x0 = np.inf
    x1 = -np.inf
    y0 = np.inf
    y1 = -np.inf
    z0 = np.inf
    z1 = -np.inf
    for t in range(s, e):
        v = xs[t]
        x0 = min(x0, v)
        x1 = max(x1, v)
        v = ys[t]
        y0 = min(y0, v)
        y1 = max(y1, v)
        v = zs[t]
        z0 = min(z0, v)
        z1 = max(z1, v)
    box[nd, 0] = x0
    box[nd, 1] = x1
    box[nd, 2] = y0
    box[nd, 3] = y1
    box[nd, 4] = z0
    box[nd, 5] = z1


@jit
def _kd_build(R, leaf):
    """The implicit kd-tree of ``R`` (m >= 1, 3): ``(box, lstart, xs, ys, zs, perm)``.

    Depth ``D`` is the smallest with ``m >> D <= leaf``; node ``k``'s children
    are ``2k + 1``, ``2k + 2``; leaf ``j`` (node ``2**D - 1 + j``) holds the
    points ``lstart[j]:lstart[j + 1]`` of ``xs, ys, zs`` (the coordinates in
    leaf order), ``perm`` maps them to rows of ``R``; ``box[k]`` is the tight
    bounding box ``(xlo, xhi, ylo, yhi, zlo, zhi)`` of node ``k``'s points.
    Each node splits its range at the middle index, after a selection along
    the widest extent of its box (none when all its points coincide).
    """
    m = R.shape[0]
    depth = 0
    while (m >> depth) > leaf:
        depth += 1
    nl = 1 << depth
    first = nl - 1
    nn = 2 * nl - 1
    box = np.empty((nn, 6))
    lstart = np.empty(nl + 1, dtype=np.int64)
    xs = np.empty(m)
    ys = np.empty(m)
    zs = np.empty(m)
    for i in range(m):
        xs[i] = R[i, 0]
        ys[i] = R[i, 1]
        zs[i] = R[i, 2]
    perm = np.empty(m, dtype=np.int64)
    for i in range(m):
        perm[i] = i
    rs = np.empty(nn, dtype=np.int64)
    re = np.empty(nn, dtype=np.int64)
    rs[0] = 0
    re[0] = m
    for nd in range(nn):
        s = rs[nd]
        e = re[nd]
        _range_box(xs, ys, zs, s, e, box, nd)
        if nd >= first:
            lstart[nd - first] = s
            continue
        mid = (s + e) // 2
        wx = box[nd, 1] - box[nd, 0]
        wy = box[nd, 3] - box[nd, 2]
        wz = box[nd, 5] - box[nd, 4]
        if e - s > 1:
            rounds = _select_rounds(e - s)
            if wx >= wy and wx >= wz:
                if wx > 0.0:
                    _select(xs, ys, zs, perm, s, e, mid, rounds)
            elif wy >= wz:
                _select(ys, xs, zs, perm, s, e, mid, rounds)
            else:
                _select(zs, xs, ys, perm, s, e, mid, rounds)
        rs[2 * nd + 1] = s
        re[2 * nd + 1] = mid
        rs[2 * nd + 2] = mid
        re[2 * nd + 2] = e
    lstart[nl] = m
    return box, lstart, xs, ys, zs, perm


@jit(inline="always")
def _box_d2(box, nd, x, y, z):
    """Squared distance from ``(x, y, z)`` to ``box[nd]``, summed as a point's ``dx*dx + dy*dy + dz*dz``."""
    gx = max(max(box[nd, 0] - x, x - box[nd, 1]), 0.0)
    gy = max(max(box[nd, 2] - y, y - box[nd, 3]), 0.0)
    gz = max(max(box[nd, 4] - z, z - box[nd, 5]), 0.0)
    return gx * gx + gy * gy + gz * gz


def _chunk_order(nch: int, runs: int = _RUNS) -> np.ndarray:
    """The order in which ``_kd_query`` takes its ``nch`` chunks: ``runs`` runs of consecutive chunks,
    the runs in the order ``r * stride % runs`` (``stride`` coprime to ``runs``, near 0.618 runs).

    Each thread's share of the chunks is a stretch of this order, so it gets
    runs from all over the queries (the costly queries tend to come together: a
    symmetry plane, a tip cap -- one half of the wing's took twice the other's
    time), while the queries of a run stay consecutive (the tree nodes they visit
    stay in cache).
    """
    k = max(1, min(nch, runs))
    stride = max(min(2, k - 1), int(0.6180339887498949 * k), 1)
    while math.gcd(stride, k) != 1:
        stride += 1
    edge = (np.arange(k + 1) * nch) // k
    return np.concatenate([np.arange(edge[r], edge[r + 1]) for r in (np.arange(k) * stride) % k])


@task_jit
def _kd_query(lo, hi, box, lstart, xs, ys, zs, perm, R, Q, bound2, chunk, order, dist, idx):
    """``dist[q], idx[q]``: nearest row of ``R`` to ``Q[q]`` with squared distance ``< bound2``,
    else ``inf, m``, for the queries of the chunks ``order[lo:hi]``.

    Ties go to the smallest row index.  The chunks of ``chunk`` queries are the
    tasks (:func:`tfi_quat._jit.parallel_for` over ``order.size``), in the order
    ``order`` (:func:`_chunk_order`); within a chunk each query first tries the
    previous one's answer.
    """
    for c in range(lo, hi):
        _kd_chunk(box, lstart, xs, ys, zs, perm, R, Q, bound2, chunk, order[c], dist, idx)


@jit
def _kd_chunk(box, lstart, xs, ys, zs, perm, R, Q, bound2, chunk, b, dist, idx):
    """Chunk ``b`` of :func:`_kd_query`."""
    n = Q.shape[0]
    m = xs.size
    nl = lstart.size - 1
    first = nl - 1
    sn = np.empty(_STACK, dtype=np.int64)
    sd = np.empty(_STACK)
    hint = -1
    for q in range(b * chunk, min(n, (b + 1) * chunk)):
        x = Q[q, 0]
        y = Q[q, 1]
        z = Q[q, 2]
        best = bound2
        bi = -1                                      # none yet: only d2 < bound2 is accepted
        if hint >= 0:
            dx = R[hint, 0] - x
            dy = R[hint, 1] - y
            dz = R[hint, 2] - z
            d2 = dx * dx + dy * dy + dz * dz
            if d2 < best:
                best = d2
                bi = hint
        sp = 0
        md = _box_d2(box, 0, x, y, z)
        if md <= best:
            sn[0] = 0
            sd[0] = md
            sp = 1
        while sp > 0:
            sp -= 1
            nd = sn[sp]
            if sd[sp] > best:
                continue
            while True:
                if nd >= first:                      # a leaf: its points
                    j0 = nd - first
                    for t in range(lstart[j0], lstart[j0 + 1]):
                        dx = xs[t] - x
                        dy = ys[t] - y
                        dz = zs[t] - z
                        d2 = dx * dx + dy * dy + dz * dz
                        if d2 <= best:
                            j = perm[t]
                            # a tie goes to the smaller row (bi = -1: none yet, so
                            # d2 == bound2 is never accepted)
                            if d2 < best or j < bi:
                                best = d2
                                bi = j
                    break
                ch = 2 * nd + 1
                m0 = _box_d2(box, ch, x, y, z)
                m1 = _box_d2(box, ch + 1, x, y, z)
                if m0 <= m1:
                    near = ch
                    far = ch + 1
                    mn = m0
                    mf = m1
                else:
                    near = ch + 1
                    far = ch
                    mn = m1
                    mf = m0
                if mf <= best:                       # later, unless best has dropped below by then
                    sn[sp] = far
                    sd[sp] = mf
                    sp += 1
                if mn <= best:
                    nd = near
                else:
                    break
        if bi >= 0:
            dist[q] = np.sqrt(best)
            idx[q] = bi
            hint = bi
        else:
            dist[q] = np.inf
            idx[q] = m


def _points_array(x, name: str) -> np.ndarray:
    P = np.ascontiguousarray(x, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"nearest_within: {name} must have shape (n, 3), got {P.shape}")
    with np.errstate(over="ignore", invalid="ignore"):
        finite = np.isfinite(np.add.reduce(P, axis=None))   # one pass, no temporary
    if not finite:                                  # a NaN or inf, or a sum that overflowed
        bad = ~np.isfinite(P).all(axis=1)
        if bad.any():
            raise ValueError(f"nearest_within: {name} contains a non-finite (NaN or infinite) "
                             f"coordinate ({int(np.count_nonzero(bad))} row(s), first row "
                             f"{int(np.argmax(bad))})")
    return P


def nearest_within(ref, query, bound) -> tuple[np.ndarray, np.ndarray]:
    """Nearest row of ``ref`` to each row of ``query``, among those closer than ``bound``.

    The answer of ``scipy.spatial.cKDTree(ref).query(query,
    distance_upper_bound=bound)``, exactly (see the module notes).

    Parameters
    ----------
    ref : (m, 3) array_like of float
        Reference points (converted to C-ordered float64), finite; ``m = 0``
        is allowed (no query has a neighbour).
    query : (n, 3) array_like of float
        Query points, finite; ``n = 0`` is allowed.
    bound : float
        ``>= 0``; ``inf`` for an unbounded query (every query gets the
        nearest ref point when ``m > 0``), ``0`` for none.

    Returns
    -------
    d : (n,) float64
        ``sqrt(dx*dx + dy*dy + dz*dz)`` (float64, ``dx = r_x - q_x``, ...) of
        the nearest ref point ``r`` whose ``dx*dx + dy*dy + dz*dz <
        bound*bound`` (strictly, in float64, as cKDTree: a point exactly at
        ``bound`` does not count), ``inf`` where there is none.
    idx : (n,) int64
        Its row in ``ref``, ``m`` where there is none.  Among ref points at
        the same (computed) distance the smallest row; cKDTree may return
        another of them.

    Raises
    ------
    ValueError
        ``ref`` or ``query`` is not ``(k, 3)`` or has a NaN or infinite
        coordinate (the message names which, and the first bad row);
        ``bound`` is not a real number, is NaN or is negative.

    Notes
    -----
    ``bound*bound`` is what is compared: a finite ``bound`` above ~1.3e154
    acts as ``inf`` and one below ~1.5e-162 as ``0``, as in cKDTree; squared
    distances that overflow (coordinates beyond ~1e154 apart) never count.
    """
    if isinstance(bound, np.ndarray) and bound.ndim == 0:
        bound = bound[()]
    if isinstance(bound, (bool, np.bool_)) or not isinstance(bound, numbers.Real):
        raise ValueError(f"nearest_within: bound must be a real number, got {bound!r}")
    bound = float(bound)
    if np.isnan(bound):
        raise ValueError("nearest_within: bound must not be NaN")
    if bound < 0.0:
        raise ValueError(f"nearest_within: bound must be >= 0, got {bound!r}")
    R = _points_array(ref, "ref")
    Q = _points_array(query, "query")
    m = R.shape[0]
    n = Q.shape[0]
    dist = np.full(n, np.inf)
    idx = np.full(n, m, dtype=np.int64)
    bound2 = bound * bound
    if m == 0 or n == 0 or not bound2 > 0.0:        # nothing can be strictly closer than 0
        return dist, idx
    # squared distances may overflow (huge coordinates; never a candidate then) or underflow:
    # silence numpy's warnings for the uncompiled kernels (TFI_QUAT_JIT=0)
    if m * n < DIRECT_BELOW:
        _direct_nearest(R, Q, bound2, dist, idx)
        return dist, idx
    with np.errstate(over="ignore", under="ignore"):
        tree = _kd_build(R, LEAF)
        with serial_below(_QUERY_WORK * n):
            runs = _RUNS if threads() > 1 else 1
            order = _chunk_order(-(-n // CHUNK), runs)
            parallel_for(_kd_query, order.size, *tree, R, Q, bound2, CHUNK, order, dist, idx)
    return dist, idx
