"""Grid quality: cell volumes (areas in 2-D) and negative-cell checks.

Kernels are numba functions over one block; the drivers take a :class:`Block`
or :class:`Grid` and return plain arrays.

Cell volume of a hexahedron: the sum of the six tetrahedra around the
diagonal from corner (0,0,0) to corner (1,1,1), one per monotone path along
the cell edges, so every quadrilateral face is split through one of the two
diagonal corners.  It is exact for cells with planar faces, independent of
the handedness of nothing else, and signed: a right-handed (i, j, k) cell has
a positive volume.  In 2-D the area is half the cross product of the
diagonals (signed, positive when (i, j) is counter-clockwise).
"""

from __future__ import annotations

import numpy as np

from ._jit import pjit, prange
from .grid import Block, Grid

__all__ = ["cell_volumes", "volume_ratio_summary", "negative_cells", "wall_orthogonality",
           "orthogonality_change"]


@pjit
def _hex_volumes(x, out):
    ni, nj, nk = x.shape[0], x.shape[1], x.shape[2]
    for k in prange(nk - 1):
        for j in range(nj - 1):
            for i in range(ni - 1):
                x0 = x[i, j, k, 0]
                y0 = x[i, j, k, 1]
                z0 = x[i, j, k, 2]
                ax = x[i + 1, j + 1, k + 1, 0] - x0
                ay = x[i + 1, j + 1, k + 1, 1] - y0
                az = x[i + 1, j + 1, k + 1, 2] - z0
                v = 0.0
                # six monotone paths 0 -> e1 -> e1+e2 -> 7; det[p1-0, p2-p1, 7-p2]
                # = det[p1-0, p2-0, 7-0] (adding rows), with the permutation sign.
                for p in range(6):
                    if p == 0:
                        d1 = (1, 0, 0); d2 = (1, 1, 0); sg = 1.0   # noqa: E702
                    elif p == 1:
                        d1 = (0, 1, 0); d2 = (1, 1, 0); sg = -1.0  # noqa: E702
                    elif p == 2:
                        d1 = (0, 1, 0); d2 = (0, 1, 1); sg = 1.0   # noqa: E702
                    elif p == 3:
                        d1 = (0, 0, 1); d2 = (0, 1, 1); sg = -1.0  # noqa: E702
                    elif p == 4:
                        d1 = (0, 0, 1); d2 = (1, 0, 1); sg = 1.0   # noqa: E702
                    else:
                        d1 = (1, 0, 0); d2 = (1, 0, 1); sg = -1.0  # noqa: E702
                    px = x[i + d1[0], j + d1[1], k + d1[2], 0] - x0
                    py = x[i + d1[0], j + d1[1], k + d1[2], 1] - y0
                    pz = x[i + d1[0], j + d1[1], k + d1[2], 2] - z0
                    qx = x[i + d2[0], j + d2[1], k + d2[2], 0] - x0
                    qy = x[i + d2[0], j + d2[1], k + d2[2], 1] - y0
                    qz = x[i + d2[0], j + d2[1], k + d2[2], 2] - z0
                    det = px * (qy * az - qz * ay) - py * (qx * az - qz * ax) + pz * (qx * ay - qy * ax)
                    v += sg * det
                out[i, j, k] = v / 6.0


@pjit
def _quad_areas(x, out):
    ni, nj = x.shape[0], x.shape[1]
    for j in prange(nj - 1):
        for i in range(ni - 1):
            d1x = x[i + 1, j + 1, 0, 0] - x[i, j, 0, 0]
            d1y = x[i + 1, j + 1, 0, 1] - x[i, j, 0, 1]
            d2x = x[i, j + 1, 0, 0] - x[i + 1, j, 0, 0]
            d2y = x[i, j + 1, 0, 1] - x[i + 1, j, 0, 1]
            out[i, j, 0] = 0.5 * (d1x * d2y - d1y * d2x)


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
    xyz = block.xyz if isinstance(block, Block) else np.asarray(block, dtype=np.float64)
    ni, nj, nk = xyz.shape[:3]
    if ndim is None:
        ndim = 2 if nk == 1 else 3
    if ndim == 2:
        out = np.empty((max(ni - 1, 0), max(nj - 1, 0), 1), order="F")
        if out.size:
            _quad_areas(xyz, out)
        return out
    out = np.empty((max(ni - 1, 0), max(nj - 1, 0), max(nk - 1, 0)), order="F")
    if out.size:
        _hex_volumes(xyz, out)
    return out


