"""Face geometry of tfi_quat.grid against a brute-force oracle: slices of an index array."""

from __future__ import annotations

import doctest

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import tfi_quat.grid
from tfi_quat import Block, GridValueError
from tfi_quat.grid import (FACES, face_axes, face_axis, face_cells, face_ijk, face_index, face_layer, face_shape,
                           faces_of)

from conftest import sheared_box

# the oracle: each face written out by hand as a slice of an array indexed (i, j, k)
SLICE = {"imin": lambda a: a[0], "imax": lambda a: a[-1],
         "jmin": lambda a: a[:, 0], "jmax": lambda a: a[:, -1],
         "kmin": lambda a: a[:, :, 0], "kmax": lambda a: a[:, :, -1]}
NORMAL = {"imin": (0, 0), "imax": (0, 1), "jmin": (1, 0), "jmax": (1, 1), "kmin": (2, 0), "kmax": (2, 1)}


def index_array(shape):
    """(n0, n1, n2, 3) int64: every entry holds its own (i, j, k)."""
    return np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1)


dims_st = st.tuples(st.integers(1, 6), st.integers(1, 6), st.integers(1, 6))
face_st = st.sampled_from(FACES)


@st.composite
def face_range(draw):
    """(dims, face, range) with a range inside the face."""
    dims = draw(dims_st)
    face = draw(face_st)
    na, nb = SLICE[face](index_array(dims)).shape[:2]
    a0 = draw(st.integers(0, na - 1))
    a1 = draw(st.integers(a0, na - 1))
    b0 = draw(st.integers(0, nb - 1))
    b1 = draw(st.integers(b0, nb - 1))
    return dims, face, ((a0, a1), (b0, b1))


@given(dims=dims_st, face=face_st)
def test_whole_face_indices_are_the_slice_of_an_index_array(dims, face):
    want = SLICE[face](index_array(dims))
    got = face_ijk(dims, face)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, want)
    assert face_shape(dims, face) == want.shape[:2]
    assert face_ijk(dims, FACES.index(face)).tolist() == want.tolist()     # a face number works too


@given(face_range())
def test_face_range_indices_are_the_slice_of_the_face(case):
    dims, face, ((a0, a1), (b0, b1)) = case
    want = SLICE[face](index_array(dims))[a0:a1 + 1, b0:b1 + 1]
    np.testing.assert_array_equal(face_ijk(dims, face, ((a0, a1), (b0, b1))), want)


@given(dims=dims_st, face=face_st, depth=st.integers(0, 5))
def test_axes_and_layers_match_the_oracle(dims, face, depth):
    d, side = NORMAL[face]
    assert face_axis(face) == (d, side) and face_index(face) == 2 * d + side
    normal, a, b = face_axes(face)
    assert normal == d and (a, b) == tuple(m for m in range(3) if m != d)
    ids = SLICE[face](index_array(dims))
    # the normal index is constant on the face; the running ones count along the face's axes
    assert set(ids[..., d].ravel().tolist()) == {face_layer(dims, face)}
    np.testing.assert_array_equal(ids[..., a], np.arange(dims[a])[:, None] + 0 * ids[..., a])
    np.testing.assert_array_equal(ids[..., b], np.arange(dims[b])[None, :] + 0 * ids[..., b])
    if depth < dims[d]:
        inner = index_array(dims)
        inner = inner[(slice(None),) * d + (slice(depth, None) if side == 0 else slice(None, dims[d] - depth),)]
        assert set(SLICE[face](inner)[..., d].ravel().tolist()) == {face_layer(dims, face, depth)}


@given(face_range(), st.integers(0, 4))
def test_face_cells_select_the_cells_next_to_the_range(case, depth):
    dims, face, ((a0, a1), (b0, b1)) = case
    d, side = NORMAL[face]
    cshape = tuple(max(n - 1, 1) for n in dims)          # one cell along a dimension of one point
    if depth >= cshape[d]:
        return
    cells = index_array(cshape)
    got = cells[face_cells(dims, face, ((a0, a1), (b0, b1)), depth)]
    # brute force: every cell in the layer whose running indices lie in the range's cells
    layer = depth if side == 0 else cshape[d] - 1 - depth
    run = [m for m in range(3) if m != d]
    lo_hi = [(a0, a1), (b0, b1)]
    mask = cells[..., d] == layer
    for m, (lo, hi) in zip(run, lo_hi):
        mask &= (cells[..., m] >= lo) & (cells[..., m] < hi) if dims[m] > 1 else cells[..., m] == 0
    want = cells[mask]                                   # C order: first running index slowest
    assert got.shape[:2] == (a1 - a0 if dims[run[0]] > 1 else 1, b1 - b0 if dims[run[1]] > 1 else 1)
    np.testing.assert_array_equal(got.reshape(-1, 3), want)


def test_face_ijk_addresses_block_face():
    b = Block(sheared_box(5, 4, 3))
    for f in FACES:
        ijk = face_ijk(b.dims, f)
        np.testing.assert_array_equal(b.xyz[ijk[..., 0], ijk[..., 1], ijk[..., 2]], b.face(f))


def test_faces_of():
    assert faces_of(3) == FACES and faces_of(2) == ("imin", "imax", "jmin", "jmax")


@pytest.mark.parametrize("rng", [((0, 4), (0, 2)), ((2, 1), (0, 0)), ((-1, 1), (0, 0)), ((0, 1), (0, 3)),
                                 ((0, 1),), "1-2", 42])
def test_bad_ranges_are_errors_that_name_the_face(rng):
    with pytest.raises(GridValueError, match="face jmin"):
        face_ijk((4, 5, 3), "jmin", rng)
    with pytest.raises(GridValueError, match="face jmin"):
        face_cells((4, 5, 3), "jmin", rng)


def test_unknown_faces_are_errors():
    for bad in ("top", 6, -1, True):
        with pytest.raises(GridValueError, match="face"):
            face_ijk((3, 3, 3), bad)
        with pytest.raises(GridValueError, match="face"):
            face_axis(bad)


def test_docstring_examples():
    res = doctest.testmod(tfi_quat.grid, optionflags=doctest.ELLIPSIS)
    assert res.attempted >= 4 and res.failed == 0
