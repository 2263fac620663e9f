"""Tests of tfi_quat.tfi: arclength parameters and Soni TFI kernels (docs/method.md §3.2, §3.4, §3.5)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from tfi_quat import GridValueError, blending, tfi
from tfi_quat import quaternion as qa
from tfi_quat.grid import Block
from tfi_quat._jit import parallel_for
from tfi_quat.kernels import by_direction

import oracles
from conftest import sheared_box

ORDERS = list(itertools.permutations(range(3)))
SHAPES = [(5, 4, 3), (6, 5, 4), (1, 4, 3), (5, 1, 3), (4, 3, 1), (2, 2, 2), (3, 7, 2), (1, 1, 4)]


# ------------------------------------------------------------------ helpers
def rot(q, v):
    """Independent oracle: rotate v by unit quaternions q (w, x, y, z) with scipy."""
    q = np.asarray(q, dtype=float)
    v = np.asarray(v, dtype=float)
    shape = np.broadcast_shapes(q.shape[:-1], v.shape[:-1])
    qq = np.array(np.broadcast_to(q, shape + (4,))).reshape(-1, 4)
    vv = np.array(np.broadcast_to(v, shape + (3,))).reshape(-1, 3)
    return Rotation.from_quat(qq, scalar_first=True).apply(vv).reshape(shape + (3,))


def quat(rv):
    """Unit quaternions (w, x, y, z) from rotation vectors (..., 3)."""
    rv = np.asarray(rv, dtype=float)
    return Rotation.from_rotvec(rv.reshape(-1, 3)).as_quat(scalar_first=True).reshape(rv.shape[:-1] + (4,))


def warped_block(shape, seed=0, amp=0.04):
    """A sheared box with a smooth random warp, float64 F order."""
    ni, nj, nk = shape
    xyz = sheared_box(ni, nj, nk).copy(order="F")
    rng = np.random.default_rng(seed)
    a = rng.uniform(-1.0, 1.0, (3, 3))
    xyz += amp * np.sin(xyz @ a.T + rng.uniform(0.0, 6.0, 3))
    return np.asfortranarray(xyz)


def dfun(p, seed=0):
    rng = np.random.default_rng(seed + 100)
    a = rng.uniform(-1.0, 1.0, (3, 3))
    return 0.2 * np.sin(p @ a.T + 0.3)


def qfun(p, seed=0, amp=0.6):
    rng = np.random.default_rng(seed + 200)
    a = rng.uniform(-1.0, 1.0, (3, 3))
    return quat(amp * np.cos(p @ a.T + 0.5))


def faces_of(xyz, fun, **kw):
    b = Block(xyz)
    return [np.array(fun(b.face(f), **kw)) for f in range(6)]


def flip_signs(fq, seed):
    """Negate random face quaternions (same rotations)."""
    rng = np.random.default_rng(seed + 300)
    return [q * np.where(rng.random(q.shape[:-1]) < 0.5, -1.0, 1.0)[..., None] for q in fq]


def expected_face(xyz, f, fd, fq, c):
    p = Block(xyz).face(f)
    if fq is None:
        return p + fd[f]
    return c + fd[f] + rot(fq[f], p - c)


def scale(xyz):
    return max(1.0, float(np.max(np.abs(xyz))))


def ref_update(xyz, s, fd, fq, c, order):
    D, Q = oracles.tfi_block_fields(fd, fq, s, order)
    if Q is None:
        return xyz + D, D, Q
    return c + D + rot(Q, xyz - c), D, Q


shapes_st = st.sampled_from(SHAPES)
orders_st = st.sampled_from(ORDERS)
seeds_st = st.integers(0, 10_000)


# ================================================================== arclength
def test_arclength_ends_monotone_and_dtype(box_xyz):
    s = tfi.arclength(box_xyz)
    assert s.shape == box_xyz.shape and s.dtype == tfi.S_DTYPE and s.flags.f_contiguous
    for d in range(3):
        sd = np.moveaxis(s[..., d], d, 0)
        assert np.all(sd[0] == 0.0) and np.all(sd[-1] == 1.0)
        assert np.all(np.diff(sd, axis=0) > 0.0)


@given(shapes_st, seeds_st)
def test_arclength_matches_cumulative_length(shape, seed):
    xyz = warped_block(shape, seed)
    s = tfi.arclength(xyz)
    for d in range(3):
        x = np.moveaxis(xyz, d, 0)
        sd = np.moveaxis(s[..., d], d, 0)
        if x.shape[0] == 1:
            assert np.all(sd == 0.0)
            continue
        seg = np.linalg.norm(np.diff(x, axis=0), axis=-1)
        cum = np.concatenate([np.zeros((1,) + seg.shape[1:]), np.cumsum(seg, axis=0)])
        np.testing.assert_allclose(sd, cum / cum[-1], rtol=0, atol=1e-14)
        assert np.all(sd[-1] == 1.0) and np.all(sd[0] == 0.0)
        assert np.all(np.diff(sd, axis=0) >= 0.0)


def test_arclength_geometric_stretching_is_analytic():
    n, r = 17, 1.3
    g = (r ** np.arange(n) - 1.0) / (r ** (n - 1) - 1.0)        # geometric spacing, 0..1
    direction = np.array([0.3, -0.5, 0.8])
    xyz = np.zeros((n, 3, 2, 3), order="F")
    for j in range(3):
        for k in range(2):
            length = 1.0 + j + 2.0 * k
            xyz[:, j, k] = np.array([j, 2.0 * k, 1.0]) + length * g[:, None] * direction
    s = tfi.arclength(xyz)
    np.testing.assert_allclose(s[..., 0], np.broadcast_to(g[:, None, None], (n, 3, 2)), rtol=0, atol=2e-15)
    curve = tfi.arclength_curve(xyz[:, 1, 1])
    np.testing.assert_allclose(curve, g, rtol=0, atol=2e-15)


def test_arclength_zero_length_lines_are_index_uniform():
    # a pole: all points of the i-lines at j = 0 collapse onto one point (O-O grid cap)
    ni, nj, nk = 5, 4, 3
    xyz = sheared_box(ni, nj, nk).copy(order="F")
    xyz[:, 0, :, :] = xyz[:1, 0, :, :]
    xyz[:, 0, 1, :] += 1e-17          # round-off noise on a collapsed line
    s = tfi.arclength(xyz)
    np.testing.assert_array_equal(s[:, 0, :, 0], np.broadcast_to(np.linspace(0, 1, ni)[:, None], (ni, nk)))
    assert np.all(np.isfinite(s))
    # the whole block collapsed to one point: everything index-uniform
    s = tfi.arclength(np.zeros((3, 5, 2, 3), order="F"))
    np.testing.assert_array_equal(s[..., 1], np.broadcast_to(np.linspace(0, 1, 5)[None, :, None], (3, 5, 2)))


def test_arclength_surface_and_curve_agree_with_the_block(box_xyz):
    s64 = tfi.arclength(box_xyz)
    surf = tfi.arclength_surface(Block(box_xyz).face("kmin"))
    assert surf.shape == box_xyz.shape[:2] + (2,)
    np.testing.assert_array_equal(surf, s64[:, :, 0, :2])
    np.testing.assert_array_equal(tfi.arclength_curve(box_xyz[:, 2, 1]), s64[:, 2, 1, 0])
    np.testing.assert_array_equal(tfi.arclength_curve(box_xyz[:1, 2, 1]), [0.0])


def test_arclength_kernel_uncompiled_equals_compiled():
    xyz = warped_block((4, 3, 3), 7)
    xyz[:, 0, :, :] = xyz[:1, 0, :, :]
    a = np.empty_like(xyz)
    b = np.empty_like(xyz)
    # arclength runs the wall-layer arclength kernels with no layer (zero thicknesses)
    for d in range(3):
        zero = np.zeros(tuple(xyz.shape[m] for m in range(3) if m != d))
        by_direction(blending._arc_layer_i, blending._arc_layer_jk, d, xyz,
                     tfi.ZERO_LENGTH_RTOL, zero, zero, a)
        by_direction(blending._arc_layer_i.py_func, blending._arc_layer_jk.py_func, d, xyz,
                     tfi.ZERO_LENGTH_RTOL, zero, zero, b)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, tfi.arclength(xyz))


@pytest.mark.parametrize("bad, match", [
    (np.zeros((3, 4, 5, 3)), "xyz: expected a Fortran-ordered"),
    (np.zeros((3, 4, 5, 3), dtype=np.float32, order="F"), "xyz: expected dtype float64"),
    (np.zeros((3, 4, 3), order="F"), r"xyz: expected shape \(ni, nj, nk, 3\)"),
    ([[[[0.0, 0.0, 0.0]]]], "xyz: expected a numpy array"),
])
def test_arclength_rejects_bad_input(bad, match):
    with pytest.raises(GridValueError, match=match):
        tfi.arclength(bad)


def test_arclength_rejects_bad_curve_and_surface_shapes():
    with pytest.raises(GridValueError, match="r: expected shape"):
        tfi.arclength_curve(np.zeros((4, 2)))
    with pytest.raises(GridValueError, match="r: expected shape"):
        tfi.arclength_surface(np.zeros((4, 3)))


# ================================================================== lead order
def test_lead_order_rule_and_ties():
    assert tfi.lead_order([0, 0, 100, 100, 0, 0]) == (1, 0, 2)
    assert tfi.lead_order([0, 0, 0, 0, 30, 0]) == (2, 0, 1)
    assert tfi.lead_order([5, 5, 10, 0, 1, 1]) == (0, 1, 2)        # 10 vs 10: lowest index leads
    assert tfi.lead_order([0, 0, 0, 0, 0, 0]) == (0, 1, 2)
    assert tfi.lead_order([1, 2, 3, 4, 5, 6]) == (2, 1, 0)
    assert tfi.lead_order([0, 0, 7, 0]) == (1, 0)
    assert tfi.lead_order(np.array([3, 0, 3, 0])) == (0, 1)


@pytest.mark.parametrize("bad", [[1, 2, 3], [1, 2, 3, 4, 5, 6, 7], [0, 0, -1, 0], ["a"] * 4, [1.5, 0, 0, 0]])
def test_lead_order_rejects_bad_counts(bad):
    with pytest.raises(GridValueError, match="prescribed_counts"):
        tfi.lead_order(bad)


# ================================================================== segment
@given(seeds_st)
def test_interp_segment_linear_delta_and_slerp(seed):
    rng = np.random.default_rng(seed)
    d0, d1 = rng.normal(size=3), rng.normal(size=3)
    q0, q1 = quat(rng.normal(size=3)), quat(rng.normal(size=3))
    if rng.random() < 0.5:
        q1 = -q1                            # same rotation, other hemisphere
    s = np.concatenate([[0.0], np.sort(rng.random(7)), [1.0]])
    delta, q = tfi.interp_segment(d0, q0, d1, q1, s)
    np.testing.assert_allclose(delta, (1 - s[:, None]) * d0 + s[:, None] * d1, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(delta[0], d0)
    np.testing.assert_array_equal(delta[-1], d1)
    np.testing.assert_array_equal(q[0], q0)
    sign = 1.0 if np.dot(q0, q1) >= 0 else -1.0
    np.testing.assert_array_equal(q[-1], sign * q1)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, rtol=0, atol=1e-15)
    oracle = Slerp([0.0, 1.0], Rotation.from_quat([q0, q1], scalar_first=True))(s)
    v = rng.normal(size=3)
    np.testing.assert_allclose(rot(q, v), oracle.apply(v), rtol=0, atol=1e-13)
    # shortest arc, continuous: consecutive values stay in one hemisphere
    assert np.all(np.sum(q[1:] * q[:-1], axis=1) > 0.0)


def test_interp_segment_baseline_and_tiny_angles():
    delta, q = tfi.interp_segment([0, 0, 0], None, [1, 2, 3], None, [0.0, 0.25, 1.0])
    assert q is None
    np.testing.assert_array_equal(delta[1], [0.25, 0.5, 0.75])
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    q1 = quat(np.array([1e-12, 0.0, 0.0]))
    _, q = tfi.interp_segment(np.zeros(3), q0, np.zeros(3), q1, np.linspace(0, 1, 5))
    np.testing.assert_allclose(q[:, 1], np.linspace(0, 1, 5) * q1[1], rtol=1e-12, atol=0)
    _, q = tfi.interp_segment(np.zeros(3), q0, np.zeros(3), q0, np.linspace(0, 1, 5))
    np.testing.assert_array_equal(q, np.broadcast_to(q0, (5, 4)))


def test_interp_segment_validation_and_uncompiled():
    with pytest.raises(GridValueError, match="q0, q1"):
        tfi.interp_segment(np.zeros(3), [1, 0, 0, 0], np.zeros(3), None, [0.5])
    with pytest.raises(GridValueError, match="q1: quaternions must be unit"):
        tfi.interp_segment(np.zeros(3), [1, 0, 0, 0], np.zeros(3), [2, 0, 0, 0], [0.5])
    with pytest.raises(GridValueError, match="s: expected"):
        tfi.interp_segment(np.zeros(3), None, np.zeros(3), None, [1.5])
    with pytest.raises(GridValueError, match="delta1: expected shape"):
        tfi.interp_segment(np.zeros(3), None, np.zeros(2), None, [0.5])
    q0, q1 = quat(np.array([0.1, 0.2, 0.3])), -quat(np.array([-0.4, 0.9, 0.1]))
    s = np.array([0.0, 0.3, 0.7, 1.0])
    a = np.empty((4, 4))
    b = np.empty((4, 4))
    tfi._segment_q(q0, q1, s, a)
    tfi._segment_q.py_func(q0, q1, s, b)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-15)


# ================================================================== 3-D block TFI
@given(shapes_st, orders_st, seeds_st, st.booleans())
def test_deform_block_reproduces_faces_and_equals_reference(shape, order, seed, with_q):
    xyz = warped_block(shape, seed)
    s = tfi.arclength(xyz)
    fd = faces_of(xyz, dfun, seed=seed)
    fq = flip_signs(faces_of(xyz, qfun, seed=seed), seed) if with_q else None
    c = np.array([0.3, -0.2, 0.5])
    out = tfi.deform_block(xyz, s, fd, fq, c, order)
    sc = scale(xyz)
    for f in range(6):
        np.testing.assert_allclose(Block(out).face(f), expected_face(xyz, f, fd, fq, c),
                                   rtol=0, atol=2e-14 * sc, err_msg=f"face {f}")
    ref, D, Q = ref_update(xyz, s, fd, fq, c, order)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-14 * sc)
    b = Block(D)
    for f in range(6):
        np.testing.assert_allclose(b.face(f), fd[f], rtol=0, atol=1e-15)
    if with_q:
        np.testing.assert_allclose(np.linalg.norm(Q, axis=-1), 1.0, rtol=0, atol=1e-12)
        bq = Block(np.zeros(shape + (3,)))
        for f in range(6):            # the reference reproduces the face rotations (up to sign)
            idx = [slice(None)] * 3
            idx[f // 2] = -1 if f % 2 else 0
            qf = Q[tuple(idx)]
            dot = np.abs(np.sum(qf * fq[f], axis=-1))
            np.testing.assert_allclose(dot, 1.0, rtol=0, atol=1e-13)
        del bq


@given(shapes_st, orders_st, seeds_st)
def test_sign_of_face_quaternions_does_not_matter(shape, order, seed):
    xyz = warped_block(shape, seed)
    s = tfi.arclength(xyz)
    fd = faces_of(xyz, dfun, seed=seed)
    fq = faces_of(xyz, qfun, seed=seed, amp=1.2)
    c = np.zeros(3)
    a = tfi.deform_block(xyz, s, fd, fq, c, order)
    b = tfi.deform_block(xyz, s, fd, flip_signs(fq, seed), c, order)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-13 * scale(xyz))


@given(shapes_st, orders_st, seeds_st)
def test_rigid_motion_of_all_faces_moves_block_rigidly(shape, order, seed):
    rng = np.random.default_rng(seed)
    xyz = warped_block(shape, seed)
    s = tfi.arclength(xyz)
    q0 = quat(rng.uniform(-2.0, 2.0, 3))
    d0 = rng.normal(size=3)
    c = rng.normal(size=3)
    fd = [np.broadcast_to(d0, Block(xyz).face(f).shape).copy() for f in range(6)]
    fq = flip_signs([np.broadcast_to(q0, Block(xyz).face(f).shape[:2] + (4,)).copy() for f in range(6)], seed)
    out = tfi.deform_block(xyz, s, fd, fq, c, order)
    np.testing.assert_allclose(out, c + d0 + rot(q0, xyz - c), rtol=0, atol=1e-12 * scale(xyz))
    # method "tfi" (baseline) with a pure translation translates the block
    out = tfi.deform_block(xyz, s, fd, None, c, order)
    np.testing.assert_allclose(out, xyz + d0, rtol=0, atol=1e-14 * scale(xyz))


def test_precomputed_face_parameters_give_the_same_result():
    xyz = warped_block((6, 5, 4), 8)
    s = tfi.arclength(xyz)
    fs = tfi.face_params(s)
    for f in range(6):
        np.testing.assert_array_equal(fs[f], Block(s).face(f))
        assert fs[f].flags.f_contiguous
    fd, fq = faces_of(xyz, dfun), faces_of(xyz, qfun)
    for order in [(0, 1, 2), (2, 0, 1)]:
        np.testing.assert_array_equal(tfi.deform_block(xyz, s, fd, fq, np.ones(3), order, face_s=fs),
                                      tfi.deform_block(xyz, s, fd, fq, np.ones(3), order))
    x2 = block2d(6, 5)
    s2 = tfi.arclength(x2)
    sides = sides_of(faces_of(x2, dfun)[:4])
    np.testing.assert_array_equal(
        tfi.deform_block_2d(x2, s2, sides, None, np.zeros(3), (1, 0), face_s=tfi.face_params(s2)[:4]),
        tfi.deform_block_2d(x2, s2, sides, None, np.zeros(3), (1, 0)))


def test_zero_motion_is_bit_exact_and_in_place_works():
    xyz = warped_block((6, 5, 4), 3)
    s = tfi.arclength(xyz)
    b = Block(xyz)
    fd = [np.zeros(b.face(f).shape) for f in range(6)]
    fq = [np.broadcast_to([1.0, 0, 0, 0], b.face(f).shape[:2] + (4,)) for f in range(6)]
    for q in (fq, None):
        np.testing.assert_array_equal(tfi.deform_block(xyz, s, fd, q, np.ones(3), (2, 0, 1)), xyz)
    fd = faces_of(xyz, dfun)
    fq = faces_of(xyz, qfun)
    expect = tfi.deform_block(xyz, s, fd, fq, np.ones(3), (1, 2, 0))
    work = xyz.copy(order="F")
    res = tfi.deform_block(work, s, fd, fq, np.ones(3), (1, 2, 0), out=work)
    assert res is work
    np.testing.assert_array_equal(work, expect)


@pytest.mark.parametrize("order", ORDERS)
def test_tfi_built_grid_and_affine_field_are_reproduced(order):
    shape = (6, 5, 4)
    g = warped_block(shape, 11, amp=0.08)
    s = tfi.arclength(g)
    # a grid built by Soni TFI from a boundary is reproduced from its own boundary
    built, _ = oracles.tfi_block_fields(faces_of(g, lambda p: p), None, s, order)
    again, _ = oracles.tfi_block_fields(faces_of(built, lambda p: p), None, s, order)
    np.testing.assert_allclose(again, built, rtol=0, atol=1e-14 * scale(g))
    # ... and deforming it to another TFI-built grid lands exactly on that grid
    h = warped_block(shape, 12, amp=0.1) * 1.3 + 0.2
    target, _ = oracles.tfi_block_fields(faces_of(h, lambda p: p), None, s, order)
    fd = [Block(target).face(f) - Block(built).face(f) for f in range(6)]
    out = tfi.deform_block(np.asfortranarray(built), s, fd, None, np.zeros(3), order)
    np.testing.assert_allclose(out, target, rtol=0, atol=1e-14 * scale(h))
    # an affine field on a grid of straight, identically stretched lines (sheared and
    # stretched box): the grid is TFI of its boundary, so affine fields are reproduced
    u = [(np.geomspace(1.0, 3.0, n) - 1.0) / 2.0 for n in shape]
    A = np.array([[2.0, 0.3, 0.1], [0.2, 1.5, -0.4], [0.0, 0.25, 1.0]])
    xyz = np.asfortranarray(np.stack(np.meshgrid(*u, indexing="ij"), -1) @ A.T + [1.0, -2.0, 0.5])
    s = tfi.arclength(xyz)
    B = np.array([[0.1, -0.2, 0.05], [0.3, 0.0, 0.1], [-0.1, 0.2, 0.2]])
    field = lambda p: p @ B.T + [0.5, 0.1, -0.3]  # noqa: E731
    D, _ = oracles.tfi_block_fields(faces_of(xyz, field), None, s, order)
    np.testing.assert_allclose(D, field(xyz), rtol=0, atol=1e-14 * scale(xyz))
    fq = [np.broadcast_to(quat([0.1, 0.2, -0.3]), Block(xyz).face(f).shape[:2] + (4,)) for f in range(6)]
    c = np.array([1.0, 0.0, 0.5])
    out = tfi.deform_block(xyz, s, faces_of(xyz, field), fq, c, order)
    np.testing.assert_allclose(out, c + field(xyz) + rot(fq[0][0, 0], xyz - c), rtol=0, atol=1e-14 * scale(xyz))


@pytest.mark.parametrize("order", [(0, 1, 2), (1, 0, 2), (2, 1, 0)])
def test_fused_kernels_uncompiled_equal_compiled(order):
    xyz = warped_block((3, 4, 3), 2)
    s = tfi.arclength(xyz)
    fd, fq = faces_of(xyz, dfun), flip_signs(faces_of(xyz, qfun), 1)
    dims = xyz.shape[:3]
    fdd, fqq = tfi._faces(fd, dims, 3, "fd"), tfi._faces(fq, dims, 4, "fq")
    tables = tfi._tables(dims, order, fdd, fqq, tfi.face_params(s), True)
    lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN = tables
    a, b = np.empty_like(xyz), np.empty_like(xyz)
    for hasq in (True, False):
        kern = tfi._volume_kernel(True, hasq, False)
        bad = np.zeros(xyz.shape[1] * xyz.shape[2], dtype=bool)
        nk = xyz.shape[2]
        parallel_for(kern, nk, xyz, s, a, 0.1, 0.2, 0.3, *order, *tables, lineD, gD, hD, bad)
        kern.py_func(0, nk, xyz, s, b, 0.1, 0.2, 0.3, *order, *tables, lineD, gD, hD, bad)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-15)
    # the set-up kernel too
    again = [np.empty_like(t) for t in tables]
    L, M, N = order
    QL = tfi._pair(fqq, L, 4)
    q0 = np.array(QL[..., 0], order="F")
    tfi._coherent.py_func(q0)
    QL[..., 0] = q0
    fs = tfi.face_params(s)
    tfi._prep_kernel(True).py_func(
        tfi._pair(fs, M, 3), tfi._pair(fs, N, 3), dims[M], dims[N], L, M, N, tfi._pair(fdd, L, 3),
        tfi._pair(fdd, M, 3), tfi._pair(fdd, N, 3), QL, tfi._pair(fqq, M, 4), tfi._pair(fqq, N, 4),
        True, *again)
    for x, y in zip(tables, again):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-15)


# ------------------------------------------------------------- docs/method.md §4, property 7
def o_grid(ni=17, nj=9, nk=4, c_grid=False):
    """Wall at jmin (ellipse or C-shape), far field at jmax, straight wall-normal lines
    whose stretching varies with i and k; i around, k extrusion with a twist and scale."""
    t = np.linspace(0.0, 1.0, ni)
    eta = np.linspace(0.0, 1.0, nj)
    xyz = np.zeros((ni, nj, nk, 3), order="F")
    for k in range(nk):
        z = 0.5 * k
        sc = 1.0 + 0.15 * k
        if c_grid:                         # U-shaped wall: lower leg, nose, upper leg
            u = 3.0 * t - 1.5
            wall = np.where(np.abs(u) <= 0.5, 0.0, 1.0)
            phi = np.clip(u, -0.5, 0.5) * np.pi
            xw = sc * (np.cos(phi) * (1 - wall) + wall * (-(np.abs(u) - 0.5) * 3.0)) * -1.0
            yw = sc * np.where(np.abs(u) <= 0.5, 0.4 * np.sin(phi), 0.4 * np.sign(u))
            xf, yf = 8.0 * np.cos(np.pi * (t - 0.5)) * -1.0 - 2.0, 8.0 * np.sin(np.pi * (t - 0.5))
        else:
            th = 2.0 * np.pi * t
            xw, yw = sc * np.cos(th), sc * 0.3 * np.sin(th) * (1.0 + 0.2 * np.cos(th))
            xf, yf = 8.0 * np.cos(th), 8.0 * np.sin(th)
        beta = 1.0 + 3.0 * (1.0 + np.cos(2.0 * np.pi * t + 0.7 * k))   # line-dependent stretching
        g = (np.exp(beta[:, None] * eta[None, :]) - 1.0) / (np.exp(beta[:, None]) - 1.0)
        xyz[:, :, k, 0] = xw[:, None] + (xf - xw)[:, None] * g
        xyz[:, :, k, 1] = yw[:, None] + (yf - yw)[:, None] * g
        xyz[:, :, k, 2] = z + 0.05 * g * np.sin(2.0 * np.pi * t)[:, None]
    return xyz


def one_d_faces(xyz, s, wall_d, wall_q):
    """Faces whose values come from 1-D interpolation along j between wall (jmin) and far
    field (jmax, at rest); returns the faces and the exact 1-D fields of the whole block."""
    ni, nj, nk = xyz.shape[:3]
    D = np.zeros((ni, nj, nk, 3))
    Q = None if wall_q is None else np.zeros((ni, nj, nk, 4))
    for i in range(ni):
        for k in range(nk):
            d, q = tfi.interp_segment(wall_d[i, k], None if wall_q is None else wall_q[i, k],
                                      np.zeros(3), None if wall_q is None else [1.0, 0, 0, 0],
                                      s[i, :, k, 1])
            D[i, :, k] = d
            if Q is not None:
                Q[i, :, k] = q
    fd = [Block(D).face(f).copy() for f in range(6)]
    fq = None if Q is None else [Block(Q[..., :3]).face(f).copy() for f in range(6)]
    if Q is not None:
        for f in range(6):
            idx = [slice(None)] * 3
            idx[f // 2] = -1 if f % 2 else 0
            fq[f] = Q[tuple(idx)].copy()
    return fd, fq, D, Q


@pytest.mark.parametrize("c_grid", [False, True])
def test_one_d_derived_sides_give_the_one_d_interpolation(c_grid):
    xyz = o_grid(c_grid=c_grid)
    ni, nj, nk = xyz.shape[:3]
    s = tfi.arclength(xyz)
    assert np.ptp(s[:, 1, :, 1]) > 1e-3           # the wall-normal distribution varies along the wall
    p = xyz[:, 0]
    wall_d = 0.1 * np.stack([np.sin(p[..., 0]), np.cos(p[..., 1]), 0.2 * p[..., 2]], -1)
    wall_q = quat(np.stack([0.1 * p[..., 1], 0.2 + 0.05 * p[..., 2], 0.3 * np.sin(p[..., 0])], -1))
    fd, fq, D, Q = one_d_faces(xyz, s, wall_d, wall_q)
    counts = [0, 0, ni * nk, ni * nk, 0, 0]        # wall at jmin, fixed far field at jmax
    order = tfi.lead_order(counts)
    assert order[0] == 1
    c = np.array([0.2, 0.1, 0.3])
    out = tfi.deform_block(xyz, s, fd, fq, c, order)
    np.testing.assert_allclose(out, c + D + rot(Q, xyz - c), rtol=0, atol=1e-13 * scale(xyz))
    out = tfi.deform_block(xyz, s, fd, None, c, order)
    np.testing.assert_allclose(out, xyz + D, rtol=0, atol=1e-13 * scale(xyz))
    # leading with another direction: spurious motion, largest relative to the first cell
    wrong = tfi.deform_block(xyz, s, fd, fq, c, (0, 1, 2))
    err = np.linalg.norm(wrong - (c + D + rot(Q, xyz - c)), axis=-1)
    h1 = np.linalg.norm(xyz[:, 1] - xyz[:, 0], axis=-1)
    assert np.max(err[:, 1] / h1) > 1e-3


def test_wrong_lead_moves_near_wall_points_by_the_parameter_mismatch():
    """2-D: uniform wall translation F, far field at rest, sides 1-D derived.  Leading
    with i gives Δ = truth + (s_j(i,j) - (1-s_i) s_j(0,j) - s_i s_j(ni-1,j)) F."""
    xyz = np.asfortranarray(o_grid(nk=1, c_grid=True))
    xyz[..., 2] = 0.0
    s = tfi.arclength(xyz)
    F = np.array([0.3, -0.1, 0.0])
    ni, nj = xyz.shape[:2]
    wall_d = np.broadcast_to(F, (ni, 1, 3))
    fd, _, D, _ = one_d_faces(xyz, s, wall_d, None)
    sides = [fd[0][:, 0], fd[1][:, 0], fd[2][:, 0], fd[3][:, 0]]
    right = tfi.deform_block_2d(xyz, s, sides, None, np.zeros(3), tfi.lead_order([0, 0, ni, ni]))
    np.testing.assert_allclose(right, xyz + D, rtol=0, atol=1e-14 * scale(xyz))
    wrong = tfi.deform_block_2d(xyz, s, sides, None, np.zeros(3), (0, 1))
    si, sj = s[:, :, 0, 0], s[:, :, 0, 1]
    mismatch = sj - (1 - si) * sj[:1] - si * sj[-1:]
    np.testing.assert_allclose(wrong[:, :, 0] - (xyz + D)[:, :, 0], mismatch[..., None] * F,
                               rtol=0, atol=1e-14 * scale(xyz))
    h1 = np.linalg.norm(xyz[:, 1, 0] - xyz[:, 0, 0], axis=-1)
    assert np.max(np.abs(mismatch[:, 1]) * np.linalg.norm(F) / h1) > 0.01


# ================================================================== 2-D
def block2d(ni=7, nj=5, seed=0):
    xyz = warped_block((ni, nj, 1), seed)
    xyz[..., 2] = 0.0
    return xyz


def sides_of(fields):
    return [fields[0][:, 0], fields[1][:, 0], fields[2][:, 0], fields[3][:, 0]]


@given(st.sampled_from([(7, 5), (2, 6), (5, 2), (1, 4), (4, 1)]), st.sampled_from([(0, 1), (1, 0)]),
       seeds_st, st.booleans())
def test_deform_block_2d_reproduces_sides_and_equals_reference(shape, order, seed, with_q):
    xyz = block2d(*shape, seed=seed)
    s = tfi.arclength(xyz)
    fd = sides_of(faces_of(xyz, dfun, seed=seed)[:4])
    fq = sides_of(flip_signs(faces_of(xyz, qfun, seed=seed)[:4], seed)) if with_q else None
    c = np.array([0.3, 0.2, 0.0])
    out = tfi.deform_block_2d(xyz, s, fd, fq, c, order)
    D, Q = oracles.tfi_block_fields(fd, fq, s, order)
    ref = xyz + D if Q is None else c + D + rot(Q, xyz - c)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-14 * scale(xyz))
    sides = [out[0, :, 0], out[-1, :, 0], out[:, 0, 0], out[:, -1, 0]]
    pts = [xyz[0, :, 0], xyz[-1, :, 0], xyz[:, 0, 0], xyz[:, -1, 0]]
    for f in range(4):
        exp = pts[f] + fd[f] if fq is None else c + fd[f] + rot(fq[f], pts[f] - c)
        np.testing.assert_allclose(sides[f], exp, rtol=0, atol=2e-14 * scale(xyz))
    if with_q:
        np.testing.assert_allclose(np.linalg.norm(Q, axis=-1), 1.0, rtol=0, atol=1e-12)


def test_deform_block_2d_rigid_and_uncompiled():
    xyz = block2d(6, 5, 4)
    s = tfi.arclength(xyz)
    q0 = quat([0.0, 0.0, 0.7])
    d0 = np.array([0.5, -0.2, 0.0])
    n = [5, 5, 6, 6]
    fd = [np.broadcast_to(d0, (m, 3)) for m in n]
    fq = [np.broadcast_to(q0, (m, 4)) for m in n]
    c = np.array([1.0, 2.0, 0.0])
    out = tfi.deform_block_2d(xyz, s, fd, fq, c, (1, 0))
    np.testing.assert_allclose(out, c + d0 + rot(q0, xyz - c), rtol=0, atol=1e-13)
    fd, fq = sides_of(faces_of(xyz, dfun)[:4]), sides_of(faces_of(xyz, qfun)[:4])
    dims = xyz.shape[:3]
    tables = tfi._tables(dims, (1, 0, 2), tfi._sides_as_faces(fd, dims, 3, "d"),
                         tfi._sides_as_faces(fq, dims, 4, "q"), tfi.face_params(s), False)
    a, b = np.empty_like(xyz), np.empty_like(xyz)
    lineD, _, gD, _, hD, _, _, _ = tables
    for hasq in (True, False):
        kern = tfi._volume_kernel(False, hasq, False)
        bad = np.zeros(xyz.shape[1], dtype=bool)
        nj = xyz.shape[1]
        parallel_for(kern, nj, xyz, s, a, 0.5, 0.5, 0.0, 1, 0, 2, *tables, lineD, gD, hD, bad)
        kern.py_func(0, nj, xyz, s, b, 0.5, 0.5, 0.0, 1, 0, 2, *tables, lineD, gD, hD, bad)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-15)


@pytest.mark.parametrize("lead", [0, 1])
def test_tfi_patch_fills_interior_like_the_block_reference(lead):
    xyz = block2d(7, 6, 9)
    surf = xyz[:, :, 0]
    s = tfi.arclength_surface(surf)
    delta = np.array(dfun(surf, seed=3))
    q = flip_signs([np.array(qfun(surf, seed=3))], 2)[0]
    delta0, q0 = delta.copy(), q.copy()
    delta[1:-1, 1:-1] = np.nan
    q[1:-1, 1:-1] = np.nan
    oracles.tfi_patch(delta, q, s, lead=lead)
    sides = lambda a: [a[0], a[-1], a[:, 0], a[:, -1]]  # noqa: E731
    D, Q = oracles.tfi_block_fields(sides(delta0), sides(q0), tfi.arclength(xyz), (lead, 1 - lead))
    np.testing.assert_allclose(delta, D[:, :, 0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(q[1:-1, 1:-1], Q[1:-1, 1:-1, 0], rtol=0, atol=1e-15)
    for a, b in zip(sides(delta), sides(delta0)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, rtol=0, atol=1e-12)
    # the leading direction matters on a patch with line-dependent parameters
    other = np.where(np.isnan(delta), 0, delta).copy()
    other[1:-1, 1:-1] = 0.0
    oracles.tfi_patch(other, None, s, lead=1 - lead)
    assert np.max(np.abs(other - delta)) > 1e-6


def test_tfi_patch_affine_field_and_validation():
    u, v = np.linspace(0, 1, 5), (np.geomspace(1, 4, 6) - 1) / 3
    surf = np.stack(np.meshgrid(u, v, indexing="ij"), -1) @ np.array([[1.0, 0.2, 0.3], [0.1, 2.0, -0.2]])
    s = tfi.arclength_surface(surf)
    field = surf @ np.array([[0.3, -0.1, 0.2], [0.0, 0.5, 0.1], [0.2, 0.2, -0.4]]).T + 0.1
    delta = field.copy()
    delta[1:-1, 1:-1] = 0.0
    oracles.tfi_patch(delta, None, s)
    np.testing.assert_allclose(delta, field, rtol=0, atol=1e-15)
    with pytest.raises(GridValueError, match="delta: expected a writeable float64"):
        oracles.tfi_patch(delta.astype(np.float32), None, s)
    with pytest.raises(GridValueError, match="s: expected"):
        oracles.tfi_patch(delta, None, s[:, :-1])
    with pytest.raises(GridValueError, match="lead"):
        oracles.tfi_patch(delta, None, s, lead=2)
    with pytest.raises(GridValueError, match="q: expected"):
        oracles.tfi_patch(delta, np.zeros((5, 5, 4)), s)


# ------------------------------------------------------------- degenerate blends
def test_near_zero_blend_falls_back_to_rotation_vectors():
    """Sides at a = 0, a = na-1 at rest; b-sides rotated by +180° and -180° about z
    (the same rotation, opposite hemispheres of the identity): the linear correction
    nearly cancels the slerp value (|V| ~ 1e-3 on the middle row of this warped grid,
    just above QNORM_MIN); fused and reference agree and stay unit.  The exact
    cancellation, where the fallback must run, is the next test."""
    ni, nj = 5, 5
    xyz = block2d(ni, nj, 1)
    s = tfi.arclength(xyz)
    fd, fq = _half_turn_sides(ni, nj, np.zeros(3))
    c = np.zeros(3)
    out = tfi.deform_block_2d(xyz, s, fd, fq, c, (0, 1))
    D, Q = oracles.tfi_block_fields(fd, fq, s, (0, 1))
    assert np.all(np.isfinite(out)) and np.all(np.isfinite(Q))
    np.testing.assert_allclose(np.linalg.norm(Q, axis=-1), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out, c + D + rot(Q, xyz - c), rtol=0, atol=1e-14 * scale(xyz))
    w = np.abs(Q[..., 0])
    assert np.min(w) < 0.5        # the fallback keeps the large rotations of the sides
    # the same case in 3-D (extruded, k faces derived from the 2-D solution)
    nk = 3
    x3 = np.asfortranarray(np.repeat(xyz, nk, axis=2))
    x3[..., 2] = np.linspace(0.0, 1.0, nk)[None, None, :]
    s3 = tfi.arclength(x3)
    fd3 = [np.zeros(Block(x3).face(f).shape) for f in range(6)]
    fq3 = [np.repeat(fq[f][:, None, :], nk, axis=1) for f in range(4)] + [Q[:, :, 0], Q[:, :, 0]]
    out3 = tfi.deform_block(x3, s3, fd3, fq3, c, (0, 1, 2))
    ref3, _, Q3 = ref_update(x3, s3, fd3, fq3, c, (0, 1, 2))
    np.testing.assert_allclose(out3, ref3, rtol=0, atol=1e-14 * scale(x3))
    np.testing.assert_allclose(np.linalg.norm(Q3, axis=-1), 1.0, rtol=0, atol=1e-12)


def _half_turn_sides(ni, nj, delta):
    """Sides at rest in rotation on i, rotated by +180 and -180 deg about z on jmin / jmax."""
    ident = np.array([1.0, 0, 0, 0])
    half = np.array([0.0, 0, 0, 1.0])
    jmin = np.tile(half, (ni, 1))
    jmax = np.tile(-half, (ni, 1))
    jmin[0] = jmin[-1] = jmax[0] = jmax[-1] = ident
    fq = [np.tile(ident, (nj, 1)), np.tile(ident, (nj, 1)), jmin, jmax]
    fd = [np.tile(delta, (n, 1)) for n in (nj, nj, ni, ni)]
    return fd, fq


@pytest.mark.parametrize("in_place", [False, True])
def test_fallback_points_of_the_fused_kernels_equal_the_reference(in_place):
    """On a uniform grid s_j = 1/2 exactly on the middle row, where the linear blend
    U + (1 - s_j)(F_jmin - U) + s_j (F_jmax - U) of +-180 deg vanishes: the fused
    kernels must take the rotation-vector fallback there, and give the reference's
    result also when updating in place (out = xyz_u, Δ != 0)."""
    ni, nj = 5, 5
    xyz = np.zeros((ni, nj, 1, 3), order="F")
    xyz[..., 0] = np.linspace(0.0, 1.0, ni)[:, None, None] + 0.3
    xyz[..., 1] = np.linspace(0.0, 2.0, nj)[None, :, None] + 0.1
    s = tfi.arclength(xyz)
    assert np.all(s[:, 2, 0, 1] == 0.5)
    delta = np.array([0.1, -0.2, 0.0])
    fd, fq = _half_turn_sides(ni, nj, delta)
    c = np.array([0.2, 0.4, 0.0])
    order = (0, 1)
    # the linear Boolean sum on the middle row: U = 1, V = 1 + (half - 1)/2 + (-half - 1)/2 = 0
    sj = s[1:-1, 2, 0, 1][:, None]
    V = fq[0][0] + (1 - sj) * (fq[2][1:-1] - fq[0][0]) + sj * (fq[3][1:-1] - fq[0][0])
    assert np.linalg.norm(V, axis=-1).max() < tfi.QNORM_MIN
    D, Q = oracles.tfi_block_fields(fd, fq, s, order)
    np.testing.assert_allclose(np.linalg.norm(Q, axis=-1), 1.0, rtol=0, atol=1e-12)
    ref = c + D + rot(Q, xyz - c)
    work = xyz.copy(order="F")
    out = tfi.deform_block_2d(work, s, fd, fq, c, order, out=work if in_place else None)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-14 * scale(xyz))
    # 3-D: extruded, k faces derived from the 2-D solution
    nk = 3
    x3 = np.asfortranarray(np.repeat(xyz, nk, axis=2))
    x3[..., 2] = np.linspace(0.0, 1.0, nk)[None, None, :]
    s3 = tfi.arclength(x3)
    fd3 = [np.repeat(fd[f][:, None, :], nk, axis=1) for f in range(4)] + [D[:, :, 0], D[:, :, 0]]
    fq3 = [np.repeat(fq[f][:, None, :], nk, axis=1) for f in range(4)] + [Q[:, :, 0], Q[:, :, 0]]
    for order3 in [(0, 1, 2), (2, 0, 1)]:
        ref3, _, Q3 = ref_update(x3, s3, fd3, fq3, c, order3)
        np.testing.assert_allclose(np.linalg.norm(Q3, axis=-1), 1.0, rtol=0, atol=1e-12)
        work = x3.copy(order="F")
        out3 = tfi.deform_block(work, s3, fd3, fq3, c, order3, out=work if in_place else None)
        np.testing.assert_allclose(out3, ref3, rtol=0, atol=1e-14 * scale(x3))


# ------------------------------------------------------------- no full-size temporaries
@pytest.mark.parametrize("with_q", [True, False])
def test_fused_stage_allocates_only_surface_tables(with_q):
    """docs/method.md §6: the volume stage writes R_d without full-size Δ or Q arrays.

    Peak memory traced while deforming a 128^3 block into a given ``out`` stays
    below half of one full-size Δ array (24 bytes per point); the O(surface)
    tables are ~1000 bytes per face point, 0.3 of it here.  (numpy allocations
    are traced; the kernels themselves allocate nothing.)
    """
    import tracemalloc

    n = 128
    u = np.linspace(0.0, 1.0, n)
    xyz = np.empty((n, n, n, 3), order="F")
    xyz[..., 0] = 2.0 * u[:, None, None] + 0.3 * u[None, :, None]
    xyz[..., 1] = 1.5 * u[None, :, None] + 0.2 * u[None, None, :] ** 2
    xyz[..., 2] = u[None, None, :] + 0.1 * u[:, None, None] * u[None, :, None]
    s = tfi.arclength(xyz)
    fs = tfi.face_params(s)
    b = Block(xyz)
    fd = [0.01 * np.sin(b.face(f)) for f in range(6)]
    fq = [qa.normalize(np.concatenate([np.ones(b.face(f).shape[:2] + (1,)), 0.02 * np.cos(b.face(f))], -1))
          for f in range(6)] if with_q else None
    out = np.empty_like(xyz, order="F")
    c = np.array([0.5, 0.5, 0.5])
    tfi.deform_block(xyz, s, fd, fq, c, (1, 2, 0), out=out, face_s=fs)        # compile / warm
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        tfi.deform_block(xyz, s, fd, fq, c, (1, 2, 0), out=out, face_s=fs)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    full_delta = 24 * n ** 3
    assert peak < 0.5 * full_delta, f"peak {peak / 1e6:.1f} MB vs one full-size Δ {full_delta / 1e6:.1f} MB"
    assert np.all(np.isfinite(out))


def test_volume_kernels_are_task_kernels_and_cached():
    """The kernels of the volume stage are task kernels (serial over a task range, run on the
    thread pool, noalias; docs/method.md §6), cached, never numba parallel loops; the
    O(surface) set-up is serial; one kernel object per kind, made once."""
    from tfi_quat import _jit
    kinds = [tfi._volume_kernel(*key) for key in itertools.product((True, False), repeat=3)]
    assert len({id(k) for k in kinds}) == 8
    assert tfi._volume_kernel(True, True, False) is tfi._volume_kernel(True, True, False)
    # O(surface): serial, one call
    serial = (tfi._prep_kernel(True), tfi._prep_kernel(False), tfi._gather)
    for k in (*kinds, blending._arc_layer_i, blending._arc_layer_jk, tfi._fields2, *serial):
        if not _jit.ENABLED:                   # TFI_QUAT_JIT=0: plain Python functions
            assert k.py_func is k
            continue
        assert not k.targetoptions.get("parallel"), k
        assert k.targetoptions.get("nogil"), k
        task = k not in serial
        assert (k._compiler.pipeline_class is _jit.task_jit.keywords["pipeline_class"]) is task, k
        assert (type(k._cache).__name__ == "FunctionCache") == _jit.CACHE, k


# ------------------------------------------------------------- argument validation
def test_deform_block_validates_arguments():
    xyz = warped_block((4, 3, 2), 0)
    s = tfi.arclength(xyz)
    fd, fq = faces_of(xyz, dfun), faces_of(xyz, qfun)
    c = np.zeros(3)
    with pytest.raises(GridValueError, match="xyz_u: expected a Fortran-ordered"):
        tfi.deform_block(np.ascontiguousarray(xyz), s, fd, fq, c, (0, 1, 2))
    with pytest.raises(GridValueError, match=r"s: expected shape \(4, 3, 2, 3\)"):
        tfi.deform_block(xyz, s[:, :2], fd, fq, c, (0, 1, 2))
    with pytest.raises(GridValueError, match="s: expected dtype float64"):
        tfi.deform_block(xyz, np.asfortranarray(s, dtype=np.float32), fd, fq, c, (0, 1, 2))
    with pytest.raises(GridValueError, match=r"face_delta\[3\] \(jmax\): expected shape"):
        tfi.deform_block(xyz, s, fd[:3] + [fd[3][:, :1]] + fd[4:], fq, c, (0, 1, 2))
    with pytest.raises(GridValueError, match="face_delta: expected a sequence of 6"):
        tfi.deform_block(xyz, s, fd[:5], fq, c, (0, 1, 2))
    with pytest.raises(GridValueError, match=r"face_q\[4\] \(kmin\): quaternions must be unit"):
        tfi.deform_block(xyz, s, fd, fq[:4] + [2.0 * fq[4]] + fq[5:], c, (0, 1, 2))
    with pytest.raises(GridValueError, match="non-finite"):
        tfi.deform_block(xyz, s, [f * np.nan for f in fd], fq, c, (0, 1, 2))
    with pytest.raises(GridValueError, match="order: expected a permutation"):
        tfi.deform_block(xyz, s, fd, fq, c, (0, 1, 1))
    with pytest.raises(GridValueError, match="centre"):
        tfi.deform_block(xyz, s, fd, fq, [0, 0], (0, 1, 2))
    with pytest.raises(GridValueError, match="out: expected"):
        tfi.deform_block(xyz, s, fd, fq, c, (0, 1, 2), out=np.empty(xyz.shape))
    bad = [f.copy() for f in fd]
    bad[0][0, 0] += 0.5                      # imin disagrees with jmin on their edge
    with pytest.raises(GridValueError, match="faces imin and jmin disagree"):
        tfi.deform_block(xyz, s, bad, fq, c, (0, 1, 2))
    with pytest.raises(GridValueError, match=r"face_s\[2\] \(jmin\): expected a float64"):
        tfi.deform_block(xyz, s, fd, fq, c, (0, 1, 2), face_s=list(tfi.face_params(s)[:2]) + [s[0]] + list(tfi.face_params(s)[3:]))
    with pytest.raises(GridValueError, match="nk == 1"):
        tfi.deform_block_2d(xyz, s, fd[:4], None, c, (0, 1))
    with pytest.raises(GridValueError, match="order"):
        oracles.tfi_block_fields(fd, None, s, (0, 1, 2, 3))


@pytest.mark.parametrize("lead", [0, 1])
@pytest.mark.parametrize("with_q", [True, False])
def test_compiled_patch_kernel_equals_the_reference(lead, with_q):
    rng = np.random.default_rng(7 + lead)
    na, nb = 23, 17
    a = np.linspace(0.0, 1.0, na) ** 1.7
    b = np.linspace(0.0, 2.0, nb)
    P = np.zeros((na, nb, 3))
    P[..., 0] = a[:, None]
    P[..., 1] = b[None, :] + 0.1 * a[:, None] ** 2
    P[..., 2] = 0.2 * np.sin(3 * a[:, None]) * np.cos(b[None, :])
    s = tfi.arclength_surface(P)
    d = rng.normal(size=(na, nb, 3))
    q = qa.normalize(rng.normal(size=(na, nb, 4)) * 0.3 + [1.0, 0.0, 0.0, 0.0]) if with_q else None
    d1, d2 = d.copy(), d.copy()
    q1 = None if q is None else q.copy()
    q2 = None if q is None else q.copy()
    oracles.tfi_patch(d1, q1, s, lead)
    tfi.tfi_patch_fast(d2, q2, tfi.patch_params(s), lead)
    np.testing.assert_allclose(d2, d1, rtol=0, atol=1e-13)
    assert np.array_equal(d2[0], d[0]) and np.array_equal(d2[:, -1], d[:, -1])
    if with_q:
        sign = np.sign(np.sum(q1 * q2, axis=-1))[..., None]
        np.testing.assert_allclose(q2 * sign, q1, rtol=0, atol=1e-13)
        np.testing.assert_allclose(np.linalg.norm(q2, axis=-1), 1.0, atol=1e-14)


# ================================================================== faces from global arrays
def global_rows(xyz, nfaces, seed):
    """Rows of the block's face points in global arrays, as the Deformer's ``face_gid``.

    One row per distinct face point (shared edges and corners share a row),
    rows shuffled and a few left unused; returns the face index arrays (face
    ``f`` of shape ``Block.face(f).shape[:2]``), the number of rows and each
    row's point (unused rows: 0).
    """
    dims = xyz.shape[:3]
    rng = np.random.default_rng(seed + 400)
    flat = np.arange(int(np.prod(dims))).reshape(dims, order="F")
    keys = []
    for f in range(nfaces):
        idx = [slice(None)] * 3
        idx[f // 2] = dims[f // 2] - 1 if f % 2 else 0
        keys.append(flat[tuple(idx)])
    uk = np.unique(np.concatenate([k.ravel() for k in keys]))
    G = uk.size + 3
    row = rng.permutation(G)[:uk.size]
    face_index = [row[np.searchsorted(uk, k)] for k in keys]
    P = np.zeros((G, 3))
    P[row] = xyz.reshape(-1, 3, order="F")[uk]
    return face_index, G, P


def global_values(P, seed, with_q):
    """Δ and sign-scrambled unit Q at the global points (C order, as the Deformer's)."""
    gd = np.ascontiguousarray(dfun(P, seed=seed))
    if not with_q:
        return gd, None
    gq = qfun(P, seed=seed)
    gq *= np.where(np.random.default_rng(seed + 500).random(len(P)) < 0.5, -1.0, 1.0)[:, None]
    return gd, np.ascontiguousarray(gq)


def gathered(g, face_index, side=False):
    """The old path's per-face copies ``g[face_index[f]]`` (2-D sides as (n, c))."""
    if g is None:
        return None
    return [g[f[:, 0]] if side else g[f] for f in face_index]


@given(shapes_st, orders_st, seeds_st, st.booleans(), st.booleans())
def test_deform_block_gathered_is_bit_identical_to_deform_block(shape, order, seed, with_q, in_place):
    xyz = warped_block(shape, seed)
    s = tfi.arclength(xyz)
    face_index, G, P = global_rows(xyz, 6, seed)
    gd, gq = global_values(P, seed, with_q)
    c = np.array([0.3, -0.2, 0.5])
    expect = tfi.deform_block(xyz, s, gathered(gd, face_index), gathered(gq, face_index), c, order,
                              face_s=tfi.face_params(s))
    plan = tfi.gather_plan(face_index, s, order)
    assert plan.dims == shape and plan.order == order and plan.n_index <= G and plan.ndim == 3
    work = xyz.copy(order="F")
    out = tfi.deform_block_gathered(work, s, gd, gq, plan, c, out=work if in_place else None)
    assert (out is work) == in_place
    np.testing.assert_array_equal(out, expect)
    if not in_place:
        np.testing.assert_array_equal(work, xyz)


@given(st.sampled_from([(7, 5), (2, 6), (5, 2), (1, 4), (4, 1)]), st.sampled_from([(0, 1), (1, 0)]),
       seeds_st, st.booleans(), st.booleans())
def test_deform_block_gathered_2d_is_bit_identical_to_deform_block_2d(shape, order, seed, with_q, flat):
    xyz = block2d(*shape, seed=seed)
    s = tfi.arclength(xyz)
    face_index, G, P = global_rows(xyz, 4, seed)
    gd, gq = global_values(P, seed, with_q)
    c = np.array([0.3, 0.2, 0.0])
    expect = tfi.deform_block_2d(xyz, s, gathered(gd, face_index, True), gathered(gq, face_index, True),
                                 c, order)
    plan = tfi.gather_plan([f[:, 0] for f in face_index] if flat else face_index, s, order,
                           face_s=tfi.face_params(s))
    assert plan.ndim == 2
    np.testing.assert_array_equal(tfi.deform_block_gathered(xyz, s, gd, gq, plan, c), expect)
    work = xyz.copy(order="F")
    tfi.deform_block_gathered(work, s, gd, gq, plan, c, out=work)
    np.testing.assert_array_equal(work, expect)


@given(st.sampled_from([(6, 5, 4), (2, 5, 3), (4, 1, 3), (5, 4, 2)]), orders_st, seeds_st)
def test_based_update_is_the_update_of_the_stored_base_point(shape, order, seed):
    """``base=plan.base_tables(B)``: bit for bit the update of ``R_u + TFI(B)`` computed
    first by the baseline kernel and passed as ``xyz_u`` (the two-level arms), 3-D and 2-D."""
    cases = [(warped_block(shape, seed), 6, order)]
    cases.append((block2d(shape[0], shape[1] + 1, seed=seed), 4, order[:2] if order[0] < 2 else (1, 0)))
    for xyz, nf, o in cases:
        if nf == 4 and sorted(o) != [0, 1]:
            o = (0, 1)
        s = tfi.arclength(xyz)
        face_index, G, P = global_rows(xyz, nf, seed)
        gd, gq = global_values(P, seed, True)
        gb, _ = global_values(P * 0.7 - 0.1, seed + 1, False)
        plan = tfi.gather_plan(face_index, s, o)
        c = np.array([0.3, -0.2, 0.5 if nf == 6 else 0.0])
        arm = tfi.deform_block_gathered(xyz, s, gb, None, plan, np.zeros(3))
        expect = tfi.deform_block_gathered(arm, s, gd, gq, plan, c)
        base = plan.base_tables(gb)
        got = tfi.deform_block_gathered(xyz, s, gd, gq, plan, c, base=base)
        np.testing.assert_array_equal(got, expect)
        # the plan's kept tables are rebuilt by later calls; the base tables are a copy
        tfi.deform_block_gathered(xyz, s, gb * 3.0, None, plan, np.zeros(3))
        np.testing.assert_array_equal(tfi.deform_block_gathered(xyz, s, gd, gq, plan, c, base=base),
                                      expect)
        with pytest.raises(GridValueError, match="only for quaternion"):
            tfi.deform_block_gathered(xyz, s, gd, None, plan, c, base=base)
        with pytest.raises(GridValueError, match="in place"):
            tfi.deform_block_gathered(xyz, s, gd, gq, plan, c, out=xyz, base=base)


def test_based_update_takes_the_fallback_like_the_stored_base_point():
    """The half-turn sides of the fallback test, about a shifted base: the rows that need
    the rotation-vector fallback give the stored-base result bit for bit."""
    ni, nj = 5, 5
    xyz = np.zeros((ni, nj, 1, 3), order="F")
    xyz[..., 0] = np.linspace(0.0, 1.0, ni)[:, None, None] + 0.3
    xyz[..., 1] = np.linspace(0.0, 2.0, nj)[None, :, None] + 0.1
    s = tfi.arclength(xyz)
    fd, fq = _half_turn_sides(ni, nj, np.array([0.1, -0.2, 0.0]))
    ids = np.arange(ni * nj).reshape(ni, nj, 1, order="F")
    face_index = [ids[0], ids[-1], ids[:, 0], ids[:, -1]]
    gd = np.zeros((ni * nj, 3))
    gq = np.zeros((ni * nj, 4))
    gq[:, 0] = 1.0
    for f, d, q in zip(face_index, fd, fq):
        gd[f[:, 0]] = d
        gq[f[:, 0]] = q
    gb = np.zeros((ni * nj, 3))
    gb[:, 0] = 0.05 * np.arange(ni * nj) % 0.3
    plan = tfi.gather_plan(face_index, s, (0, 1))
    c = np.array([0.2, 0.4, 0.0])
    arm = tfi.deform_block_gathered(xyz, s, gb, None, plan, np.zeros(3))
    expect = tfi.deform_block_gathered(arm, s, gd, gq, plan, c)
    got = tfi.deform_block_gathered(xyz, s, gd, gq, plan, c, base=plan.base_tables(gb))
    np.testing.assert_array_equal(got, expect)
    assert np.all(np.isfinite(got))


@pytest.mark.parametrize("keep", [True, False])
def test_a_plan_reused_with_new_values_gives_each_step_its_own_result(keep):
    """Tables kept in the plan are rebuilt from each call's values (quaternion and baseline
    alternating, in place and not), in 3-D and 2-D."""
    for xyz, nf, order in [(warped_block((6, 5, 4), 2), 6, (1, 2, 0)), (block2d(7, 5, 3), 4, (1, 0))]:
        s = tfi.arclength(xyz)
        face_index, G, P = global_rows(xyz, nf, 5)
        plan = tfi.gather_plan(face_index, s, order, keep_tables=keep)
        ref = tfi.deform_block if nf == 6 else tfi.deform_block_2d
        out = np.empty_like(xyz, order="F")
        for step, with_q in enumerate([True, True, False, True, False, False, True]):
            gd, gq = global_values(P * (1.0 + 0.3 * step), step, with_q)
            c = np.array([0.1 * step, 0.2, 0.0])
            expect = ref(xyz, s, gathered(gd, face_index, nf == 4), gathered(gq, face_index, nf == 4),
                         c, order)
            if step % 3 == 2:
                work = xyz.copy(order="F")
                tfi.deform_block_gathered(work, s, gd, gq, plan, c, out=work)
                np.testing.assert_array_equal(work, expect, err_msg=f"step {step}")
            else:
                tfi.deform_block_gathered(xyz, s, gd, gq, plan, c, out=out)
                np.testing.assert_array_equal(out, expect, err_msg=f"step {step}")
            if step == 1:
                kept = plan.nbytes
            elif step == 2 and keep:      # the baseline shares the quaternion calls' Δ tables
                assert plan.nbytes - kept < 4096, (kept, plan.nbytes)
        assert (plan.nbytes > tfi.gather_plan(face_index, s, order).nbytes) == keep, repr(plan)


def test_one_plan_shared_by_threads_gives_each_call_its_own_result():
    from concurrent.futures import ThreadPoolExecutor

    xyz = warped_block((9, 8, 7), 4)
    s = tfi.arclength(xyz)
    face_index, G, P = global_rows(xyz, 6, 6)
    plan = tfi.gather_plan(face_index, s, (2, 0, 1))
    values = [global_values(P * (1.0 + 0.2 * m), m, True) for m in range(8)]
    expect = [tfi.deform_block(xyz, s, gathered(gd, face_index), gathered(gq, face_index), np.zeros(3),
                               (2, 0, 1)) for gd, gq in values]
    with ThreadPoolExecutor(4) as pool:
        got = list(pool.map(lambda v: tfi.deform_block_gathered(xyz, s, *v, plan, np.zeros(3)), values))
    for m in range(8):
        np.testing.assert_array_equal(got[m], expect[m], err_msg=f"call {m}")


def test_gather_kernel_uncompiled_equals_compiled():
    xyz = warped_block((5, 4, 3), 1)
    s = tfi.arclength(xyz)
    face_index, G, P = global_rows(xyz, 6, 1)
    gd, gq = global_values(P, 1, True)
    plan = tfi.gather_plan(face_index, s, (1, 2, 0))
    pairs = lambda: [t[:3] for t in plan._new_tables(True)]      # noqa: E731
    a, b = sum(pairs(), ()), sum(pairs(), ())
    tfi._gather(gd, gq, True, True, *plan._index, *a)
    tfi._gather.py_func(gd, gq, True, True, *plan._index, *b)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    # the pair tables hold the faces' values; the leading ones' quaternions sign-coherent
    np.testing.assert_array_equal(a[0][..., 1], gd[face_index[3]])       # L = 1: jmax
    np.testing.assert_array_equal(np.abs(a[3][..., 0]), np.abs(gq[face_index[2]]))
    q0 = np.array(gq[face_index[2]], order="F")
    tfi._coherent(q0)
    np.testing.assert_array_equal(a[3][..., 0], q0)


@given(st.integers(1, 9), st.integers(1, 4), st.integers(1, 9), st.integers(1, 30),
       st.integers(0, 3), st.booleans(), st.integers(0, 2 ** 32 - 1))
def test_small_2d_gather_with_numpy_is_the_compiled_gather(na, nb, ma, G, extra, hasq, seed):
    """A small 2-D plan's tables are gathered with numpy (no compiled gather in the demo):
    the same bits as the compiled :func:`tfi._gather`, sign-coherent quaternions included."""
    rng = np.random.default_rng(seed)
    gd = rng.normal(size=(G, 3))
    gq = rng.normal(size=(G, 4)) if hasq else np.zeros((1, 4))
    iL = rng.integers(0, G, size=(na + extra, nb, 2))
    iM = rng.integers(0, G, size=(ma + extra, nb, 2))
    iN = np.zeros((2, 2, 2), dtype=np.int64)

    def tables():
        F = (np.full((na, nb, 3, 2), np.nan, order="F"), np.full((ma, nb, 3, 2), np.nan, order="F"),
             np.zeros((2, 2, 3, 2), order="F"))
        Q = ((np.full((na, nb, 4, 2), np.nan, order="F"), np.full((ma, nb, 4, 2), np.nan, order="F"))
             if hasq else (np.zeros((2, 2, 4, 2), order="F"),) * 2) + (np.zeros((2, 2, 4, 2), order="F"),)
        return F + Q

    a, b = tables(), tables()
    assert 2 * (na * nb + ma * nb) < tfi._GATHER_NUMPY_BELOW      # the numpy path
    tfi._gather_tables(gd, gq, hasq, False, iL, iM, iN, *a)
    tfi._gather(gd, gq, hasq, False, iL, iM, iN, *b)
    for x, y in zip(a, b):
        assert x.tobytes() == y.tobytes()
    np.testing.assert_array_equal(a[0][..., 1], gd[iL[:na, :, 1]])    # an independent check
    assert not np.isnan(a[1]).any()


@given(st.integers(1, 12), st.integers(1, 4), st.integers(0, 2 ** 32 - 1))
def test_coherent_with_numpy_is_the_compiled_kernel(na, nb, seed):
    """The same sign flips, with zero and NaN dot products (no flip there) and -0.0 entries."""
    rng = np.random.default_rng(seed)
    q = rng.choice([-1.0, -0.5, -0.0, 0.0, 0.5, 1.0, np.nan], p=[.2, .15, .1, .1, .15, .2, .1],
                   size=(na, nb, 4))
    a, b = q.copy(), q.copy()
    tfi._coherent_numpy(a)
    tfi._coherent(b)
    assert a.tobytes() == b.tobytes()


def test_large_2d_and_3d_gathers_are_compiled(monkeypatch):
    """Above the threshold and in 3-D the compiled gather runs (its answer is checked above)."""
    calls = []
    monkeypatch.setattr(tfi, "_gather", lambda *args: calls.append(args[3]))
    na = tfi._GATHER_NUMPY_BELOW // 4 + 1
    F, Q = np.zeros((na, 1, 3, 2), order="F"), np.zeros((na, 1, 4, 2), order="F")
    idx = np.zeros((na, 1, 2), dtype=np.int64)
    gd, gq = np.zeros((1, 3)), np.zeros((1, 4))
    tfi._gather_tables(gd, gq, True, False, idx, idx, idx, F, F, F, Q, Q, Q)      # large 2-D
    tfi._gather_tables(gd, gq, True, True, idx[:2], idx[:2], idx[:2], F[:2], F[:2], F[:2],
                       Q[:2], Q[:2], Q[:2])                                      # small 3-D
    assert calls == [False, True]


def test_gather_plan_and_deform_block_gathered_validate_arguments():
    xyz = warped_block((4, 3, 2), 0)
    s = tfi.arclength(xyz)
    fi, G, P = global_rows(xyz, 6, 0)
    gd, gq = global_values(P, 0, True)
    c = np.zeros(3)
    with pytest.raises(GridValueError, match="face_index: expected a sequence of 6"):
        tfi.gather_plan(fi[:5], s, (0, 1, 2))
    with pytest.raises(GridValueError, match=r"face_index\[3\] \(jmax\): expected shape \(4, 2\)"):
        tfi.gather_plan(fi[:3] + [fi[3][:, :1]] + fi[4:], s, (0, 1, 2))
    with pytest.raises(GridValueError, match=r"face_index\[0\] \(imin\): expected integers"):
        tfi.gather_plan([fi[0] + 0.0] + fi[1:], s, (0, 1, 2))
    with pytest.raises(GridValueError, match=r"face_index\[5\] \(kmax\): negative row -1"):
        tfi.gather_plan(fi[:5] + [fi[5] * 0 - 1], s, (0, 1, 2))
    bad = [f.copy() for f in fi]
    bad[0][0, 0] = G                          # imin names another row than jmin on their edge
    with pytest.raises(GridValueError, match="faces imin and jmin name different rows"):
        tfi.gather_plan(bad, s, (0, 1, 2))
    with pytest.raises(GridValueError, match="order: expected a permutation"):
        tfi.gather_plan(fi, s, (0, 1, 1))
    with pytest.raises(GridValueError, match="nk == 1"):
        tfi.gather_plan(fi[:4], s, (0, 1))
    with pytest.raises(GridValueError, match=r"s: expected an array"):
        tfi.gather_plan(fi, s[..., 0], (0, 1, 2))
    with pytest.raises(GridValueError, match=r"face_s: expected the 6 face arrays"):
        tfi.gather_plan(fi, s, (0, 1, 2), face_s=tfi.face_params(s)[:4])
    plan = tfi.gather_plan(fi, s, (0, 1, 2))
    assert plan.n_index == 1 + max(int(f.max()) for f in fi)
    with pytest.raises(GridValueError, match="plan: expected a GatherPlan"):
        tfi.deform_block_gathered(xyz, s, gd, gq, fi, c)
    with pytest.raises(GridValueError, match=r"xyz_u: the plan is for a block of \(4, 3, 2\)"):
        tfi.deform_block_gathered(np.asfortranarray(xyz[:3]), s, gd, gq, plan, c)
    with pytest.raises(GridValueError, match="xyz_u: expected a Fortran-ordered"):
        tfi.deform_block_gathered(np.ascontiguousarray(xyz), s, gd, gq, plan, c)
    with pytest.raises(GridValueError, match=r"s: expected shape \(4, 3, 2, 3\)"):
        tfi.deform_block_gathered(xyz, s[:, :2], gd, gq, plan, c)
    with pytest.raises(GridValueError, match=r"g_delta: the plan's faces use rows up to"):
        tfi.deform_block_gathered(xyz, s, gd[:plan.n_index - 1], gq, plan, c)
    with pytest.raises(GridValueError, match=r"g_q: expected a float64 array of shape \(G, 4\)"):
        tfi.deform_block_gathered(xyz, s, gd, gq[:, :3], plan, c)
    with pytest.raises(GridValueError, match=r"g_delta: expected a float64 array"):
        tfi.deform_block_gathered(xyz, s, gd.astype(np.float32), gq, plan, c)
    with pytest.raises(GridValueError, match="centre"):
        tfi.deform_block_gathered(xyz, s, gd, gq, plan, [0, 0])
    with pytest.raises(GridValueError, match="out: expected"):
        tfi.deform_block_gathered(xyz, s, gd, gq, plan, c, out=np.empty(xyz.shape))
    assert "GatherPlan(dims=(4, 3, 2)" in repr(plan)


@given(seeds_st)
def test_fallback_log_is_half_the_quaternion_log(seed):
    """kernels.rel_log (the fallback's tangent map) is quaternion.log of conj(b) ⊗ q, halved:
    the package has one quaternion log (tiny angles, both hemispheres, and zero included)."""
    from tfi_quat import kernels
    rng = np.random.default_rng(seed)
    b = quat(rng.normal(size=3))
    rv = rng.normal(size=3) * rng.choice([1e-200, 1e-40, 1e-9, 1.0, 3.0])
    q = qa.multiply(b, quat(rv))
    for qq in (q, -q):
        got = np.array(kernels.rel_log(*b, *qq))
        np.testing.assert_allclose(got, 0.5 * qa.log(qa.multiply(qa.conjugate(b), qq)), rtol=0, atol=1e-15)
        np.testing.assert_allclose(got, 0.5 * qa.log(quat(rv)), rtol=0, atol=1e-14)
    for bb in (b, -b):
        assert np.array_equal(np.array(kernels.rel_log(*b, *bb)), np.zeros(3))