def _orientation(vol: np.ndarray) -> float:
    """+1 or -1: the sign of the block's total volume (its handedness)."""
    return -1.0 if vol.sum() < 0.0 else 1.0


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


def volume_ratio_summary(grid: Grid, reference: Grid) -> dict:
    """Number of negative cells and the smallest cell-volume ratio to ``reference``.

    Returns
    -------
    dict with keys ``negative`` (int), ``min_ratio`` (float) and ``where``
    ((block, i, j, k) 0-based of the smallest ratio).
    """
    neg = 0
    best = (np.inf, None)
    for b, (blk, ref) in enumerate(zip(grid, reference)):
        v = cell_volumes(blk, grid.ndim)
        vr = cell_volumes(ref, grid.ndim)
        ok = vr != 0.0
        ratio = np.full(v.shape, np.inf)
        ratio[ok] = v[ok] / vr[ok]
        neg += int(np.count_nonzero(ratio <= 0.0))
        if ratio.size:
            m = int(np.argmin(ratio))
            if ratio.flat[m] < best[0]:
                ijk = np.unravel_index(m, ratio.shape)
                best = (float(ratio.flat[m]), (b, *map(int, ijk)))
    return {"negative": neg, "min_ratio": best[0], "where": best[1]}


# ------------------------------------------------------------ near-wall orthogonality
def _wall_specs(grid: Grid, walls):
    from .spec import as_patch_specs
    return [spec.resolve(grid) for spec in as_patch_specs(walls, "walls")]


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
        NaN at degenerate wall points (collapsed edges, zero-length lines).
        The wall normal comes from central differences of the patch points,
        one-sided on the patch edges (first order: robust at sharp trailing
        edges, where second-order one-sided differences overshoot; on a
        curved wall the edge values are off by about half the turning angle
        of the last wall interval, an error a comparison with a reference
        shares).
    """
    from .deform import _face_ijk
    from .grid import FACES

    layers = int(layers)
    if layers < 1:
        raise ValueError(f"layers must be >= 1, got {layers}")
    out = []
    for spec in _wall_specs(grid, walls):
        blk = grid[spec.block]
        d, side = divmod(FACES.index(spec.face), 2)
        nl = min(layers, blk.dims[d] - 1)
        ijk = _face_ijk(blk.dims, spec.face, spec.range)
        x = blk.xyz
        w = x[ijk[..., 0], ijk[..., 1], ijk[..., 2]]
        nrm = _patch_normals(w, grid.ndim)
        ang = np.full(w.shape[:2] + (layers,), np.nan)
        step = -1 if side else 1
        for lay in range(nl):
            a = ijk.copy()
            b = ijk.copy()
            a[..., d] += step * lay
            b[..., d] += step * (lay + 1)
            e = x[b[..., 0], b[..., 1], b[..., 2]] - x[a[..., 0], a[..., 1], a[..., 2]]
            # atan2 of |n x e| and |n . e|: accurate near 0 deg, where arccos is not
            cr = np.linalg.norm(np.cross(nrm, e), axis=-1)
            dt = np.abs(np.einsum("abc,abc->ab", nrm, e))
            a_l = np.degrees(np.arctan2(cr, dt))
            a_l[np.linalg.norm(e, axis=-1) == 0.0] = np.nan
            ang[..., lay] = a_l
        out.append(ang)
    return out


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
