"""Quaternion kernels and drivers against scipy's Rotation / Slerp.

Every kernel runs compiled and uncompiled (``kernel.py_func``) through the
``impl`` parameter; inputs come from hypothesis, with angles near 0 and near
pi and antipodal pairs drawn on purpose.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from tfi_quat import GridValueError
from tfi_quat import quaternion as Q

UNIT_TOL = 1e-12
TOL = 1e-12

# angles that stress the formulas: ~0, ~pi/2, ~pi
SPECIAL_ANGLES = [0.0, 1e-300, 1e-15, 1e-10, 1e-6, 1e-3, math.pi / 2,
                  math.pi - 1e-3, math.pi - 1e-6, math.pi - 1e-10, math.pi - 1e-15, math.pi]

finite = st.floats(-1.0, 1.0, allow_nan=False)
vec3 = st.tuples(finite, finite, finite).map(np.array).filter(lambda v: np.linalg.norm(v) > 1e-3)
angle = st.one_of(st.floats(0.0, math.pi), st.sampled_from(SPECIAL_ANGLES))
signed_angle = st.one_of(st.floats(-2 * math.pi, 2 * math.pi), st.sampled_from(SPECIAL_ANGLES),
                         st.sampled_from(SPECIAL_ANGLES).map(lambda a: -a))
sign = st.sampled_from([1.0, -1.0])


@st.composite
def unit_quat(draw):
    """A unit quaternion built from an axis and an angle (angles near 0/pi included), random sign."""
    ax = draw(vec3)
    a = draw(angle)
    r = Rotation.from_rotvec(ax / np.linalg.norm(ax) * a)
    return draw(sign) * r.as_quat(scalar_first=True)


@pytest.fixture(params=["jit", "py"], scope="module")
def impl(request):
    """Run a kernel compiled (``jit``) or as plain Python (``py``)."""
    if request.param == "jit":
        return lambda k: k
    return lambda k: k.py_func


def R(q):
    return Rotation.from_quat(np.asarray(q), scalar_first=True)


def qs(r):
    return r.as_quat(scalar_first=True)


def same_rotation(a, b, tol=TOL):
    """max |a - b| up to the sign of the quaternion."""
    a = np.asarray(a)
    b = np.asarray(b)
    return min(np.abs(a - b).max(), np.abs(a + b).max()) <= tol


def unit(q, tol=UNIT_TOL):
    return abs(np.linalg.norm(q) - 1.0) <= tol


# ------------------------------------------------------------------ core kernels
@given(a=unit_quat(), b=unit_quat())
def test_kmul_kdot_kconj_match_scipy(impl, a, b):
    out = np.empty(4)
    impl(Q.kmul)(a, b, out)
    assert same_rotation(out, qs(R(a) * R(b)))
    assert unit(out)
    assert impl(Q.kdot)(a, b) == pytest.approx(float(a @ b), abs=1e-15)
    impl(Q.kconj)(a, out)
    assert same_rotation(out, qs(R(a).inv()))
    assert unit(out)
    # aliasing: out may be an input
    c = a.copy()
    impl(Q.kmul)(c, b, c)
    assert same_rotation(c, qs(R(a) * R(b)))


@given(a=st.one_of(st.tuples(finite, finite, finite, finite).map(np.array),
                   st.sampled_from([np.zeros(4), np.array([0, 0, 0, 3e-298]), np.array([1e-170, -2e-170, 0, 0]),
                                    np.array([1e300, 1e300, -1e300, 0])])))
def test_knormalize(impl, a):
    """Unit to round-off even where the squares under- or overflow."""
    out = np.empty(4)
    with np.errstate(over="ignore", under="ignore"):     # numpy scalars in the uncompiled run
        n = impl(Q.knormalize)(a, out)
    m = np.abs(a).max()
    exact = m * np.linalg.norm(a / m) if m > 0 else 0.0
    assert n == pytest.approx(exact, rel=1e-15, abs=0)
    if n > 0:
        np.testing.assert_allclose(out, (a / m) / np.linalg.norm(a / m), rtol=0, atol=1e-15)
    else:
        np.testing.assert_array_equal(out, [1, 0, 0, 0])
    assert unit(out)


@given(q=unit_quat(), v=vec3)
def test_krotate_matches_scipy(impl, q, v):
    out = np.empty(3)
    impl(Q.krotate)(q, v, out)
    np.testing.assert_allclose(out, R(q).apply(v), rtol=0, atol=1e-15 * 8)


@given(a=unit_quat(), b=unit_quat(), t=st.one_of(st.floats(0, 1), st.sampled_from([0.0, 1.0, 1e-9, 1 - 1e-9])),
       flip=sign)
def test_kslerp_matches_scipy_and_takes_shortest_arc(impl, a, b, t, flip):
    out = np.empty(4)
    impl(Q.kslerp)(a, flip * b, t, out)     # antipodal b gives the same result
    ref = Slerp([0.0, 1.0], Rotation.concatenate([R(a), R(b)]))([t])[0]
    assert same_rotation(out, qs(ref), 1e-10)
    assert unit(out)
    if t == 0.0:
        np.testing.assert_array_equal(out, a)
    if t == 1.0:            # exactly the other end, in a's hemisphere
        np.testing.assert_array_equal(out, (1.0 if a @ (flip * b) >= 0 else -1.0) * flip * b)
    # shortest arc: the path stays within the hemisphere of a
    assert out @ a >= -1e-12


@given(a=unit_quat(), ax=vec3, ang=angle, t=st.one_of(st.floats(0, 1), st.sampled_from([0.0, 0.5, 1.0])),
       flip=sign)
def test_kslerp_relative_angles_near_0_and_180_deg(impl, a, ax, ang, t, flip):
    """b = a ⊗ exp(ang · axis) with the relative angle drawn near 0 and near 180 deg."""
    rel = Rotation.from_rotvec(ax / np.linalg.norm(ax) * ang)
    b = flip * qs(R(a) * rel)
    out = np.empty(4)
    impl(Q.kslerp)(a, b, t, out)
    assert unit(out)
    assert np.all(np.isfinite(out))
    # independent oracle: a ⊗ exp(t · v), the rotation t of the way from a to b
    expect = qs(R(a) * Rotation.from_rotvec(rel.as_rotvec() * t))
    if ang < math.pi - 1e-6:
        assert same_rotation(out, expect, 1e-12)
        ref = Slerp([0.0, 1.0], Rotation.concatenate([R(a), R(b)]))([t])[0]
        assert same_rotation(out, qs(ref), 1e-12)
    else:
        # within 1e-6 of a half turn the path may go either way round (the 4-D dot
        # product is ~0); along the chosen great circle it is still slerp
        s = 1.0 if a @ b >= 0 else -1.0
        om = math.atan2(np.linalg.norm(a - s * b), np.linalg.norm(a + s * b)) * 2.0
        lin = (math.sin((1 - t) * om) * a + math.sin(t * om) * s * b) / math.sin(om)
        np.testing.assert_allclose(out, lin, rtol=0, atol=1e-12)


@pytest.mark.parametrize("theta", [1e-300, 1e-200, 1e-100, 1e-20, 1e-12, 1e-8])
def test_kslerp_tiny_angles_keep_relative_accuracy(impl, theta):
    """From the identity, the vector part of slerp is t sin(theta/2) n to relative round-off."""
    n = np.array([0.6, -0.8, 0.0])
    a = np.array([1.0, 0.0, 0.0, 0.0])
    b = np.concatenate([[math.cos(theta / 2)], math.sin(theta / 2) * n])
    out = np.empty(4)
    for t in (0.0, 1e-3, 0.25, 0.5, 0.999, 1.0):
        impl(Q.kslerp)(a, b, t, out)
        assert unit(out) and np.all(np.isfinite(out))
        np.testing.assert_allclose(out[1:], math.sin(t * theta / 2) * n, rtol=1e-14, atol=0)
        assert out[0] == pytest.approx(1.0, abs=1e-16)


# ------------------------------------------------------------------ axis-angle
@given(ax=vec3, a=signed_angle, scale=st.floats(1e-3, 1e3))
def test_kfrom_axis_angle_matches_scipy(impl, ax, a, scale):
    out = np.empty(4)
    impl(Q.kfrom_axis_angle)(ax * scale, a, out)
    assert same_rotation(out, qs(Rotation.from_rotvec(ax / np.linalg.norm(ax) * a)))
    assert unit(out)


def test_kfrom_axis_angle_zero_axis_is_identity(impl):
    out = np.empty(4)
    impl(Q.kfrom_axis_angle)(np.zeros(3), 1.0, out)
    np.testing.assert_array_equal(out, [1, 0, 0, 0])


@given(q=unit_quat())
def test_kto_axis_angle_matches_scipy(impl, q):
    axis = np.empty(3)
    a = impl(Q.kto_axis_angle)(q, axis)
    assert 0.0 <= a <= math.pi
    assert a == pytest.approx(R(q).magnitude(), abs=1e-12)
    assert unit(axis)
    back = np.empty(4)
    Q.kfrom_axis_angle(axis, a, back)
    assert same_rotation(back, q)
    if 1e-6 < a < math.pi - 1e-6:      # axis well defined: same as scipy's rotation vector
        np.testing.assert_allclose(axis * a, R(q).as_rotvec(), atol=1e-12)


def test_kto_axis_angle_identity(impl):
    axis = np.empty(3)
    assert impl(Q.kto_axis_angle)(np.array([-1.0, 0, 0, 0]), axis) == 0.0
    np.testing.assert_array_equal(axis, [1, 0, 0])


# ------------------------------------------------------------------ matrices
@given(q=unit_quat())
def test_kto_matrix_matches_scipy(impl, q):
    m = np.empty((3, 3))
    impl(Q.kto_matrix)(q, m)
    np.testing.assert_allclose(m, R(q).as_matrix(), rtol=0, atol=1e-15 * 8)


@given(q=unit_quat())
def test_kfrom_matrix_matches_scipy(impl, q):
    out = np.empty(4)
    impl(Q.kfrom_matrix)(R(q).as_matrix(), out)
    assert same_rotation(out, q)
    assert out[0] >= 0.0
    assert unit(out)


@pytest.mark.parametrize("axis", [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, -2, 3)])
@pytest.mark.parametrize("a", [math.pi, math.pi - 1e-9, 1e-9, 0.0])
def test_kfrom_matrix_every_shepperd_branch(impl, axis, a):
    """Half turns put the largest term on each diagonal entry in turn."""
    r = Rotation.from_rotvec(np.array(axis) / np.linalg.norm(axis) * a)
    out = np.empty(4)
    impl(Q.kfrom_matrix)(r.as_matrix(), out)
    assert same_rotation(out, qs(r))
    assert unit(out)


# ------------------------------------------------------------------ two vectors
def _check_two_vectors(q, a, b, tol=TOL):
    ah = a / np.linalg.norm(a)
    bh = b / np.linalg.norm(b)
    assert unit(q)
    assert q[0] >= 0.0
    np.testing.assert_allclose(R(q).apply(ah), bh, rtol=0, atol=tol)
    # minimal: the rotation angle is the angle between the vectors, the axis normal to both
    ang = math.atan2(np.linalg.norm(np.cross(ah, bh)), ah @ bh)
    assert R(q).magnitude() == pytest.approx(ang, abs=1e-12)
    v = q[1:]
    assert abs(v @ ah) <= tol and abs(v @ bh) <= tol


@given(a=vec3, b=vec3)
def test_kfrom_two_vectors_matches_scipy(impl, a, b):
    out = np.empty(4)
    impl(Q.kfrom_two_vectors)(a, b, out)
    _check_two_vectors(out, a, b)
    ah, bh = a / np.linalg.norm(a), b / np.linalg.norm(b)
    if np.linalg.norm(np.cross(ah, bh)) > 1e-3:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref, _ = Rotation.align_vectors(bh[None], ah[None])
        assert same_rotation(out, qs(ref), 1e-10)


@given(a=vec3, eps=st.sampled_from([0.0, 1e-300, 1e-17, 1e-14, 1e-10, 1e-6, 1e-3]), perp=vec3, anti=sign)
def test_kfrom_two_vectors_near_parallel_and_antiparallel(impl, a, eps, perp, anti):
    ah = a / np.linalg.norm(a)
    b = anti * ah + eps * np.cross(ah, perp)
    out = np.empty(4)
    impl(Q.kfrom_two_vectors)(a, b, out)
    assert np.all(np.isfinite(out))
    _check_two_vectors(out, a, b)


@pytest.mark.parametrize("a", [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 1), (0.3, -0.4, 0.5)])
def test_kfrom_two_vectors_exactly_antiparallel_is_half_turn(impl, a):
    a = np.array(a, dtype=float)
    out = np.empty(4)
    impl(Q.kfrom_two_vectors)(a, -a, out)
    assert out[0] == pytest.approx(0.0, abs=1e-15)
    _check_two_vectors(out, a, -a)


def test_kfrom_two_vectors_parallel_and_zero_are_identity(impl):
    out = np.empty(4)
    impl(Q.kfrom_two_vectors)(np.array([0.0, 2, 0]), np.array([0.0, 5, 0]), out)
    np.testing.assert_array_equal(out, [1, 0, 0, 0])
    impl(Q.kfrom_two_vectors)(np.zeros(3), np.array([0.0, 5, 0]), out)
    np.testing.assert_array_equal(out, [1, 0, 0, 0])


# ------------------------------------------------------------------ log / exp
@given(q=unit_quat())
def test_klog_matches_scipy(impl, q):
    v = np.empty(3)
    impl(Q.klog)(q, v)
    assert np.linalg.norm(v) <= math.pi + 1e-15
    assert np.linalg.norm(v) == pytest.approx(R(q).magnitude(), abs=1e-12)
    if R(q).magnitude() < math.pi - 1e-6:
        np.testing.assert_allclose(v, R(q).as_rotvec(), rtol=0, atol=1e-12)
    back = np.empty(4)
    Q.kexp(v, back)
    assert same_rotation(back, q)


@given(ax=vec3, a=signed_angle)
def test_kexp_matches_scipy(impl, ax, a):
    v = ax / np.linalg.norm(ax) * a
    out = np.empty(4)
    impl(Q.kexp)(v, out)
    assert same_rotation(out, qs(Rotation.from_rotvec(v)))
    assert unit(out)


def test_klog_kexp_tiny_angles_keep_relative_accuracy(impl):
    for a in [1e-300, 1e-200, 1e-20, 1e-9]:
        v = np.array([a, -2 * a, 0.5 * a])
        q = np.empty(4)
        impl(Q.kexp)(v, q)
        back = np.empty(3)
        impl(Q.klog)(q, back)
        np.testing.assert_allclose(back, v, rtol=1e-14)
    zero = np.empty(3)
    impl(Q.klog)(np.array([-1.0, 0, 0, 0]), zero)
    np.testing.assert_array_equal(zero, 0.0)


# ------------------------------------------------------------------ blend
def _nlerp_reference(qs_, w):
    """Independent numpy blend: flip to the largest weight's hemisphere, sum, normalise."""
    ref = qs_[int(np.argmax(w))]
    s = np.where(qs_ @ ref < 0, -1.0, 1.0)
    acc = (w * s) @ qs_
    return acc / np.linalg.norm(acc)


