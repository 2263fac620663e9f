"""Grid quality: cell volumes, corner Jacobians, skewness, aspect ratio, volume
ratio to a reference grid, near-wall orthogonality, and a report of them all.

Definitions (formulas in ``docs/quality.md``).  A cell has corners
``c(a, b, c) = x[i + a, j + b, k + c]``, ``a, b, c`` in {0, 1}; its 12 edges
are the differences along i, j, k, each pointing in its index's positive
sense.

- **volume** (area in 2-D): signed.  Hexahedron: the six tetrahedra around
  the diagonal from ``c(0,0,0)`` to ``c(1,1,1)``, one per monotone path along
  the cell edges (the Kuhn triangulation: two cells split their common face
  the same way, so the cells tile the block); exact for cells with planar
  faces.  Quadrilateral: half the
  cross product of the diagonals.  Positive for right-handed (i, j, k) cells
  (counter-clockwise (i, j) in 2-D).
- **jacobian**: at each of the 8 corners (4 in 2-D) the determinant of the
  three (two) edge vectors leaving that corner along i, j, k, taken in the
  positive index sense; the cell's value is the smallest of them.
- **scaled_jacobian**: the same determinant of the *unit* edge vectors, the
  smallest over the corners; 1 for a rectangular box, <= 0 for a folded or
  collapsed corner.
- **skewness**: equiangle skewness over the 24 face-corner angles (4 in 2-D),
  ``max((θmax - 90) / 90, (90 - θmin) / 90)``, in [0, 1].
- **aspect_ratio**: longest over shortest of the 12 (4) edges; infinite when
  an edge has zero length.
- **volume_ratio**: deformed over reference volume of the same cell.
- near-wall **orthogonality**: :func:`wall_orthogonality`.

A cell is **negative** when its volume is <= 0 and **negative-Jacobian**
when any corner Jacobian is <= 0 (the stricter test: it also catches
non-convex cells and collapsed edges), both taken in the block's
handedness (the sign of its total volume, of the reference block when one is
given), so a left-handed block is valid.  It is **degenerate** when
``|volume| <= rtol * Lmax**3`` (``Lmax**2`` in 2-D), ``Lmax`` its longest
edge.

Kernels are numba functions over one block, parallel over the cell rows
(fixed j and k); the drivers take a :class:`Block` or :class:`Grid`.
:func:`quality_report` makes one pass per block that reduces every metric to
its min, max, mean and the places of the extremes without storing per-cell
fields, then revisits only the rows that hold bad cells to list them.
:func:`cell_metrics` returns the per-cell fields (for pictures and tests).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ._jit import jit, parallel_for, task_jit
from .errors import GridValueError
from .grid import Block, Grid, face_axis, face_cells, face_ijk, face_layer
from .spec import resolve_patch_specs

__all__ = ["METRICS", "cell_volumes", "cell_metrics", "cell_orthogonality", "quality_report",
           "QualityReport", "BlockQuality", "MetricStats", "WallOrthogonality",
           "volume_ratio_summary", "negative_cells", "invalid_cells", "wall_orthogonality", "orthogonality_change",
           "CellCheck", "CheckReference", "check_block", "check_reference"]

#: per-cell metrics, in the order of the kernels' output
METRICS = ("volume", "jacobian", "scaled_jacobian", "skewness", "aspect_ratio", "volume_ratio")
_NM = len(METRICS)
#: metrics whose small values are the bad ones (the others: large values)
_LOW_IS_BAD = ("volume", "jacobian", "scaled_jacobian", "volume_ratio")

# cell flags (bits) written by the field kernel
NEGATIVE = 1
NEGATIVE_JACOBIAN = 2
DEGENERATE = 4
COLLAPSED = 8

# counter columns of the stats kernel after the per-metric finite counts
_C_NEG, _C_NEGJ, _C_DEG, _C_COL = _NM, _NM + 1, _NM + 2, _NM + 3
_NCNT = _NM + 4

_HALF_PI = 0.5 * math.pi


# ------------------------------------------------------------------ per-cell kernels
@jit(inline="always")
def _tet_sum(x, i, j, k, s, di, dj, dk, qi, qj, qk, ei, ej, ek):
    """``s + d x q`` with ``d = c(d*) - c(e*)`` and ``q = c(q*) - c000`` (a term of
    :func:`_hex_volume`)."""
    dx = x[i + di, j + dj, k + dk, 0] - x[i + ei, j + ej, k + ek, 0]
    dy = x[i + di, j + dj, k + dk, 1] - x[i + ei, j + ej, k + ek, 1]
    dz = x[i + di, j + dj, k + dk, 2] - x[i + ei, j + ej, k + ek, 2]
    qx = x[i + qi, j + qj, k + qk, 0] - x[i, j, k, 0]
    qy = x[i + qi, j + qj, k + qk, 1] - x[i, j, k, 1]
    qz = x[i + qi, j + qj, k + qk, 2] - x[i, j, k, 2]
    return s[0] + (dy * qz - dz * qy), s[1] + (dz * qx - dx * qz), s[2] + (dx * qy - dy * qx)


@jit
def _hex_volume(x, i, j, k):
    """Signed volume of hexahedron (i, j, k) (:func:`_hex_volume_inline`, called: the kernels
    that use it compile faster than with it inlined)."""
    return _hex_volume_inline(x, i, j, k)


@jit(inline="always")
def _hex_volume_inline(x, i, j, k):
    """Signed volume of hexahedron (i, j, k): sum over the six monotone-path tetrahedra,
    ``a . S / 6`` with ``a = c111 - c000`` and
    ``S = (c100 - c010) x (c110 - c000) + (c010 - c001) x (c011 - c000) + (c001 - c100) x (c101 - c000)``.

    Straight-line code, inlined where a loop over cells must vectorise
    (:func:`_ratio_rows`)."""
    return _hex_volume6_inline(x, i, j, k) / 6.0


@jit(inline="always")
def _hex_volume6_inline(x, i, j, k):
    """Six times :func:`_hex_volume_inline` (``a . S``), the same operations: its sign is
    the volume's except where the volume underflows to 0 (:func:`_sign6`)."""
    s = _tet_sum(x, i, j, k, (0.0, 0.0, 0.0), 1, 0, 0, 1, 1, 0, 0, 1, 0)
    s = _tet_sum(x, i, j, k, s, 0, 1, 0, 0, 1, 1, 0, 0, 1)
    s = _tet_sum(x, i, j, k, s, 0, 0, 1, 1, 0, 1, 1, 0, 0)
    ax = x[i + 1, j + 1, k + 1, 0] - x[i, j, k, 0]
    ay = x[i + 1, j + 1, k + 1, 1] - x[i, j, k, 1]
    az = x[i + 1, j + 1, k + 1, 2] - x[i, j, k, 2]
    return ax * s[0] + ay * s[1] + az * s[2]


@jit(inline="always")
def _quad_area(x, i, j):
    """Signed area of quadrilateral (i, j): half the cross product of its diagonals."""
    d1x = x[i + 1, j + 1, 0, 0] - x[i, j, 0, 0]
    d1y = x[i + 1, j + 1, 0, 1] - x[i, j, 0, 1]
    d2x = x[i, j + 1, 0, 0] - x[i + 1, j, 0, 0]
    d2y = x[i, j + 1, 0, 1] - x[i + 1, j, 0, 1]
    return 0.5 * (d1x * d2y - d1y * d2x)


@jit
def _edge(x, i0, j0, k0, i1, j1, k1):
    """Unit vector, length and squared length of the edge from point 0 to point 1."""
    dx = x[i1, j1, k1, 0] - x[i0, j0, k0, 0]
    dy = x[i1, j1, k1, 1] - x[i0, j0, k0, 1]
    dz = x[i1, j1, k1, 2] - x[i0, j0, k0, 2]
    l2 = dx * dx + dy * dy + dz * dz
    ln = math.sqrt(l2)
    inv = 1.0 / ln if ln > 0.0 else 0.0
    return dx * inv, dy * inv, dz * inv, ln, l2


@jit
def _corner(u, v, w, fuv, fuw, fvw):
    """(scaled Jacobian, Jacobian, min cos, max cos) at a corner with edges u, v, w (from _edge)
    along i, j, k; f.. = -1 where one of the pair's edges points into the corner."""
    sj = (u[0] * (v[1] * w[2] - v[2] * w[1]) - u[1] * (v[0] * w[2] - v[2] * w[0])
          + u[2] * (v[0] * w[1] - v[1] * w[0]))
    cuv = fuv * (u[0] * v[0] + u[1] * v[1] + u[2] * v[2])
    cuw = fuw * (u[0] * w[0] + u[1] * w[1] + u[2] * w[2])
    cvw = fvw * (v[0] * w[0] + v[1] * w[1] + v[2] * w[2])
    return sj, sj * u[3] * v[3] * w[3], min(cuv, min(cuw, cvw)), max(cuv, max(cuw, cvw))


