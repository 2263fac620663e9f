"""Wall-layer blending parameters (tfi_quat.blending)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tfi_quat import tfi
from tfi_quat.blending import wall_layer_block, wall_layer_line
from tfi_quat.kernels import by_direction

from _deform_grids import stretched


@pytest.fixture(params=["compiled", "python"])
def line_kernel(request):
    from tfi_quat import blending
    if request.param == "compiled":
        return wall_layer_line

    def run(s, length, lam0, lam1):
        s = np.ascontiguousarray(s, dtype=np.float64)
        out = np.empty_like(s)
        blending._layer_line.py_func(s, float(length), float(lam0), float(lam1), out)
        return out
    return run


@given(n=st.integers(3, 80), first=st.floats(1e-6, 0.05), length=st.floats(0.01, 50.0),
       w0=st.floats(0.0, 1.0), w1=st.floats(0.0, 1.0), ell=st.floats(1e-3, 5.0))
def test_exact_ends_and_monotone(n, first, length, w0, w1, ell):
    s = stretched(n, min(first, 0.5 / n), 1.0)
    chi = wall_layer_line(s, length, ell * w0, ell * w1)
    assert chi[0] == 0.0 and chi[-1] == 1.0
    assert np.all(np.diff(chi) >= 0.0)
    assert np.all(np.isfinite(chi))


def test_no_layer_is_the_arclength(line_kernel):
    s = stretched(30, 1e-3, 1.0)
    np.testing.assert_array_equal(line_kernel(s, 10.0, 0.0, 0.0), s)


def test_flat_in_the_layer_and_linear_beyond(line_kernel):
    """A 20-long line with a 0.2 layer at its first end: chi ~ 0 inside, s shifted by <= 0.2 / L outside."""
    s = np.linspace(0.0, 1.0, 2001)
    L, lam = 20.0, 0.2
    chi = line_kernel(s, L, lam, 0.0)
    a = lam / L
    inside = s < 0.1 * a
    assert np.all(chi[inside] < 1e-2 * s[inside] + 1e-300)      # slope ~ (s/a)^2: flat
    assert np.max(np.abs(chi - s)) < 1.2 * a                      # bounded shift
    far = s > 5 * a
    np.testing.assert_allclose(np.diff(chi[far]) / np.diff(s[far]), np.diff(chi[far])[0] / np.diff(s[far])[0],
                               rtol=1e-9)                          # linear beyond the layer


def test_reversing_a_line_swaps_the_ends(line_kernel):
    s = stretched(41, 2e-3, 1.0)
    rs = 1.0 - s[::-1]
    a = line_kernel(s, 5.0, 0.3, 0.05)
    b = line_kernel(rs, 5.0, 0.05, 0.3)
    np.testing.assert_allclose(1.0 - b[::-1], a, atol=1e-13)


def test_short_line_and_zero_length_line(line_kernel):
    s = np.linspace(0, 1, 9)
    chi = line_kernel(s, 1e-3, 1.0, 1.0)          # far shorter than the layer: Hermite-like
    assert chi[0] == 0 and chi[-1] == 1 and np.all(np.diff(chi) > 0)
    np.testing.assert_allclose(chi[4], 0.5, atol=1e-12)
    np.testing.assert_array_equal(line_kernel(s, 0.0, 1.0, 0.0), s)   # collapsed line


def test_block_parameters_are_the_line_parameters():
    """wall_layer_block applies wall_layer_line to every line of every direction."""
    ni, nj, nk = 6, 9, 5
    i, j, k = np.meshgrid(stretched(ni, 0.02, 1.0), stretched(nj, 1e-3, 1.0), np.linspace(0, 1, nk),
                          indexing="ij")
    xyz = np.asfortranarray(np.stack([2.0 * i + 0.1 * j, 3.0 * j ** 1.2, k + 0.2 * i * j], -1))
    s = tfi.arclength(xyz)
    rng = np.random.default_rng(0)
    lam = [rng.uniform(0, 0.5, size=(nj, nk)), rng.uniform(0, 0.5, size=(nj, nk)),
           rng.uniform(0, 0.5, size=(ni, nk)), rng.uniform(0, 0.5, size=(ni, nk)),
           rng.uniform(0, 0.5, size=(ni, nj)), rng.uniform(0, 0.5, size=(ni, nj))]
    out = wall_layer_block(xyz, s, lam)
    assert out.flags.f_contiguous
    for a in range(nj):
        for b in range(nk):
            L = np.linalg.norm(np.diff(xyz[:, a, b], axis=0), axis=1).sum()
            np.testing.assert_allclose(out[:, a, b, 0], wall_layer_line(s[:, a, b, 0], L, lam[0][a, b],
                                                                        lam[1][a, b]), atol=1e-15)
    for a in range(ni):
        for b in range(nj):
            L = np.linalg.norm(np.diff(xyz[a, b, :], axis=0), axis=1).sum()
            np.testing.assert_allclose(out[a, b, :, 2], wall_layer_line(s[a, b, :, 2], L, lam[4][a, b],
                                                                        lam[5][a, b]), atol=1e-15)
    with pytest.raises(Exception, match="face arrays"):
        wall_layer_block(xyz, s, lam[:4])


# ------------------------------------------------ block kernels against a line-by-line reference
@pytest.fixture(autouse=True)
def _quiet_python_kernels():
    """With TFI_QUAT_JIT=0 the kernels run on numpy scalars, which warn where the compiled
    code silently overflows (t / a for the 1e-300 thicknesses below: f = 1 either way)."""
    from tfi_quat import _jit
    if _jit.ENABLED:
        yield
        return
    with np.errstate(over="ignore", divide="ignore", invalid="ignore", under="ignore"):
        yield


def _bits(a):
    return np.ascontiguousarray(a).view(np.uint64)


def assert_same_bits(got, want):
    assert got.shape == want.shape
    diff = _bits(got) != _bits(want)
    if diff.any():
        idx = np.argwhere(diff.reshape(got.shape))
        raise AssertionError(f"{int(diff.sum())} of {got.size} values differ, first at {tuple(idx[0])}: "
                             f"{got[tuple(idx[0])]!r} != {want[tuple(idx[0])]!r}")


def _ref_length(p):
    """Sequential sum of the segment lengths of the points p (n, 3), as the kernels add them."""
    length = 0.0
    for m in range(1, p.shape[0]):
        dx = p[m, 0] - p[m - 1, 0]
        dy = p[m, 1] - p[m - 1, 1]
        dz = p[m, 2] - p[m - 1, 2]
        length += math.sqrt(dx * dx + dy * dy + dz * dz)
    return length


def _lines(dims, d):
    """Index tuples of every line of direction d (with the line as a slice), and its face index."""
    others = [m for m in range(3) if m != d]
    for a in range(dims[others[0]]):
        for b in range(dims[others[1]]):
            idx = [0, 0, 0]
            idx[others[0]], idx[others[1]] = a, b
            idx[d] = slice(None)
            yield tuple(idx), (a, b)


def ref_wall_layer_block(xyz, s, lam, ndim=3):
    """``wall_layer_block`` line by line: lengths in Python, parameters from ``wall_layer_line``."""
    dims = xyz.shape[:3]
    out = np.array(s, dtype=np.float64, order="F")
    for d in range(ndim):
        others = tuple(dims[m] for m in range(3) if m != d)
        l0 = np.asarray(lam[2 * d], dtype=np.float64).reshape(others)
        l1 = np.asarray(lam[2 * d + 1], dtype=np.float64).reshape(others)
        for idx, ab in _lines(dims, d):
            length = _ref_length(xyz[idx])
            out[idx + (d,)] = wall_layer_line(s[idx + (d,)], length, l0[ab], l1[ab])
    return out


def ref_arclength(xyz, rtol=tfi.ZERO_LENGTH_RTOL):
    """``tfi.arclength`` line by line: sequential sums, the zero-length fallback, exact 1 at the end."""
    dims = xyz.shape[:3]
    s = np.empty(xyz.shape, order="F")
    for d in range(3):
        n = dims[d]
        for idx, _ in _lines(dims, d):
            p = xyz[idx]
            if n == 1:
                s[idx + (d,)] = 0.0
                continue
            cum = np.empty(n)
            a = 0.0
            cum[0] = 0.0
            for m in range(1, n):
                dx = p[m, 0] - p[m - 1, 0]
                dy = p[m, 1] - p[m - 1, 1]
                dz = p[m, 2] - p[m - 1, 2]
                a += math.sqrt(dx * dx + dy * dy + dz * dz)
                cum[m] = a
            if not a > rtol * max(abs(p[0, 0]), abs(p[0, 1]), abs(p[0, 2]),
                                  abs(p[-1, 0]), abs(p[-1, 1]), abs(p[-1, 2])):
                cum = np.arange(n, dtype=np.float64)
                a = n - 1.0
            line = cum / a
            line[-1] = 1.0
            s[idx + (d,)] = line
    return s


#: shapes with dims of 1 and 2, more lines than one task of direction i
#: (LINES_PER_TASK) and more than one tile of directions j and k (TILE)
BLOCK_SHAPES = [(1, 1, 1), (1, 4, 3), (4, 1, 3), (5, 4, 1), (2, 2, 2), (2, 7, 1), (1, 2, 6), (3, 4, 2),
                (7, 6, 5), (3, 13, 11), (130, 3, 2), (257, 2, 3), (9, 70, 3)]


def random_block(shape, seed):
    """A curvilinear block with collapsed lines (zero length), repeated points and a tiny line."""
    rng = np.random.default_rng(seed)
    ni, nj, nk = shape
    u = [np.cumsum(rng.uniform(0.1, 1.0, n)) for n in shape]
    i, j, k = np.meshgrid(*u, indexing="ij")
    xyz = np.stack([i + 0.3 * j * np.sin(k), j + 0.2 * k * k, k + 0.1 * i * j], -1)
    xyz += 0.05 * rng.standard_normal(xyz.shape)
    xyz = np.asfortranarray(xyz)
    if ni > 1 and nj > 1 and nk > 1:
        jj, kk = rng.integers(nj), rng.integers(nk)
        xyz[:, jj, kk] = xyz[0, jj, kk]                     # a collapsed line of direction i
        ii, kk = rng.integers(ni), rng.integers(nk)
        xyz[ii, :, kk] = xyz[ii, 0, kk]                     # ... of direction j
        xyz[:, :, 0] = xyz[:1, :1, 0]                       # a collapsed face (a pole): lines of i and j
        ii, jj = rng.integers(ni), rng.integers(nj)
        xyz[ii, jj, 1:] = xyz[ii, jj, 0] + 1e-14 * rng.standard_normal((nk - 1, 3))  # zero-length by rtol
    if nk > 2:
        xyz[:, :, 2] = xyz[:, :, 1]                         # repeated points along k
    return xyz


def random_lam(shape, ndim, seed):
    """Face thicknesses: zero on about half of the lines, some negative, tiny, huge or infinite."""
    rng = np.random.default_rng(seed)
    dims = shape
    lam = []
    for d in range(ndim):
        others = tuple(dims[m] for m in range(3) if m != d)
        for _ in range(2):
            v = rng.uniform(0.0, 3.0, others)
            r = rng.uniform(size=others)
            v[r < 0.5] = 0.0
            v[(r >= 0.5) & (r < 0.55)] = -0.5
            v[(r >= 0.55) & (r < 0.6)] = 1e-300
            v[(r >= 0.6) & (r < 0.65)] = 1e8
            v[(r >= 0.65) & (r < 0.67)] = np.inf
            lam.append(v)
    return lam


@pytest.mark.parametrize("shape", BLOCK_SHAPES)
def test_arclength_is_the_sequential_reference(shape):
    xyz = random_block(shape, 1)
    assert_same_bits(tfi.arclength(xyz), ref_arclength(xyz))
    assert_same_bits(tfi.arclength(xyz, rtol=1e-3), ref_arclength(xyz, rtol=1e-3))


@pytest.mark.parametrize("shape", BLOCK_SHAPES)
def test_block_kernel_is_the_line_reference_bit_for_bit(shape):
    """All of out=None, out=s and a separate out, on tfi.arclength's s and on an arbitrary s."""
    xyz = random_block(shape, 2)
    lam = random_lam(shape, 3, 3)
    rng = np.random.default_rng(4)
    arbitrary = np.asfortranarray(rng.uniform(-0.2, 1.2, xyz.shape))    # not 0 where n == 1 either
    for s in (tfi.arclength(xyz), arbitrary):
        want = ref_wall_layer_block(xyz, s, lam)
        assert_same_bits(wall_layer_block(xyz, s, lam), want)
        out = np.full(xyz.shape, np.nan, order="F")
        got = wall_layer_block(xyz, s, lam, out=out)
        assert got is out
        assert_same_bits(out, want)
        s2 = s.copy(order="F")
        got = wall_layer_block(xyz, s2, lam, out=s2)
        assert got is s2
        assert_same_bits(s2, want)


