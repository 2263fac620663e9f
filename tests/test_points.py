"""Coincident point pairs (tfi_quat._points.close_pairs) against brute force and cKDTree.

The reference is all pairs ``i < j`` with ``dx*dx + dy*dy + dz*dz <= tol*tol``
in float64 (the test cKDTree and close_pairs make), in lexicographic order.
Against brute force the sets must be identical bit for bit, including pairs
planted within a few units in the last place of ``tol`` along the sweep
direction (where a projection window without a rounding margin loses pairs).
Against cKDTree, whose node-level acceptance may differ at the last ulp, the
planted distances stay clear of ``tol`` by a relative 1e-6.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from tfi_quat import _points
from tfi_quat import generate as gen
from tfi_quat._points import DIRECTION, close_pairs

EMPTY = np.empty((0, 2), dtype=np.int64)


# ---------------------------------------------------------------- references
def brute(P, tol):
    """All pairs i < j passing cKDTree's test, lexicographic."""
    P = np.asarray(P, dtype=np.float64)
    n = len(P)
    if n < 2:
        return EMPTY
    d = P[:, None, :] - P[None, :, :]
    d2 = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]
    hit = np.triu(d2 <= tol * tol, k=1)
    return np.argwhere(hit).astype(np.int64)        # argwhere is row-major: lexicographic


def kdtree(P, tol):
    pairs = cKDTree(P).query_pairs(tol, output_type="ndarray").astype(np.int64)
    if len(pairs) == 0:
        return EMPTY
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def check_form(out, n):
    assert isinstance(out, np.ndarray)
    assert out.dtype == np.int64 and out.ndim == 2 and out.shape[1] == 2
    if len(out):
        assert out.min() >= 0 and out.max() < n
        assert np.all(out[:, 0] < out[:, 1])
        key = out[:, 0] * n + out[:, 1]
        assert np.all(np.diff(key) > 0), "rows not strictly lexicographic (or repeated)"


def same(out, ref):
    if not np.array_equal(out, ref):
        a = set(map(tuple, out.tolist()))
        b = set(map(tuple, ref.tolist()))
        raise AssertionError(f"{len(out)} vs {len(ref)} pairs; extra {sorted(a - b)[:5]}, "
                             f"missing {sorted(b - a)[:5]}")


@pytest.fixture
def spy(monkeypatch):
    """Counts calls of the cKDTree fallback."""
    calls = []
    real = _points._kdtree_pairs

    def wrapped(P, tol):
        calls.append(len(P))
        return real(P, tol)

    monkeypatch.setattr(_points, "_kdtree_pairs", wrapped)
    return calls


def _unit_vectors(rng, k):
    v = rng.normal(size=(k, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def planted_cloud(seed, n0, scale, offset, rel_tol, n_plant, rel_dists, along_direction):
    """Random points with partners planted at ``tol * r`` for ``r`` in ``rel_dists`` (0: exact copy)."""
    rng = np.random.default_rng(seed)
    base = offset + scale * rng.uniform(-1.0, 1.0, size=(n0, 3))
    tol = rel_tol * scale
    extra = []
    for _ in range(n_plant):
        a = base[rng.integers(n0)]
        r = rel_dists[rng.integers(len(rel_dists))]
        v = DIRECTION if along_direction else _unit_vectors(rng, 1)[0]
        extra.append(a + (tol * r) * v)
    P = np.concatenate([base, np.array(extra).reshape(-1, 3)])
    return P[rng.permutation(len(P))], tol


# ---------------------------------------------------------------- against brute force
# relative distances right at tol: a few ulps either side, and clearly either side
ULPS = [1.0 + k * np.finfo(float).eps for k in range(-6, 7)]
NEAR = [0.0, 0.0, 0.5, 1.0 - 1e-6, 1.0 + 1e-6, 1.0 - 1e-3, 1.0 + 1e-3, 2.0] + ULPS


@given(seed=st.integers(0, 2**32 - 1), n0=st.integers(1, 60),
       scale_exp=st.integers(-150, 100), offset=st.sampled_from([0.0, 1.0, -7.5, 1e3, 1e6]),
       rel_tol=st.sampled_from([0.0, 1e-12, 1e-10, 1e-6, 1e-3, 0.05, 0.3]),
       n_plant=st.integers(0, 40), along=st.booleans())
def test_planted_pairs_match_brute_force(seed, n0, scale_exp, offset, rel_tol, n_plant, along):
    scale = 10.0 ** scale_exp
    P, tol = planted_cloud(seed, n0, scale, offset * scale, rel_tol, n_plant, NEAR, along)
    out = close_pairs(P, tol)
    check_form(out, len(P))
    same(out, brute(P, tol))


@given(seed=st.integers(0, 2**32 - 1), k=st.integers(-8, 8), n=st.integers(2, 40),
       scale_exp=st.integers(-150, 150), spread=st.sampled_from([0.0, 1.0, 1e3]))
def test_ulp_boundary_along_direction(seed, k, n, scale_exp, spread):
    """Pairs ``tol * (1 + k eps)`` apart along the sweep direction: the worst case for the window."""
    rng = np.random.default_rng(seed)
    scale = 10.0 ** scale_exp
    tol = scale * rng.uniform(0.5, 2.0)
    a = scale * spread * rng.uniform(-1.0, 1.0, size=(n, 3))
    b = a + (tol * (1.0 + k * np.finfo(float).eps)) * DIRECTION
    P = np.concatenate([a, b])
    out = close_pairs(P, tol)
    check_form(out, len(P))
    same(out, brute(P, tol))


@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 80), dup=st.integers(0, 30))
def test_tol_zero_finds_exact_duplicates_only(seed, n, dup):
    rng = np.random.default_rng(seed)
    P = rng.uniform(-1, 1, size=(n, 3))
    if n:
        idx = rng.integers(n, size=dup)
        near = P[idx].copy()
        near[::2] = np.nextafter(near[::2], np.inf)       # one ulp off: not a duplicate
        P = np.concatenate([P, P[idx], near])
    out = close_pairs(P, 0.0)
    check_form(out, len(P))
    same(out, brute(P, 0.0))
    for i, j in out:
        assert np.array_equal(P[i], P[j])