@jit
def _hex_row(x, j, k, s, rtol, xr, has_ref, rb, rf):
    """Metrics of the hexahedra of row (j, k) into ``rb`` (ni - 1, len(METRICS) + 1)
    and their flag bits into ``rf`` (ni - 1).

    ``rb[i, :len(METRICS)]`` are the metrics (volume and Jacobians multiplied
    by the orientation ``s``), ``rb[i, len(METRICS)]`` the oriented reference
    volume (0 without a reference).  Edge m of a cell with corners
    ``c(a, b, c) = x[i + a, j + b, k + c]``: i-edges ``i0..i3`` at
    ``b + 2c``, j-edges ``ja0..ja3`` at ``a + 2c``, k-edges ``ka0..ka3`` at
    ``a + 2b``; the upper (a = 1) j- and k-edges of cell i are the lower ones
    of cell i + 1.
    """
    nci = x.shape[0] - 1
    # lower (a = 0) j- and k-edges of cell 0
    ja0 = _edge(x, 0, j, k, 0, j + 1, k)
    ja2 = _edge(x, 0, j, k + 1, 0, j + 1, k + 1)
    ka0 = _edge(x, 0, j, k, 0, j, k + 1)
    ka2 = _edge(x, 0, j + 1, k, 0, j + 1, k + 1)
    for i in range(nci):
        i0 = _edge(x, i, j, k, i + 1, j, k)
        i1 = _edge(x, i, j + 1, k, i + 1, j + 1, k)
        i2 = _edge(x, i, j, k + 1, i + 1, j, k + 1)
        i3 = _edge(x, i, j + 1, k + 1, i + 1, j + 1, k + 1)
        ja1 = _edge(x, i + 1, j, k, i + 1, j + 1, k)
        ja3 = _edge(x, i + 1, j, k + 1, i + 1, j + 1, k + 1)
        ka1 = _edge(x, i + 1, j, k, i + 1, j, k + 1)
        ka3 = _edge(x, i + 1, j + 1, k, i + 1, j + 1, k + 1)
        c0 = _corner(i0, ja0, ka0, 1.0, 1.0, 1.0)
        c1 = _corner(i0, ja1, ka1, -1.0, -1.0, 1.0)
        c2 = _corner(i1, ja0, ka2, -1.0, 1.0, -1.0)
        c3 = _corner(i1, ja1, ka3, 1.0, -1.0, -1.0)
        c4 = _corner(i2, ja2, ka0, 1.0, -1.0, -1.0)
        c5 = _corner(i2, ja3, ka1, -1.0, 1.0, -1.0)
        c6 = _corner(i3, ja2, ka2, -1.0, -1.0, 1.0)
        c7 = _corner(i3, ja3, ka3, 1.0, 1.0, 1.0)
        sj = min(min(min(c0[0], c1[0]), min(c2[0], c3[0])), min(min(c4[0], c5[0]), min(c6[0], c7[0])))
        sjx = max(max(max(c0[0], c1[0]), max(c2[0], c3[0])), max(max(c4[0], c5[0]), max(c6[0], c7[0])))
        jmn = min(min(min(c0[1], c1[1]), min(c2[1], c3[1])), min(min(c4[1], c5[1]), min(c6[1], c7[1])))
        jmx = max(max(max(c0[1], c1[1]), max(c2[1], c3[1])), max(max(c4[1], c5[1]), max(c6[1], c7[1])))
        cmin = min(min(min(c0[2], c1[2]), min(c2[2], c3[2])), min(min(c4[2], c5[2]), min(c6[2], c7[2])))
        cmax = max(max(max(c0[3], c1[3]), max(c2[3], c3[3])), max(max(c4[3], c5[3]), max(c6[3], c7[3])))
        lmin = min(min(min(i0[3], i1[3]), min(i2[3], i3[3])),
                   min(min(min(ja0[3], ja1[3]), min(ja2[3], ja3[3])), min(min(ka0[3], ka1[3]), min(ka2[3], ka3[3]))))
        lmax = max(max(max(i0[3], i1[3]), max(i2[3], i3[3])),
                   max(max(max(ja0[3], ja1[3]), max(ja2[3], ja3[3])), max(max(ka0[3], ka1[3]), max(ka2[3], ka3[3]))))
        vol = s * _hex_volume(x, i, j, k)
        if s < 0.0:
            sj = -sjx
            jmn = -jmx
        rb[i, 0] = vol
        rb[i, 1] = jmn
        rb[i, 2] = sj
        # (θmax - 90) / 90 = asin(-cos θmax) / (π/2), (90 - θmin) / 90 = asin(cos θmin) / (π/2)
        sk = max(-cmin, cmax)
        rb[i, 3] = math.asin(min(1.0, sk)) / _HALF_PI if sk > 0.0 else 0.0
        rb[i, 4] = lmax / lmin if lmin > 0.0 else np.inf
        if has_ref:
            vr = s * _hex_volume(xr, i, j, k)
            rb[i, 5] = vol / vr if vr != 0.0 else np.nan
            rb[i, 6] = vr
        else:
            rb[i, 5] = np.nan
            rb[i, 6] = 0.0
        f = 0
        if vol <= 0.0:
            f |= 1
        if jmn <= 0.0:
            f |= 2
        if abs(vol) <= rtol * lmax * lmax * lmax:
            f |= 4
        if lmin == 0.0:
            f |= 8
        rf[i] = f
        ja0 = ja1
        ja2 = ja3
        ka0 = ka1
        ka2 = ka3


@jit
def _edge2(x, i0, j0, i1, j1):
    """2-D :func:`_edge`: unit vector (x, y) and length."""
    dx = x[i1, j1, 0, 0] - x[i0, j0, 0, 0]
    dy = x[i1, j1, 0, 1] - x[i0, j0, 0, 1]
    ln = math.sqrt(dx * dx + dy * dy)
    inv = 1.0 / ln if ln > 0.0 else 0.0
    return dx * inv, dy * inv, ln


@jit
def _corner2(u, v, fuv):
    """(scaled Jacobian, Jacobian, cos) at a quadrilateral corner with edges u (i), v (j)."""
    sj = u[0] * v[1] - u[1] * v[0]
    return sj, sj * u[2] * v[2], fuv * (u[0] * v[0] + u[1] * v[1])


@jit
def _quad_row(x, j, s, rtol, xr, has_ref, rb, rf):
    """2-D :func:`_hex_row`: the quadrilaterals of row j; corner (a, b) has the
    i-edge at ``b`` and the j-edge at ``a``."""
    nci = x.shape[0] - 1
    ja0 = _edge2(x, 0, j, 0, j + 1)
    for i in range(nci):
        i0 = _edge2(x, i, j, i + 1, j)
        i1 = _edge2(x, i, j + 1, i + 1, j + 1)
        ja1 = _edge2(x, i + 1, j, i + 1, j + 1)
        c0 = _corner2(i0, ja0, 1.0)
        c1 = _corner2(i0, ja1, -1.0)
        c2 = _corner2(i1, ja0, -1.0)
        c3 = _corner2(i1, ja1, 1.0)
        if s < 0.0:
            sj = -max(max(c0[0], c1[0]), max(c2[0], c3[0]))
            jmn = -max(max(c0[1], c1[1]), max(c2[1], c3[1]))
        else:
            sj = min(min(c0[0], c1[0]), min(c2[0], c3[0]))
            jmn = min(min(c0[1], c1[1]), min(c2[1], c3[1]))
        cmin = min(min(c0[2], c1[2]), min(c2[2], c3[2]))
        cmax = max(max(c0[2], c1[2]), max(c2[2], c3[2]))
        lmin = min(min(i0[2], i1[2]), min(ja0[2], ja1[2]))
        lmax = max(max(i0[2], i1[2]), max(ja0[2], ja1[2]))
        vol = s * _quad_area(x, i, j)
        rb[i, 0] = vol
        rb[i, 1] = jmn
        rb[i, 2] = sj
        # (θmax - 90) / 90 = asin(-cos θmax) / (π/2), (90 - θmin) / 90 = asin(cos θmin) / (π/2)
        sk = max(-cmin, cmax)
        rb[i, 3] = math.asin(min(1.0, sk)) / _HALF_PI if sk > 0.0 else 0.0
        rb[i, 4] = lmax / lmin if lmin > 0.0 else np.inf
        if has_ref:
            vr = s * _quad_area(xr, i, j)
            rb[i, 5] = vol / vr if vr != 0.0 else np.nan
            rb[i, 6] = vr
        else:
            rb[i, 5] = np.nan
            rb[i, 6] = 0.0
        f = 0
        if vol <= 0.0:
            f |= 1
        if jmn <= 0.0:
            f |= 2
        if abs(vol) <= rtol * lmax * lmax:
            f |= 4
        if lmin == 0.0:
            f |= 8
        rf[i] = f
        ja0 = ja1