@pytest.mark.parametrize("shape", [(1, 1), (1, 5), (6, 1), (2, 2), (9, 7), (130, 3), (3, 70)])
def test_patch_kernel_is_the_line_reference_bit_for_bit(shape):
    """ndim=2 on a patch given as (na, nb, 1, 3), as the Deformer passes its patches (1-D lam)."""
    na, nb = shape
    xyz = random_block((na, nb, 1), 5)
    s = np.zeros(xyz.shape, order="F")
    s[:, :, 0, :2] = tfi.arclength_surface(np.ascontiguousarray(xyz[:, :, 0]))
    lam = [v.reshape(-1) for v in random_lam((na, nb, 1), 2, 6)]
    want = ref_wall_layer_block(xyz, s, lam, ndim=2)
    assert_same_bits(wall_layer_block(xyz, s, lam, ndim=2), want)
    s2 = s.copy(order="F")
    wall_layer_block(xyz, s2, lam, ndim=2, out=s2)
    assert_same_bits(s2, want)


def test_ndim_2_on_a_3d_block_keeps_the_third_parameter():
    xyz = random_block((6, 5, 4), 7)
    s = tfi.arclength(xyz)
    lam = random_lam((6, 5, 4), 2, 8)
    got = wall_layer_block(xyz, s, lam, ndim=2)
    assert_same_bits(got, ref_wall_layer_block(xyz, s, lam, ndim=2))
    assert_same_bits(got[..., 2], s[..., 2])


