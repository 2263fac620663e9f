"""The coupling interface of the Deformer: the wall in the solver's terms."""

from __future__ import annotations

import numpy as np
import pytest

from tfi_quat.deform import Deformer
from tfi_quat.grid import face_axes

import _deform_grids as G

CASES = {
    "o-grid": G.o_grid,
    "two-block": G.two_block_o,
    "o-grid-3d": G.o_grid_3d,
    "box-pair": G.box_pair,
}


@pytest.fixture(scope="module", params=sorted(CASES))
def deformer(request):
    grid, walls, sym, fixed = CASES[request.param]()
    return Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)


def test_surface_ids_list_every_wall_copy_patch_by_patch_in_fortran_order(deformer):
    ids = deformer.surface_ids()
    grid = deformer.grid
    assert ids.dtype == np.int64 and ids.shape[1] == 4
    walls = [p for p in deformer.connectivity.patches if p.kind == "wall"]
    row = 0
    for p in walls:
        spec = p.spec.resolve(grid)
        (a0, a1), (b0, b1) = spec.range
        d, a, b = face_axes(spec.face)
        n = (a1 - a0 + 1) * (b1 - b0 + 1)
        part = ids[row:row + n]
        assert np.all(part[:, 0] == spec.block)
        dims = grid[spec.block].dims
        assert np.all(part[:, 1 + d] == (0 if spec.face.endswith("min") else dims[d] - 1))
        # the first running index fastest
        want_a = np.tile(np.arange(a0, a1 + 1), b1 - b0 + 1)
        want_b = np.repeat(np.arange(b0, b1 + 1), a1 - a0 + 1)
        assert np.array_equal(part[:, 1 + a], want_a)
        assert np.array_equal(part[:, 1 + b], want_b)
        row += n
    assert row == ids.shape[0]
    if grid.ndim == 2:
        assert np.all(ids[:, 3] == 0)


def test_surface_points_are_the_grid_points_and_cover_every_wall_point(deformer):
    ids = deformer.surface_ids()
    pts = deformer.surface_points()
    for r, (b, i, j, k) in enumerate(ids):
        assert np.array_equal(pts[r], deformer.grid[b].xyz[i, j, k])
    distinct = np.unique(deformer.wall_points(), axis=0)
    assert np.array_equal(np.unique(pts, axis=0), distinct)


def test_surface_ids_are_a_copy():
    grid, walls, sym, fixed = G.o_grid()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed)
    ids = d.surface_ids()
    ids[:] = -1
    assert np.all(d.surface_ids() >= 0)