@given(seed=st.integers(0, 2**32 - 1), shape=st.tuples(st.integers(1, 7), st.integers(1, 7), st.integers(1, 7)),
       rel_tol=st.sampled_from([0.0, 1e-10, 0.3, 0.99, 1.0, 1.001, 1.5, 2.5]),
       rotate=st.booleans(), copies=st.integers(1, 3))
def test_lattices_match_brute_force(seed, shape, rel_tol, rotate, copies):
    """Regular lattices (many equal or nearly equal projections), overlapping copies, ties at tol."""
    rng = np.random.default_rng(seed)
    h = float(rng.uniform(0.01, 10.0))
    ii, jj, kk = np.meshgrid(*(np.arange(s) for s in shape), indexing="ij")
    L = h * np.stack([ii, jj, kk], axis=-1).reshape(-1, 3).astype(float)
    if rotate:
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        L = L @ q.T
    parts = [L]
    for _ in range(copies - 1):                         # a second block sharing a face / the whole lattice
        shift = h * rng.integers(-2, 3, size=3) * rng.integers(0, 2, size=3)
        parts.append(L + shift)
    P = np.concatenate(parts)
    P = P[rng.permutation(len(P))]
    tol = rel_tol * h
    out = close_pairs(P, tol)
    check_form(out, len(P))
    same(out, brute(P, tol))


@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 60), budget=st.sampled_from([0, 1, 3, 10]),
       rel_tol=st.sampled_from([0.0, 1e-6, 0.2, 1.0]))
