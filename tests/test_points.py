"""tfi_quat._points: close_pairs and nearest_within against brute force and cKDTree.

close_pairs (coincident point pairs):

The reference is all pairs ``i < j`` with ``dx*dx + dy*dy + dz*dz <= tol*tol``
in float64 (the test cKDTree and close_pairs make), in lexicographic order.
Against brute force the sets must be identical bit for bit, including pairs
planted within a few units in the last place of ``tol`` along the sweep
direction (where a projection window without a rounding margin loses pairs).
Against cKDTree, whose node-level acceptance may differ at the last ulp, the
planted distances stay clear of ``tol`` by a relative 1e-6.

nearest_within (bounded nearest neighbours): see the comment opening its section.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from tfi_quat import _points
from tfi_quat import generate as gen
from tfi_quat._points import DIRECTION, LEAF, close_pairs, nearest_within

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


@pytest.fixture(autouse=True)
def compiled_searches(monkeypatch):
    """Every test here runs the compiled searches (sweep, kd-tree) on its small sets, not the
    direct numpy answer for sets below DIRECT_BELOW pairs; the ``direct`` tests at the end
    compare the two."""
    monkeypatch.setattr(_points, "DIRECT_BELOW", 0)


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


def _boundary_points(grid) -> np.ndarray:
    """Every block's points on its six faces (a block point on several faces once), stacked."""
    pts = []
    for blk in grid:
        x = blk.xyz
        mask = np.zeros(x.shape[:3], dtype=bool)
        mask[[0, -1]] = True
        mask[:, [0, -1]] = True
        mask[:, :, [0, -1]] = True
        pts.append(x[mask])
    return np.concatenate(pts)


@pytest.mark.parametrize("make", [
    lambda: gen.wing(ni=33, nj=12, nk_wing=11, nk_cap=5, nk_out=7),   # interfaces, wake cut, collapsed sheet
    lambda: gen.airfoil(topology="C", ni=65, nj=17),                  # wake cut
    lambda: gen.cylinder(ni=33, nj=9),                                # periodic seam
], ids=["wing", "c-airfoil", "o-cylinder"])
def test_generated_grid_boundaries(make, spy):
    grid = make()
    P = _boundary_points(grid)
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


# ================================================================ nearest_within
# The reference is brute force with cKDTree's test: ``d2 = dx*dx + dy*dy + dz*dz``
# in float64 (numpy sums left to right, no fused multiply-add), a candidate when
# ``d2 < bound*bound``, the smallest d2, the smallest row index among equal d2,
# ``sqrt(d2)``; ``inf`` and ``m`` when there is no candidate.  Against it the
# answers must be identical bit for bit.  Against cKDTree the distances must be
# identical and the index either cKDTree's or, at a tie, a smaller one at the
# same squared distance.


def nn_brute(R, Q, bound):
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3)
    Q = np.asarray(Q, dtype=np.float64).reshape(-1, 3)
    m, n = len(R), len(Q)
    d = np.full(n, np.inf)
    idx = np.full(n, m, dtype=np.int64)
    if m == 0 or n == 0:
        return d, idx
    with np.errstate(over="ignore", invalid="ignore"):
        dx = R[None, :, 0] - Q[:, None, 0]
        dy = R[None, :, 1] - Q[:, None, 1]
        dz = R[None, :, 2] - Q[:, None, 2]
        d2 = dx * dx + dy * dy + dz * dz
        ok = d2 < float(bound) * float(bound)
    best = np.where(ok, d2, np.inf).min(axis=1)
    hit = ok.any(axis=1)
    first = np.argmax(ok & (d2 == best[:, None]), axis=1)     # argmax: the first True
    d[hit] = np.sqrt(best[hit])
    idx[hit] = first[hit]
    return d, idx


def sq(R, Q):
    """Row-wise ``dx*dx + dy*dy + dz*dz`` of ``R - Q``, as the kernels sum it."""
    with np.errstate(over="ignore", invalid="ignore"):
        dx = R[:, 0] - Q[:, 0]
        dy = R[:, 1] - Q[:, 1]
        dz = R[:, 2] - Q[:, 2]
        return dx * dx + dy * dy + dz * dz


def check_nn_form(out, n, m):
    d, idx = out
    assert isinstance(d, np.ndarray) and isinstance(idx, np.ndarray)
    assert d.dtype == np.float64 and d.shape == (n,)
    assert idx.dtype == np.int64 and idx.shape == (n,)
    assert np.all((idx >= 0) & (idx <= m))
    assert np.array_equal(np.isinf(d), idx == m), "inf exactly where the index is m"


def same_nn(out, ref):
    d, idx = out
    dr, ir = ref
    bad = np.flatnonzero((idx != ir) | ~((d == dr) | (np.isinf(d) & np.isinf(dr))))
    if bad.size:
        k = bad[:5]
        raise AssertionError(f"{bad.size} of {len(d)} queries differ; first {k.tolist()}: "
                             f"d {d[k].tolist()} vs {dr[k].tolist()}, idx {idx[k].tolist()} vs {ir[k].tolist()}")


