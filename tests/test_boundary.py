"""Boundary quaternions (docs/method.md §3.1): rigid motions recovered exactly, invariance,
smoothness under bending, halo rows across patch edges, degenerate points, bad input.

scipy's Rotation is the independent oracle for the rigid motions.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from tfi_quat import DeformationError, GridValueError
from tfi_quat import quaternion as Q
from tfi_quat.boundary import boundary_motion, surface_normals


# ------------------------------------------------------------------ surfaces
def sphere_patch(na=11, nb=9, radius=2.0, centre=(0.3, -0.1, 0.5)):
    """A latitude-longitude patch of a sphere, away from the poles."""
    th, ph = np.meshgrid(np.linspace(0.4, 2.4, na), np.linspace(-0.3, 1.9, nb), indexing="ij")
    r = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=-1)
    return radius * r + np.asarray(centre)


def naca0012(n=41, closed=True):
    """Closed NACA 0012 section, lower TE -> LE -> upper TE, ``(2n-1, 2)``; cosine spacing."""
    xs = 0.5 * (1.0 - np.cos(np.linspace(0.0, np.pi, n)))
    yt = 0.6 * (0.2969 * np.sqrt(xs) - 0.1260 * xs - 0.3516 * xs ** 2 + 0.2843 * xs ** 3
                - 0.1036 * xs ** 4)
    x = np.concatenate([xs[::-1], xs[1:]])
    y = np.concatenate([-yt[::-1], yt[1:]])
    return np.stack([x, y], axis=-1)


def wing_patch(n=21, nspan=7):
    """Wrapped NACA 0012 wing, tapered and twisted: strong curvature at the leading edge."""
    sec = naca0012(n)
    eta = np.linspace(0.0, 1.0, nspan)
    chord = 1.0 - 0.5 * eta
    twist = np.radians(-6.0) * eta
    x = sec[:, None, 0] * chord
    y = sec[:, None, 1] * chord
    xr = x * np.cos(twist) + y * np.sin(twist) + 0.3 * eta
    yr = -x * np.sin(twist) + y * np.cos(twist) + 0.1 * eta ** 2
    z = np.broadcast_to(3.0 * eta, xr.shape)
    return np.stack([xr, yr, z], axis=-1)


def cap_patch(na=9, nb=13, collapsed_rows=1):
    """Ellipsoidal wing-tip cap: the first ``collapsed_rows`` rows all sit on the pole."""
    th = np.concatenate([np.zeros(collapsed_rows - 1), np.linspace(0.0, 1.3, na - collapsed_rows + 1)])
    th, ph = np.meshgrid(th, np.linspace(0.0, 2.0 * np.pi, nb), indexing="ij")
    return np.stack([0.4 * np.sin(th) * np.cos(ph), 0.2 * np.sin(th) * np.sin(ph), 0.5 * np.cos(th)], axis=-1)


def airfoil_curve(n=41):
    """The NACA 0012 wall curve of a 2-D grid ``(2n-1, 3)``, z = 0, closed at the trailing edge."""
    sec = naca0012(n)
    return np.column_stack([sec, np.zeros(len(sec))])


def curve_halo(r):
    """Halo of a closed curve across its trailing edge: r[-2] before r[0], r[1] after r[-1]."""
    return np.concatenate([r[-2:-1], r, r[1:2]])


def nan_halo(r):
    """A surface padded with NaN rows: no neighbours anywhere."""
    h = np.full((r.shape[0] + 2, r.shape[1] + 2, 3), np.nan)
    h[1:-1, 1:-1] = r
    return h


SURFACES = {
    "sphere": sphere_patch(),
    "wing": wing_patch(),
    "cap": cap_patch(),
    "cap2": cap_patch(collapsed_rows=2),
    "duplicated_row": np.concatenate([sphere_patch()[:5], sphere_patch()[4:]]),
}


def apply(rot, t, r):
    return rot.apply(r.reshape(-1, 3)).reshape(r.shape) + t


def qerr(q, qt):
    """Largest per-point distance between q and qt, up to sign."""
    qt = np.broadcast_to(qt, q.shape)
    return np.minimum(np.abs(q - qt).max(-1), np.abs(q + qt).max(-1)).max()


def reconstruct(q, delta, ru, c):
    return c + delta + Q.rotate(q, ru - c)


def check_signs(q):
    """Neighbours in the same hemisphere (no sign flips), along both index directions."""
    if q.ndim == 2:
        q = q[:, None, :]
    assert np.all(np.einsum("ijk,ijk->ij", q[1:], q[:-1]) > 0)
    assert np.all(np.einsum("ijk,ijk->ij", q[:, 1:], q[:, :-1]) > 0)


vec3 = st.tuples(*[st.floats(-1.0, 1.0)] * 3).map(np.array).filter(lambda v: np.linalg.norm(v) > 1e-2)
angle_deg = st.one_of(st.floats(0.0, 179.0), st.sampled_from([0.0, 1e-9, 1e-4, 90.0, 178.999, 179.0]))


# ------------------------------------------------------------------ rigid motions
@given(name=st.sampled_from(sorted(SURFACES)), axis=vec3, deg=angle_deg, t=vec3.map(lambda v: 5.0 * v),
       centre=st.one_of(st.none(), vec3.map(lambda v: 3.0 * v)))
def test_rigid_motion_of_surfaces_is_recovered_at_every_point(name, axis, deg, t, centre):
    ru = SURFACES[name]
    rot = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(deg))
    rd = apply(rot, t, ru)
    q, delta = boundary_motion(ru, rd, centre)
    c = ru.reshape(-1, 3).mean(axis=0) if centre is None else centre
    scale = max(np.abs(ru).max(), np.abs(t).max(), np.abs(c).max(), 1.0)
    assert q.shape == ru.shape[:-1] + (4,) and delta.shape == ru.shape
    assert qerr(q, rot.as_quat(scalar_first=True)) <= 1e-12
    np.testing.assert_allclose(delta, np.broadcast_to(t + rot.apply(c) - c, delta.shape),
                               rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(reconstruct(q, delta, ru, c), rd, rtol=0, atol=1e-12 * scale)
    check_signs(q)
    assert q[0, 0, 0] >= 0.0


@given(deg=st.one_of(st.floats(-179.0, 179.0), st.sampled_from([-179.0, 179.0, 0.0, 1e-10])),
       t=vec3.map(lambda v: 5.0 * v * np.array([1.0, 1.0, 0.0])), halo=st.booleans())
def test_rigid_motion_of_airfoil_curve_is_recovered(deg, t, halo):
    ru = airfoil_curve()
    rot = Rotation.from_rotvec([0.0, 0.0, np.radians(deg)])
    rd = apply(rot, t, ru)
    kw = dict(halo_u=curve_halo(ru), halo_d=curve_halo(rd)) if halo else {}
    q, delta = boundary_motion(ru, rd, plane_normal=(0, 0, 1), **kw)
    c = ru.mean(axis=0)
    assert q.shape == (len(ru), 4) and delta.shape == ru.shape
    assert qerr(q, rot.as_quat(scalar_first=True)) <= 1e-12
    np.testing.assert_allclose(delta, np.broadcast_to(t + rot.apply(c) - c, delta.shape), rtol=0, atol=1e-12 * 5)
    np.testing.assert_allclose(reconstruct(q, delta, ru, c), rd, rtol=0, atol=5e-12)
    check_signs(q)


def test_half_turn_of_a_surface_is_recovered():
    """180 deg: antiparallel normals need a chosen perpendicular axis, then Q2 completes it."""
    ru = SURFACES["wing"]
    for axis in ([0, 0, 1], [1, 0, 0], [0.3, 0.4, -0.5]):
        rot = Rotation.from_rotvec(np.array(axis) / np.linalg.norm(axis) * np.pi)
        q, delta = boundary_motion(ru, apply(rot, 0.0, ru))
        assert qerr(q, rot.as_quat(scalar_first=True)) <= 1e-12


def test_zero_motion_gives_identity_and_zero_delta():
    for ru in SURFACES.values():
        q, delta = boundary_motion(ru, ru.copy())
        assert qerr(q, [1.0, 0, 0, 0]) <= 1e-15
        np.testing.assert_allclose(delta, 0.0, atol=1e-15)


# ------------------------------------------------------------------ invariance (docs/method.md §3.6)
def bent(ru, amount=0.4):
    """A smooth non-rigid deformation: bend about x growing along z, plus a stretch."""
    b = amount * (ru[..., 2] / 3.0) ** 2
    rd = ru.copy()
    rd[..., 1] = ru[..., 1] * np.cos(b) - ru[..., 2] * np.sin(b) + 0.05 * ru[..., 0] ** 2
    rd[..., 2] = ru[..., 1] * np.sin(b) + ru[..., 2] * np.cos(b)
    rd[..., 0] = ru[..., 0] * (1.0 + 0.1 * ru[..., 2])
    return rd


@given(g=vec3, deg=st.floats(0.0, 180.0), shift=vec3.map(lambda v: 10.0 * v), default_centre=st.booleans())
def test_moving_the_whole_problem_moves_q_and_delta(g, deg, shift, default_centre):
    ru = wing_patch()
    rd = apply(Rotation.from_rotvec([0.2, -0.4, 0.3]), [0.1, 0.2, -0.3], bent(ru))
    c = np.array([0.4, -0.2, 1.0])
    cc = None if default_centre else c
    q, delta = boundary_motion(ru, rd, cc)
    # translation with the centre: nothing changes
    qt, dt = boundary_motion(ru + shift, rd + shift, None if default_centre else c + shift)
    assert qerr(qt, q) <= 1e-10
    np.testing.assert_allclose(dt, delta, rtol=0, atol=1e-10 * 10)
    # rotation of points and centre: q -> G q G*, delta -> G delta
    G = Rotation.from_rotvec(g / np.linalg.norm(g) * np.radians(deg))
    qg, dg = boundary_motion(apply(G, 0.0, ru), apply(G, 0.0, rd), None if default_centre else G.apply(c))
    gq = G.as_quat(scalar_first=True)
    expect = Q.multiply(Q.multiply(gq, q), Q.conjugate(gq))
    assert qerr(qg, expect) <= 1e-10
    np.testing.assert_allclose(dg, G.apply(delta.reshape(-1, 3)).reshape(delta.shape), rtol=0, atol=1e-10 * 10)


def test_block_face_slices_in_fortran_order_and_inputs_untouched():
    """The Deformer passes face slices of Fortran-ordered blocks; results do not depend on layout."""
    ru = wing_patch()
    rd = bent(ru)
    q, delta = boundary_motion(ru, rd)
    block_u = np.asfortranarray(np.stack([ru, ru + 1.0], axis=2))      # (ni, nj, nk, 3)
    block_d = np.asfortranarray(np.stack([rd, rd + 1.0], axis=2))
    keep_u, keep_d = block_u.copy(), block_d.copy()
    qf, df = boundary_motion(block_u[:, :, 0, :], block_d[:, :, 0, :])
    np.testing.assert_array_equal(qf, q)
    np.testing.assert_array_equal(df, delta)
    np.testing.assert_array_equal(block_u, keep_u)
    np.testing.assert_array_equal(block_d, keep_d)


def test_nonrigid_motion_reproduces_the_deformed_wall():
    for name, ru in SURFACES.items():
        rd = bent(ru)
        c = np.array([0.1, 0.2, 0.3])
        q, delta = boundary_motion(ru, rd, c)
        assert np.all(np.isfinite(q)) and np.all(np.isfinite(delta)), name
        np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
        np.testing.assert_allclose(reconstruct(q, delta, ru, c), rd, rtol=0, atol=1e-12 * 4)


# ------------------------------------------------------------------ bending: smooth q
@pytest.mark.parametrize("total_deg", [30.0, 170.0, 300.0])
def test_bending_a_plate_gives_the_local_rotation_without_sign_flips(total_deg):
    """A plate rolled onto a cylinder: the local rotation about -y grows with x.

    Past 180 deg the scalar part changes sign; the field must stay continuous
    (q . q_neighbour close to 1), which a w >= 0 convention would break.
    """
    na, nb, length = 61, 5, 2.0
    x, y = np.meshgrid(np.linspace(0.0, length, na), np.linspace(-0.3, 0.3, nb), indexing="ij")
    ru = np.stack([x, y, np.zeros_like(x)], axis=-1)
    rb = length / np.radians(total_deg)
    phi = x / rb
    rd = np.stack([rb * np.sin(phi), y, rb * (1.0 - np.cos(phi))], axis=-1)
    q, delta = boundary_motion(ru, rd)
    expect = Q.from_axis_angle([0.0, -1.0, 0.0], phi)
    # central differences on a circle with uniform spacing give the exact tangent
    assert qerr(q[1:-1], expect[1:-1]) <= 1e-12
    step = np.radians(total_deg) / (na - 1)
    assert qerr(q[[0, -1]], expect[[0, -1]]) <= math.sin(step / 4) + 1e-12      # one-sided ends
    check_signs(q)
    d_i = np.einsum("ijk,ijk->ij", q[1:], q[:-1])
    assert d_i.min() >= math.cos(step) - 1e-12
    np.testing.assert_allclose(np.einsum("ijk,ijk->ij", q[:, 1:], q[:, :-1]), 1.0, atol=1e-12)


def test_bending_a_2d_beam_curve_is_smooth():
    n = 81
    x = np.linspace(0.0, 3.0, n)
    ru = np.column_stack([x, np.zeros(n), np.zeros(n)])
    phi = 0.5 * x ** 2          # bending angle grows along the beam, up to 4.5 rad
    # integrate the rotated tangent: an inextensible beam
    dx = np.diff(x)
    mid = 0.5 * (phi[1:] + phi[:-1])
    rd = np.zeros_like(ru)
    rd[1:, 0] = np.cumsum(np.cos(mid) * dx)
    rd[1:, 1] = np.cumsum(np.sin(mid) * dx)
    q, _ = boundary_motion(ru, rd, plane_normal=[0, 0, 1])
    check_signs(q)
    assert np.einsum("ik,ik->i", q[1:], q[:-1]).min() > 0.99
    # rotation about +z only, angle close to the bending angle
    np.testing.assert_allclose(q[:, 1:3], 0.0, atol=1e-15)
    ang = np.unwrap(2.0 * np.arctan2(q[:, 3], q[:, 0]))
    # the chord directions: (phi[i-1] + 2 phi[i] + phi[i+1]) / 4 inside, the segment angle at the ends
    expect = np.concatenate([mid[:1], 0.25 * (phi[:-2] + 2.0 * phi[1:-1] + phi[2:]), mid[-1:]])
    np.testing.assert_allclose(ang, expect, rtol=0, atol=1e-12)


# ------------------------------------------------------------------ halo rows
@pytest.mark.parametrize("axis", [0, 1])
def test_split_wall_with_halos_matches_the_unsplit_wall(axis):
    ru = wing_patch(n=21, nspan=9)
    rd = apply(Rotation.from_rotvec([0.3, 0.1, -0.2]), [1.0, 0.0, 0.5], bent(ru, 0.8))
    q, delta = boundary_motion(ru, rd, np.zeros(3))
    hu, hd = nan_halo(ru), nan_halo(rd)
    k = 10 if axis == 0 else 4          # split row/column, shared by both parts
    n = ru.shape[axis]
    sl_a, sl_b = slice(0, k + 1), slice(k, n)
    hs_a, hs_b = slice(0, k + 3), slice(k, n + 2)

    def take(a, s):
        return a[s] if axis == 0 else a[:, s]

    for s, hs in ((sl_a, hs_a), (sl_b, hs_b)):
        qp, dp = boundary_motion(take(ru, s), take(rd, s), np.zeros(3),
                                 halo_u=take(hu, hs), halo_d=take(hd, hs))
        assert qerr(qp, take(q, s)) <= 1e-15
        np.testing.assert_allclose(dp, take(delta, s), rtol=0, atol=1e-14)
    # without halos the split row is computed one-sided: it differs
    qa, _ = boundary_motion(take(ru, sl_a), take(rd, sl_a), np.zeros(3))
    edge = (k, slice(None)) if axis == 0 else (slice(None), k)
    assert qerr(qa[edge], q[edge]) > 1e-6


def test_curve_halo_across_trailing_edge_gives_one_rotation_there():
    ru = airfoil_curve()
    rd = ru.copy()
    rd[:, 1] += 0.05 * ru[:, 0] ** 2          # camber change: non-rigid
    hu, hd = curve_halo(ru), curve_halo(rd)
    q, _ = boundary_motion(ru, rd, plane_normal=(0, 0, 1), halo_u=hu, halo_d=hd)
    assert qerr(q[:1], q[-1]) <= 1e-15        # both copies of the TE point see the same neighbours
    q0, _ = boundary_motion(ru, rd, plane_normal=(0, 0, 1))
    assert qerr(q0[:1], q0[-1]) > 1e-6        # one-sided at the two ends otherwise


def test_all_nan_halo_equals_no_halo():
    ru = sphere_patch()
    rd = bent(ru)
    q, d = boundary_motion(ru, rd)
    qh, dh = boundary_motion(ru, rd, halo_u=nan_halo(ru), halo_d=nan_halo(rd))
    np.testing.assert_array_equal(qh, q)
    np.testing.assert_array_equal(dh, d)


# ------------------------------------------------------------------ normals and degenerate points
def test_surface_normals_of_sphere_and_cap_pole():
    ru = sphere_patch(centre=(0, 0, 0))
    n, ok = surface_normals(ru)
    assert ok.all()
    np.testing.assert_allclose(np.abs(np.einsum("ijk,ijk->ij", n, ru / 2.0)), 1.0, atol=2e-2)
    # one consistent side
    assert np.all(np.sign(np.einsum("ijk,ijk->ij", n, ru)) == np.sign(np.einsum("k,k->", n[5, 4], ru[5, 4])))
    n, ok = surface_normals(cap_patch())
    assert not ok[0].any() and ok[1:].all()
    np.testing.assert_array_equal(n[0], 0.0)
    np.testing.assert_allclose(np.linalg.norm(n[1:], axis=-1), 1.0, atol=1e-15)


def test_curve_normals_are_t_cross_plane_normal():
    t = np.linspace(0.0, 2.0 * np.pi, 33)
    circle = np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)])
    n, ok = surface_normals(circle, plane_normal=(0, 0, 2.0))
    assert ok.all()
    np.testing.assert_allclose(n[1:-1], circle[1:-1], atol=1e-14)      # counter-clockwise: outward
    n, ok = surface_normals(circle, halo=curve_halo(circle), plane_normal=(0, 0, 1))
    np.testing.assert_allclose(n, circle, atol=1e-14)


def test_degenerate_points_never_give_nan():
    rng = np.random.default_rng(7)
    # every point coincident: no normal anywhere -> identity, pure translation
    ru = np.ones((4, 5, 3))
    rd = ru + [0.5, -1.0, 2.0]
    q, delta = boundary_motion(ru, rd)
    np.testing.assert_array_equal(q, np.broadcast_to([1.0, 0, 0, 0], q.shape))
    np.testing.assert_allclose(delta, rd - ru, atol=1e-15)
    # a patch collapsed to a line (all tangents parallel)
    line = np.zeros((6, 3, 3))
    line[..., 0] = np.linspace(0, 1, 6)[:, None]
    q, delta = boundary_motion(line, line + rng.normal(size=line.shape) * 0.1)
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(delta))
    # a single row with its neighbour rows in the halo is fine
    sp = sphere_patch()
    hu = nan_halo(sp)[:3]
    hd = nan_halo(bent(sp))[:3]
    hu[2, 1:-1], hd[2, 1:-1] = sp[1], bent(sp)[1]
    q, delta = boundary_motion(sp[:1], bent(sp)[:1], halo_u=hu, halo_d=hd)
    # same neighbours as row 0 of the whole patch (the row above is NaN): the same q
    assert qerr(q, boundary_motion(sp, bent(sp))[0][:1]) <= 1e-15
    # a curve with repeated points at both ends
    ru = np.concatenate([airfoil_curve()[:1], airfoil_curve(), airfoil_curve()[-1:]])
    rot = Rotation.from_rotvec([0, 0, 1.0])
    q, delta = boundary_motion(ru, apply(rot, 0.0, ru), plane_normal=(0, 0, 1))
    assert qerr(q, rot.as_quat(scalar_first=True)) <= 1e-12
    # random noise on a cap with two collapsed rows: still finite and reproducing rd
    ru = cap_patch(collapsed_rows=3)
    rd = ru + 0.01 * rng.normal(size=ru.shape)
    rd[:3] = rd[0, 0]                    # the pole stays one point
    q, delta = boundary_motion(ru, rd)
    assert np.all(np.isfinite(q))
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    c = ru.reshape(-1, 3).mean(axis=0)
    np.testing.assert_allclose(reconstruct(q, delta, ru, c), rd, atol=1e-14)


def test_degenerate_row_takes_neighbour_rotation():
    """Collapsed rows are filled from the next valid row (propagated over two rows)."""
    ru = cap_patch(collapsed_rows=2)
    rd = bent(ru + [0.0, 0.0, 1.0])
    q, _ = boundary_motion(ru, rd)
    _, ok = surface_normals(ru)
    assert not ok[:2].any() and ok[2:].all()
    for j in range(1, ru.shape[1] - 1):
        near = Q.blend(q[2, j - 1:j + 2], np.ones(3))
        assert qerr(q[1, j], near) <= 1e-15


# ------------------------------------------------------------------ bad input
def _bad_cases():
    ru = sphere_patch(5, 4)
    rd = ru + 0.1
    cu = airfoil_curve(5)
    h = nan_halo(ru)
    hd = nan_halo(rd)
    bad_interior = h.copy()
    bad_interior[2, 2, 0] += 1e-9
    inf_halo = h.copy()
    inf_halo[0, 1] = np.inf
    pattern = hd.copy()
    pattern[0, 1] = rd[0, 0]
    nan_ru = ru.copy()
    nan_ru[1, 2, 1] = np.nan
    return [
        ((np.ones((4, 4)), rd), {}, GridValueError, "ru"),
        ((ru, np.ones((5, 4, 2))), {}, GridValueError, "rd"),
        ((ru, rd[:4]), {}, DeformationError, "rd"),
        ((nan_ru, rd), {}, GridValueError, r"ru: NaN.*\(1, 2\)"),
        ((ru, "x"), {}, GridValueError, "rd"),
        ((ru[:1], rd[:1]), {}, GridValueError, r"ru: shape \(1, 4, 3\).*curve"),
        ((cu[:1], cu[:1]), {"plane_normal": (0, 0, 1)}, GridValueError, "ru.*n >= 2"),
        ((ru, rd, [0, 0]), {}, GridValueError, "centre"),
        ((ru, rd, [0, np.nan, 0]), {}, GridValueError, "centre"),
        ((cu, cu + 1.0), {}, GridValueError, "plane_normal"),
        ((cu, cu + 1.0), {"plane_normal": (0, 0, 0)}, GridValueError, "plane_normal"),
        ((ru, rd), {"plane_normal": (0, 0, 1)}, GridValueError, "plane_normal"),
        ((ru, rd), {"halo_u": h}, DeformationError, "halo_d"),
        ((ru, rd), {"halo_d": hd}, DeformationError, "halo_u"),
        ((ru, rd), {"halo_u": h[1:], "halo_d": hd}, DeformationError, "halo_u"),
        ((ru, rd), {"halo_u": bad_interior, "halo_d": hd}, DeformationError, "halo_u.*interior"),
        ((ru, rd), {"halo_u": inf_halo, "halo_d": hd}, GridValueError, "halo_u"),
        ((ru, rd), {"halo_u": h, "halo_d": pattern}, DeformationError, "halo_d"),
        ((cu, cu), {"plane_normal": (0, 0, 1), "halo_u": cu, "halo_d": cu}, DeformationError, "halo_u"),
    ]


@pytest.mark.parametrize("args, kwargs, exc, match", _bad_cases())
def test_bad_input_raises_naming_the_argument(args, kwargs, exc, match):
    with pytest.raises(exc, match=match):
        boundary_motion(*args, **kwargs)


def test_surface_normals_bad_input():
    with pytest.raises(GridValueError, match="plane_normal"):
        surface_normals(airfoil_curve(5))
    with pytest.raises(DeformationError, match="halo"):
        surface_normals(sphere_patch(), halo=sphere_patch())


def test_interior_fast_path_equals_the_general_kernel():
    """Interior points take a straight-line path; it must be the same algorithm."""
    from tfi_quat import boundary as B
    for ru in (wing_patch(), SURFACES["duplicated_row"], cap_patch(collapsed_rows=2)):
        rd = apply(Rotation.from_rotvec([0.5, 2.0, -1.0]), [1.0, 2.0, 3.0], bent(ru, 1.5))
        q, _ = boundary_motion(ru, rd)
        e = np.zeros(3)
        for i in range(ru.shape[0]):
            for j in range(ru.shape[1]):
                w, x, y, z, good = B._point_quaternion(ru, rd, i, j, True, e)
                if good:
                    assert qerr(q[i, j], np.array([w, x, y, z])) <= 1e-14
                fw, fx, fy, fz, fgood = B._interior_quaternion(ru, rd, i, j) \
                    if 0 < i < ru.shape[0] - 1 and 0 < j < ru.shape[1] - 1 else (0, 0, 0, 0, False)
                if fgood:
                    assert good and qerr(np.array([fw, fx, fy, fz]), np.array([w, x, y, z])) <= 1e-14


def test_regression_edge_angles_cancelling_exactly_gave_nan():
    """Four edge rotations 0, 180, +90, -90 deg about the normal: their unit sines and
    cosines sum to exactly (0, 0).  The straight-line interior kernel used to normalise
    that zero vector into NaN; the angle is undefined, so the point must fall back to
    the general kernel (Q2 = identity), and nothing may be NaN."""
    ru = np.zeros((3, 3, 3))
    rd = np.zeros((3, 3, 3))
    edges_u = {(2, 1): (1, .5), (0, 1): (-1, .5), (1, 2): (0, 1), (1, 0): (.5, -.5)}
    edges_d = {(2, 1): (1, .5), (0, 1): (1, -.5), (1, 2): (-1, 0), (1, 0): (-.5, -.5)}
    for k in edges_u:
        ru[k][:2] = edges_u[k]
        rd[k][:2] = edges_d[k]
    for k in [(0, 0), (0, 2), (2, 0), (2, 2)]:
        ru[k][:2] = rd[k][:2] = np.array(k) - 1.0
    q, delta = boundary_motion(ru, rd)
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(delta))
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, rtol=0, atol=1e-12)
    # the normal stays +z (Q1 = identity) and the in-plane angle is undefined (Q2 = identity)
    assert qerr(q[1:2, 1:2], [1.0, 0.0, 0.0, 0.0]) <= 1e-15
    c = ru.reshape(-1, 3).mean(axis=0)
    np.testing.assert_allclose(reconstruct(q, delta, ru, c), rd, rtol=0, atol=1e-14)


@given(deg=st.floats(-180.0, 180.0), shift=vec3.map(lambda v: 10.0 * v), g=vec3,
       gdeg=st.floats(0.0, 180.0))
def test_moving_the_whole_2d_problem_moves_q_and_delta(deg, shift, g, gdeg):
    """docs/method.md §3.6 for a wall curve: translating the problem leaves (q, delta) unchanged;
    rotating it by G (points, centre and the plane normal) gives (G q G*, G delta)."""
    ru = airfoil_curve()
    rd = ru.copy()
    rd[:, 1] += 0.05 * ru[:, 0] ** 2                 # camber change (non-rigid) ...
    rd = apply(Rotation.from_rotvec([0.0, 0.0, np.radians(deg)]), [0.2, -0.1, 0.0], rd)   # ... then moved
    e = np.array([0.0, 0.0, 1.0])
    q, delta = boundary_motion(ru, rd, plane_normal=e)
    qt, dt = boundary_motion(ru + shift, rd + shift, plane_normal=e)
    assert qerr(qt, q) <= 1e-10
    np.testing.assert_allclose(dt, delta, rtol=0, atol=1e-10 * 10)
    G = Rotation.from_rotvec(g / np.linalg.norm(g) * np.radians(gdeg))
    qg, dg = boundary_motion(G.apply(ru), G.apply(rd), plane_normal=G.apply(e))
    gq = G.as_quat(scalar_first=True)
    assert qerr(qg, Q.multiply(Q.multiply(gq, q), Q.conjugate(gq))) <= 1e-10
    np.testing.assert_allclose(dg, G.apply(delta), rtol=0, atol=1e-10 * 10)
    # every q of a curve is a rotation about the plane normal
    axis_part = qg[:, 1:] - np.outer(qg[:, 1:] @ G.apply(e), G.apply(e))
    np.testing.assert_allclose(axis_part, 0.0, rtol=0, atol=1e-13)