@given(qlist=st.lists(unit_quat(), min_size=1, max_size=6), data=st.data())
def test_kblend_matches_reference_and_is_left_invariant(impl, qlist, data):
    q = np.array(qlist)
    w = np.array(data.draw(st.lists(st.floats(0.01, 1.0), min_size=len(q), max_size=len(q))))
    out = np.empty(4)
    impl(Q.kblend)(q, w, out)
    assert unit(out)
    np.testing.assert_allclose(out, _nlerp_reference(q, w), rtol=0, atol=1e-12)
    ref = q[int(np.argmax(w))]
    assert out @ ref > 0
    # blending commutes with a common rotation applied on the left (where the hemisphere
    # of each input is decided robustly: not 180 deg away from the reference)
    assume(np.abs(q @ ref).min() > 1e-6)
    g = data.draw(unit_quat())
    gq = np.array([qs(R(g) * R(qi)) for qi in q])
    out2 = np.empty(4)
    impl(Q.kblend)(gq, w, out2)
    assert same_rotation(out2, qs(R(g) * R(out)), 1e-12)


@given(a=unit_quat(), b=unit_quat(), fa=sign, fb=sign)
def test_kblend_two_equal_weights_is_slerp_midpoint(impl, a, b, fa, fb):
    if abs(a @ b) < 1e-6:      # 180 deg apart: the midpoint is not unique
        return
    out = np.empty(4)
    impl(Q.kblend)(np.array([fa * a, fb * b]), np.array([0.5, 0.5]), out)
    mid = Slerp([0.0, 1.0], Rotation.concatenate([R(a), R(b)]))([0.5])[0]
    assert same_rotation(out, qs(mid), 1e-10)


