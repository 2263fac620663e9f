"""Wall-layer blending parameters (tfi_quat.blending)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from tfi_quat import tfi
from tfi_quat.blending import wall_layer_block, wall_layer_line

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