def test_lines_without_layers_are_s_and_two_point_lines_with_two_layers_too():
    """Zero thicknesses leave s (also a non-arclength s); a 2-point line has a zero integral."""
    xyz = random_block((2, 5, 3), 9)
    rng = np.random.default_rng(10)
    s = np.asfortranarray(rng.uniform(0.0, 1.0, xyz.shape))
    zero = [np.zeros((5, 3)), np.zeros((5, 3)), np.zeros((2, 3)), np.zeros((2, 3)),
            np.zeros((2, 5)), np.zeros((2, 5))]
    assert_same_bits(wall_layer_block(xyz, s, zero), s)
    both = [np.ones((5, 3)), np.ones((5, 3))] + zero[2:]
    got = wall_layer_block(xyz, s, both)
    assert_same_bits(got, ref_wall_layer_block(xyz, s, both))
    s = tfi.arclength(xyz)
    got = wall_layer_block(xyz, s, both)
    assert_same_bits(got, ref_wall_layer_block(xyz, s, both))
    assert_same_bits(got[..., 0], s[..., 0])                # s = [0, 1]: g' = 0 at both points


@pytest.mark.parametrize("shape", BLOCK_SHAPES)
def test_fused_arclength_and_layer_is_the_two_calls_bit_for_bit(shape):
    from tfi_quat.blending import wall_layer_arclength
    xyz = random_block(shape, 11)
    for ndim, rtol in ((3, tfi.ZERO_LENGTH_RTOL), (2, tfi.ZERO_LENGTH_RTOL), (3, 1e-3)):
        lam = random_lam(shape, ndim, 12)
        want = ref_wall_layer_block(xyz, ref_arclength(xyz, rtol), lam, ndim=ndim)
        assert_same_bits(wall_layer_arclength(xyz, lam, ndim, rtol=rtol), want)
        out = np.full(xyz.shape, np.nan, order="F")
        assert wall_layer_arclength(xyz, lam, ndim, rtol=rtol, out=out) is out
        assert_same_bits(out, want)


