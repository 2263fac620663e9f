"""Numpy reference forms of the cell-validity quantities (an oracle for
``tfi_quat.quality.invalid_cells`` and a check on the generated grids).

Written with whole-array numpy operations, independently of the compiled
row kernels of ``tfi_quat.quality``.
"""

from __future__ import annotations

import numpy as np


def cell_volumes(xyz: np.ndarray) -> np.ndarray:
    """Cell sizes of one block: signed areas (nk == 1) or hexahedron volumes.

    Parameters
    ----------
    xyz : ndarray, shape (ni, nj, nk, 3)

    Returns
    -------
    ndarray of float64
        ``(ni-1, nj-1)`` signed quad areas ``(d/di x d/dj) . e_z`` (half the
        cross product of the diagonals) when ``nk == 1``, else
        ``(ni-1, nj-1, nk-1)`` hexahedron volumes (sum of the six tetrahedra
        of the Kuhn split along the (0,0,0)-(1,1,1) diagonal).
    """
    x = np.asarray(xyz, dtype=np.float64)
    if x.shape[2] == 1:
        p = x[:, :, 0, :2]
        d1 = p[1:, 1:] - p[:-1, :-1]
        d2 = p[:-1, 1:] - p[1:, :-1]
        return 0.5 * (d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0])
    c = {}
    for a in (0, 1):
        for b in (0, 1):
            for g in (0, 1):
                c[a, b, g] = x[a:x.shape[0] - 1 + a, b:x.shape[1] - 1 + b, g:x.shape[2] - 1 + g]
    p0, p7 = c[0, 0, 0], c[1, 1, 1]
    e = [(1, 0, 0), (0, 1, 0), (0, 0, 1)]
    vol = np.zeros(p0.shape[:3])
    for perm, sign in (((0, 1, 2), 1), ((1, 2, 0), 1), ((2, 0, 1), 1),
                       ((0, 2, 1), -1), ((2, 1, 0), -1), ((1, 0, 2), -1)):
        a = e[perm[0]]
        ab = tuple(e[perm[0]][m] + e[perm[1]][m] for m in range(3))
        v1 = c[a] - p0
        v2 = c[ab] - p0
        v3 = p7 - p0
        vol += sign * np.einsum("...i,...i->...", np.cross(v1, v2), v3)
    return vol / 6.0


def corner_jacobians(xyz: np.ndarray) -> np.ndarray:
    """Smallest scaled corner Jacobian of every cell of one block.

    Parameters
    ----------
    xyz : ndarray, shape (ni, nj, nk, 3)

    Returns
    -------
    ndarray of float64, in [-1, 1]
        ``(ni-1, nj-1)`` when ``nk == 1``: per quad, the smallest over its
        four corners of ``(a x b) . e_z / (|a| |b|)``, ``a`` and ``b`` the
        cell's edges along +i and +j at that corner (the sine of the corner
        angle); positive for convex, positively oriented quads only.  Else
        ``(ni-1, nj-1, nk-1)``: per hexahedron, the smallest over its eight
        corners of ``det(a, b, c) / (|a| |b| |c|)``.  A cell of positive
        volume (:func:`cell_volumes`) may still have a negative corner here
        (an arrowhead quad, a twisted hexahedron).  Zero-length edges give 0.
    """
    return corner_dets(xyz, unit=True).min(axis=-1)


def corner_dets(xyz, unit: bool = False) -> np.ndarray:
    """Per cell and corner, the determinant of the cell's edges leaving the corner along
    +i, +j (and +k), numpy whole-array code: ``(ni-1, nj-1, 4)`` when ``nk == 1`` (the
    z-component of ``a x b``), else ``(ni-1, nj-1, nk-1, 8)``.  ``unit``: of the unit
    edges (zero-length edges give 0)."""
    x = np.asarray(xyz, dtype=np.float64)

    def edge(d):
        if not unit:
            return d
        n = np.linalg.norm(d, axis=-1, keepdims=True)
        return d / np.where(n > 0.0, n, np.inf)

    out = []
    if x.shape[2] == 1:
        p = x[:, :, 0, :2]
        di = edge(p[1:] - p[:-1])                     # (ni-1, nj, 2)
        dj = edge(p[:, 1:] - p[:, :-1])               # (ni, nj-1, 2)
        for a in (0, 1):
            for b in (0, 1):
                u = di[:, b:b + dj.shape[1]]
                v = dj[a:a + di.shape[0]]
                out.append(u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0])
        return np.stack(out, -1)
    di = edge(x[1:] - x[:-1])
    dj = edge(x[:, 1:] - x[:, :-1])
    dk = edge(x[:, :, 1:] - x[:, :, :-1])
    ni, nj, nk = x.shape[:3]
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                u = di[:, b:b + nj - 1, c:c + nk - 1]
                v = dj[a:a + ni - 1, :, c:c + nk - 1]
                w = dk[a:a + ni - 1, b:b + nj - 1]
                out.append(np.einsum("...i,...i->...", np.cross(u, v), w))
    return np.stack(out, -1)


def invalid(xyz: np.ndarray, corner_tol: float):
    """``(count, first)`` of the cells that are not valid: area or volume <= 0, or a
    scaled corner Jacobian <= -corner_tol; ``first`` the 0-based index of the first
    in C order (two entries when ``nk == 1``), None when every cell is valid."""
    v, cj = cell_volumes(xyz), corner_jacobians(xyz)
    bad = ~(v > 0.0) | ~(cj > -corner_tol)
    first = tuple(int(c) for c in np.argwhere(bad)[0]) if bad.any() else None
    return int(bad.sum()), first
