"""Cell metrics and the quality report against independent numpy and analytic values."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import tfi_quat
from tfi_quat import Block, CaseError, Grid, GridValueError
from tfi_quat import quality as Q
from tfi_quat._jit import parallel_for
from tfi_quat.quality import (METRICS, cell_metrics, cell_orthogonality, cell_volumes, invalid_cells, quality_report,
                              wall_orthogonality)

import _cells
from conftest import annulus, sheared_box

CORNERS = list(itertools.product((0, 1), repeat=3))


# ------------------------------------------------------------------ numpy oracle
def _corners(xyz):
    """(nci, ncj, nck, 2, 2, 2, 3): the 8 corners c(a, b, c) of every hexahedron."""
    ni, nj, nk = xyz.shape[:3]
    out = np.empty((ni - 1, nj - 1, nk - 1, 2, 2, 2, 3))
    for a, b, c in CORNERS:
        out[:, :, :, a, b, c] = xyz[a:ni - 1 + a, b:nj - 1 + b, c:nk - 1 + c]
    return out


def oracle_hex(xyz):
    """Every metric of every hexahedron, written independently with numpy (det, arccos)."""
    c = _corners(xyz)
    vol = 0.0
    o = c[..., 0, 0, 0, :]
    # Kuhn triangulation: the six monotone paths 000 -> p -> q -> 111
    for perm in itertools.permutations(range(3)):
        p = [0, 0, 0]
        pts = [o]
        for axis in perm:
            p[axis] = 1
            pts.append(c[..., p[0], p[1], p[2], :])
        m = np.stack([pts[1] - pts[0], pts[2] - pts[1], pts[3] - pts[2]], axis=-2)
        sign = np.linalg.det(np.eye(3)[list(perm)])
        vol = vol + sign * np.linalg.det(m) / 6.0
    jac, sj, angles, lengths = [], [], [], []
    for a, b, cc in CORNERS:
        p0 = c[..., a, b, cc, :]
        e = [c[..., 1, b, cc, :] - c[..., 0, b, cc, :], c[..., a, 1, cc, :] - c[..., a, 0, cc, :],
             c[..., a, b, 1, :] - c[..., a, b, 0, :]]
        jac.append(np.linalg.det(np.stack(e, axis=-2)))
        unit = [v / np.linalg.norm(v, axis=-1, keepdims=True) for v in e]
        sj.append(np.linalg.det(np.stack(unit, axis=-2)))
        # the angles between the edges leaving the corner towards its neighbours
        nb = [c[..., 1 - a, b, cc, :] - p0, c[..., a, 1 - b, cc, :] - p0, c[..., a, b, 1 - cc, :] - p0]
        for m, n in ((0, 1), (0, 2), (1, 2)):
            cosang = np.einsum("...d,...d", nb[m], nb[n]) / (np.linalg.norm(nb[m], axis=-1) *
                                                             np.linalg.norm(nb[n], axis=-1))
            angles.append(np.degrees(np.arccos(np.clip(cosang, -1, 1))))
        lengths += [np.linalg.norm(v, axis=-1) for v in e]
    angles = np.stack(angles)
    skew = np.maximum((angles.max(0) - 90.0) / 90.0, (90.0 - angles.min(0)) / 90.0)
    lengths = np.stack(lengths)
    return {"volume": vol, "jacobian": np.min(jac, axis=0), "scaled_jacobian": np.min(sj, axis=0),
            "skewness": skew, "aspect_ratio": lengths.max(0) / lengths.min(0)}


def oracle_quad(xyz):
    x = xyz[:, :, 0, :2]
    p = [x[:-1, :-1], x[1:, :-1], x[1:, 1:], x[:-1, 1:]]      # counter-clockwise corners
    area = 0.5 * sum(p[m][..., 0] * p[(m + 1) % 4][..., 1] - p[(m + 1) % 4][..., 0] * p[m][..., 1]
                     for m in range(4))
    jac, sj, ang, ln = [], [], [], []
    for m in range(4):
        fwd = p[(m + 1) % 4] - p[m]
        back = p[(m - 1) % 4] - p[m]
        cr = fwd[..., 0] * back[..., 1] - fwd[..., 1] * back[..., 0]
        nf, nb = np.linalg.norm(fwd, axis=-1), np.linalg.norm(back, axis=-1)
        jac.append(cr)
        sj.append(cr / (nf * nb))
        ang.append(np.degrees(np.arccos(np.clip(np.einsum("...d,...d", fwd, back) / (nf * nb), -1, 1))))
        ln.append(nf)
    ang = np.stack(ang)
    skew = np.maximum((ang.max(0) - 90) / 90, (90 - ang.min(0)) / 90)
    out = {"volume": area, "jacobian": np.min(jac, 0), "scaled_jacobian": np.min(sj, 0), "skewness": skew,
           "aspect_ratio": np.max(ln, 0) / np.min(ln, 0)}
    return {k: v[..., None] for k, v in out.items()}


def check_against_oracle(xyz, ndim):
    got = cell_metrics(xyz, ndim)
    want = (oracle_quad if ndim == 2 else oracle_hex)(xyz)
    scale = np.abs(want["volume"]).max()
    for name, w in want.items():
        tol = 1e-12 * scale if name in ("volume", "jacobian") else 1e-9
        np.testing.assert_allclose(got[name], w, rtol=1e-10, atol=tol, err_msg=name)
    return got


def _rotation(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def box(ni, nj, nk, h=(1.0, 1.0, 1.0)):
    i, j, k = np.meshgrid(np.arange(ni) * h[0], np.arange(nj) * h[1], np.arange(nk) * h[2], indexing="ij")
    return np.asfortranarray(np.stack([i, j, k], -1).astype(float))


# ------------------------------------------------------------------ per-cell metrics
def test_unit_cube_cells():
    m = cell_metrics(box(3, 4, 5))
    assert m["volume"].shape == (2, 3, 4)
    for name, value in (("volume", 1), ("jacobian", 1), ("scaled_jacobian", 1), ("skewness", 0),
                        ("aspect_ratio", 1)):
        np.testing.assert_allclose(m[name], value, atol=1e-15, err_msg=name)
    assert np.isnan(m["volume_ratio"]).all() and not m["flags"].any()


def test_rectangular_box_aspect_ratio_and_volume():
    m = cell_metrics(box(3, 3, 3, h=(0.5, 2.0, 0.1)))
    np.testing.assert_allclose(m["aspect_ratio"], 20.0)
    np.testing.assert_allclose(m["volume"], 0.1)
    np.testing.assert_allclose(m["jacobian"], 0.1)
    np.testing.assert_allclose(m["scaled_jacobian"], 1.0)


@given(theta=st.floats(5.0, 175.0), la=st.floats(0.1, 10.0), lb=st.floats(0.1, 10.0), lc=st.floats(0.1, 10.0),
       angle=st.floats(0.0, 6.28), ax=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(0.1, 1)))
def test_sheared_parallelepiped_has_the_known_angles(theta, la, lb, lc, angle, ax):
    """Edges a along x, b at theta to a in the x-y plane, c along z, rotated anywhere:
    face angles theta and 180 - theta on the k-faces, 90 elsewhere."""
    t = math.radians(theta)
    a = np.array([la, 0, 0])
    b = lb * np.array([math.cos(t), math.sin(t), 0])
    c = np.array([0, 0, lc])
    R = _rotation(ax, angle)
    xyz = np.empty((3, 2, 2, 3), order="F")
    for i, j, k in itertools.product(range(3), range(2), range(2)):
        xyz[i, j, k] = R @ (i * a + j * b + k * c) + np.array([1.0, -2.0, 3.0])
    m = cell_metrics(xyz)
    vol = la * lb * lc * math.sin(t)
    np.testing.assert_allclose(m["volume"], vol, rtol=1e-11)
    np.testing.assert_allclose(m["jacobian"], vol, rtol=1e-11)
    np.testing.assert_allclose(m["scaled_jacobian"], math.sin(t), rtol=1e-11)
    np.testing.assert_allclose(m["skewness"], abs(90.0 - theta) / 90.0, atol=1e-9)
    np.testing.assert_allclose(m["aspect_ratio"], max(la, lb, lc) / min(la, lb, lc), rtol=1e-12)
    check_against_oracle(xyz, 3)


def test_frustum_with_planar_faces_has_its_exact_volume():
    # square frustum: bottom side 2, top side 1, height 3 -> h/3 (A1 + A2 + sqrt(A1 A2)) = 7
    xyz = np.empty((2, 2, 2, 3), order="F")
    for i, j, k in itertools.product(range(2), repeat=3):
        half = 1.0 if k == 0 else 0.5
        xyz[i, j, k] = ((2 * i - 1) * half, (2 * j - 1) * half, 3.0 * k)
    assert cell_volumes(xyz)[0, 0, 0] == pytest.approx(7.0, rel=1e-14)
    assert cell_metrics(xyz)["volume"][0, 0, 0] == pytest.approx(7.0, rel=1e-14)


@given(seed=st.integers(0, 2**31), amp=st.floats(0.0, 0.35))
def test_hex_metrics_match_the_numpy_oracle_on_warped_grids(seed, amp):
    xyz = sheared_box(5, 4, 3) + amp * 0.3 * np.random.default_rng(seed).standard_normal((5, 4, 3, 3))
    xyz = np.asfortranarray(xyz)
    got = check_against_oracle(xyz, 3)
    np.testing.assert_array_equal(got["volume"], cell_volumes(xyz))    # one formula everywhere


@given(seed=st.integers(0, 2**31), amp=st.floats(0.0, 0.3))
def test_quad_metrics_match_the_numpy_oracle(seed, amp):
    xyz = annulus(9, 6).copy(order="F")
    xyz[..., :2] += amp * 0.1 * np.random.default_rng(seed).standard_normal(xyz[..., :2].shape)
    got = check_against_oracle(xyz, 2)
    np.testing.assert_array_equal(got["volume"], cell_volumes(xyz))


def test_2d_annulus_analytic():
    """Polar cells are isosceles trapezoids: area (r1^2 - r0^2) sin(dt) / 2, base angles
    90 -+ dt/2, so skewness (dt/2) / 90 deg.  i runs counter-clockwise and j outwards:
    the cells are clockwise in (i, j), their areas and Jacobians negative."""
    ni, nj = 9, 5
    xyz = annulus(ni, nj)
    dt = (np.pi / 2) / (ni - 1)
    r = np.geomspace(1.0, 3.0, nj)
    m = cell_metrics(xyz)
    area = 0.5 * (r[1:] ** 2 - r[:-1] ** 2) * math.sin(dt)
    np.testing.assert_allclose(m["volume"][:, :, 0], -np.broadcast_to(area, (ni - 1, nj - 1)), rtol=1e-13)
    np.testing.assert_allclose(m["skewness"], math.degrees(dt) / 2 / 90, rtol=1e-10)
    chord_in = 2 * r[:-1] * math.sin(dt / 2)
    chord_out = 2 * r[1:] * math.sin(dt / 2)
    radial = r[1:] - r[:-1]
    ar = np.maximum(np.maximum(chord_out, radial), chord_in) / np.minimum(np.minimum(chord_in, radial), chord_out)
    np.testing.assert_allclose(m["aspect_ratio"][0, :, 0], ar, rtol=1e-12)
    # corner Jacobian: the cross product of the unit edges, -sin(90 -+ dt/2) at every corner
    np.testing.assert_allclose(m["scaled_jacobian"], -math.cos(dt / 2), rtol=1e-12)
    assert (m["flags"] & Q.NEGATIVE).all()
    rep = quality_report(Grid([Block(xyz)], ndim=2))        # a left-handed block is valid
    assert rep.blocks[0].handedness == -1 and rep.negative == 0
    assert rep.metrics["scaled_jacobian"].min == pytest.approx(math.cos(dt / 2), rel=1e-12)


def test_one_cell_thick_extrusion_matches_2d():
    x2 = annulus(9, 5)
    h = 0.25
    x3 = np.repeat(x2, 2, axis=2)
    x3[:, :, 1, 2] = h
    x3 = np.asfortranarray(x3)
    m2 = cell_metrics(x2)
    m3 = cell_metrics(x3)
    assert m3["volume"].shape == (8, 4, 1)
    np.testing.assert_allclose(m3["volume"], m2["volume"] * h, rtol=1e-13)
    np.testing.assert_allclose(m3["jacobian"], m2["jacobian"] * h, rtol=1e-13)
    np.testing.assert_allclose(m3["scaled_jacobian"], m2["scaled_jacobian"], rtol=1e-13)
    np.testing.assert_allclose(m3["skewness"], m2["skewness"], rtol=1e-12, atol=1e-15)
    check_against_oracle(x3, 3)


@given(seed=st.integers(0, 2**31), angle=st.floats(-3.1, 3.1), scale=st.floats(0.01, 100.0))
def test_metrics_move_with_a_similarity_transform(seed, angle, scale):
    rng = np.random.default_rng(seed)
    x = np.asfortranarray(sheared_box(4, 3, 3) + 0.03 * rng.standard_normal((4, 3, 3, 3)))
    R = _rotation(rng.standard_normal(3) + 1e-3, angle)
    y = np.asfortranarray(scale * (x @ R.T) + rng.standard_normal(3))
    a, b = cell_metrics(x), cell_metrics(y)
    np.testing.assert_allclose(b["volume"], scale ** 3 * a["volume"], rtol=1e-9)
    np.testing.assert_allclose(b["jacobian"], scale ** 3 * a["jacobian"], rtol=1e-9)
    for name in ("scaled_jacobian", "skewness", "aspect_ratio"):
        np.testing.assert_allclose(b[name], a[name], rtol=1e-8, atol=1e-10, err_msg=name)


def test_flipped_cell_and_flags():
    xyz = box(4, 4, 4)
    xyz[1, 1, 1] = (2.6, 2.6, 2.6)          # pushed through its neighbours: cells fold
    m = cell_metrics(xyz)
    want = oracle_hex(xyz)
    np.testing.assert_array_equal(m["flags"] & Q.NEGATIVE != 0, want["volume"] <= 0)
    np.testing.assert_array_equal(m["flags"] & Q.NEGATIVE_JACOBIAN != 0, want["jacobian"] <= 0)
    assert (want["volume"] <= 0).any() and (want["jacobian"] <= 0).sum() > (want["volume"] <= 0).sum()


def test_degenerate_and_collapsed_cells():
    xyz = box(2, 2, 2)
    xyz[:, :, 1] = xyz[:, :, 0]             # the top face on the bottom one: zero volume
    m = cell_metrics(xyz)
    f = int(m["flags"][0, 0, 0])
    assert m["volume"][0, 0, 0] == 0.0 and f & Q.DEGENERATE and f & Q.NEGATIVE and f & Q.COLLAPSED
    assert m["aspect_ratio"][0, 0, 0] == np.inf
    xyz = box(2, 2, 2)
    xyz[1, 1, 1] = xyz[1, 1, 0]             # one collapsed edge: a positive volume, a zero Jacobian
    m = cell_metrics(xyz)
    f = int(m["flags"][0, 0, 0])
    assert m["volume"][0, 0, 0] > 0 and f & Q.COLLAPSED and f & Q.NEGATIVE_JACOBIAN
    assert not f & Q.DEGENERATE and not f & Q.NEGATIVE
    assert m["jacobian"][0, 0, 0] == 0.0 and m["scaled_jacobian"][0, 0, 0] == 0.0


def test_volume_ratio_of_an_affine_map():
    x = sheared_box(5, 4, 3)
    A = np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.2], [0.05, 0.0, 1.1]])
    y = np.asfortranarray(x @ A.T + 0.5)
    m = cell_metrics(y, ref=x)
    np.testing.assert_allclose(m["volume_ratio"], np.linalg.det(A), rtol=1e-12)


def _summary_reference(grid, ref):
    """volume_ratio_summary written plainly: ratios in C order, ``np.argmin`` over them."""
    neg, best = 0, (np.inf, None)
    for b, (blk, rb) in enumerate(zip(grid, ref)):
        v, vr = cell_volumes(blk, grid.ndim), cell_volumes(rb, grid.ndim)
        ratio = np.full(v.shape, np.inf)
        ok = vr != 0.0
        ratio[ok] = v[ok] / vr[ok]
        neg += int(np.count_nonzero(ratio <= 0.0))
        m = int(np.argmin(ratio))
        if ratio.flat[m] < best[0]:
            best = (float(ratio.flat[m]), (b, *map(int, np.unravel_index(m, ratio.shape))))
    return {"negative": neg, "min_ratio": best[0], "where": best[1]}


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), two_d=st.booleans(), nan=st.booleans())
def test_volume_ratio_summary_matches_its_definition(seed, two_d, nan):
    """Ties (cells repeated along k and i), zero reference volumes, flipped cells, a NaN."""
    rng = np.random.default_rng(seed)
    blocks, refs = [], []
    for _ in range(int(rng.integers(1, 3))):
        ni, nj, nk = (int(n) for n in rng.integers(2, 6, 3))
        nk = 1 if two_d else nk
        x = np.zeros((ni, nj, nk, 3))
        x[..., 0] = np.arange(ni)[:, None, None] * rng.choice([1.0, 0.5])
        x[..., 1] = rng.choice([0.0, 1.0, 2.0], nj).cumsum()[None, :, None]   # repeated rows: zero volumes
        x[..., 2] = np.arange(nk)[None, None, :]
        y = x.copy()
        y[..., 1] *= rng.choice([1.0, -1.0, 0.5])                               # flipped or squeezed: ties
        y[..., 0] += 0.3 * (rng.random(y.shape[:3]) < 0.2)
        if nan:
            y[tuple(int(rng.integers(n)) for n in y.shape[:3]) + (0,)] = np.nan
        blocks.append(Block(np.asfortranarray(y), allow_nonfinite=True))
        refs.append(Block(np.asfortranarray(x)))
    ndim = 2 if two_d else 3
    grid, ref = Grid(blocks, ndim, allow_nonfinite=True), Grid(refs, ndim)
    got, want = Q.volume_ratio_summary(grid, ref), _summary_reference(grid, ref)
    assert got["negative"] == want["negative"] and got["where"] == want["where"]
    assert got["min_ratio"] == want["min_ratio"] or (np.isnan(got["min_ratio"]) and np.isnan(want["min_ratio"]))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), ni=st.integers(2, 9), nj=st.integers(2, 7), nan=st.booleans())
def test_small_2d_ratio_rows_with_numpy_are_the_compiled_rows(seed, ni, nj, nan):
    """Small 2-D blocks reduce their ratios with numpy (no compiled kernel in the demo): the
    same counts, smallest ratios (bits: -0.0 and 0.0 ties, inf rows, the first NaN) and first
    indices as the compiled :func:`_ratio_rows`."""
    rng = np.random.default_rng(seed)
    vals = np.array([0.0, -0.0, 1.0, 2.0, -1.0, 0.5, np.inf])
    xr = np.asfortranarray(rng.choice(vals[:6], (ni, nj, 1, 3)))     # many zero areas: inf
    x = np.asfortranarray(rng.choice(vals[:6], (ni, nj, 1, 3)) * rng.choice([1.0, 1e300], (ni, nj, 1, 3)))
    if nan:
        x[int(rng.integers(ni)), int(rng.integers(nj)), 0, int(rng.integers(2))] = np.nan
    out = [(np.empty(nj - 1, dtype=np.int64), np.empty(nj - 1), np.empty(nj - 1, dtype=np.int64))
           for _ in range(2)]
    assert (ni - 1) * (nj - 1) < Q._RATIOS_NUMPY_BELOW
    Q._ratio_rows_2d(x, xr, *out[0])
    parallel_for(Q._ratio_rows, 1, x, xr, None, *out[1])
    for a, b in zip(*out):
        assert a.tobytes() == b.tobytes()


def _det3(u, v, w):
    """The corner determinant as the per-corner check expanded it (numpy, no fused multiply-add)."""
    return (u[..., 0] * (v[..., 1] * w[..., 2] - v[..., 2] * w[..., 1])
            - u[..., 1] * (v[..., 0] * w[..., 2] - v[..., 2] * w[..., 0])
            + u[..., 2] * (v[..., 0] * w[..., 1] - v[..., 1] * w[..., 0]))


def _check_reference(x, xr, block=0, max_locations=5):
    """check_block written plainly in numpy: every corner's determinant of its own three edges
    (no shared cross products), ratios per cell, rows in order k then j, NaN first."""
    def dets(y):
        di, dj, dk = y[1:] - y[:-1], y[:, 1:] - y[:, :-1], y[:, :, 1:] - y[:, :, :-1]
        ni, nj, nk = y.shape[:3]
        return {(a, b, c): _det3(di[:, b:b + nj - 1, c:c + nk - 1], dj[a:a + ni - 1, :, c:c + nk - 1],
                                 dk[a:a + ni - 1, b:b + nj - 1])
                for a, b, c in CORNERS}
    jd, jr = dets(x), dets(xr)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.stack([np.where(jr[c] != 0.0, jd[c] / jr[c], np.inf) for c in CORNERS], -1)
    q = q.min(axis=-1)                                       # NaN if any corner is NaN
    v, vr = cell_volumes(x, 3), cell_volumes(xr, 3)
    neg = ((vr > 0.0) & ~(v > 0.0)) | ((vr < 0.0) & ~(v < 0.0))
    negj = ~(q > 0.0)
    order = lambda a: np.transpose(a, (2, 1, 0)).reshape(-1)   # rows k, then j, then i
    flat_q = order(q)
    nan = np.flatnonzero(np.isnan(flat_q))
    at = int(nan[0]) if nan.size else int(np.argmin(flat_q))
    nci, ncj = q.shape[:2]
    cell = lambda f: (block, f % nci, (f // nci) % ncj, f // (nci * ncj))
    lo = float(flat_q[at])
    bad = np.flatnonzero(order(neg | negj))
    first, rows = [], set()
    for f in bad:
        if f // nci not in rows:
            rows.add(f // nci)
            first.append(cell(int(f)))
    return lo, (None if lo == np.inf else cell(at)), int(neg.sum()), int(negj.sum()), tuple(first[:max_locations])


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), amp=st.sampled_from([0.0, 0.05, 0.4, 1.5]), nan=st.booleans(),
       collapse=st.booleans(), flip=st.booleans())
def test_check_block_matches_the_per_corner_determinants_bit_for_bit(seed, amp, nan, collapse, flip):
    """check_block's shared cross products give the bits of one determinant per corner: the
    smallest ratio (NaN first, first cell in row order), its cell, the counts, the first bad
    cells; with and without the reference's volume sign (CheckReference)."""
    rng = np.random.default_rng(seed)
    ni, nj, nk = (int(n) for n in rng.integers(2, 9, 3))
    xr = np.stack(np.meshgrid(np.arange(ni) * 1.0, np.arange(nj) * 0.7, np.arange(nk) * 1.3, indexing="ij"), -1)
    xr = xr + 0.1 * rng.standard_normal(xr.shape)
    if flip:
        xr = xr[::-1].copy()                                 # a left-handed reference
    if collapse:
        xr[:, 0, 0] = xr[:, 0, 0].mean(axis=0)               # a collapsed line: zero Jacobians, volumes
    x = xr + amp * rng.standard_normal(xr.shape)
    if amp == 0.0:
        x = xr.copy()                                        # no motion: every counted ratio 1
    if nan:
        x[tuple(int(rng.integers(n)) for n in x.shape[:3]) + (int(rng.integers(3)),)] = np.nan
    x, xr = np.asfortranarray(x), np.asfortranarray(xr)
    want = _check_reference(x, xr, 2)
    cref = Q.check_reference(xr)
    vr = cell_volumes(xr, 3)
    assert cref.sign == (1 if (vr > 0).all() else -1 if (vr < 0).all() else 0) and cref.xyz is xr
    for ref in (xr, cref):
        got = Q.check_block(x, ref, 3, 2)
        assert (got.min_at, got.negative, got.negative_jacobian, got.first) == want[1:], type(ref)
        assert np.float64(got.min_ratio).tobytes() == np.float64(want[0]).tobytes() or \
            (np.isnan(got.min_ratio) and np.isnan(want[0])) or got.min_ratio == want[0] == 0.0
    if amp == 0.0 and not nan:
        assert got.ok and got.min_ratio == 1.0 and got.negative == 0