@settings(max_examples=40, deadline=None)
@given(st.tuples(st.integers(1, 12), st.integers(1, 12), st.just(1)), st.integers(0, 2 ** 32 - 1),
       st.sampled_from([0, 1, 2]), st.sampled_from([tfi.ZERO_LENGTH_RTOL, 1e-3, 0.3]))
def test_small_2d_blocks_with_numpy_are_the_compiled_kernels(shape, seed, ndim, rtol):
    """2-D blocks below _ARC_NUMPY_BELOW points take the numpy path (the demo compiles no
    arclength kernel): the same bits as the compiled kernels, with collapsed, tiny and
    repeated lines and zero, negative, tiny, huge and infinite thicknesses."""
    from tfi_quat import blending
    rng = np.random.default_rng(seed)
    xyz = random_block(shape, seed)
    ni, nj = shape[:2]
    xyz[:, rng.integers(nj)] = xyz[rng.integers(ni), rng.integers(nj)]    # a collapsed line of i
    xyz[rng.integers(ni), :] = xyz[rng.integers(ni), rng.integers(nj)]    # ... of j
    i = rng.integers(ni)
    xyz[i, :] = xyz[i, :1] + 1e-14 * rng.standard_normal((nj, 1, 3))      # zero-length by rtol
    if ni > 2:
        xyz[2] = xyz[1]                                                     # repeated points
    lam = random_lam(shape, ndim, seed + 1)
    assert ni * nj < blending._ARC_NUMPY_BELOW
    small = blending.wall_layer_arclength(xyz, lam, ndim, rtol=rtol)
    plain = tfi.arclength(xyz, rtol=rtol)
    below = blending._ARC_NUMPY_BELOW
    try:
        blending._ARC_NUMPY_BELOW = 0                           # the compiled kernels
        assert_same_bits(small, blending.wall_layer_arclength(xyz, lam, ndim, rtol=rtol))
        assert_same_bits(plain, tfi.arclength(xyz, rtol=rtol))
    finally:
        blending._ARC_NUMPY_BELOW = below
    assert_same_bits(plain, ref_arclength(xyz, rtol))           # the independent reference


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0.0, 1.0), min_size=1, max_size=40), st.sampled_from([1e-300, 1e-3, 0.7, 5.0, 1e8]),
       st.sampled_from([0.0, -0.5, 1e-300, 0.01, 0.3, 2.0, 1e8, np.inf]),
       st.sampled_from([0.0, -0.5, 1e-300, 0.05, 0.3, 1e8, np.inf]))