def test_small_budgets_same_answer(seed, n, budget, rel_tol):
    rng = np.random.default_rng(seed)
    P = rng.uniform(-1, 1, size=(n, 3))
    P = np.concatenate([P, P[: n // 3], P[: n // 4] + 1e-3 * rng.normal(size=(n // 4, 3))])
    out = close_pairs(P, rel_tol, budget=budget)
    check_form(out, len(P))
    same(out, brute(P, rel_tol))


@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 3000), decades=st.integers(0, 300),
       ties=st.booleans())
def test_sort_by_projection_skewed(seed, n, decades, ties):
    """The bucket sort on skewed keys (most in one coarse, then one fine bucket) and ties."""
    rng = np.random.default_rng(seed)
    p = np.sign(rng.uniform(-1, 1, n)) * 10.0 ** rng.uniform(-decades, 0, n) if decades else rng.normal(size=n)
    if ties and n:
        p = np.round(p * 4) / 4
    pmin, pmax = (p.min(), p.max()) if n else (0.0, 0.0)
    order, ps = _points._sort_by_projection(p, pmin, pmax)
    assert np.array_equal(np.sort(order), np.arange(n))
    assert np.array_equal(ps, p[order])
    assert np.all(np.diff(ps) >= 0)


@given(seed=st.integers(0, 2**32 - 1), n0=st.integers(50, 400), decades=st.integers(1, 12),
       rel_tol=st.sampled_from([1e-14, 1e-10, 1e-6]))
def test_geometric_clustering_matches_brute_force(seed, n0, decades, rel_tol):
    """Points clustered towards one spot over many decades (wall spacing): skewed buckets."""
    rng = np.random.default_rng(seed)
    r = 10.0 ** rng.uniform(-decades, 0, n0)
    P = r[:, None] * _unit_vectors(rng, n0) + np.array([0.5, 0.25, -1.0])
    k = n0 // 3
    P = np.concatenate([P, P[:k] + (rel_tol * r[:k] * rng.choice([0.5, 0.999, 1.001, 2.0], k))[:, None]
                        * _unit_vectors(rng, k)])
    tol = rel_tol * float(np.median(r))
    out = close_pairs(P, tol)
    check_form(out, len(P))
    same(out, brute(P, tol))


# ---------------------------------------------------------------- against cKDTree
@given(seed=st.integers(0, 2**32 - 1), n0=st.integers(500, 5000),
       rel_tol=st.sampled_from([1e-10, 1e-6, 1e-3]), frac=st.sampled_from([0.0, 0.1, 0.5, 1.0]),
       offset=st.sampled_from([0.0, 10.0]))
def test_moderate_clouds_match_ckdtree(seed, n0, rel_tol, frac, offset):
    clear = [0.0, 0.3, 1.0 - 1e-6, 1.0 + 1e-6, 1.0 - 1e-2, 1.0 + 1e-2, 3.0]
    P, tol = planted_cloud(seed, n0, 1.0, offset, rel_tol, int(frac * n0), clear, along_direction=False)
    out = close_pairs(P, tol)
    check_form(out, len(P))
    same(out, kdtree(P, tol))


@given(seed=st.integers(0, 2**32 - 1), shape=st.tuples(st.integers(4, 30), st.integers(4, 30), st.integers(1, 12)),
       rel_tol=st.sampled_from([1e-10, 0.25, 0.7]), rotate=st.booleans())
def test_structured_blocks_match_ckdtree(seed, shape, rel_tol, rotate):
    """Two abutting structured blocks (shared face), only their boundary points, like the Deformer's set."""
    rng = np.random.default_rng(seed)
    ni, nj, nk = shape
    u = np.linspace(0.0, 1.0, ni) ** 1.5
    v = np.linspace(0.0, 1.0, nj)
    w = np.geomspace(1e-3, 1.0, nk) if nk > 1 else np.zeros(1)
    X = np.stack(np.meshgrid(u, v, w, indexing="ij"), axis=-1)
    X[..., 2] += 0.1 * np.sin(3 * X[..., 1])
    blocks = [X, X + np.array([1.0, 0.0, 0.0])]          # block 2's face i=0 is block 1's face i=-1
    pts = []
    for B in blocks:
        mask = np.zeros(B.shape[:3], dtype=bool)
        mask[[0, -1]] = True
        mask[:, [0, -1]] = True
        mask[:, :, [0, -1]] = True
        pts.append(B[mask])
    P = np.concatenate(pts)
    if rotate:
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        P = P @ q.T
    h = 1.0 / max(ni, nj, nk, 2)
    tol = rel_tol * h
    out = close_pairs(P, tol)
    check_form(out, len(P))
    ref = kdtree(P, tol)
    same(out, ref)
    assert len(ref) >= nj * nk                            # the shared face at least


@pytest.mark.parametrize("make", [
    lambda: gen.wing(ni=33, nj=12, nk_wing=11, nk_cap=5, nk_out=7),   # interfaces, wake cut, collapsed sheet
    lambda: gen.airfoil(topology="C", ni=65, nj=17),                  # wake cut
    lambda: gen.cylinder(ni=33, nj=9),                                # periodic seam
], ids=["wing", "c-airfoil", "o-cylinder"])
def test_generated_grid_boundaries(make, spy):
    grid = make()
    pts = []
    for blk in grid:
        x = blk.xyz
        mask = np.zeros(x.shape[:3], dtype=bool)
        mask[[0, -1]] = True
        mask[:, [0, -1]] = True
        mask[:, :, [0, -1]] = True
        pts.append(x[mask])
    P = np.concatenate(pts)
    tol = 1e-10 * np.linalg.norm(P.max(0) - P.min(0))
    out = close_pairs(P, tol)
    ref = kdtree(P, tol)
    assert len(ref) > 0
    same(out, ref)
    assert spy == [], "the sweep fell back on a grid boundary"


# ---------------------------------------------------------------- clusters and the fallback
@pytest.mark.parametrize("k", [2, 50, 1500, 3000])
def test_pole_cluster_all_pairs_without_fallback(k, spy):
    """``k`` copies of one point among others: ``k (k - 1) / 2`` pairs, more than points; no fallback."""
    rng = np.random.default_rng(k)
    others = rng.uniform(-1, 1, size=(200, 3))
    pole = np.tile([[0.25, -0.5, 0.125]], (k, 1))
    P = np.concatenate([others, pole, others[:20]])
    P = P[rng.permutation(len(P))]
    out = close_pairs(P, 1e-9)
    check_form(out, len(P))
    assert len(out) == k * (k - 1) // 2 + 20
    same(out, kdtree(P, 1e-9))
    assert spy == []


def test_near_pole_cluster_within_tol(spy):
    """A pole whose copies scatter within tol / 4 (rounding in collapsed faces)."""
    rng = np.random.default_rng(7)
    tol = 1e-8
    pole = np.array([1.0, 2.0, 3.0]) + (tol / 4) * _unit_vectors(rng, 800) * rng.uniform(0, 1, (800, 1))
    P = np.concatenate([rng.uniform(-5, 5, size=(500, 3)), pole])
    out = close_pairs(P, tol)
    assert len(out) == 800 * 799 // 2
    same(out, kdtree(P, tol))
    assert spy == []


def test_false_candidates_trigger_fallback(spy):
    """Many points with equal projections but far apart: the sweep gives up, cKDTree answers."""
    rng = np.random.default_rng(3)
    # a plane perpendicular to DIRECTION: every projection equal, no pair within tol
    e1 = np.cross(DIRECTION, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(DIRECTION, e1)
    n = 600
    ab = rng.uniform(-1, 1, size=(n, 2))
    P = ab[:, :1] * e1 + ab[:, 1:] * e2
    P = np.concatenate([P, P[:10]])
    out = close_pairs(P, 1e-6)
    assert len(spy) == 1, "quadratic false candidates must fall back"
    same(out, kdtree(P, 1e-6))
    same(out, brute(P, 1e-6))
    spy.clear()
    out2 = close_pairs(P, 1e-6, budget=10 ** 9)          # a huge budget: the sweep does it all
    assert spy == []
    same(out2, out)


def test_forced_fallback_budget_zero(spy):
    rng = np.random.default_rng(11)
    P = rng.uniform(-1, 1, size=(300, 3))
    tol = 0.05
    P = np.concatenate([P, P[:30] + 0.5 * tol * _unit_vectors(rng, 30)])
    ref = brute(P, tol)
    same(close_pairs(P, tol), ref)
    assert spy == []
    same(close_pairs(P, tol, budget=0), ref)
    assert len(spy) == 1


def test_budget_counts_only_failed_comparisons(spy):
    """Exact duplicates only: no comparison fails, so even budget 0 never falls back."""
    rng = np.random.default_rng(5)
    P = rng.uniform(-1, 1, size=(100, 3))
    P = np.concatenate([P, P, P])
    out = close_pairs(P, 1e-12, budget=0)
    assert spy == []
    assert len(out) == 300
    same(out, brute(P, 1e-12))


# ---------------------------------------------------------------- edge cases
def test_empty_and_single():
    for P in (np.empty((0, 3)), np.zeros((1, 3)), [[1.0, 2.0, 3.0]]):
        out = close_pairs(P, 1.0)
        assert out.shape == (0, 2) and out.dtype == np.int64
    out = close_pairs(np.zeros((2, 3)), 0.0)
    assert out.tolist() == [[0, 1]]


def test_all_points_identical():
    out = close_pairs(np.ones((40, 3)), 0.0)
    same(out, np.argwhere(np.triu(np.ones((40, 40), dtype=bool), k=1)))


def test_signed_zero_is_a_duplicate():
    P = np.array([[0.0, 0.0, 0.0], [-0.0, 0.0, -0.0], [1.0, 0.0, 0.0]])
    assert close_pairs(P, 0.0).tolist() == [[0, 1]]


def test_inputs_converted():
    rng = np.random.default_rng(2)
    P = rng.integers(0, 4, size=(60, 3))                 # ints, many duplicates
    ref = brute(P.astype(float), 0.0)
    same(close_pairs(P, 0), ref)
    same(close_pairs(np.asfortranarray(P.astype(float)), 0.0), ref)
    same(close_pairs(P.astype(float)[::-1][::-1], np.float32(0.0)), ref)
    same(close_pairs(P.astype(float), np.array(0.0)), ref)
    big = np.zeros((120, 6))
    big[::2, ::2] = P
    same(close_pairs(big[::2, ::2], 0.0), ref)           # non-contiguous view


def test_huge_coordinates(spy):
    """Projections that would overflow are scaled (cKDTree refuses such sets)."""
    P = np.array([[1e308, 0.0, 0.0], [-1e308, 0.0, 0.0], [1e308, 0.0, 0.0], [1e308, 1.0, 0.0],
                  [-1.7e308, -1.7e308, 1.7e308], [-1.7e308, -1.7e308, 1.7e308], [0.0, 0.0, 0.0]])
    out = close_pairs(P, 0.5)
    assert out.tolist() == [[0, 2], [4, 5]]
    assert spy == []
    with np.errstate(over="ignore", invalid="ignore"):
        same(out, brute(P, 0.5))


def test_tiny_tol_underflow_semantics():
    """tol**2 underflows to 0: pairs whose squared distance underflows pass, as in cKDTree."""
    P = np.array([[0.0, 0.0, 0.0], [1e-170, 0.0, 0.0], [1e-165, 0.0, 0.0], [1e-150, 0.0, 0.0]])
    out = close_pairs(P, 1e-170)
    same(out, brute(P, 1e-170))
    assert out.tolist() == [[0, 1], [0, 2], [1, 2]]
    # a cloud so small that the rounding margin is below the pairs' projection gap
    P = np.array([[0.0, 0.0, 0.0], [1e-170, 0.0, 0.0], [1e-160, 0.0, 0.0]])
    out = close_pairs(P, 1e-175)
    same(out, brute(P, 1e-175))
    assert out.tolist() == [[0, 1]]


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("n", [1, 2, 50])
def test_non_finite_points_raise(bad, n):
    P = np.zeros((n, 3))
    P[n // 2, 1] = bad
    with pytest.raises(ValueError, match="non-finite"):
        close_pairs(P, 1e-3)
    P = np.zeros((n, 3))
    P[0, 0] = bad                                          # the first point (the projection's origin)
    with pytest.raises(ValueError, match="non-finite"):
        close_pairs(P, 1e-3)


@pytest.mark.parametrize("tol, what", [(np.nan, "finite"), (np.inf, "finite"), (-1e-9, ">= 0"),
                                       (1e200, "too large"), ("1", "real"), (None, "real"),
                                       ([1.0], "real"), (1j, "real"), (True, "real")])
def test_bad_tol_raises(tol, what):
    with pytest.raises(ValueError, match=what):
        close_pairs(np.zeros((3, 3)), tol)


@pytest.mark.parametrize("shape", [(3,), (4, 2), (2, 4), (2, 3, 1)])
def test_bad_shape_raises(shape):
    with pytest.raises(ValueError, match="shape"):
        close_pairs(np.zeros(shape), 1.0)


def test_negative_budget_raises():
    with pytest.raises(ValueError, match="budget"):
        close_pairs(np.zeros((3, 3)), 1.0, budget=-1)


def test_direction_is_generic():
    assert np.isclose(np.linalg.norm(DIRECTION), 1.0, rtol=0, atol=4e-16)
    a = np.abs(DIRECTION)
    assert a.min() > 0.2 and np.min(np.abs(np.diff(np.sort(a)))) > 0.1
    # no small integer lattice vector is (nearly) perpendicular to it
    r = np.arange(-20, 21)
    ijk = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)
    ijk = ijk[np.any(ijk != 0, axis=1)]
    assert np.min(np.abs(ijk @ DIRECTION)) > 1e-4


def test_plain_python_kernels(monkeypatch):
    """The kernels uncompiled (what TFI_QUAT_JIT=0 runs) give the same pairs."""
    for name in ("_project", "_sort_by_projection", "_sweep", "_lexsorted", "_insertion_sort",
                 "_bucket", "_bucket_counts"):
        monkeypatch.setattr(_points, name, getattr(_points, name).py_func)
    rng = np.random.default_rng(9)
    for n0, tol in ((40, 0.0), (300, 0.02), (100, 1e-9)):
        P = rng.uniform(-1, 1, size=(n0, 3))
        P = np.concatenate([P, P[: n0 // 2], np.tile(P[:1], (40, 1)),
                            P[: n0 // 4] + 0.5 * max(tol, 1e-12) * _unit_vectors(rng, n0 // 4)])
        same(close_pairs(P, tol), brute(P, tol))