def test_check_block_rows_split_among_threads_give_one_answer():
    """The smallest ratio is the block's first whatever the split of the rows into tasks (each
    task skips rows that cannot beat its earlier ones): equal minima in many rows."""
    rng = np.random.default_rng(7)
    xr = np.stack(np.meshgrid(np.arange(9.0), np.arange(7.0), np.arange(6.0), indexing="ij"), -1)
    x = xr.copy()
    x[..., 2] *= 0.5                                          # every ratio 0.5: ties everywhere
    x[4, 3:, 2:, 0] += 0.3 * rng.random((4, 4))
    x, xr = np.asfortranarray(x), np.asfortranarray(xr)
    want = _check_reference(x, xr)
    res = np.empty((6 * 5, 6))
    for split in ([0, 30], [0, 1, 30], [0, 7, 13, 29, 30], list(range(31))):
        for lo, hi in zip(split[:-1], split[1:]):
            Q._step_check(lo, hi, x, xr, 3, 1, res)
        nan = np.flatnonzero(res[:, 5] > 0)
        r = int(nan[0]) if nan.size else int(np.argmin(res[:, 0]))
        assert (res[r, 0], (0, int(res[r, 1]), r % 6, r // 6)) == (want[0], want[1]), split
    assert Q.check_block(x, xr, 3).min_at == want[1]


def test_check_block_and_check_reference_refuse_bad_input():
    x = np.asfortranarray(sheared_box(3, 3, 3))
    with pytest.raises(GridValueError, match="xyz"):
        Q.check_block(np.ascontiguousarray(x), x, 3)
    with pytest.raises(GridValueError, match="ref"):
        Q.check_reference(np.ascontiguousarray(x))
    with pytest.raises(GridValueError, match="ref.*ndim 3"):
        Q.check_block(np.asfortranarray(x[:, :, :1]), Q.check_reference(x), 2)
    with pytest.raises(GridValueError, match="shape"):
        Q.check_block(np.asfortranarray(x[:2]), Q.check_reference(x), 3)
    assert Q.check_reference(x).sign == 1 and Q.check_reference(np.asfortranarray(x[::-1])).sign == -1
    assert Q.check_reference(np.zeros((1, 3, 3, 3), order="F")).sign == 0
    flat = np.asfortranarray(x[:, :, :1])
    assert Q.check_reference(flat).sign == 1 and Q.check_reference(flat).ndim == 2


def test_compiled_and_uncompiled_kernels_agree():
    x = np.asfortranarray(sheared_box(4, 3, 3) + 0.05 * np.random.default_rng(3).standard_normal((4, 3, 3, 3)))
    rows = np.arange(4, dtype=np.int64)
    for kernel in (Q._block_fields, Q._block_fields.py_func):
        out = np.empty((3, 4, len(METRICS)), order="F")
        flags = np.empty((3, 4), dtype=np.uint8, order="F")
        parallel_for(kernel, rows.size, x, x * 1.1, True, 3, 1.0, 1e-12, rows, out, flags)
        if kernel is Q._block_fields:
            ref = out.copy()
        else:
            np.testing.assert_allclose(out, ref, rtol=1e-15)
    rb = np.empty((3, len(METRICS) + 1))
    rf = np.empty(3, dtype=np.uint8)
    Q._hex_row.py_func(x, 1, 1, 1.0, 1e-12, x, False, rb, rf)
    np.testing.assert_allclose(rb[:, :5], ref[:, 3, :5], rtol=1e-15)


def test_bad_arguments():
    with pytest.raises(GridValueError, match="shape"):
        cell_metrics(np.zeros((3, 3, 3)))
    with pytest.raises(GridValueError, match="reference"):
        cell_metrics(box(3, 3, 3), ref=box(3, 3, 4))



# ------------------------------------------------------------------ cell validity
def _folded(xyz, seed, nfold, planar):
    """``xyz`` with ``nfold`` points pushed hard enough to fold some cells."""
    rng = np.random.default_rng(seed)
    x = xyz.copy(order="F")
    scale = np.abs(np.diff(xyz, axis=0)).max()
    for _ in range(nfold):
        idx = tuple(int(rng.integers(0, n)) for n in x.shape[:3])
        x[idx][:2 if planar else 3] += rng.normal(0.0, 1.5 * scale, 2 if planar else 3)
    return x


@given(seed=st.integers(0, 2**31), nfold=st.integers(0, 6), planar=st.booleans(),
       tol=st.sampled_from([0.0, 1e-9, 0.2]))
def test_invalid_cells_agree_with_the_numpy_reference(seed, nfold, planar, tol):
    xyz = annulus(9, 7) if planar else sheared_box(6, 5, 4)
    x = _folded(xyz, seed, nfold, planar)
    count, first = invalid_cells(x, corner_tol=tol)
    ref_count, ref_first = _cells.invalid(x, tol)
    assert count == ref_count
    assert first == (None if ref_first is None else ref_first + ((0,) if planar else ()))


@pytest.mark.parametrize("planar", [True, False])
def test_invalid_cell_kernel_compiled_and_uncompiled_agree(planar, monkeypatch):
    x = _folded(annulus(7, 5) if planar else sheared_box(4, 3, 3), 3, 4, planar)
    ndim = 2 if planar else 3
    got = [Q._invalid_cells(x, ndim, 1e-9)]
    monkeypatch.setattr(Q, "_invalid_rows", Q._invalid_rows.py_func)
    got.append(Q._invalid_cells(x, ndim, 1e-9))
    assert got[0] == got[1] and got[0][0] > 0
    assert got[0] == (_cells.invalid(x, 1e-9)[0], *invalid_cells(x, ndim, 1e-9)[1])


def test_invalid_cells_right_handed_strict_and_tolerant_corners():
    x = box(3, 3, 3)
    assert invalid_cells(x) == (0, None)
    # validity is absolute: a left-handed block is all invalid (the report calls it valid)
    assert invalid_cells(np.asfortranarray(x[::-1])) == (8, (0, 0, 0))
    # a collapsed edge: the cell keeps a positive volume, two corners get a scaled Jacobian of 0
    y = box(2, 2, 2)
    y[1, 1, 1] = y[1, 1, 0]
    assert invalid_cells(y) == (1, (0, 0, 0)) and invalid_cells(y, corner_tol=1e-9) == (0, None)
    # an arrowhead quad: positive area, a reflex corner
    q = np.zeros((2, 2, 1, 3), order="F")
    q[0, 0, 0, :2], q[1, 0, 0, :2], q[0, 1, 0, :2], q[1, 1, 0, :2] = [0, 0], [2, 0], [0, 2], [0.4, 0.4]
    assert cell_volumes(q)[0, 0, 0] > 0 and invalid_cells(q) == (1, (0, 0, 0))
    assert invalid_cells(q, corner_tol=0.9) == (0, None)      # its reflex corner: -0.88
    # NaN coordinates make their cells invalid; blocks without cells have none
    z = box(3, 3, 3)
    z[2, 2, 2, 0] = np.nan
    assert invalid_cells(z, corner_tol=1e-9) == (1, (1, 1, 1))
    assert invalid_cells(box(1, 3, 3)) == (0, None) and invalid_cells(box(3, 3, 1), ndim=3) == (0, None)


def test_invalid_cells_bad_arguments():
    for bad in (-1e-3, np.nan, np.inf, "x"):
        with pytest.raises(GridValueError, match="corner_tol must be a finite number >= 0"):
            invalid_cells(box(2, 2, 2), corner_tol=bad)
    with pytest.raises(GridValueError, match="nk == 1"):
        invalid_cells(box(2, 2, 2), ndim=2)
    with pytest.raises(GridValueError, match="shape"):
        invalid_cells(np.zeros((3, 3, 3)))


# ------------------------------------------------------------------ the report
def _grid3(x):
    return Grid([Block(x)], ndim=3)


def test_report_stats_equal_the_per_cell_fields():
    rng = np.random.default_rng(5)
    xs = [np.asfortranarray(sheared_box(6, 5, 4) + 0.02 * rng.standard_normal((6, 5, 4, 3))),
          np.asfortranarray(sheared_box(3, 7, 5) + 0.02 * rng.standard_normal((3, 7, 5, 3)) + 5.0)]
    g = Grid([Block(x) for x in xs], ndim=3)
    ref = Grid([Block(sheared_box(6, 5, 4)), Block(sheared_box(3, 7, 5) + 5.0)], ndim=3)
    rep = quality_report(g, ref=ref)
    fields = [cell_metrics(x, ref=r.xyz) for x, r in zip(xs, ref)]
    for name in METRICS:
        allv = np.concatenate([f[name].ravel(order="F") for f in fields])
        st_ = rep.metrics[name]
        assert st_.min == allv.min() and st_.max == allv.max(), name
        assert st_.mean == pytest.approx(allv.mean(), rel=1e-12)
        assert st_.count == allv.size
        b, *ijk = st_.argmin
        assert fields[b][name][tuple(ijk)] == st_.min
        b, *ijk = st_.argmax
        assert fields[b][name][tuple(ijk)] == st_.max
        for bq, f in zip(rep.blocks, fields):
            assert bq.metrics[name].min == f[name].min()
    assert rep.ncells == sum(f["volume"].size for f in fields) and rep.npoints == g.npoints
    assert rep.negative == 0 and rep.valid and rep.has_reference


def test_report_lists_negative_cells_with_block_and_indices():
    xa = box(4, 4, 4)
    xb = box(5, 4, 3)
    xb[2, 1, 1] = (4.5, 3.5, 2.5)
    g = Grid([Block(xa), Block(xb)], ndim=3)
    rep = quality_report(g, max_locations=50)
    want = oracle_hex(xb)
    neg = [tuple(int(c) for c in ijk) for ijk in np.argwhere(want["volume"] <= 0)]
    negj = np.argwhere(want["jacobian"] <= 0)
    assert rep.negative == len(neg) > 0 and rep.negative_jacobian == len(negj)
    assert rep.blocks[0].negative == 0 and rep.blocks[1].negative == len(neg)
    # file order: i fastest, then j, then k
    order = sorted(neg, key=lambda t: (t[2], t[1], t[0]))
    assert rep.negative_cells == [(1, *t) for t in order]
    assert not rep.valid
    text = rep.summary()
    b, i, j, k = rep.negative_cells[0]
    assert f"block {b + 1} ({i + 1}, {j + 1}, {k + 1})" in text       # 1-based in the text
    d = rep.to_dict(one_based=True)
    assert d["index_base"] == 1 and d["negative_cells"][0] == [b + 1, i + 1, j + 1, k + 1]
    assert quality_report(g, max_locations=2).negative_cells == rep.negative_cells[:2]


def test_left_handed_blocks_are_valid():
    x = box(4, 3, 3)
    flipped = np.asfortranarray(x[::-1])
    rep = quality_report(_grid3(flipped))
    assert rep.blocks[0].handedness == -1 and rep.negative == 0 and rep.negative_jacobian == 0
    assert rep.metrics["volume"].min == pytest.approx(1.0) and rep.metrics["scaled_jacobian"].min == 1.0
    # a flipped deformation of a right-handed reference is all negative
    rep = quality_report(_grid3(flipped), ref=_grid3(x))
    assert rep.blocks[0].handedness == 1 and rep.negative == rep.ncells
    assert rep.metrics["volume_ratio"].max == pytest.approx(-1.0)


def test_report_2d_and_degenerate_counts():
    g = tfi_quat.read("grids/naca0012_c_257x65.x")
    rep = quality_report(g, walls=["1:jmin:65-193"], layers=3)
    assert rep.ndim == 2 and rep.ncells == 256 * 64 and rep.negative == 0 and rep.degenerate == 0
    want = oracle_quad(g[0].xyz)
    assert rep.metrics["skewness"].max == pytest.approx(want["skewness"].max(), rel=1e-9)
    assert rep.metrics["volume"].min == pytest.approx(want["volume"].min(), rel=1e-9)
    assert "area" in rep.summary() and rep.walls[0].points == 129
    x = box(3, 3, 1)
    x[1, 0, 0] = x[0, 0, 0]                 # a collapsed edge: cell (0, 0) is a triangle
    rep = quality_report(Grid([Block(x)], ndim=2))
    assert rep.negative_jacobian_cells == [(0, 0, 0, 0)] and rep.negative == 0
    assert rep.collapsed == 1 and rep.degenerate == 0 and rep.negative_jacobian == 1
    assert rep.metrics["aspect_ratio"].count == 3       # the collapsed cell's is infinite


def test_report_orthogonality_and_change():
    # a polar grid whose first layer is tilted by 12 deg: the change is 12 deg at layer 1
    t = np.linspace(0.0, 1.5 * np.pi, 33)[:, None]
    r = np.linspace(1.0, 3.0, 9)[None, :]
    ref = np.zeros((33, 9, 1, 3), order="F")
    ref[:, :, 0, 0] = r * np.cos(t)
    ref[:, :, 0, 1] = r * np.sin(t)
    x = ref.copy(order="F")
    w = x[:, 0, 0, :2]
    n = w / np.linalg.norm(w, axis=1, keepdims=True)
    tg = np.stack([-n[:, 1], n[:, 0]], axis=1)
    h = np.linalg.norm(x[:, 1, 0, :2] - w, axis=1, keepdims=True)
    ang = np.radians(12.0)
    x[:, 1, 0, :2] = w + h * (np.cos(ang) * n + np.sin(ang) * tg)
    g, gr = Grid([Block(x)], ndim=2), Grid([Block(ref)], ndim=2)
    rep = quality_report(g, ref=gr, walls=["1:jmin"], layers=5)
    wo = rep.walls[0]
    assert wo.change_max == pytest.approx(12.0, abs=1e-6) and wo.change_argmax[-1] == 0
    assert wo.change_layer_max[0] == pytest.approx(12.0, abs=1e-6) and len(wo.change_layer_max) == 5
    want = np.abs(wall_orthogonality(g, ["1:jmin"], 5)[0] - wall_orthogonality(gr, ["1:jmin"], 5)[0])
    assert wo.change_mean == pytest.approx(np.nanmean(want))
    assert rep.orthogonality["change_max"] == wo.change_max
    assert "change max" in rep.summary()
    # per-cell orthogonality change: layer 1 cells (j = 0) carry it, deeper ones are 0, beyond 5 NaN
    c = cell_orthogonality(g, ["1:jmin"], layers=5, ref=gr)[0]
    assert c.shape == (32, 8, 1)
    np.testing.assert_allclose(c[1:-1, 0, 0], 12.0, atol=1e-6)
    assert np.isnan(c[:, 5:]).all() and np.nanmax(c[:, 2:5]) < 1e-6


def test_report_to_dict_is_json_and_round_trips():
    g = tfi_quat.read("grids/two_block_65x33.x")
    rep = quality_report(g, ref=g, walls=["1:jmin"])
    for base in (False, True):
        d = rep.to_dict(one_based=base)
        assert json.loads(json.dumps(d, allow_nan=False)) == d
    d = rep.to_dict()
    assert set(d["metrics"]) == set(METRICS) and len(d["blocks"]) == 2
    assert d["metrics"]["volume_ratio"]["min"] == 1.0 and d["orthogonality"]["change_max"] == 0.0


def test_report_on_the_3d_wing_with_its_case():
    from tfi_quat.case import load_case
    case = load_case("grids/wing_ch_501k.toml")
    g = tfi_quat.read(case.grid)
    rep = quality_report(g, walls=case.walls)
    assert rep.negative == 0 and rep.degenerate == 0 and len(rep.walls) == 2
    # sharp trailing edge: corners where the wake line continues the wall have a zero Jacobian
    assert rep.negative_jacobian == sum(b.negative_jacobian for b in rep.blocks)
    assert all(len(b.dims) == 3 for b in rep.blocks)


def test_report_bad_arguments():
    g = _grid3(box(3, 3, 3))
    with pytest.raises(GridValueError, match="block"):
        quality_report(g, ref=Grid([Block(box(3, 3, 3)), Block(box(3, 3, 3))], ndim=3))
    with pytest.raises(GridValueError, match="dimensions"):
        quality_report(g, ref=_grid3(box(3, 3, 4)))
    with pytest.raises(CaseError, match="block"):
        quality_report(g, walls=["3:imin"])
    with pytest.raises(CaseError, match="walls: cannot read 42"):
        wall_orthogonality(g, walls=[42])
    with pytest.raises(CaseError, match="range exceeds the face size 3 x 3"):
        cell_orthogonality(g, walls=["1:kmax:1-4,1-3"])
    with pytest.raises(ValueError, match="layers"):
        quality_report(g, walls=["1:imin"], layers=0)
    with pytest.raises(GridValueError, match="Grid"):
        quality_report(box(3, 3, 3))