def test_wall_layer_line_with_numpy_is_the_compiled_line(pts, length, lam0, lam1):
    """wall_layer_line runs numpy (the demo compiles no _layer_line): the compiled kernel's bits."""
    from tfi_quat import blending
    s = np.sort(np.array(pts))
    s[0], s[-1] = 0.0, 1.0
    want = np.empty_like(s)
    blending._layer_line(s, length, lam0, lam1, want)
    assert_same_bits(wall_layer_line(s, length, lam0, lam1), want)
    assert_same_bits(wall_layer_line(s[::-1] * 0.5, length, lam0, lam1),      # not an arclength
                     _compiled_line(blending, s[::-1] * 0.5, length, lam0, lam1))


def _compiled_line(blending, s, length, lam0, lam1):
    out = np.empty_like(s)
    blending._layer_line(np.ascontiguousarray(s), length, lam0, lam1, out)
    return out


def test_block_kernels_uncompiled_equal_compiled():
    """The drivers' own code (py_func: what TFI_QUAT_JIT=0 runs) gives the compiled bits."""
    from tfi_quat import blending
    xyz = random_block((130, 4, 3), 13)
    s = tfi.arclength(xyz)
    lam = random_lam((130, 4, 3), 3, 14)
    dims = xyz.shape[:3]
    for d in range(3):
        others = tuple(dims[m] for m in range(3) if m != d)
        a, b = s.copy(order="F"), s.copy(order="F")
        layer = (blending._layer_dir_i, blending._layer_dir_jk)
        by_direction(*layer, d, xyz, s, lam[2 * d], lam[2 * d + 1], a)
        by_direction(*(k.py_func for k in layer), d, xyz, s, lam[2 * d], lam[2 * d + 1], b)
        assert_same_bits(a, b)
        a[...] = np.nan
        b[...] = np.nan
        fused = (blending._arc_layer_i, blending._arc_layer_jk)
        by_direction(*fused, d, xyz, tfi.ZERO_LENGTH_RTOL, lam[2 * d], lam[2 * d + 1], a)
        by_direction(*(k.py_func for k in fused), d, xyz, tfi.ZERO_LENGTH_RTOL, lam[2 * d],
                     lam[2 * d + 1], b)
        assert_same_bits(a[..., d], b[..., d])
        assert others == lam[2 * d].shape


def test_fused_validates_arguments():
    from tfi_quat.blending import wall_layer_arclength
    xyz = random_block((3, 4, 5), 15)
    lam = random_lam((3, 4, 5), 3, 16)
    with pytest.raises(Exception, match="face arrays"):
        wall_layer_arclength(xyz, lam[:4])
    with pytest.raises(Exception, match="Fortran"):
        wall_layer_arclength(np.ascontiguousarray(xyz), lam)
    with pytest.raises(Exception, match="out"):
        wall_layer_arclength(xyz, lam, out=np.empty(xyz.shape))