@jit
def _row(x, xr, has_ref, ndim, r, s, rtol, rb, rf):
    """Row r (``j + (nj - 1) * k``) of a block's cells into ``rb``, ``rf``."""
    ncj = x.shape[1] - 1
    if ndim == 3:
        _hex_row(x, r % ncj, r // ncj, s, rtol, xr, has_ref, rb, rf)
    else:
        _quad_row(x, r, s, rtol, xr, has_ref, rb, rf)


@task_jit
def _hex_volumes(lo, hi, x, out):
    """Hexahedron volumes of the cell planes ``lo <= k < hi`` into ``out``."""
    ni, nj = x.shape[0], x.shape[1]
    for k in range(lo, hi):
        for j in range(nj - 1):
            for i in range(ni - 1):
                out[i, j, k] = _hex_volume(x, i, j, k)


@task_jit
def _quad_areas(lo, hi, x, out):
    """Quadrilateral areas of the cell rows ``lo <= j < hi`` into ``out``."""
    ni = x.shape[0]
    for j in range(lo, hi):
        for i in range(ni - 1):
            out[i, j, 0] = _quad_area(x, i, j)


@task_jit
def _ratio_rows(lo_k, hi_k, x, xr, hexa, neg, low, first):
    """Cell-volume ratios ``x`` / ``xr`` of one block reduced over each row of cells (fixed j, k),
    without storing them: row ``r = j + (nj - 1) k`` writes ``neg[r]`` (ratios <= 0),
    ``low[r]`` (the smallest ratio, or the first NaN) and ``first[r]`` (its first i; -1 when
    every ratio of the row is infinite).  A ratio is ``v / vr`` (volumes, areas in 2-D), infinite
    where ``vr == 0``, as :func:`volume_ratio_summary` defines it.  Task: the cell planes
    ``lo_k <= k < hi_k``.  ``hexa`` True: 3-D cells, None: 2-D (the other's code is pruned
    before typing, so a 2-D run compiles no hexahedron volumes)."""
    nci = x.shape[0] - 1
    ncj = x.shape[1] - 1
    for k in range(lo_k, hi_k):
        q = np.empty(nci)
        for j in range(ncj):
            if hexa is not None:
                for i in range(nci):
                    vr = _hex_volume_inline(xr, i, j, k)
                    q[i] = _hex_volume_inline(x, i, j, k) / vr if vr != 0.0 else np.inf
            else:
                for i in range(nci):
                    vr = _quad_area(xr, i, j)
                    q[i] = _quad_area(x, i, j) / vr if vr != 0.0 else np.inf
            r = j + ncj * k
            n = 0
            lo = np.inf
            at = -1
            for i in range(nci):
                if q[i] <= 0.0:
                    n += 1
                if lo == lo and (q[i] != q[i] or q[i] < lo):      # the first NaN stays
                    lo = q[i]
                    at = i
            neg[r] = n
            low[r] = lo
            first[r] = at


@task_jit
def _block_stats(lo, hi, x, xr, has_ref, ndim, s, rtol, vmin, vmax, tot, arg, cnt, refsum):
    """Reduce every metric of one block over each of the rows of cells ``lo <= r < hi``
    (fixed j, k).

    Row ``r = j + (nj - 1) * k`` writes ``vmin[r, m]``, ``vmax[r, m]``, ``tot[r, m]``
    (min, max and sum of metric m over its finite values), ``arg[r, m, 0/1]``
    (flat cell index ``i + (ni - 1) * r`` of the min / max), ``cnt[r, :]``
    (finite values per metric, then negative, negative-Jacobian, degenerate
    and collapsed cells) and ``refsum[r]`` (sum of the oriented reference volumes).
    """
    nci = x.shape[0] - 1
    nm = vmin.shape[1]
    for r in range(lo, hi):
        rb = np.empty((nci, nm + 1))
        rf = np.empty(nci, dtype=np.uint8)
        _row(x, xr, has_ref, ndim, r, s, rtol, rb, rf)
        for m in range(nm):
            vlo = np.inf
            vhi = -np.inf
            ilo = 0
            ihi = 0
            t = 0.0
            n = 0
            for i in range(nci):
                val = rb[i, m]
                if math.isfinite(val):
                    t += val
                    n += 1
                    if val < vlo:
                        vlo = val
                        ilo = i
                    if val > vhi:
                        vhi = val
                        ihi = i
            vmin[r, m] = vlo
            vmax[r, m] = vhi
            tot[r, m] = t
            cnt[r, m] = n
            arg[r, m, 0] = ilo + nci * r
            arg[r, m, 1] = ihi + nci * r
        c1 = 0
        c2 = 0
        c4 = 0
        c8 = 0
        rs = 0.0
        for i in range(nci):
            f = rf[i]
            c1 += f & 1
            c2 += (f >> 1) & 1
            c4 += (f >> 2) & 1
            c8 += (f >> 3) & 1
            rs += rb[i, nm]
        cnt[r, nm] = c1
        cnt[r, nm + 1] = c2
        cnt[r, nm + 2] = c4
        cnt[r, nm + 3] = c8
        refsum[r] = rs


@task_jit
def _block_fields(lo, hi, x, xr, has_ref, ndim, s, rtol, rows, out, flags):
    """Per-cell metrics of the cell rows ``rows[lo:hi]`` of one block.

    ``out`` float64 (ni - 1, len(rows), len(METRICS)), ``flags`` uint8
    (ni - 1, len(rows)): NEGATIVE | NEGATIVE_JACOBIAN | DEGENERATE | COLLAPSED.
    """
    nci = x.shape[0] - 1
    nm = out.shape[2]
    for q in range(lo, hi):
        rb = np.empty((nci, nm + 1))
        rf = np.empty(nci, dtype=np.uint8)
        _row(x, xr, has_ref, ndim, rows[q], s, rtol, rb, rf)
        for i in range(nci):
            flags[i, q] = rf[i]
            for m in range(nm):
                out[i, q, m] = rb[i, m]


@task_jit
def _invalid_rows(lo, hi, x, ndim, corner_tol, count, first):
    """The invalid cells of the rows of cells ``lo <= r < hi`` (``r = j + (nj - 1) k``) of
    one block: ``count[r]`` of them, the first at ``i = first[r]`` (-1: none).

    A cell is invalid unless its volume (area) is positive and its smallest
    scaled corner Jacobian is above ``-corner_tol``, both as right-handed
    (orientation +1; the per-cell metrics of :func:`_row`).  No temporaries the
    size of the block.
    """
    nci = x.shape[0] - 1
    rb = np.empty((max(nci, 0), _NM + 1))
    rf = np.empty(max(nci, 0), dtype=np.uint8)
    for r in range(lo, hi):
        _row(x, x, False, ndim, r, 1.0, 0.0, rb, rf)
        n = 0
        f = -1
        for i in range(nci):
            if not (rb[i, 0] > 0.0 and rb[i, 2] > -corner_tol):
                n += 1
                if f < 0:
                    f = i
        count[r] = n
        first[r] = f


def _invalid_cells(x, ndim: int, corner_tol: float) -> tuple:
    """Count the invalid cells of one block (:func:`_invalid_rows`, rows of cells on the
    threads) and find the first in C order of ``(i, j, k)``: ``(count, i, j, k)``,
    ``(0, -1, -1, -1)`` when every cell is valid."""
    ncj = x.shape[1] - 1
    nck = x.shape[2] - 1 if ndim == 3 else 1
    nrows = max(ncj, 0) * max(nck, 0)
    count = np.zeros(nrows, np.int64)
    first = np.full(nrows, -1, np.int64)
    parallel_for(_invalid_rows, nrows, x, ndim, float(corner_tol), count, first)
    rows = np.flatnonzero(first >= 0)
    if rows.size == 0:
        return int(count.sum()), -1, -1, -1
    key = (first[rows] * ncj + rows % ncj) * nck + rows // ncj      # C order of (i, j, k)
    best = int(key.min())
    return int(count.sum()), best // (ncj * nck), (best // nck) % ncj, best % nck


@jit(inline="always")
def _nan_min(a, b):
    """The smaller of a and b; NaN if a is NaN (a select, so loops stay vectorisable)."""
    return a if (a < b or a != a) else b


@jit(inline="always")
def _corner_ratio2(x, xr, i, j, a, b):
    """Corner Jacobian of corner (a, b) of quadrilateral (i, j) (the edges leaving it along +i,
    +j) over the reference's; inf where the reference's is 0."""
    ux = xr[i + 1, j + b, 0, 0] - xr[i, j + b, 0, 0]
    uy = xr[i + 1, j + b, 0, 1] - xr[i, j + b, 0, 1]
    vx = xr[i + a, j + 1, 0, 0] - xr[i + a, j, 0, 0]
    vy = xr[i + a, j + 1, 0, 1] - xr[i + a, j, 0, 1]
    jr = ux * vy - uy * vx
    ux = x[i + 1, j + b, 0, 0] - x[i, j + b, 0, 0]
    uy = x[i + 1, j + b, 0, 1] - x[i, j + b, 0, 1]
    vx = x[i + a, j + 1, 0, 0] - x[i + a, j, 0, 0]
    vy = x[i + a, j + 1, 0, 1] - x[i + a, j, 0, 1]
    return (ux * vy - uy * vx) / jr if jr != 0.0 else np.inf


#: ``v / 6.0 > 0`` exactly when ``v > _TINY6`` (and ``< 0`` when ``v < -_TINY6``): below three
#: times the smallest subnormal, ``v / 6`` rounds to zero.  The check compares the volumes of
#: :func:`_hex_volume6_inline` with it, the signs :func:`cell_volumes` gives without a division.
_TINY6 = 3.0 * 2.0 ** -1074


@jit(inline="always")
def _node_cross(x, i, j, k, X, ii):
    """The four crosses of node line ``i`` into ``X[:, ii]`` (:func:`_node_crosses`)."""
    j1 = j + np.uint64(1)
    k1 = k + np.uint64(1)
    # j-edges at k (c = 0) and k + 1 (c = 1), k-edges at j (b = 0) and j + 1 (b = 1)
    p0 = x[i, j1, k, 0] - x[i, j, k, 0]
    p1 = x[i, j1, k, 1] - x[i, j, k, 1]
    p2 = x[i, j1, k, 2] - x[i, j, k, 2]
    q0 = x[i, j1, k1, 0] - x[i, j, k1, 0]
    q1 = x[i, j1, k1, 1] - x[i, j, k1, 1]
    q2 = x[i, j1, k1, 2] - x[i, j, k1, 2]
    u0 = x[i, j, k1, 0] - x[i, j, k, 0]
    u1 = x[i, j, k1, 1] - x[i, j, k, 1]
    u2 = x[i, j, k1, 2] - x[i, j, k, 2]
    w0 = x[i, j1, k1, 0] - x[i, j1, k, 0]
    w1 = x[i, j1, k1, 1] - x[i, j1, k, 1]
    w2 = x[i, j1, k1, 2] - x[i, j1, k, 2]
    X[0, ii] = p1 * u2 - p2 * u1             # (b, c) = (0, 0)
    X[1, ii] = p0 * u2 - p2 * u0
    X[2, ii] = p0 * u1 - p1 * u0
    X[3, ii] = p1 * w2 - p2 * w1             # (1, 0)
    X[4, ii] = p0 * w2 - p2 * w0
    X[5, ii] = p0 * w1 - p1 * w0
    X[6, ii] = q1 * u2 - q2 * u1             # (0, 1)
    X[7, ii] = q0 * u2 - q2 * u0
    X[8, ii] = q0 * u1 - q1 * u0
    X[9, ii] = q1 * w2 - q2 * w1             # (1, 1)
    X[10, ii] = q0 * w2 - q2 * w0
    X[11, ii] = q0 * w1 - q1 * w0


@task_jit
def _node_crosses(x, j, k, X):
    """Pass 1 of a row of cells (j, k) in :func:`_step_check` (3-D): at each node line ``i`` of
    the row's four lines of nodes (``j..j+1``, ``k..k+1``), the cross products ``J_c x K_b`` of
    the j-edges ``J_c = x[i, j+1, k+c] - x[i, j, k+c]`` and the k-edges
    ``K_b = x[i, j+b, k+1] - x[i, j+b, k]`` into ``X[3 (b + 2 c) + m, i]`` (component m, the
    middle one negated as a determinant expands it).  The corner
    ``c(a, b, c)`` of cell i has its j- and k-edges on node line ``i + a``, so the corner
    Jacobian is the cell's i-edge at ``(b, c)`` dotted with this cross on line ``i + a``: the
    8 corners of a cell need 4 new crosses, not 8 determinants (unsigned indices, compiled with
    no aliasing: a loop that vectorises; one array per call, which vectorises better than
    both in one loop)."""
    for ii in range(X.shape[1]):
        _node_cross(x, np.uint64(ii), j, k, X, ii)


@jit(inline="always")
def _dot_cross(u0, u1, u2, X, q, i):
    """``u . (J x K)`` with the cross of :func:`_node_crosses` at ``X[q:q+3, i]``: the
    determinant ``u0 (J1 K2 - J2 K1) - u1 (J0 K2 - J2 K0) + u2 (J0 K1 - J1 K0)``."""
    return u0 * X[q, i] - u1 * X[q + 1, i] + u2 * X[q + 2, i]


@jit(inline="always")
def _ratio_of(jd, jr):
    return jd / jr if jr != 0.0 else np.inf


@jit(inline="always")
def _cell_ratio(x, xr, i, j, k, Xd, Xr):
    """The smallest corner-Jacobian ratio of hexahedron (i, j, k) to the reference's, NaN first
    (corners whose reference Jacobian is 0 count as inf), from the crosses of
    :func:`_node_crosses` of ``x`` (``Xd``) and ``xr`` (``Xr``); corners in the order
    ``(b, c)`` = (0, 0), (1, 0), (0, 1), (1, 1), ``a`` = 1 then 0 (which zero of +-0 is
    the minimum depends on it)."""
    i1 = i + np.uint64(1)
    m = 0.0
    for bc in range(4):
        jb = j + np.uint64(bc & 1)
        kc = k + np.uint64(bc >> 1)
        q = 3 * bc
        d0 = x[i1, jb, kc, 0] - x[i, jb, kc, 0]
        d1 = x[i1, jb, kc, 1] - x[i, jb, kc, 1]
        d2 = x[i1, jb, kc, 2] - x[i, jb, kc, 2]
        r0 = xr[i1, jb, kc, 0] - xr[i, jb, kc, 0]
        r1 = xr[i1, jb, kc, 1] - xr[i, jb, kc, 1]
        r2 = xr[i1, jb, kc, 2] - xr[i, jb, kc, 2]
        p = _nan_min(_ratio_of(_dot_cross(d0, d1, d2, Xd, q, i1), _dot_cross(r0, r1, r2, Xr, q, i1)),
                     _ratio_of(_dot_cross(d0, d1, d2, Xd, q, i), _dot_cross(r0, r1, r2, Xr, q, i)))
        m = p if bc == 0 else _nan_min(p, m)
    return m


@jit(inline="always")
def _wrong_sign6(vd, vr):
    """True when the volume ``vd / 6`` has not the sign of ``vr / 6`` (False when that is 0)."""
    return (vr > _TINY6 and not vd > _TINY6) or (vr < -_TINY6 and not vd < -_TINY6)


@jit(inline="always")
def _cell_check(x, xr, i, j, k, Xd, Xr, vr, below, rat, bad):
    """Cell i of :func:`_cell_checks` with the reference volume (times 6) ``vr``: ``rat[i]``,
    ``bad[i]`` and the cell's share of the counts."""
    m = _cell_ratio(x, xr, i, j, k, Xd, Xr)
    w = _wrong_sign6(_hex_volume6_inline(x, i, j, k), vr)
    nj = not m > 0.0
    rat[i] = m
    bad[i] = (1 if w else 0) + (2 if nj else 0)
    return 1 if w else 0, 1 if nj else 0, 1 if m != m else 0, 0 if m >= below else 1


@task_jit
def _cell_checks(x, xr, j, k, Xd, Xr, ref_sign, below, rat, bad):
    """Pass 2 of a row of cells (j, k) in :func:`_step_check` (3-D): per cell i, ``rat[i]``
    (:func:`_cell_ratio`) and ``bad[i]``: 1 if the cell is negative (its volume has not the sign
    of the reference cell's), 2 if negative-Jacobian (``rat[i]`` not > 0), or both.  Returns the
    counts ``(negative, negative-Jacobian, NaN ratios, ratios not >= below)``.

    ``ref_sign``: +1 (-1) when every reference cell's volume is known to be positive (negative,
    :class:`CheckReference`), which spares computing them; 0: computed cell by cell.  Unsigned
    indices, no branches in the loops, compiled with no aliasing: loops that vectorise."""
    nneg = 0
    nnj = 0
    nnan = 0
    nlow = 0
    if ref_sign == 0:
        for ii in range(rat.shape[0]):
            i = np.uint64(ii)
            c = _cell_check(x, xr, i, j, k, Xd, Xr, _hex_volume6_inline(xr, i, j, k), below, rat, bad)
            nneg += c[0]
            nnj += c[1]
            nnan += c[2]
            nlow += c[3]
    else:
        vr = _TINY6 * 2.0 * ref_sign
        for ii in range(rat.shape[0]):
            c = _cell_check(x, xr, np.uint64(ii), j, k, Xd, Xr, vr, below, rat, bad)
            nneg += c[0]
            nnj += c[1]
            nnan += c[2]
            nlow += c[3]
    return nneg, nnj, nnan, nlow


@jit
def _quad_ratios(x, xr, j, rat, bad):
    """2-D: per quadrilateral (i, j) of a row its smallest corner ratio and the ``bad`` flags of
    :func:`_cell_checks` (unsigned indices, a loop that vectorises)."""
    for ii in range(rat.shape[0]):
        i = np.uint64(ii)
        r = _corner_ratio2(x, xr, i, j, 0, 0)
        r = _nan_min(_corner_ratio2(x, xr, i, j, 1, 0), r)
        r = _nan_min(_corner_ratio2(x, xr, i, j, 0, 1), r)
        r = _nan_min(_corner_ratio2(x, xr, i, j, 1, 1), r)
        rat[ii] = r
        vd = _quad_area(x, i, j)
        vr = _quad_area(xr, i, j)
        w = (vr > 0.0 and not vd > 0.0) or (vr < 0.0 and not vd < 0.0)
        bad[ii] = (1 if w else 0) + (0 if r > 0.0 else 2)


@jit
def _ratio_row(x, xr, ndim, j, k, ref_sign, below, rat, bad, Xd, Xr, res):
    """Row (j, k) of :func:`_step_check` into ``res`` (6,): ``(smallest ratio (NaN first), its i,
    negative cells, negative-Jacobian cells, first bad i or -1, NaN cells)``; a row whose
    ratios are all ``>= below`` (the smallest of the task's earlier rows: this row cannot hold
    the block's first smallest) gets ``(inf, -1)`` for the first two, unless it has a NaN."""
    nci = x.shape[0] - 1
    # unsigned indices: numba then emits no negative-index wrap-around, and the loops vectorise
    j = np.uint64(j)
    k = np.uint64(k)
    if ndim == 3:
        _node_crosses(x, j, k, Xd)
        _node_crosses(xr, j, k, Xr)
        nneg, nnj, nnan, nlow = _cell_checks(x, xr, j, k, Xd, Xr, ref_sign, below, rat, bad)
    else:
        _quad_ratios(x, xr, j, rat, bad)
        nneg = 0
        nnj = 0
        nnan = 0
        for i in range(nci):
            nneg += bad[i] & 1
            nnj += bad[i] >> 1
            nnan += 1 if rat[i] != rat[i] else 0
        nlow = nci
    first = -1
    if nneg + nnj > 0:
        for i in range(nci):
            if bad[i] != 0:
                first = i
                break
    best = np.inf
    at = -1
    if nnan > 0:
        for i in range(nci):
            if rat[i] != rat[i]:
                best = rat[i]
                at = i
                break
    elif nlow > 0:
        for i in range(nci):
            if rat[i] < best:
                best = rat[i]
                at = i
    res[0] = best
    res[1] = at
    res[2] = nneg
    res[3] = nnj
    res[4] = first
    res[5] = nnan


@task_jit
def _step_check(lo, hi, x, xr, ndim, ref_sign, res):
    """Per row of cells ``r = j + (nj - 1) k``, ``res[r]`` (6,): the smallest corner-Jacobian
    ratio to ``xr`` and its i, the negative and negative-Jacobian cells, the first bad i
    (-1: none), the cells whose ratio is NaN (:func:`_ratio_row`; a row that cannot hold the
    smallest ratio, because an earlier row of the task has one at most as small, reports
    ``(inf, -1)`` as its smallest, so that the first smallest over the rows is the block's
    whatever the split into tasks).  Rows in parallel, scratch of a few rows per task.
    Task: the rows ``lo <= r < hi``."""
    ncj = x.shape[1] - 1
    nci = x.shape[0] - 1
    Xd = np.empty((12, x.shape[0]))
    Xr = np.empty((12, x.shape[0]))
    rat = np.empty(nci)
    bad = np.empty(nci, dtype=np.int64)
    below = np.inf
    for r in range(lo, hi):
        _ratio_row(x, xr, ndim, r % ncj, r // ncj, ref_sign, below, rat, bad, Xd, Xr, res[r])
        if res[r, 0] < below:
            below = res[r, 0]


@task_jit
def _volume_sign_counts(lo, hi, x, out):
    """Cells of the planes ``lo <= k < hi`` whose volume is positive (``out[k, 0]``) and
    negative (``out[k, 1]``) as :func:`cell_volumes` computes it (3-D)."""
    for k in range(lo, hi):
        npos = 0
        nneg = 0
        for j in range(x.shape[1] - 1):
            for i in range(x.shape[0] - 1):
                v = _hex_volume6_inline(x, i, j, k)
                npos += 1 if v > _TINY6 else 0
                nneg += 1 if v < -_TINY6 else 0
        out[k, 0] = npos
        out[k, 1] = nneg


# ------------------------------------------------------------------ per-cell drivers
def _xyz(block, what: str = "block") -> np.ndarray:
    xyz = block.xyz if isinstance(block, Block) else np.asarray(block, dtype=np.float64)
    if xyz.ndim != 4 or xyz.shape[-1] != 3:
        raise GridValueError(f"{what}: expected coordinates of shape (ni, nj, nk, 3), got {xyz.shape}")
    return np.asfortranarray(xyz, dtype=np.float64)


def _ndim(xyz: np.ndarray, ndim) -> int:
    if ndim is None:
        return 2 if xyz.shape[2] == 1 else 3
    if ndim not in (2, 3):
        raise GridValueError(f"ndim must be 2 or 3, got {ndim!r}")
    if ndim == 2 and xyz.shape[2] != 1:
        raise GridValueError(f"a 2-D block needs nk == 1, got nk = {xyz.shape[2]}")
    return int(ndim)


def _cell_shape(dims, ndim: int) -> tuple[int, int, int]:
    ni, nj, nk = dims
    return max(ni - 1, 0), max(nj - 1, 0), (max(nk - 1, 0) if ndim == 3 else 1)


def cell_volumes(block: Block | np.ndarray, ndim: int | None = None) -> np.ndarray:
    """Signed cell volumes (3-D) or areas (2-D) of one block.

    Parameters
    ----------
    block : Block or ndarray (ni, nj, nk, 3)
    ndim : {2, 3}, optional
        Default: 2 when ``nk == 1``, else 3.

    Returns
    -------
    ndarray, float64, shape (ni-1, nj-1, nk-1) in 3-D or (ni-1, nj-1, 1) in 2-D
        Positive for right-handed (counter-clockwise in 2-D) cells.
    """
    xyz = _xyz(block)
    ndim = _ndim(xyz, ndim)
    out = np.empty(_cell_shape(xyz.shape[:3], ndim), order="F")
    if out.size:
        if ndim == 2:
            parallel_for(_quad_areas, xyz.shape[1] - 1, xyz, out)
        else:
            parallel_for(_hex_volumes, xyz.shape[2] - 1, xyz, out)
    return out


def _check_ref(xyz: np.ndarray, ref, where: str) -> np.ndarray:
    xr = _xyz(ref, f"{where} reference")
    if xr.shape != xyz.shape:
        raise GridValueError(f"{where}: reference has dimensions {xr.shape[:3]}, the grid {xyz.shape[:3]}")
    return xr


def _fields(xyz, xr, ndim, s, rtol, rows):
    """Kernel call: per-cell metrics (nci, len(rows), NM) and flags of the given rows."""
    nci = xyz.shape[0] - 1
    out = np.empty((nci, rows.size, _NM), order="F")
    flags = np.empty((nci, rows.size), dtype=np.uint8, order="F")
    if out.size:
        parallel_for(_block_fields, rows.size, xyz, xr if xr is not None else xyz, xr is not None,
                     ndim, float(s), float(rtol), rows, out, flags)
    return out, flags


def cell_metrics(block: Block | np.ndarray, ndim: int | None = None, ref: Block | np.ndarray | None = None,
                 rtol: float = 1e-12) -> dict:
    """Every per-cell metric of one block (definitions in the module docstring).

    Parameters
    ----------
    block : Block or ndarray (ni, nj, nk, 3)
    ndim : {2, 3}, optional
        Default: 2 when ``nk == 1``, else 3.
    ref : Block or ndarray (ni, nj, nk, 3), optional
        The same block before deformation, for ``volume_ratio``.
    rtol : float
        Degenerate-cell tolerance: ``|volume| <= rtol * Lmax**3`` (``**2`` in 2-D).

    Returns
    -------
    dict of ndarray, float64, shape (ni-1, nj-1, nk-1) (2-D: (ni-1, nj-1, 1))
        ``volume``, ``jacobian``, ``scaled_jacobian``, ``skewness``,
        ``aspect_ratio``, ``volume_ratio`` (NaN without ``ref`` or where the
        reference volume is 0), signed as the cells are in the file (no
        handedness correction), and ``flags`` (uint8, bits
        :data:`NEGATIVE` (volume <= 0), :data:`NEGATIVE_JACOBIAN`,
        :data:`DEGENERATE`, :data:`COLLAPSED` (a zero-length edge)).
    """
    xyz = _xyz(block)
    ndim = _ndim(xyz, ndim)
    xr = None if ref is None else _check_ref(xyz, ref, "block")
    shape = _cell_shape(xyz.shape[:3], ndim)
    nrows = shape[1] * shape[2]
    vals, flags = _fields(xyz, xr, ndim, 1.0, rtol, np.arange(nrows, dtype=np.int64))
    out = {name: vals[:, :, m].reshape(shape, order="F") for m, name in enumerate(METRICS)}
    out["flags"] = flags.reshape(shape, order="F")
    return out


# ------------------------------------------------------------------ the report
def _f(v) -> float | None:
    """A JSON number: None for NaN and infinities."""
    v = float(v)
    return v if math.isfinite(v) else None


def _loc(t, base: int):
    return None if t is None else [int(t[0]) + base] + [int(c) + base for c in t[1:]]


@dataclass(frozen=True)
class MetricStats:
    """Min, max and mean of one metric over the cells where it is finite.

    Attributes
    ----------
    min, max, mean : float
        NaN when no cell has a finite value.
    count : int
        Cells with a finite value (aspect ratio: not those with a zero-length
        edge; volume ratio: not those with a zero reference volume).
    argmin, argmax : (block, i, j, k) or None
        0-based cell of the extreme values.
    """

    min: float
    max: float
    mean: float
    count: int
    argmin: tuple | None = None
    argmax: tuple | None = None

    def to_dict(self, base: int = 0) -> dict:
        return {"min": _f(self.min), "max": _f(self.max), "mean": _f(self.mean), "count": int(self.count),
                "argmin": _loc(self.argmin, base), "argmax": _loc(self.argmax, base)}


_EMPTY = MetricStats(math.nan, math.nan, math.nan, 0)


def _merge(parts: list[MetricStats]) -> MetricStats:
    parts = [p for p in parts if p.count]
    if not parts:
        return _EMPTY
    n = sum(p.count for p in parts)
    lo = min(parts, key=lambda p: p.min)
    hi = max(parts, key=lambda p: p.max)
    return MetricStats(lo.min, hi.max, sum(p.mean * p.count for p in parts) / n, n, lo.argmin, hi.argmax)


@dataclass
class BlockQuality:
    """Quality of one block.

    Attributes
    ----------
    block : int
        0-based block number.
    dims : (ni, nj, nk)
    cells : int
    handedness : {1, -1}
        Sign of the block's total volume (of the reference block when given);
        volumes and Jacobians in :attr:`metrics` are multiplied by it.
    metrics : dict of str -> MetricStats
        One entry per name in :data:`METRICS` (``volume_ratio``: empty without
        a reference).
    negative, negative_jacobian, degenerate, collapsed : int
        Cells with volume <= 0, with a corner Jacobian <= 0, with
        ``|volume| <= rtol * Lmax**3``, with a zero-length edge.
    negative_cells, negative_jacobian_cells, degenerate_cells : list of (i, j, k)
        The first few (0-based, in file order: i fastest).
    """

    block: int
    dims: tuple
    cells: int
    handedness: int
    metrics: dict
    negative: int = 0
    negative_jacobian: int = 0
    degenerate: int = 0
    collapsed: int = 0
    negative_cells: list = field(default_factory=list)
    negative_jacobian_cells: list = field(default_factory=list)
    degenerate_cells: list = field(default_factory=list)

    def to_dict(self, base: int = 0) -> dict:
        loc = lambda cells: [[int(c) + base for c in ijk] for ijk in cells]   # noqa: E731
        return {"block": self.block + base, "dims": list(self.dims), "cells": self.cells,
                "handedness": "right" if self.handedness > 0 else "left",
                "metrics": {k: v.to_dict(base) for k, v in self.metrics.items()},
                "negative": self.negative, "negative_jacobian": self.negative_jacobian,
                "degenerate": self.degenerate, "collapsed": self.collapsed,
                "negative_cells": loc(self.negative_cells),
                "negative_jacobian_cells": loc(self.negative_jacobian_cells),
                "degenerate_cells": loc(self.degenerate_cells)}


@dataclass
class WallOrthogonality:
    """Near-wall orthogonality on one wall patch (:func:`wall_orthogonality`).

    Attributes
    ----------
    patch : PatchSpec
        The resolved patch (0-based; ``str(patch)`` is the 1-based text).
    points : int
        Wall points.
    layers : int
    max, mean : float
        Angle (deg) between the wall normal and the grid lines of the first
        ``layers`` layers, over every point and layer (NaN ignored).
    layer_max, layer_mean : list of float
        The same per layer (layer 0 touches the wall).
    argmax : (block, i, j, k, layer) or None
        0-based wall point and layer of ``max``.
    change_max, change_mean, change_layer_max, change_layer_mean, change_argmax
        ``|angle - angle in the reference|``, when a reference was given
        (None otherwise).
    """

    patch: object
    points: int
    layers: int
    max: float
    mean: float
    layer_max: list
    layer_mean: list
    argmax: tuple | None = None
    change_max: float | None = None
    change_mean: float | None = None
    change_layer_max: list | None = None
    change_layer_mean: list | None = None
    change_argmax: tuple | None = None

    def to_dict(self, base: int = 0) -> dict:
        fl = lambda xs: None if xs is None else [_f(x) for x in xs]   # noqa: E731
        return {"patch": str(self.patch), "points": self.points, "layers": self.layers,
                "max": _f(self.max), "mean": _f(self.mean),
                "layer_max": fl(self.layer_max), "layer_mean": fl(self.layer_mean),
                "argmax": _loc(self.argmax, base),
                "change_max": None if self.change_max is None else _f(self.change_max),
                "change_mean": None if self.change_mean is None else _f(self.change_mean),
                "change_layer_max": fl(self.change_layer_max),
                "change_layer_mean": fl(self.change_layer_mean),
                "change_argmax": _loc(self.change_argmax, base)}


_LABELS = {"volume": ("volume", "area"), "jacobian": ("jacobian (corner min)",) * 2,
           "scaled_jacobian": ("scaled jacobian",) * 2, "skewness": ("skewness (equiangle)",) * 2,
           "aspect_ratio": ("aspect ratio",) * 2, "volume_ratio": ("volume ratio", "area ratio")}


@dataclass
class QualityReport:
    """The quality of a grid, per block and grid-wide (:func:`quality_report`).

    Attributes
    ----------
    ndim, npoints, ncells : int
    blocks : list of BlockQuality
    metrics : dict of str -> MetricStats
        Grid-wide, one entry per name in :data:`METRICS`.
    negative, negative_jacobian, degenerate, collapsed : int
        Grid-wide counts (see :class:`BlockQuality`).
    negative_cells, negative_jacobian_cells, degenerate_cells : list of (block, i, j, k)
        The first few over the grid (0-based).
    walls : list of WallOrthogonality
        One per wall patch (empty without walls).
    orthogonality : dict
        Over every wall: ``max``, ``mean`` and, with a reference,
        ``change_max``, ``change_mean`` (degrees); empty without walls.
    has_reference : bool
    layers : int
    rtol : float
    """

    ndim: int
    npoints: int
    ncells: int
    blocks: list
    metrics: dict
    negative: int
    negative_jacobian: int
    degenerate: int
    collapsed: int
    negative_cells: list
    negative_jacobian_cells: list
    degenerate_cells: list
    walls: list
    orthogonality: dict
    has_reference: bool
    layers: int
    rtol: float

    @property
    def valid(self) -> bool:
        """No cell with a volume <= 0 (the test a flow solver applies)."""
        return self.negative == 0

    def to_dict(self, one_based: bool = False) -> dict:
        """JSON-ready dict (plain lists, floats, ints, str; None for NaN/inf).

        Parameters
        ----------
        one_based : bool
            Block and cell indices 1-based (as the CLI and files), else 0-based
            (as the Python API); the dict says which under ``index_base``.
        """
        base = 1 if one_based else 0
        loc = lambda cells: [_loc(c, base) for c in cells]   # noqa: E731
        return {"index_base": base, "ndim": self.ndim, "npoints": self.npoints, "ncells": self.ncells,
                "has_reference": self.has_reference, "layers": self.layers, "rtol": self.rtol,
                "valid": self.valid,
                "metrics": {k: v.to_dict(base) for k, v in self.metrics.items()},
                "negative": self.negative, "negative_jacobian": self.negative_jacobian,
                "degenerate": self.degenerate, "collapsed": self.collapsed,
                "negative_cells": loc(self.negative_cells),
                "negative_jacobian_cells": loc(self.negative_jacobian_cells),
                "degenerate_cells": loc(self.degenerate_cells),
                "orthogonality": {k: _f(v) for k, v in self.orthogonality.items()},
                "walls": [w.to_dict(base) for w in self.walls],
                "blocks": [b.to_dict(base) for b in self.blocks]}

    def summary(self) -> str:
        """A readable text report; block and cell indices 1-based."""
        d2 = 1 if self.ndim == 2 else 0
        cell = "cell"
        lines = [f"{self.ndim}-D grid: {len(self.blocks)} block(s), {self.npoints:,} points, "
                 f"{self.ncells:,} {cell}s" + ("; reference grid given" if self.has_reference else "")]

        def g(v):
            return "-" if v is None or not math.isfinite(v) else f"{v:.4g}"

        def at(t):
            if t is None:
                return ""
            b, *ijk = (c + 1 for c in t)
            return f"block {b} ({', '.join(map(str, ijk[:2 if d2 else 3]))})"

        rows = [("metric", "min", "mean", "max", "worst at (block, i, j[, k])")]
        for name in METRICS:
            st = self.metrics[name]
            if name == "volume_ratio" and not self.has_reference:
                continue
            worst = st.argmin if name in _LOW_IS_BAD else st.argmax
            rows.append((_LABELS[name][d2], g(st.min), g(st.mean), g(st.max), at(worst)))
        lines.append("")
        lines += _table(rows)
        vol = "area" if d2 else "volume"
        lines.append("")
        lines.append(f"cells: {self.negative} negative ({vol} <= 0), {self.negative_jacobian} with a corner "
                     f"Jacobian <= 0, {self.degenerate} degenerate (|{vol}| <= {self.rtol:g} Lmax^"
                     f"{2 if d2 else 3}), {self.collapsed} with a zero-length edge")
        for what, cells in (("negative", self.negative_cells),
                            ("corner Jacobian <= 0", self.negative_jacobian_cells),
                            ("degenerate", self.degenerate_cells)):
            if cells:
                lines.append(f"  {what} (first {len(cells)}): " + "; ".join(at(c) for c in cells))
        lines.append("")
        rows = [("block", "dims", "cells", "hand", "neg", "negJ", "degen", "min sJ", "max skew", "max AR")
                + (("min ratio", "max ratio") if self.has_reference else ())]
        for b in self.blocks:
            m = b.metrics
            rows.append((str(b.block + 1), " x ".join(map(str, b.dims[:2] if d2 else b.dims)), f"{b.cells:,}",
                         "R" if b.handedness > 0 else "L", str(b.negative), str(b.negative_jacobian),
                         str(b.degenerate), g(m["scaled_jacobian"].min), g(m["skewness"].max),
                         g(m["aspect_ratio"].max))
                        + ((g(m["volume_ratio"].min), g(m["volume_ratio"].max)) if self.has_reference else ()))
        lines += _table(rows)
        if self.walls:
            lines.append("")
            lines.append(f"near-wall orthogonality, first {self.layers} layers: angle (deg) between the "
                         "wall normal and the grid lines leaving the wall")
            rows = [("wall", "points", "max", "mean") + (("change max", "change mean", "change max at")
                                                         if self.has_reference else ())]
            for w in self.walls:
                row = (str(w.patch), str(w.points), g(w.max), g(w.mean))
                if self.has_reference:
                    where = ""
                    if w.change_argmax is not None:
                        where = at(w.change_argmax[:4]) + f" layer {w.change_argmax[4] + 1}"
                    row += (g(w.change_max), g(w.change_mean), where)
                rows.append(row)
            lines += _table(rows)
        return "\n".join(lines)


def _table(rows) -> list[str]:
    """Rows of strings as columns padded to their widest entry; a column whose
    entries are all numbers (or "-") is right-aligned, header included."""
    ncol = len(rows[0])
    widths = [max(len(r[c]) for r in rows) for c in range(ncol)]

    def number(t):
        try:
            float(t.replace(",", ""))
            return True
        except ValueError:
            return t == "-"
    right = [c > 0 and all(number(r[c]) for r in rows[1:]) for c in range(ncol)]
    return ["  " + "  ".join(t.rjust(w) if rj else t.ljust(w) for t, w, rj in zip(r, widths, right)).rstrip()
            for r in rows]


def _block_stats_call(xyz, xr, ndim, s, rtol):
    nci, ncj, nck = _cell_shape(xyz.shape[:3], ndim)
    nrows = ncj * nck
    lo = np.empty((nrows, _NM))
    hi = np.empty((nrows, _NM))
    tot = np.empty((nrows, _NM))
    arg = np.empty((nrows, _NM, 2), dtype=np.int64)
    cnt = np.empty((nrows, _NCNT), dtype=np.int64)
    refsum = np.empty(nrows)
    if nci and nrows:
        parallel_for(_block_stats, nrows, xyz, xr if xr is not None else xyz, xr is not None, ndim,
                     float(s), float(rtol), lo, hi, tot, arg, cnt, refsum)
    return lo, hi, tot, arg, cnt, refsum


def _block_quality(b: int, blk: Block, ref: Block | None, ndim: int, rtol: float, max_locations: int):
    xyz = blk.xyz
    xr = None if ref is None else _check_ref(xyz, ref, f"block {b + 1}")
    shape = _cell_shape(xyz.shape[:3], ndim)
    lo, hi, tot, arg, cnt, refsum = _block_stats_call(xyz, xr, ndim, 1.0, rtol)
    total = refsum.sum() if xr is not None else tot[:, 0].sum()
    s = 1
    if total < 0.0:          # left-handed block: every sign flips
        s = -1
        lo, hi, tot, arg, cnt, refsum = _block_stats_call(xyz, xr, ndim, -1.0, rtol)

    def where(flat):
        return (b, *(int(c) for c in np.unravel_index(int(flat), shape, order="F")))

    metrics = {}
    for m, name in enumerate(METRICS):
        n = int(cnt[:, m].sum())
        if n == 0:
            metrics[name] = _EMPTY
            continue
        rmin = int(np.argmin(lo[:, m]))
        rmax = int(np.argmax(hi[:, m]))
        metrics[name] = MetricStats(float(lo[rmin, m]), float(hi[rmax, m]), float(tot[:, m].sum() / n), n,
                                    where(arg[rmin, m, 0]), where(arg[rmax, m, 1]))
    counts = cnt.sum(axis=0)
    bq = BlockQuality(b, blk.dims, int(np.prod(shape)), s, metrics, int(counts[_C_NEG]), int(counts[_C_NEGJ]),
                      int(counts[_C_DEG]), int(counts[_C_COL]))
    # list the first few bad cells: revisit only the rows that hold some
    bad = np.flatnonzero(cnt[:, _C_NEG:_C_DEG + 1].sum(axis=1) > 0)
    lists = {NEGATIVE: bq.negative_cells, NEGATIVE_JACOBIAN: bq.negative_jacobian_cells,
             DEGENERATE: bq.degenerate_cells}
    start = 0
    while start < bad.size and min(len(v) for v in lists.values()) < max_locations:
        rows = bad[start:start + 64].astype(np.int64)
        start += rows.size
        _, flags = _fields(xyz, xr, ndim, s, rtol, rows)
        for bit, out in lists.items():
            if len(out) >= max_locations:
                continue
            qi = np.argwhere((flags.T & bit) != 0)     # (row, i) pairs in file order: rows, then i
            for q, i in qi[:max_locations - len(out)]:
                r = int(rows[q])
                out.append((int(i), r % shape[1], r // shape[1]))
    return bq


def quality_report(grid: Grid, ref: Grid | None = None, walls=None, layers: int = 5, rtol: float = 1e-12,
                   max_locations: int = 10) -> QualityReport:
    """Measure the quality of a grid: every cell metric, bad cells, near-wall orthogonality.

    Parameters
    ----------
    grid : Grid
    ref : Grid, optional
        The same grid before deformation (same blocks and dimensions): adds the
        cell volume ratio ``grid / ref`` and the orthogonality change, and
        decides each block's handedness.
    walls : sequence of PatchSpec or "B:FACE[:A1-A2,B1-B2]", optional
        Wall patches (1-based text, as in case files) for the near-wall
        orthogonality.
    layers : int
        Grid-line segments off the wall measured per wall point (>= 1).
    rtol : float
        Degenerate-cell tolerance: ``|volume| <= rtol * Lmax**3`` (``**2`` in 2-D).
    max_locations : int
        How many negative, negative-Jacobian and degenerate cells to list.

    Returns
    -------
    QualityReport

    Raises
    ------
    GridValueError
        ``ref`` does not match ``grid`` (block count, dimensions, ndim).
    CaseError
        A wall patch names a block, face or range the grid does not have.

    Examples
    --------
    >>> import tfi_quat as tq
    >>> from tfi_quat.quality import quality_report
    >>> g = tq.read("grids/naca0012_c_257x65.x")
    >>> rep = quality_report(g, walls=["1:jmin:65-193"])
    >>> rep.negative
    0
    """
    if not isinstance(grid, Grid):
        raise GridValueError(f"grid: expected a Grid, got {type(grid).__name__}")
    if ref is not None:
        if not isinstance(ref, Grid):
            raise GridValueError(f"ref: expected a Grid, got {type(ref).__name__}")
        if len(ref) != len(grid) or ref.ndim != grid.ndim:
            raise GridValueError(f"ref: has {len(ref)} block(s), {ref.ndim}-D; the grid {len(grid)}, "
                                 f"{grid.ndim}-D")
    layers = int(layers)
    if layers < 1:
        raise ValueError(f"layers must be >= 1, got {layers}")
    rtol = float(rtol)
    if not rtol >= 0.0:
        raise ValueError(f"rtol must be >= 0, got {rtol}")
    max_locations = max(0, int(max_locations))
    ndim = grid.ndim
    blocks = [_block_quality(b, blk, None if ref is None else ref[b], ndim, rtol, max_locations)
              for b, blk in enumerate(grid)]
    metrics = {name: _merge([bq.metrics[name] for bq in blocks]) for name in METRICS}

    def first(attr):
        out = []
        for bq in blocks:
            out += [(bq.block, *c) for c in getattr(bq, attr)]
        return out[:max_locations]

    wall_stats, ortho = _orthogonality_stats(grid, ref, walls, layers) if walls else ([], {})
    return QualityReport(
        ndim=ndim, npoints=grid.npoints, ncells=sum(bq.cells for bq in blocks), blocks=blocks,
        metrics=metrics, negative=sum(bq.negative for bq in blocks),
        negative_jacobian=sum(bq.negative_jacobian for bq in blocks),
        degenerate=sum(bq.degenerate for bq in blocks), collapsed=sum(bq.collapsed for bq in blocks),
        negative_cells=first("negative_cells"), negative_jacobian_cells=first("negative_jacobian_cells"),
        degenerate_cells=first("degenerate_cells"), walls=wall_stats, orthogonality=ortho,
        has_reference=ref is not None, layers=layers, rtol=rtol)


def _orientation(vol: np.ndarray) -> float:
    """+1 or -1: the sign of the block's total volume (its handedness)."""
    return -1.0 if vol.sum() < 0.0 else 1.0


def invalid_cells(block: Block | np.ndarray, ndim: int | None = None,
                  corner_tol: float = 0.0) -> tuple[int, tuple[int, int, int] | None]:
    """Count the invalid cells of one block (the validity test of the grid generators).

    A cell is **valid** when its volume (area in 2-D) is positive and every
    scaled corner Jacobian is greater than ``-corner_tol``, both taken as a
    right-handed cell (counter-clockwise in 2-D), unlike the handedness-
    relative counts of :func:`quality_report`.  With ``corner_tol = 0`` every
    corner must be strictly convex; a small ``corner_tol`` admits corners
    where the grid lines meet at 180 degrees (a collapsed edge).  A
    zero-length edge gives its corners a scaled Jacobian of 0; NaN
    coordinates make a cell invalid.

    Parameters
    ----------
    block : Block or ndarray (ni, nj, nk, 3)
    ndim : {2, 3}, optional
        Default: 2 when ``nk == 1``, else 3.
    corner_tol : float
        Tolerance on the scaled corner Jacobians, >= 0.

    Returns
    -------
    (count, first)
        The number of invalid cells and the 0-based ``(i, j, k)`` of the
        first in C order (``k = 0`` in 2-D), or None when every cell is valid.
    """
    xyz = _xyz(block)
    ndim = _ndim(xyz, ndim)
    try:
        tol = float(corner_tol)
    except (TypeError, ValueError):
        tol = math.nan
    if not (math.isfinite(tol) and tol >= 0.0):
        raise GridValueError(f"corner_tol must be a finite number >= 0, got {corner_tol!r}")
    count, i, j, k = _invalid_cells(xyz, ndim, tol)
    return int(count), (None if count == 0 else (int(i), int(j), int(k)))


def negative_cells(grid: Grid, reference: Grid | None = None):
    """Cells whose volume has the wrong sign.

    The right sign is the reference cell's sign when ``reference`` is given,
    else the sign of the block's total volume (left-handed blocks are valid).
    Degenerate cells (zero reference volume, e.g. at a collapsed edge) are
    skipped when a reference is given.

    Returns
    -------
    list of (block, ndarray (m, 3) int)
        For each block with bad cells, the 0-based (i, j, k) indices of the cells.
    """
    out = []
    for b, blk in enumerate(grid):
        v = cell_volumes(blk, grid.ndim)
        if reference is not None:
            vr = cell_volumes(reference[b], grid.ndim)
            bad = (v * np.sign(vr) <= 0.0) & (vr != 0.0)
        else:
            bad = v * _orientation(v) <= 0.0
        if bad.any():
            out.append((b, np.argwhere(bad)))
    return out


# ------------------------------------------------------------------ a deformation step's check
@dataclass(frozen=True)
class CellCheck:
    """The cells of a deformed grid against its reference (:func:`check_cells`).

    Attributes
    ----------
    min_ratio : float
        The smallest ratio, over every cell corner, of the corner Jacobian
        (the determinant of the three edges leaving the corner along i, j, k,
        in the positive index sense; two in 2-D) to the same corner's in the
        reference; corners whose reference Jacobian is 0 are skipped.  1 for
        a translated grid; <= 0 where a corner folded.  NaN when a cell has
        non-finite coordinates; ``inf`` when no corner counts.
    min_at : (block, i, j, k) or None
        0-based cell of ``min_ratio``.
    negative : int
        Cells whose volume (area) has not the sign of the reference cell's
        (reference cells of zero volume skipped): the count
        :func:`negative_cells` gives with the reference.
    negative_jacobian : int
        Cells with a corner ratio <= 0 (or NaN): the stricter test.
    first : tuple of (block, i, j, k)
        0-based, up to ``max_locations`` cells that are negative or
        negative-Jacobian: the first (lowest i) of each row of cells that
        has one, rows in block order, then k, then j.
    """

    min_ratio: float
    min_at: tuple | None
    negative: int
    negative_jacobian: int
    first: tuple = ()

    @property
    def ok(self) -> bool:
        """No negative and no negative-Jacobian cell."""
        return self.negative == 0 and self.negative_jacobian == 0

    def __str__(self) -> str:
        where = "" if self.min_at is None else f" at (block, i, j, k) = {self.min_at}"
        text = (f"smallest corner-Jacobian ratio {self.min_ratio:.6g}{where}; {self.negative} "
                f"negative cell(s), {self.negative_jacobian} with a corner ratio <= 0")
        if self.first:
            text += f"; first: {', '.join(str(t) for t in self.first)} (0-based)"
        return text

    @staticmethod
    def merge(parts, max_locations: int = 5) -> "CellCheck":
        """One report for the blocks of ``parts`` (per-block reports, block order)."""
        parts = list(parts)
        nan = [p for p in parts if p.min_ratio != p.min_ratio]
        lo = nan[0] if nan else min(parts, key=lambda p: p.min_ratio, default=None)
        first = tuple(t for p in parts for t in p.first)[:max_locations]
        return CellCheck(math.inf if lo is None else lo.min_ratio, None if lo is None else lo.min_at,
                         sum(p.negative for p in parts), sum(p.negative_jacobian for p in parts),
                         first)


@dataclass(frozen=True)
class CheckReference:
    """A reference block for :func:`check_block`, with what a check can know of it once
    (:func:`check_reference`): its coordinates ``xyz`` (float64, Fortran-ordered
    ``(ni, nj, nk, 3)``, kept by reference: do not modify them), ``ndim``, and ``sign``, +1
    when every cell volume (area) is positive as :func:`cell_volumes` computes it, -1 when
    every one is negative, else 0.  With a sign of +-1 a check does not recompute the
    reference volumes; :class:`tfi_quat.deform.Deformer` makes one per block on its first
    check and keeps it."""

    xyz: np.ndarray
    ndim: int
    sign: int


def check_reference(ref: np.ndarray, ndim: int | None = None) -> CheckReference:
    """:class:`CheckReference` of the block coordinates ``ref`` (float64 Fortran-ordered
    ``(ni, nj, nk, 3)``; ``ndim`` default: 2 when ``nk == 1``): one pass over its cells,
    nothing the size of the block allocated (in 3-D)."""
    _check_step_array(ref, "ref")
    ndim = _ndim(ref, ndim)
    nci, ncj, nck = _cell_shape(ref.shape[:3], ndim)
    ncell = nci * ncj * nck
    if ncell == 0:
        return CheckReference(ref, ndim, 0)
    if ndim == 2:
        v = cell_volumes(ref, 2)
        npos, nneg = int((v > 0.0).sum()), int((v < 0.0).sum())
    else:
        cnt = np.empty((nck, 2), dtype=np.int64)
        parallel_for(_volume_sign_counts, nck, ref, cnt)
        npos, nneg = (int(c) for c in cnt.sum(axis=0))
    return CheckReference(ref, ndim, 1 if npos == ncell else (-1 if nneg == ncell else 0))


def _check_step_array(a, name: str) -> None:
    if not isinstance(a, np.ndarray) or a.ndim != 4 or a.shape[-1] != 3 or \
            a.dtype != np.float64 or not a.flags.f_contiguous:
        raise GridValueError(f"{name}: expected a float64 Fortran-ordered (ni, nj, nk, 3) array")


def check_block(xyz: np.ndarray, ref, ndim: int, block: int = 0,
                max_locations: int = 5) -> CellCheck:
    """:class:`CellCheck` of one block ``xyz`` against its reference ``ref``: coordinates (both
    float64 Fortran-ordered ``(ni, nj, nk, 3)``) or a :class:`CheckReference` of them, which
    spares the reference volumes when its sign is known (``block``: the block's number in the
    locations).

    One pass over the cells, rows in parallel, nothing the size of the block allocated:
    the check :meth:`tfi_quat.deform.Deformer.deform` makes with ``check=True``.  At each
    node line of a row of cells the corner Jacobians share their j- and k-edges: 4 cross
    products per node and a dot product per corner (the same numbers, bit for bit, as the
    determinant of each corner's three edges).
    """
    _check_step_array(xyz, "xyz")
    ndim = _ndim(xyz, ndim)
    sign = 0
    if isinstance(ref, CheckReference):
        if ref.ndim != ndim:
            raise GridValueError(f"ref: a CheckReference for ndim {ref.ndim}, the check is for ndim {ndim}")
        ref, sign = ref.xyz, ref.sign
    _check_step_array(ref, "ref")
    if xyz.shape != ref.shape:
        raise GridValueError(f"xyz has shape {xyz.shape}, its reference {ref.shape}")
    nci, ncj, nck = _cell_shape(xyz.shape[:3], ndim)
    if nci * ncj * nck == 0:
        return CellCheck(math.inf, None, 0, 0)
    res = np.empty((ncj * nck, 6))
    parallel_for(_step_check, res.shape[0], xyz, ref, ndim, int(sign), res)
    nan = np.flatnonzero(res[:, 5] > 0)
    r = int(nan[0]) if nan.size else int(np.argmin(res[:, 0]))
    lo = float(res[r, 0])
    at = None if res[r, 1] < 0 else (block, int(res[r, 1]), r % ncj, r // ncj)
    bad = np.flatnonzero(res[:, 4] >= 0)[:max_locations]
    first = tuple((block, int(res[q, 4]), int(q % ncj), int(q // ncj)) for q in bad)
    return CellCheck(lo, at, int(res[:, 2].sum()), int(res[:, 3].sum()), first)


#: cells of a 2-D block below which :func:`volume_ratio_summary` reduces its ratios with
#: numpy (:func:`_ratio_rows_2d`, the same values) rather than the compiled :func:`_ratio_rows`:
#: a run that only meets small 2-D blocks, as the demo, does not compile it
_RATIOS_NUMPY_BELOW = 1 << 16


def _ratio_rows_2d(x, xr, neg, low, first) -> None:
    """:func:`_ratio_rows` of a 2-D block (``hexa`` None) with numpy: the same areas (the
    same operations in the same order), ratios and reductions, bit for bit."""
    def area(p):
        d1x = p[1:, 1:, 0, 0] - p[:-1, :-1, 0, 0]
        d1y = p[1:, 1:, 0, 1] - p[:-1, :-1, 0, 1]
        d2x = p[:-1, 1:, 0, 0] - p[1:, :-1, 0, 0]
        d2y = p[:-1, 1:, 0, 1] - p[1:, :-1, 0, 1]
        return 0.5 * (d1x * d2y - d1y * d2x)

    with np.errstate(all="ignore"):            # overflow, inf - inf: as the compiled kernel
        v, vr = area(x), area(xr)
        zero = vr == 0.0
        q = np.where(zero, np.inf, v / np.where(zero, 1.0, vr))          # (nci, ncj)
    neg[:] = np.count_nonzero(q <= 0.0, axis=0)
    at = np.argmin(q, axis=0)                  # the first NaN, else the first smallest
    low[:] = q[at, np.arange(q.shape[1])]
    first[:] = np.where(low == np.inf, -1, at)


def volume_ratio_summary(grid: Grid, reference: Grid) -> dict:
    """Number of negative cells and the smallest cell-volume ratio to ``reference``.

    One pass over each block and its reference, no per-cell arrays: the
    ratios are reduced row by row of cells as they are computed.

    Returns
    -------
    dict with keys ``negative`` (int), ``min_ratio`` (float) and ``where``
    ((block, i, j, k) 0-based of the smallest ratio, the first in C order, i
    then j then k, among equal ones).  A ratio is the deformed cell's volume
    over the reference cell's (areas in 2-D), infinite where the reference
    volume is 0; a block with a NaN ratio offers no smallest ratio.
    """
    neg = 0
    best = (np.inf, None)
    for b, (blk, ref) in enumerate(zip(grid, reference)):
        x = _xyz(blk)
        xr = _check_ref(x, ref, f"block {b + 1}")
        nci, ncj, nck = _cell_shape(x.shape[:3], grid.ndim)
        nrows = ncj * nck
        if not nci * nrows:
            continue
        cnt = np.empty(nrows, dtype=np.int64)
        low = np.empty(nrows)
        first = np.empty(nrows, dtype=np.int64)
        if grid.ndim == 2 and nci * nrows < _RATIOS_NUMPY_BELOW:
            _ratio_rows_2d(x, xr, cnt, low, first)
        else:
            parallel_for(_ratio_rows, nck, x, xr, True if grid.ndim == 3 else None, cnt, low,
                         first)
        neg += int(cnt.sum())
        if np.isnan(low).any():
            continue                                # NaN < best is False: as np.argmin's NaN
        m = low.min()
        if m < best[0]:
            rows = np.flatnonzero(low == m)
            i, j, k = first[rows], rows % ncj, rows // ncj
            r = int(np.lexsort((k, j, i))[0])
            best = (float(low[rows[r]]), (b, int(i[r]), int(j[r]), int(k[r])))
    return {"negative": neg, "min_ratio": best[0], "where": best[1]}


# ------------------------------------------------------------ near-wall orthogonality
def _patch_normals(w: np.ndarray, ndim: int) -> np.ndarray:
    """Unit normals (na, nb, 3) of a wall patch from central differences
    (one-sided at the patch edges); NaN where degenerate."""
    def diff(axis):
        n = w.shape[axis]
        if n < 2:
            return np.zeros_like(w)
        return np.gradient(w, axis=axis)
    if ndim == 2:
        t = diff(0) if w.shape[0] > 1 else diff(1)
        n = np.stack([t[..., 1], -t[..., 0], np.zeros(t.shape[:-1])], axis=-1)
    else:
        n = np.cross(diff(0), diff(1))
    size = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(size > 0.0, n / size, np.nan)


def _wall_angles(grid: Grid, spec, layers: int):
    """Angles (na, nb, layers) on one resolved wall patch and its point indices (na, nb, 3)."""
    blk = grid[spec.block]
    d, _ = face_axis(spec.face)
    nl = min(layers, blk.dims[d] - 1)
    ijk = face_ijk(blk.dims, spec.face, spec.range)
    x = blk.xyz
    w = x[ijk[..., 0], ijk[..., 1], ijk[..., 2]]
    nrm = _patch_normals(w, grid.ndim)
    ang = np.full(w.shape[:2] + (layers,), np.nan)
    for lay in range(nl):
        a = ijk.copy()
        b = ijk.copy()
        a[..., d] = face_layer(blk.dims, spec.face, lay)
        b[..., d] = face_layer(blk.dims, spec.face, lay + 1)
        e = x[b[..., 0], b[..., 1], b[..., 2]] - x[a[..., 0], a[..., 1], a[..., 2]]
        # atan2 of |n x e| and |n . e|: accurate near 0 deg, where arccos is not
        cr = np.linalg.norm(np.cross(nrm, e), axis=-1)
        dt = np.abs(np.einsum("abc,abc->ab", nrm, e))
        a_l = np.degrees(np.arctan2(cr, dt))
        a_l[np.linalg.norm(e, axis=-1) == 0.0] = np.nan
        ang[..., lay] = a_l
    return ang, ijk


def wall_orthogonality(grid: Grid, walls, layers: int = 5) -> list[np.ndarray]:
    """Angles (degrees) between the wall normal and the first grid-line segments leaving the wall.

    Parameters
    ----------
    grid : Grid
    walls : sequence of PatchSpec or "B:FACE[:A1-A2,B1-B2]"
        Wall patches (1-based text, as in case files).
    layers : int
        Segments per wall point: layer ``l`` is the segment from point ``l``
        to point ``l + 1`` along the index direction leaving the wall.

    Returns
    -------
    list of ndarray, shape (na, nb, layers)
        Per patch, in ``[0, 90]`` degrees (the line's sense does not matter);
        NaN at degenerate wall points (collapsed edges, zero-length lines)
        and for layers deeper than the block.
        The wall normal comes from central differences of the patch points,
        one-sided on the patch edges (first order: robust at sharp trailing
        edges, where second-order one-sided differences overshoot; on a
        curved wall the edge values are off by about half the turning angle
        of the last wall interval, an error a comparison with a reference
        shares).
    """
    layers = int(layers)
    if layers < 1:
        raise ValueError(f"layers must be >= 1, got {layers}")
    return [_wall_angles(grid, spec, layers)[0] for spec in resolve_patch_specs(grid, walls, "walls")]


def orthogonality_change(grid: Grid, ref: Grid, walls, layers: int = 5) -> dict:
    """Change of the near-wall angles of :func:`wall_orthogonality` from ``ref``.

    Returns
    -------
    dict with ``max`` and ``mean`` (degrees) of ``|angle(grid) - angle(ref)|``
    over every wall point and layer (NaN points ignored).
    """
    a = wall_orthogonality(grid, walls, layers)
    b = wall_orthogonality(ref, walls, layers)
    diff = np.concatenate([np.abs(x - y).ravel() for x, y in zip(a, b)]) if a else np.zeros(0)
    diff = diff[np.isfinite(diff)]
    if diff.size == 0:
        return {"max": float("nan"), "mean": float("nan")}
    return {"max": float(diff.max()), "mean": float(diff.mean())}


def _nanstats(a: np.ndarray):
    """max, mean, per-layer max and mean, and the flat index of the max of (na, nb, L); NaN ignored."""
    ok = np.isfinite(a)
    if not ok.any():
        nan = [math.nan] * a.shape[-1]
        return math.nan, math.nan, nan, nan, None
    filled = np.where(ok, a, -np.inf)
    flat = int(np.argmax(filled))
    cnt = ok.sum(axis=(0, 1))
    sums = np.where(ok, a, 0.0).sum(axis=(0, 1))
    lmax = [float(v) if c else math.nan for v, c in zip(filled.max(axis=(0, 1)), cnt)]
    lmean = [float(s / c) if c else math.nan for s, c in zip(sums, cnt)]
    return float(a.flat[flat]), float(sums.sum() / cnt.sum()), lmax, lmean, flat


def _orthogonality_stats(grid: Grid, ref: Grid | None, walls, layers: int):
    specs = resolve_patch_specs(grid, walls, "walls")
    out = []
    allang, allch = [], []
    for spec in specs:
        ang, ijk = _wall_angles(grid, spec, layers)
        mx, mean, lmax, lmean, flat = _nanstats(ang)

        def where(fl):
            if fl is None:
                return None
            a, b, lay = np.unravel_index(fl, ang.shape)
            return (spec.block, *(int(c) for c in ijk[a, b]), int(lay))
        wo = WallOrthogonality(spec, int(ang.shape[0] * ang.shape[1]), layers, mx, mean, lmax, lmean, where(flat))
        allang.append(ang[np.isfinite(ang)])
        if ref is not None:
            ch = np.abs(ang - _wall_angles(ref, spec, layers)[0])
            cmx, cmean, clmax, clmean, cflat = _nanstats(ch)
            wo.change_max, wo.change_mean = cmx, cmean
            wo.change_layer_max, wo.change_layer_mean = clmax, clmean
            wo.change_argmax = where(cflat)
            allch.append(ch[np.isfinite(ch)])
        out.append(wo)
    tot = {}
    a = np.concatenate(allang) if allang else np.zeros(0)
    tot["max"] = float(a.max()) if a.size else math.nan
    tot["mean"] = float(a.mean()) if a.size else math.nan
    if ref is not None:
        c = np.concatenate(allch) if allch else np.zeros(0)
        tot["change_max"] = float(c.max()) if c.size else math.nan
        tot["change_mean"] = float(c.mean()) if c.size else math.nan
    return out, tot


def cell_orthogonality(grid: Grid, walls, layers: int = 5, ref: Grid | None = None) -> list[np.ndarray]:
    """Near-wall orthogonality (or its change from ``ref``) as a per-cell field, for pictures.

    A cell in layer ``l`` off a wall gets the largest angle (or angle
    change) of :func:`wall_orthogonality` over the 2 (2-D) or 4 (3-D) grid
    lines of that layer that bound it; cells deeper than ``layers`` and cells
    not next to a wall are NaN.  Where several walls reach one cell the
    largest value wins.

    Returns
    -------
    list of ndarray, float64, one per block, shaped as :func:`cell_volumes`
    """
    layers = int(layers)
    if layers < 1:
        raise ValueError(f"layers must be >= 1, got {layers}")
    ndim = grid.ndim
    out = [np.full(_cell_shape(b.dims, ndim), np.nan, order="F") for b in grid]
    for spec in resolve_patch_specs(grid, walls, "walls"):
        ang, _ = _wall_angles(grid, spec, layers)
        if ref is not None:
            ang = np.abs(ang - _wall_angles(ref, spec, layers)[0])
        a = np.where(np.isfinite(ang), ang, -np.inf)
        c = np.maximum(a[:-1], a[1:])                     # (na-1, nb, L)
        if ndim == 3:
            c = np.maximum(c[:, :-1], c[:, 1:])           # (na-1, nb-1, L)
        c = np.where(np.isfinite(c), c, np.nan)
        dims = grid[spec.block].dims
        nl = min(layers, dims[face_axis(spec.face)[0]] - 1)
        cells = out[spec.block]
        for lay in range(nl):
            idx = face_cells(dims, spec.face, spec.range, lay)
            tgt = cells[idx]
            cells[idx] = np.fmax(tgt, c[..., lay].reshape(tgt.shape))
    return out
