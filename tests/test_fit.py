"""Rigid fits (tfi_quat.fit) against scipy's Rotation, with and without plane constraints."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from tfi_quat import quaternion as qa
from tfi_quat.fit import constrain_to_planes, fit_rigid

angles = st.floats(-179.0, 179.0)
unit = st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)).filter(
    lambda v: np.linalg.norm(v) > 0.1)


def _as_scipy(q):
    return Rotation.from_quat([q[1], q[2], q[3], q[0]])


@given(angle=angles, axis=unit, seed=st.integers(0, 10_000))
def test_exact_rigid_motion_is_recovered(angle, axis, seed):
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(40, 3)) * [3.0, 1.0, 0.2]
    rot = Rotation.from_rotvec(np.radians(angle) * np.asarray(axis) / np.linalg.norm(axis))
    t = rng.normal(size=3)
    q, tt = fit_rigid(p, rot.apply(p) + t)
    assert q[0] >= 0.0 and abs(np.linalg.norm(q) - 1.0) < 1e-12
    assert (_as_scipy(q) * rot.inv()).magnitude() < 1e-9
    np.testing.assert_allclose(tt, t, atol=1e-9)


@given(seed=st.integers(0, 10_000))
def test_noisy_fit_matches_scipy_align_vectors(seed):
    """The least-squares rotation of centred point sets is scipy's align_vectors."""
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(30, 3))
    rot = Rotation.from_rotvec(rng.normal(size=3))
    d = rot.apply(p) + 0.05 * rng.normal(size=p.shape) + [1.0, 2.0, 3.0]
    q, t = fit_rigid(p, d)
    ref, _ = Rotation.align_vectors(d - d.mean(0), p - p.mean(0))
    assert (_as_scipy(q) * ref.inv()).magnitude() < 1e-8
    np.testing.assert_allclose(qa.rotate(q, p.mean(0)) + t, d.mean(0), atol=1e-12)


@given(angle=angles, seed=st.integers(0, 10_000))
def test_plane_constraint_keeps_the_plane(angle, seed):
    """With a symmetry plane y = 0 the fit turns about y only and translates in the plane."""
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(40, 3))
    axis, tproj = constrain_to_planes([np.array([0.0, 2.0, 0.0])])
    np.testing.assert_allclose(axis, [0.0, 1.0, 0.0])
    # a motion that is not plane-preserving: the best plane-preserving one is found
    rot = Rotation.from_rotvec([0.2, np.radians(angle), -0.1])
    d = rot.apply(p) + [0.3, 0.5, -0.2]
    q, t = fit_rigid(p, d, axis, tproj)
    assert abs(q[1]) < 1e-15 and abs(q[3]) < 1e-15
    assert abs(t[1]) < 1e-15
    # optimal among rotations about y: a brute-force scan is never better
    cost = lambda qq, tt: np.sum((qa.rotate(qq, p) + tt - d) ** 2)
    best = cost(q, t)
    for a in np.linspace(-np.pi, np.pi, 721):
        qq = np.array([np.cos(a / 2), 0.0, np.sin(a / 2), 0.0])
        tt = d.mean(0) - qa.rotate(qq, p.mean(0))
        tt[1] = 0.0
        assert cost(qq, tt) >= best - 1e-9


def test_constraints_of_several_planes():
    axis, proj = constrain_to_planes([])
    assert axis is None and np.array_equal(proj, np.eye(3))
    axis, proj = constrain_to_planes([[0, 0, 1], [0, 0, -3]])          # parallel: one axis
    np.testing.assert_allclose(axis, [0, 0, 1])
    np.testing.assert_allclose(proj, np.diag([1.0, 1.0, 0.0]), atol=1e-15)
    axis, proj = constrain_to_planes([[0, 0, 1], [1, 0, 0]])           # a corner: no rotation
    assert not np.any(axis)
    np.testing.assert_allclose(proj, np.diag([0.0, 1.0, 0.0]), atol=1e-15)
    rng = np.random.default_rng(3)
    p = rng.normal(size=(20, 3))
    q, t = fit_rigid(p, p + [1.0, 2.0, 3.0], axis, proj)
    np.testing.assert_array_equal(q, [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(t, [0.0, 2.0, 0.0])


@pytest.mark.parametrize("shape", ["planar", "collinear-2d", "one point"])
def test_degenerate_point_sets(shape):
    if shape == "planar":
        p = np.c_[np.random.default_rng(1).normal(size=(12, 2)), np.zeros(12)]
        rot = Rotation.from_rotvec([0.1, 0.4, 0.3])
        q, t = fit_rigid(p, rot.apply(p) + 1.0)
        assert (_as_scipy(q) * rot.inv()).magnitude() < 1e-9
    elif shape == "collinear-2d":
        p = np.c_[np.linspace(0, 1, 7), np.zeros(7), np.zeros(7)]
        axis, proj = constrain_to_planes([[0.0, 0.0, 1.0]])
        ang = 0.7
        qz = np.array([np.cos(ang / 2), 0, 0, np.sin(ang / 2)])
        q, t = fit_rigid(p, qa.rotate(qz, p) + [0.5, -1.0, 0.0], axis, proj)
        np.testing.assert_allclose(q, qz, atol=1e-14)
        np.testing.assert_allclose(t, [0.5, -1.0, 0.0], atol=1e-14)
    else:
        q, t = fit_rigid(np.ones((1, 3)), np.full((1, 3), 2.0))
        assert np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(qa.rotate(q, np.ones(3)) + t, [2.0, 2.0, 2.0])