@given(q=unit_quat(), signs=st.lists(sign, min_size=2, max_size=8))
def test_kblend_of_one_rotation_with_mixed_signs_is_that_rotation(impl, q, signs):
    qq = np.array([s * q for s in signs])
    out = np.empty(4)
    impl(Q.kblend)(qq, np.linspace(1.0, 2.0, len(signs)), out)
    assert same_rotation(out, q)
    assert unit(out)


def test_kblend_small_norm_falls_back_to_rotation_vectors(impl):
    eps = 1e-9
    x = qs(Rotation.from_rotvec([2 * eps, 0, 0]))
    y = qs(Rotation.from_rotvec([-2 * eps, 0, 0]))
    out = np.empty(4)
    # x - y has norm 2 sin(eps) << 1e-6: the linear blend is meaningless; the weights
    # sum to 0, so the log blend is divided by sum |w| = 2: x ⊗ exp((0 - (-4 eps)) / 2)
    impl(Q.kblend)(np.array([x, y]), np.array([1.0, -1.0]), out)
    assert np.all(np.isfinite(out)) and unit(out)
    assert same_rotation(out, qs(Rotation.from_rotvec([4 * eps, 0, 0])), 1e-15)
    # identical inputs cancelling: the reference itself, never NaN
    impl(Q.kblend)(np.array([x, x]), np.array([1.0, -1.0]), out)
    assert same_rotation(out, x, 1e-15)
    # all weights zero: the reference (the first)
    impl(Q.kblend)(np.array([y, x]), np.zeros(2), out)
    assert same_rotation(out, y, 1e-15)


