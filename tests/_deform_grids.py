"""Small canonical grids for the Deformer tests (built with numpy, no generator needed).

Each builder returns ``(grid, walls, symmetry, fixed)`` with patch strings in the
1-based text form.
"""

from __future__ import annotations

import numpy as np

from tfi_quat import Block, Grid


def stretched(n, first, total):
    """n points from 0 to total, geometric with first spacing `first`."""
    if n < 3:
        return np.linspace(0.0, total, n)
    lo, hi = 1.0 + 1e-12, 10.0
    for _ in range(200):
        r = 0.5 * (lo + hi)
        if first * (r ** (n - 1) - 1.0) / (r - 1.0) > total:
            hi = r
        else:
            lo = r
    r = 0.5 * (lo + hi)
    s = np.concatenate([[0.0], first * np.cumsum(r ** np.arange(n - 1))])
    s *= total / s[-1]
    return s


def o_grid(ni=49, nj=25, r0=1.0, r1=15.0, first=2e-3, aspect=1.0):
    """2-D O-grid around a circle (aspect 1) or ellipse; i around, periodic seam i=1 ~ i=ni."""
    t = np.linspace(0.0, 2.0 * np.pi, ni)
    t[-1] = 0.0
    r = r0 + stretched(nj, first, r1 - r0)
    xyz = np.zeros((ni, nj, 1, 3), order="F")
    xyz[:, :, 0, 0] = np.cos(t)[:, None] * r[None, :] * aspect
    xyz[:, :, 0, 1] = np.sin(t)[:, None] * r[None, :]
    xyz[-1] = xyz[0]
    return Grid([Block(xyz, name="ogrid")], ndim=2), ["1:jmin"], [], ["1:jmax"]


def two_block_o(ni=49, nj=25):
    """The O-grid cut in two blocks at i = (ni+1)/2; the second block's i direction is
    reversed, so the interfaces are point-matched with a reversed orientation."""
    g, *_ = o_grid(ni, nj)
    x = g[0].xyz
    m = ni // 2
    a = np.asfortranarray(x[: m + 1])
    b = np.asfortranarray(x[m:][::-1])          # reversed i
    grid = Grid([Block(a, name="upper"), Block(b, name="lower")], ndim=2)
    return grid, ["1:jmin", "2:jmin"], [], ["1:jmax", "2:jmax"]


def channel(ni=41, nj=21, height=1.0, bump=0.1):
    """2-D H-grid channel with a bump on the lower wall; lower wall jmin, the rest fixed."""
    x = np.linspace(-2.0, 2.0, ni)
    yb = bump * np.exp(-8.0 * x ** 2)
    eta = stretched(nj, 0.01, 1.0)
    xyz = np.zeros((ni, nj, 1, 3), order="F")
    xyz[:, :, 0, 0] = x[:, None]
    xyz[:, :, 0, 1] = yb[:, None] + eta[None, :] * (height - yb[:, None])
    return Grid([Block(xyz, name="channel")], ndim=2), ["1:jmin"], [], ["1:jmax", "1:imin", "1:imax"]


def extrude(grid2d: Grid, nk=2, dz=0.1):
    """One-cell-thick (nk=2) 3-D extrusion of a 2-D grid in +z."""
    blocks = []
    for b in grid2d:
        ni, nj, _ = b.dims
        xyz = np.zeros((ni, nj, nk, 3), order="F")
        for k in range(nk):
            xyz[:, :, k, :2] = b.xyz[:, :, 0, :2]
            xyz[:, :, k, 2] = k * dz
        blocks.append(Block(xyz, name=b.name))
    return Grid(blocks, ndim=3)


def o_grid_3d(ni=33, nj=17, nk=2):
    g, *_ = o_grid(ni, nj)
    return extrude(g, nk), ["1:jmin"], ["1:kmin", "1:kmax"], ["1:jmax"]


def box_pair(n=7):
    """Two 3-D blocks side by side in x; the second has its (i, j) axes swapped and k reversed.

    Block 1 spans x in [0, 1], block 2 x in [1, 2]; the wall is the y = 0 face of both
    (jmin of block 1, imin of block 2 after the swap).
    """
    s = np.linspace(0.0, 1.0, n)
    X, Y, Z = np.meshgrid(s, s ** 1.5, s, indexing="ij")
    a = np.stack([X, Y, Z], -1)
    b = np.stack([X + 1.0, Y, Z], -1)
    b = np.transpose(b, (1, 0, 2, 3))[:, :, ::-1]   # i<->j swapped, k reversed
    grid = Grid([Block(np.asfortranarray(a), name="left"), Block(np.asfortranarray(b), name="right")])
    return grid, ["1:jmin", "2:imin"], [], []