def check_ties(R, Q, bound, out):
    """Independently of nn_brute: the index attains the distance, is the smallest such, nothing is closer."""
    d, idx = out
    R = np.asarray(R, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    b2 = float(bound) * float(bound)
    for q in range(len(Q)):
        d2 = sq(R, np.broadcast_to(Q[q], R.shape))
        if idx[q] == len(R):
            assert not np.any(d2 < b2), f"query {q}: a ref point is closer than the bound"
            continue
        j = idx[q]
        assert d2[j] < b2 and d[q] == np.sqrt(d2[j]), f"query {q}: distance not that of its index"
        assert not np.any(d2 < d2[j]), f"query {q}: a closer ref point exists"
        assert j == np.flatnonzero(d2 == d2[j])[0], f"query {q}: not the smallest index of the tie"


def check_vs_ckdtree(R, Q, bound, out):
    d, idx = out
    R = np.asarray(R, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    dk, ik = cKDTree(R).query(Q, distance_upper_bound=bound)
    ik = ik.astype(np.int64)
    assert np.array_equal(d, dk), f"distances differ from cKDTree at {np.flatnonzero(d != dk)[:5].tolist()}"
    diff = np.flatnonzero(idx != ik)
    if diff.size:                                        # ties only: same squared distance, ours smaller
        assert np.all(ik[diff] < len(R)) and np.all(idx[diff] < ik[diff])
        assert np.array_equal(sq(R[idx[diff]], Q[diff]), sq(R[ik[diff]], Q[diff]))


def _clustered(rng, k, decades, centre=(0.5, 0.25, -1.0)):
    r = 10.0 ** rng.uniform(-decades, 0, k)
    return r[:, None] * _unit_vectors(rng, k) + np.asarray(centre)


def _ref_cloud(rng, m, kind, scale, offset):
    if kind == "uniform":
        R = rng.uniform(-1, 1, size=(m, 3))
    elif kind == "clustered":                            # towards one point over many decades
        R = _clustered(rng, m, 8)
    elif kind == "plane":
        R = np.column_stack([rng.uniform(-1, 1, (m, 2)), np.zeros(m)])
    elif kind == "line":
        R = np.outer(rng.uniform(-1, 1, m), [0.3, -0.2, 0.7])
    elif kind == "point":
        R = np.tile([[0.125, -0.5, 2.0]], (m, 1))
    else:                                                # "dups": few distinct points, many copies
        base = rng.uniform(-1, 1, size=(max(1, m // 6), 3))
        R = base[rng.integers(len(base), size=m)]
    return offset + scale * R


def _queries(rng, R, n, scale, offset):
    """Random points near and inside the ref box, copies of ref points, and far ones."""
    parts = [offset + scale * rng.uniform(-1.5, 1.5, size=(n, 3))]
    if len(R):
        parts.append(R[rng.integers(len(R), size=n // 3)])
        parts.append(R[rng.integers(len(R), size=n // 3)] + 1e-3 * scale * _unit_vectors(rng, n // 3))
    parts.append(offset + scale * (50.0 + rng.uniform(0, 1, size=(n // 5, 3))))
    Q = np.concatenate(parts)
    return Q[rng.permutation(len(Q))]


REL_BOUNDS = [0.0, 1e-9, 1e-3, 0.05, 0.3, 1.0, 3.0, 100.0, np.inf]


@given(seed=st.integers(0, 2**32 - 1), m=st.integers(0, 90), n=st.integers(0, 60),
       kind=st.sampled_from(["uniform", "clustered", "plane", "line", "point", "dups"]),
       scale_exp=st.integers(-150, 100), offset=st.sampled_from([0.0, 1.0, -7.5, 1e3, 1e6]),
       rel_bound=st.sampled_from(REL_BOUNDS))
def test_nn_matches_brute_force(seed, m, n, kind, scale_exp, offset, rel_bound):
    rng = np.random.default_rng(seed)
    scale = 10.0 ** scale_exp
    R = _ref_cloud(rng, m, kind, scale, offset * scale)
    Q = _queries(rng, R, n, scale, offset * scale)
    bound = rel_bound * scale
    out = nearest_within(R, Q, bound)
    check_nn_form(out, len(Q), m)
    same_nn(out, nn_brute(R, Q, bound))


@given(seed=st.integers(0, 2**32 - 1), m=st.integers(1, 60), n=st.integers(1, 60),
       span=st.integers(1, 6), k=st.integers(-60, 60), b=st.sampled_from([0, 1, 2, 3, 5, 7, 9]))
def test_nn_points_exactly_at_bound(seed, m, n, span, k, b):
    """Integer lattices times a power of two: squared distances exact, many exactly ``bound**2``.

    A ref point exactly at ``bound`` does not count (strict ``<``, as cKDTree); one ulp
    more bound takes it in.
    """
    rng = np.random.default_rng(seed)
    h = 2.0 ** k
    R = h * rng.integers(-span, span + 1, size=(m, 3)).astype(float)
    Q = h * rng.integers(-span - 2, span + 3, size=(n, 3)).astype(float)
    bound = b * h
    out = nearest_within(R, Q, bound)
    check_nn_form(out, n, m)
    same_nn(out, nn_brute(R, Q, bound))
    check_ties(R, Q, bound, out)
    d, _ = out
    assert np.all(d[np.isfinite(d)] < bound)
    D2 = sq(np.repeat(R, n, axis=0), np.tile(Q, (m, 1))).reshape(m, n)
    at = np.any(D2 == bound * bound, axis=0) & ~np.any(D2 < bound * bound, axis=0)
    assert np.all(np.isinf(d[at]))                       # only points at the bound: none
    up = nearest_within(R, Q, np.nextafter(bound, np.inf))
    same_nn(up, nn_brute(R, Q, np.nextafter(bound, np.inf)))
    if b > 0:
        assert np.all(up[0][at] == bound)                # ... until the bound grows by an ulp
    check_vs_ckdtree(R, Q, bound, out)


@given(seed=st.integers(0, 2**32 - 1),
       shape=st.tuples(st.integers(1, 7), st.integers(1, 7), st.integers(1, 6)),
       where=st.sampled_from(["nodes", "cells", "faces", "edges", "random"]),
       rel_bound=st.sampled_from([0.3, 0.5, 0.75, 1.0, 1.5, 2.5, np.inf]),
       rotate=st.booleans(), copies=st.integers(1, 3), shuffle=st.booleans())
def test_nn_lattice_ties(seed, shape, where, rel_bound, rotate, copies, shuffle):
    """Structured-grid-like ref sets: queries at nodes, cell/face centres and edge midpoints tie
    between up to 8 ref points (and between the copies of overlapping blocks)."""
    rng = np.random.default_rng(seed)
    h = float(rng.uniform(0.01, 10.0))
    ii, jj, kk = np.meshgrid(*(np.arange(s) for s in shape), indexing="ij")
    L = np.stack([ii, jj, kk], axis=-1).reshape(-1, 3).astype(float)
    parts = [L]
    for _ in range(copies - 1):
        parts.append(L + rng.integers(-2, 3, size=3) * rng.integers(0, 2, size=3))
    R = np.concatenate(parts)
    half = {"nodes": 0.0, "cells": 0.5, "faces": np.array([0.5, 0.5, 0.0]),
            "edges": np.array([0.5, 0.0, 0.0]), "random": None}[where]
    base = R[rng.integers(len(R), size=40)]
    Q = base + (rng.uniform(-1, 1, size=base.shape) if half is None else half)
    if shuffle:
        R = R[rng.permutation(len(R))]
    R = h * R
    Q = h * Q
    if rotate:
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        R = R @ q.T
        Q = Q @ q.T
    bound = rel_bound * h
    out = nearest_within(R, Q, bound)
    check_nn_form(out, len(Q), len(R))
    same_nn(out, nn_brute(R, Q, bound))
    check_ties(R, Q, bound, out)
    if not rotate:
        check_vs_ckdtree(R, Q, bound, out)


@given(seed=st.integers(0, 2**32 - 1), m=st.integers(1, 80), n=st.integers(0, 50),
       kind=st.sampled_from(["uniform", "clustered", "plane", "line", "point", "dups"]),
       far=st.sampled_from([0.0, 1e3, 1e12, 1e150]))
def test_nn_unbounded(seed, m, n, kind, far):
    """``bound = inf``: every query gets its nearest ref point, however far away."""
    rng = np.random.default_rng(seed)
    R = _ref_cloud(rng, m, kind, 1.0, 0.0)
    Q = rng.uniform(-1.5, 1.5, size=(n, 3)) + far * _unit_vectors(rng, max(n, 1))[:n]
    out = nearest_within(R, Q, np.inf)
    check_nn_form(out, n, m)
    assert np.all(out[1] < m)
    same_nn(out, nn_brute(R, Q, np.inf))
    if far < 1e150:
        check_vs_ckdtree(R, Q, np.inf, out)


@given(seed=st.integers(0, 2**32 - 1), m=st.integers(1, 60), n=st.integers(0, 40))
def test_nn_bound_zero_and_underflow(seed, m, n):
    """Nothing is strictly closer than 0 -- not even a copy; nor closer than a bound whose square
    underflows to 0; a bound just above that finds the copies, at the smallest index."""
    rng = np.random.default_rng(seed)
    R = rng.uniform(-1, 1, size=(m, 3))
    R = np.concatenate([R, R[rng.integers(m, size=m)]])
    Q = np.concatenate([R[rng.integers(len(R), size=n)], rng.uniform(-1, 1, size=(n, 3))])
    for bound in (0.0, 1e-170):
        d, idx = nearest_within(R, Q, bound)
        assert np.all(np.isinf(d)) and np.all(idx == len(R))
        check_vs_ckdtree(R, Q, bound, (d, idx))
    out = nearest_within(R, Q, 1e-150)
    same_nn(out, nn_brute(R, Q, 1e-150))
    d, idx = out
    assert np.all(d[:n] == 0.0)
    for q in range(n):
        assert idx[q] == np.flatnonzero(np.all(R == Q[q], axis=1))[0]


@given(seed=st.integers(0, 2**32 - 1), m0=st.integers(200, 3000), n=st.integers(1, 4000),
       rel_bound=st.sampled_from([1e-3, 0.02, 0.2, 1.0, np.inf]), decades=st.integers(0, 6),
       offset=st.sampled_from([0.0, 10.0]))
def test_nn_moderate_clouds_match_ckdtree(seed, m0, n, rel_bound, decades, offset):
    """Surface-like ref sets (a warped sheet, clustered towards one edge) and queries above it."""
    rng = np.random.default_rng(seed)
    u = 10.0 ** rng.uniform(-decades, 0, m0) if decades else rng.uniform(0, 1, m0)
    v = rng.uniform(0, 1, m0)
    R = np.column_stack([u, v, 0.1 * np.sin(3 * u) * np.cos(2 * v)]) + offset
    R = np.concatenate([R, R[: m0 // 10]])              # repeated points (interfaces)
    Q = np.concatenate([R[rng.integers(len(R), size=n // 4)],
                        np.column_stack([rng.uniform(-0.5, 1.5, (n, 2)), rng.uniform(-1, 1, n)]) + offset])
    out = nearest_within(R, Q, rel_bound)
    check_nn_form(out, len(Q), len(R))
    check_vs_ckdtree(R, Q, rel_bound, out)


def _face(x, face):
    axis = "ijk".index(face[0])
    sl = [slice(None)] * 3
    sl[axis] = 0 if face.endswith("min") else -1
    return x[tuple(sl)]


def test_nn_generated_wing_walls():
    """The Deformer's case in small: ref = the wall patches of the multiblock wing (clustered,
    an edge shared by two blocks), query = every boundary point of every block."""
    grid = gen.wing(ni=33, nj=12, nk_wing=11, nk_cap=5, nk_out=7)
    walls = []
    for p in gen.boundary_patches("wing", grid)["walls"]:
        f = _face(grid[p.block].xyz, p.face)
        if p.range is not None:
            (a0, a1), (b0, b1) = p.range
            f = f[a0:a1 + 1, b0:b1 + 1]
        walls.append(f.reshape(-1, 3))
    W = np.concatenate(walls)
    assert len(np.unique(W, axis=0)) < len(W)            # the shared edge: ties at distance 0
    P = _boundary_points(grid)
    bound = 0.2 * float(np.linalg.norm(W.max(0) - W.min(0)))
    out = nearest_within(W, P, bound)
    check_nn_form(out, len(P), len(W))
    d = out[0]
    assert 0 < np.count_nonzero(np.isfinite(d)) < len(P) and np.count_nonzero(d == 0) >= len(np.unique(W, axis=0))
    check_vs_ckdtree(W, P, bound, out)
    same_nn(out, nn_brute(W, P, bound))


@pytest.mark.parametrize("threads", [1, 2])
def test_nn_parallel_chunks(threads):
    """Enough queries for the parallel path, n not a multiple of the chunk: same answer on any
    number of threads (the warm start of each chunk does not change it)."""
    from tfi_quat._jit import use_threads
    rng = np.random.default_rng(17)
    R = np.concatenate([_clustered(rng, 800, 5), rng.uniform(-1, 1, size=(500, 3))])
    R = np.concatenate([R, R[:200]])
    line = np.cumsum(0.01 * _unit_vectors(rng, 7011), axis=0) % 2.0 - 1.0   # a coherent walk
    Q = np.concatenate([line, R[rng.integers(len(R), size=1500)]])
    from tfi_quat._jit import SERIAL_BELOW
    assert _points._QUERY_WORK * len(Q) >= SERIAL_BELOW      # the parallel path runs
    ref = nn_brute(R, Q, 0.3)
    with use_threads(threads):
        out = nearest_within(R, Q, 0.3)
    check_nn_form(out, len(Q), len(R))
    same_nn(out, ref)
    check_vs_ckdtree(R, Q, 0.3, out)


@given(nch=st.integers(1, 3000), runs=st.integers(1, 64))
def test_chunk_order_is_interleaved_runs(nch, runs):
    order = _points._chunk_order(nch, runs)
    assert order.dtype.kind == "i" and np.array_equal(np.sort(order), np.arange(nch))
    k = min(nch, runs)
    starts = np.flatnonzero(np.diff(order, prepend=-2) != 1)   # where a run of consecutive chunks begins
    assert len(starts) <= k
    if k > 2:                                            # not simply in order: runs are interleaved
        assert not np.array_equal(order, np.arange(nch))


@given(seed=st.integers(0, 2**32 - 1), chunk=st.sampled_from([1, 2, 7, 64, 10**6]),
       how=st.sampled_from(["forward", "reversed", "random", "runs"]))
def test_nn_answer_independent_of_chunks_and_order(seed, chunk, how):
    """The warm start (previous answer of the chunk) and the chunk order do not change the answer."""
    rng = np.random.default_rng(seed)
    R = np.concatenate([_clustered(rng, 400, 4), rng.uniform(-1, 1, size=(200, 3))])
    R = np.concatenate([R, R[:50]])
    Q = np.concatenate([np.cumsum(0.02 * _unit_vectors(rng, 300), axis=0), R[rng.integers(len(R), size=100)]])
    bound = 0.25
    ref = nn_brute(R, Q, bound)
    nch = -(-len(Q) // chunk)
    order = {"forward": np.arange(nch), "reversed": np.arange(nch)[::-1].copy(),
             "random": rng.permutation(nch), "runs": _points._chunk_order(nch)}[how]
    tree = _points._kd_build(R, LEAF)
    d = np.full(len(Q), -1.0)
    idx = np.full(len(Q), -1, dtype=np.int64)
    _points._kd_query(0, nch, *tree, R, Q, bound * bound, chunk, order.astype(np.int64), d, idx)
    same_nn((d, idx), ref)


# ---------------------------------------------------------------- the tree
@given(seed=st.integers(0, 2**32 - 1), c=st.integers(1, 400), k=st.integers(0, 399),
       kind=st.sampled_from(["random", "few", "equal", "sorted", "reversed", "organ"]),
       rounds=st.sampled_from([None, 0, 1, 2]))
def test_select_partitions(seed, c, k, kind, rounds):
    """``_select``: key[k] has its rank, smaller keys before, larger after, the other arrays carried
    along; ``rounds = 0`` forces the sorting fallback."""
    rng = np.random.default_rng(seed)
    k = k % c
    key = {"random": rng.normal(size=c), "few": rng.integers(0, 3, c).astype(float), "equal": np.ones(c),
           "sorted": np.arange(c, dtype=float), "reversed": -np.arange(c, dtype=float),
           "organ": np.minimum(np.arange(c), c - np.arange(c)).astype(float)}[kind]
    pad = 5
    key = np.concatenate([[9e9] * pad, key, [-9e9] * pad])
    key0 = key.copy()
    o1 = key * 2.0
    o2 = -key
    perm = np.arange(len(key))
    s, e = pad, pad + c
    r = _points._select_rounds(c) if rounds is None else rounds
    _points._select(key, o1, o2, perm, s, e, s + k, r)
    assert np.array_equal(key[:s], key0[:s]) and np.array_equal(key[e:], key0[e:])
    assert np.array_equal(np.sort(key[s:e]), np.sort(key0[s:e]))
    assert np.all(key[s:s + k] <= key[s + k]) and np.all(key[s + k + 1:e] >= key[s + k])
    assert np.array_equal(key, key0[perm]) and np.array_equal(o1, 2.0 * key) and np.array_equal(o2, -key)


@given(seed=st.integers(0, 2**32 - 1), m=st.integers(1, 700),
       kind=st.sampled_from(["uniform", "clustered", "plane", "line", "point", "dups"]),
       leaf=st.sampled_from([1, 2, 5, LEAF]))
def test_kd_build_invariants(seed, m, kind, leaf):
    rng = np.random.default_rng(seed)
    R = _ref_cloud(rng, m, kind, 1.0, 0.0)
    box, lstart, xs, ys, zs, perm = _points._kd_build(R, leaf)
    nl = len(lstart) - 1
    depth = nl.bit_length() - 1
    assert nl == 1 << depth and (m >> depth) <= leaf and (depth == 0 or (m >> (depth - 1)) > leaf)
    assert len(box) == 2 * nl - 1
    assert np.array_equal(np.sort(perm), np.arange(m))
    assert np.array_equal(np.column_stack([xs, ys, zs]), R[perm])
    assert lstart[0] == 0 and lstart[-1] == m and np.all(np.diff(lstart) >= 1)
    assert np.all(np.diff(lstart) <= -(-m // nl))      # sizes within one of m / 2**depth
    X = np.column_stack([xs, ys, zs])

    def points(nd):                                      # leaf range of node nd
        lev = (nd + 1).bit_length() - 1
        span = 1 << (depth - lev)
        j = (nd + 1 - (1 << lev)) * span
        return X[lstart[j]:lstart[j + span]]

    for nd in range(len(box)):
        p = points(nd)
        tight = np.column_stack([p.min(0), p.max(0)]).ravel()
        assert np.array_equal(box[nd], tight), f"node {nd}: box not tight"
        if nd < nl - 1:                                  # children split by a plane (or coincide)
            a, b = points(2 * nd + 1), points(2 * nd + 2)
            ax = int(np.argmax(tight[1::2] - tight[0::2]))
            assert a[:, ax].max() <= b[:, ax].min()


# ---------------------------------------------------------------- edge cases and errors
def test_nn_empty_inputs():
    for m, n in ((0, 0), (0, 4), (5, 0), (1, 0)):
        R = np.arange(3.0 * m).reshape(m, 3)
        Q = np.ones((n, 3))
        for bound in (0.0, 1.0, np.inf):
            d, idx = nearest_within(R, Q, bound)
            check_nn_form((d, idx), n, m)
            assert np.all(np.isinf(d)) and np.all(idx == m)
            if m:
                check_vs_ckdtree(R, Q, bound, (d, idx))
    d, idx = nearest_within(np.empty((0, 3)), np.zeros((3, 3)), np.inf)
    assert idx.tolist() == [0, 0, 0] and np.all(np.isinf(d))


def test_nn_single_point_and_copies():
    R = np.tile([[1.0, 2.0, 3.0]], (50, 1))
    Q = np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 4.0], [1.0, 2.0, 3.5], [100.0, 0.0, 0.0]])
    d, idx = nearest_within(R, Q, 1.0)
    assert d.tolist()[:3] == [0.0, np.inf, 0.5] and np.isinf(d[3])
    assert idx.tolist() == [0, 50, 0, 50]
    d, idx = nearest_within(R, Q, np.inf)
    assert idx.tolist() == [0, 0, 0, 0] and d[1] == 1.0


def test_nn_far_queries_rejected():
    """Queries far outside the ref box get inf at once; with no bound, their true nearest point."""
    rng = np.random.default_rng(4)
    R = rng.uniform(-1, 1, size=(500, 3))
    Q = 1e6 + rng.uniform(-1, 1, size=(300, 3))
    d, idx = nearest_within(R, Q, 10.0)
    assert np.all(np.isinf(d)) and np.all(idx == 500)
    same_nn(nearest_within(R, Q, np.inf), nn_brute(R, Q, np.inf))


def test_nn_huge_and_tiny_coordinates():
    """Squared distances that overflow never count (cKDTree: the same); subnormal ones do."""
    H = np.array([[1e308, 0.0, 0.0], [-1e308, 0.0, 0.0], [1e200, 1e200, 0.0]])
    Q = np.array([[-1e308, 0.0, 0.0], [1e308, 0.0, 0.0], [0.0, 0.0, 0.0], [1e200, 1e200, 1.0]])
    out = nearest_within(H, Q, np.inf)
    same_nn(out, nn_brute(H, Q, np.inf))
    assert out[1].tolist() == [1, 0, 3, 2] and out[0].tolist()[3] == 1.0
    T = np.array([[0.0, 0.0, 0.0], [3e-160, 0.0, 0.0], [0.0, 4e-160, 0.0]])
    Qt = np.array([[0.0, 0.0, 1e-170], [3e-160, 4e-160, 0.0]])
    out = nearest_within(T, Qt, 1e-150)
    same_nn(out, nn_brute(T, Qt, 1e-150))
    check_vs_ckdtree(T, Qt, 1e-150, out)


def test_nn_inputs_converted():
    rng = np.random.default_rng(6)
    R = rng.integers(0, 5, size=(80, 3))
    Q = rng.integers(-1, 6, size=(40, 3))
    ref = nn_brute(R.astype(float), Q.astype(float), 1.5)
    same_nn(nearest_within(R, Q, 1.5), ref)
    same_nn(nearest_within(R.tolist(), Q.tolist(), np.float32(1.5)), ref)
    same_nn(nearest_within(np.asfortranarray(R.astype(float)), Q, np.array(1.5)), ref)
    big = np.zeros((160, 6))
    big[::2, ::2] = R
    same_nn(nearest_within(big[::2, ::2], Q[:, ::-1][:, ::-1], 1.5), ref)   # non-contiguous views
    same_nn(nearest_within(R, Q, 3), nn_brute(R.astype(float), Q.astype(float), 3.0))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("which", ["ref", "query"])
@pytest.mark.parametrize("n", [1, 2, 50])
def test_nn_non_finite_raise(bad, which, n):
    for row in (0, n // 2, n - 1):
        P = np.zeros((n, 3))
        P[row, row % 3] = bad
        args = (P, np.zeros((3, 3))) if which == "ref" else (np.zeros((3, 3)), P)
        with pytest.raises(ValueError, match=f"{which} contains a non-finite.*first row {row}\\)"):
            nearest_within(*args, 1.0)
    with pytest.raises(ValueError, match=which):       # even when the other set is empty
        nearest_within(*((P, np.empty((0, 3))) if which == "ref" else (np.empty((0, 3)), P)), 1.0)


@pytest.mark.parametrize("bound, what", [(np.nan, "NaN"), (-1e-300, ">= 0"), (-np.inf, ">= 0"),
                                         ("1", "real"), (None, "real"), ([1.0], "real"), (1j, "real"),
                                         (True, "real"), (np.array([1.0]), "real")])
def test_nn_bad_bound_raises(bound, what):
    with pytest.raises(ValueError, match=what):
        nearest_within(np.zeros((3, 3)), np.zeros((2, 3)), bound)


@pytest.mark.parametrize("shape", [(3,), (4, 2), (2, 4), (2, 3, 1), ()])
@pytest.mark.parametrize("which", ["ref", "query"])
def test_nn_bad_shape_raises(shape, which):
    args = (np.zeros(shape), np.zeros((2, 3))) if which == "ref" else (np.zeros((2, 3)), np.zeros(shape))
    with pytest.raises(ValueError, match=f"{which} must have shape"):
        nearest_within(*args, 1.0)


def test_nn_finite_coordinates_whose_sum_overflows_pass():
    """The finiteness check sums the coordinates first: an overflowing sum of finite values
    falls back to the exact check instead of raising."""
    R = np.full((4, 3), 1e308)
    d, i = nearest_within(R, R[:2], 1.0)
    assert np.all(d == 0.0) and np.all(i == 0)


def test_nn_plain_python_kernels(monkeypatch):
    """The kernels uncompiled (what TFI_QUAT_JIT=0 runs) give the same answers."""
    for name in ("_swap4", "_select_rounds", "_select", "_range_box", "_kd_build",
                 "_box_d2", "_kd_query", "_kd_chunk", "_argsort", "_sift"):
        monkeypatch.setattr(_points, name, getattr(_points, name).py_func)
    monkeypatch.setattr(_points, "CHUNK", 7)
    rng = np.random.default_rng(10)
    for m, n, bound in ((1, 5, 1.0), (40, 30, 0.3), (300, 60, np.inf), (300, 60, 0.05)):
        R = _clustered(rng, m, 4)
        R = np.concatenate([R, R[: m // 3]])
        Q = np.concatenate([R[rng.integers(len(R), size=n // 2)], rng.uniform(-1, 1, size=(n, 3))])
        same_nn(nearest_within(R, Q, bound), nn_brute(R, Q, bound))
    with pytest.raises(ValueError, match="query contains a non-finite"):
        nearest_within(R, np.array([[0.0, np.nan, 0.0]]), 1.0)


@given(keys=st.lists(st.integers(-5, 5) | st.floats(-1e3, 1e3), min_size=0, max_size=60),
       s=st.integers(0, 3))
@settings(max_examples=40, deadline=None)
def test_argsort_heapsort_sorts_any_keys(keys, s):
    """The heapsort of the sorts above (buckets, pair rows, the kd-tree's fallback): a
    permutation of the range that orders it, compiled and uncompiled."""
    key = np.array([0.0] * s + [float(k) for k in keys])
    e = key.size
    for fn in (_points._argsort, _points._argsort.py_func):
        idx = np.full(e - s, -1, dtype=np.int64)
        fn(key, s, e, idx)
        assert sorted(idx.tolist()) == list(range(e - s))
        assert np.all(np.diff(key[s + idx]) >= 0.0)
    ikey = key.astype(np.int64)
    idx = np.empty(e - s, dtype=np.int64)
    _points._argsort(ikey, s, e, idx)
    assert np.array_equal(ikey[s + idx], np.sort(ikey[s:]))


# ================================================================ direct answers of small sets
def _direct(mp, chunk):
    """Switch the direct numpy answers on for every set (and chunk them ``chunk`` at a time);
    the compiled searches must then not be called."""
    mp.setattr(_points, "DIRECT_BELOW", 1 << 62)
    mp.setattr(_points, "_DIRECT_CHUNK", chunk)

    def never(*args):
        raise AssertionError("a compiled search ran on a set below DIRECT_BELOW")
    for name in ("_project", "_sort_by_projection", "_sweep", "_kd_build", "_kd_query"):
        mp.setattr(_points, name, never)


@given(seed=st.integers(0, 2**32 - 1), n0=st.integers(1, 60),
       scale_exp=st.integers(-150, 100), offset=st.sampled_from([0.0, 1.0, -7.5, 1e3, 1e6]),
       rel_tol=st.sampled_from([0.0, 1e-12, 1e-10, 1e-6, 1e-3, 0.05, 0.3]),
       n_plant=st.integers(0, 40), along=st.booleans(), chunk=st.sampled_from([1, 7, 1 << 16]))
@settings(max_examples=60, deadline=None)
def test_direct_pairs_match_brute_force_and_sweep(seed, n0, scale_exp, offset, rel_tol, n_plant,
                                                  along, chunk):
    """The direct answer of a small set: the brute-force oracle's pairs and the sweep's, bit
    for bit, in lexicographic order, with any chunking."""
    P, tol = planted_cloud(seed, n0, 10.0 ** scale_exp, offset * 10.0 ** scale_exp, rel_tol,
                           n_plant, NEAR, along)
    swept = close_pairs(P, tol)                      # DIRECT_BELOW = 0 (the autouse fixture)
    with pytest.MonkeyPatch.context() as mp:
        _direct(mp, chunk)
        out = close_pairs(P, tol)
    check_form(out, len(P))
    same(out, brute(P, tol))
    same(out, swept)


def test_direct_pairs_edge_cases():
    """Duplicates only, a pole cluster, huge and tiny coordinates, bad input: as the sweep."""
    rng = np.random.default_rng(11)
    pole = np.tile([[0.25, -0.5, 0.125]], (60, 1))
    P = np.concatenate([rng.uniform(-1, 1, size=(50, 3)), pole])
    huge = rng.uniform(-1, 1, size=(40, 3)) * 1e307
    huge = np.concatenate([huge, huge[:5]])
    tiny = rng.uniform(-1, 1, size=(40, 3)) * 1e-300
    cases = [(P, 1e-9), (P, 0.0), (np.zeros((5, 3)), 0.0), (huge, 1e150), (tiny, 1e-310),
             (np.array([[0.0, 0.0, 0.0], [-0.0, 0.0, 0.0]]), 0.0)]
    ref = [close_pairs(p, t) for p, t in cases]
    with pytest.MonkeyPatch.context() as mp:
        _direct(mp, 64)
        for (p, t), r in zip(cases, ref):
            same(close_pairs(p, t), r)
            with np.errstate(over="ignore", under="ignore"):
                same(close_pairs(p, t), brute(p, t))
        bad = P.copy()
        bad[57, 1] = np.nan
        with pytest.raises(ValueError, match=r"non-finite.*first row 57"):
            close_pairs(bad, 1e-9)
        assert close_pairs(P[:1], 1.0).shape == (0, 2)


@given(seed=st.integers(0, 2**32 - 1), m=st.integers(0, 90), n=st.integers(0, 60),
       kind=st.sampled_from(["uniform", "clustered", "plane", "line", "point", "dups"]),
       scale_exp=st.integers(-150, 100), offset=st.sampled_from([0.0, 1.0, -7.5, 1e3, 1e6]),
       rel_bound=st.sampled_from(REL_BOUNDS), chunk=st.sampled_from([1, 13, 1 << 16]))
@settings(max_examples=60, deadline=None)
def test_direct_nearest_matches_brute_force_and_tree(seed, m, n, kind, scale_exp, offset,
                                                     rel_bound, chunk):
    """The direct answer of a small problem: the oracle's and the kd-tree's, bit for bit."""
    rng = np.random.default_rng(seed)
    scale = 10.0 ** scale_exp
    R = _ref_cloud(rng, m, kind, scale, offset * scale)
    Q = _queries(rng, R, n, scale, offset * scale)
    bound = rel_bound * scale
    tree = nearest_within(R, Q, bound)
    with pytest.MonkeyPatch.context() as mp:
        _direct(mp, chunk)
        out = nearest_within(R, Q, bound)
    check_nn_form(out, len(Q), m)
    same_nn(out, nn_brute(R, Q, bound))
    same_nn(out, tree)


@given(seed=st.integers(0, 2**32 - 1), m=st.integers(1, 60), n=st.integers(1, 60),
       span=st.integers(1, 6), k=st.integers(-60, 60), b=st.sampled_from([0, 1, 2, 3, 5, 7, 9]))
@settings(max_examples=40, deadline=None)
def test_direct_nearest_exactly_at_bound_and_ties(seed, m, n, span, k, b):
    """Lattices: distances exactly at the bound excluded, the smallest row among ties."""
    rng = np.random.default_rng(seed)
    h = 2.0 ** k
    R = h * rng.integers(-span, span + 1, size=(m, 3)).astype(float)
    Q = h * rng.integers(-span - 2, span + 3, size=(n, 3)).astype(float)
    with pytest.MonkeyPatch.context() as mp:
        _direct(mp, 17)
        out = nearest_within(R, Q, b * h)
    same_nn(out, nn_brute(R, Q, b * h))
    check_ties(R, Q, b * h, out)


def test_direct_used_below_the_threshold_only(monkeypatch):
    """The default threshold: the demo's sizes are answered directly, larger sets compiled."""
    monkeypatch.undo()
    calls = []
    real = _points._direct_pairs

    def spy_direct(P, tol):
        calls.append(len(P))
        return real(P, tol)
    monkeypatch.setattr(_points, "_direct_pairs", spy_direct)
    rng = np.random.default_rng(5)
    small = rng.uniform(-1, 1, size=(640, 3))
    close_pairs(small, 1e-9)
    assert calls == [640]
    big = rng.uniform(-1, 1, size=(1 + int(np.sqrt(2 * _points.DIRECT_BELOW)), 3))
    same(close_pairs(big, 0.01), kdtree(big, 0.01))
    assert calls == [640]