def test_kblend_negative_weights_blend_rotation_vectors_when_cancelling(impl):
    """TFI-style corrections U + F - G with F == G return U."""
    u = qs(Rotation.from_rotvec([0.3, -0.2, 0.1]))
    f = qs(Rotation.from_rotvec([0.1, 0.5, -0.7]))
    out = np.empty(4)
    impl(Q.kblend)(np.array([u, f, -f]), np.array([1.0, 0.7, -0.7]), out)
    assert same_rotation(out, u, 1e-12)


# ------------------------------------------------------------------ drivers
def test_drivers_broadcast_and_round_trip():
    rng = np.random.default_rng(4)
    r = Rotation.random(12, rng=rng)
    q = qs(r).reshape(3, 4, 4)
    np.testing.assert_allclose(Q.to_matrix(q), r.as_matrix().reshape(3, 4, 3, 3), atol=1e-15)
    back = Q.from_matrix(Q.to_matrix(q))
    assert back.shape == (3, 4, 4)
    assert all(same_rotation(b, a) for a, b in zip(q.reshape(-1, 4), back.reshape(-1, 4)))
    axis, ang = Q.to_axis_angle(q)
    assert axis.shape == (3, 4, 3) and ang.shape == (3, 4)
    assert all(same_rotation(b, a) for a, b in zip(q.reshape(-1, 4), Q.from_axis_angle(axis, ang).reshape(-1, 4)))
    # one axis, many angles
    assert Q.from_axis_angle([0, 0, 1], np.linspace(0, 1, 5)).shape == (5, 4)
    v = Q.log(q)
    np.testing.assert_allclose(Q.log(Q.exp(v)), v, atol=1e-14)
    a = rng.normal(size=(7, 3))
    b = rng.normal(size=(7, 3))
    q2 = Q.from_two_vectors(a, b)
    np.testing.assert_allclose(Q.rotate(q2, a / np.linalg.norm(a, axis=1)[:, None]),
                               b / np.linalg.norm(b, axis=1)[:, None], atol=1e-14)
    assert Q.from_two_vectors([1, 0, 0], b).shape == (7, 4)
    bl = Q.blend(q, np.ones(4))            # (3, 4 inputs, 4) -> (3, 4)
    assert bl.shape == (3, 4)
    for k in range(3):
        np.testing.assert_allclose(bl[k], _nlerp_reference(q[k], np.ones(4)), atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(Q.normalize(q * 3.0), axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(Q.multiply(q, Q.conjugate(q))[..., 0], 1.0, atol=1e-15)
    s = Q.slerp(q[0, 0], q[0, 1], np.linspace(0, 1, 3))
    assert s.shape == (3, 4)


def test_drivers_give_the_kernels_one_array_type():
    """Broadcast inputs reach the kernels read-only and C-contiguous whether broadcasting copied
    them or not (one compiled and cached version per kernel, not one per mix of flags); the
    callers' arrays keep their flags."""
    q = np.array([1.0, 0.0, 0.0, 0.0])
    for shape, a in (((), q), ((5,), q), ((5,), np.tile(q, (5, 1))), ((2, 3), q)):
        flat = Q._flat(a, shape, (4,))
        assert not flat.flags.writeable and flat.flags.c_contiguous and flat.shape == (math.prod(shape), 4)
    assert q.flags.writeable
    np.testing.assert_array_equal(Q.rotate(q, np.eye(3)), np.eye(3))
    np.testing.assert_array_equal(Q.rotate(q, [0.0, 1.0, 2.0]), [0.0, 1.0, 2.0])


@given(qlist=st.lists(unit_quat(), min_size=2, max_size=7), data=st.data())
def test_array_drivers_match_scipy(qlist, data):
    """The vectorised drivers against scipy on whole arrays (antipodal signs included)."""
    q = np.array(qlist)
    p = np.array(data.draw(st.lists(unit_quat(), min_size=len(q), max_size=len(q))))
    v = np.array(data.draw(st.lists(vec3, min_size=len(q), max_size=len(q))))
    t = np.array(data.draw(st.lists(st.floats(0.0, 1.0), min_size=len(q), max_size=len(q))))
    rq, rp = R(q), R(p)
    for a, b in zip(Q.multiply(q, p), qs(rq * rp)):
        assert same_rotation(a, b)
    np.testing.assert_allclose(Q.rotate(q, v), rq.apply(v), rtol=0, atol=1e-14)
    np.testing.assert_allclose(Q.to_matrix(q), rq.as_matrix(), rtol=0, atol=1e-14)
    for a, b in zip(Q.from_matrix(rq.as_matrix()), q):
        assert same_rotation(a, b)
    np.testing.assert_allclose(np.linalg.norm(Q.log(q), axis=-1), rq.magnitude(), rtol=0, atol=1e-12)
    for a, b in zip(Q.exp(rq.as_rotvec()), q):
        assert same_rotation(a, b)
    axis, ang = Q.to_axis_angle(q)
    np.testing.assert_allclose(ang, rq.magnitude(), rtol=0, atol=1e-12)
    for a, b in zip(Q.from_axis_angle(axis, ang), q):
        assert same_rotation(a, b)
    sl = Q.slerp(q, p, t)
    np.testing.assert_allclose(np.linalg.norm(sl, axis=-1), 1.0, rtol=0, atol=UNIT_TOL)
    for k in range(len(q)):
        if abs(q[k] @ p[k]) > 1e-6:          # not a half turn apart (the path is then not unique)
            ref = Slerp([0.0, 1.0], Rotation.concatenate([rq[k], rp[k]]))([t[k]])[0]
            assert same_rotation(sl[k], qs(ref), 1e-10)


@pytest.mark.parametrize("call, name", [
    (lambda: Q.to_matrix(np.ones(3)), "q"),
    (lambda: Q.from_matrix(np.eye(4)), "m"),
    (lambda: Q.from_matrix(np.full((3, 3), np.nan)), "m"),
    (lambda: Q.from_axis_angle(np.ones(4), 1.0), "axis"),
    (lambda: Q.from_axis_angle(np.ones((2, 3)), np.ones(3)), "axis"),
    (lambda: Q.from_two_vectors(np.ones(3), np.ones(2)), "b"),
    (lambda: Q.exp(np.ones((2, 2))), "v"),
    (lambda: Q.log("abc"), "q"),
    (lambda: Q.blend(np.ones((3, 4)), np.ones(2)), "weights"),
    (lambda: Q.blend(np.ones(4), np.ones(1)), "qs"),
    (lambda: Q.blend(np.ones((2, 4)), [1.0, np.nan]), "weights"),
    (lambda: Q.multiply(np.ones(3), np.ones(4)), "a"),
    # leading shapes that do not broadcast: a GridValueError naming both, not numpy's ValueError
    (lambda: Q.multiply(np.ones((2, 4)), np.ones((3, 4))), r"a \(2,\), b \(3,\)"),
    (lambda: Q.rotate(np.ones((2, 4)), np.ones((3, 3))), r"q \(2,\), v \(3,\)"),
    (lambda: Q.slerp(np.ones((2, 4)), np.ones((2, 4)), np.ones(3)), r"t \(3,\)"),
    (lambda: Q.rotate(np.ones(4), "abc"), "v"),
    (lambda: Q.slerp(np.ones(4), np.ones(4), "abc"), "t"),
])
def test_drivers_reject_bad_input_naming_the_argument(call, name):
    with pytest.raises(GridValueError, match=name):
        call()
