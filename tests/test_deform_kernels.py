"""The Deformer's compiled per-step kernels against independent references.

``_patch_level`` against ``oracles.tfi_patch`` (the reference 2-D TFI),
``_rigid_blend`` and the fade against ``scipy.spatial.transform``, the symmetry
fix and the halo gather against their definitions.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from tfi_quat import quaternion as qa
from tfi_quat import tfi
from tfi_quat.deform import stages as S
from tfi_quat.deform import Deformer, rigid_motion, twolevel

import _deform_grids as G
import oracles


def _wxyz(r: Rotation) -> np.ndarray:
    x = r.as_quat()                      # scipy: (x, y, z, w)
    return np.concatenate([x[..., 3:], x[..., :3]], axis=-1)


def _surface(na, nb, seed):
    rng = np.random.default_rng(seed)
    u = np.cumsum(rng.uniform(0.5, 1.5, na))
    v = np.cumsum(rng.uniform(0.5, 1.5, nb))
    U, V = np.meshgrid(u / u[-1], v / v[-1], indexing="ij")
    return np.stack([U + 0.1 * np.sin(3 * V), V + 0.05 * U * U, 0.2 * U * V], -1)


def _fields(x, seed):
    rng = np.random.default_rng(seed)
    d = np.sin(x @ rng.normal(size=(3, 3)))
    rv = 0.8 * np.tanh(x @ rng.normal(size=(3, 3)))
    q = _wxyz(Rotation.from_rotvec(rv.reshape(-1, 3))).reshape(x.shape[:2] + (4,))
    q *= np.where(rng.uniform(size=x.shape[:2] + (1,)) < 0.3, -1.0, 1.0)   # mixed hemispheres
    return d, q


@given(na=st.integers(3, 9), nb=st.integers(3, 9), seed=st.integers(0, 10_000))
@settings(max_examples=40, deadline=None)
def test_patch_level_is_the_reference_patch_tfi(na, nb, seed):
    """Two patches (both leading directions) in one call, global ids scattered at random:
    interiors equal oracles.tfi_patch's to round-off, sides and unwritten points untouched."""
    rng = np.random.default_rng(seed)
    shapes = [(na, nb, 0), (nb + 1, na, 1)]
    n_tot = sum(a * b for a, b, _ in shapes)
    perm = rng.permutation(n_tot + 5)
    gd = rng.normal(size=(n_tot + 5, 3))
    gq = _wxyz(Rotation.random(n_tot + 5, random_state=seed))
    patches, refs = [], []
    off = 0
    for a, b, lead in shapes:
        x = _surface(a, b, seed + a)
        s = tfi.arclength_surface(x)
        g = perm[off:off + a * b].reshape(a, b)
        off += a * b
        d, q = _fields(x, seed + b)
        gd[g] = d
        gq[g] = q
        write = np.zeros((a, b), dtype=bool)
        write[1:-1, 1:-1] = rng.uniform(size=(a - 2, b - 2)) < 0.8
        patches.append((g, s, lead, write))
        dr, qr = d.copy(), q.copy()
        oracles.tfi_patch(dr, qr, s, lead=lead)
        refs.append((dr, qr))
    gd0, gq0 = gd.copy(), gq.copy()
    S.patch_level(gd, gq, True, *S.level_pack(patches), np.zeros(0), np.zeros((0, 3)))
    touched = np.zeros(len(gd), dtype=bool)
    for (g, s, lead, write), (dr, qr) in zip(patches, refs):
        np.testing.assert_allclose(gd[g[write]], dr[write], rtol=0, atol=1e-13)
        np.testing.assert_allclose(gq[g[write]], qr[write], rtol=0, atol=1e-13)
        touched[g[write]] = True
    np.testing.assert_array_equal(gd[~touched], gd0[~touched])
    np.testing.assert_array_equal(gq[~touched], gq0[~touched])
    # translations only (method="tfi"): the same interpolation of Δ, Q untouched
    gd2, gq2 = gd0.copy(), gq0.copy()
    S.patch_level(gd2, gq2, False, *S.level_pack(patches), np.zeros(0), np.zeros((0, 3)))
    np.testing.assert_array_equal(gd2, gd)
    np.testing.assert_array_equal(gq2, gq0)


def test_patch_level_takes_the_rotation_vector_fallback():
    """Sides a = 0, a = na-1 at rest, b-sides turned +180 and -180 deg about z: the
    hemisphere-aligned correction cancels the slerp value on the middle row, where the
    fallback must run; the result equals tfi_patch's and stays unit."""
    na, nb = 5, 5
    x = _surface(na, nb, 1)
    x[..., 2] = 0.0
    u = np.linspace(0.0, 1.0, na)
    x[..., 0] = u[:, None]
    x[..., 1] = u[None, :]
    s = tfi.arclength_surface(x)
    d = np.zeros((na, nb, 3))
    q = np.zeros((na, nb, 4))
    q[..., 0] = 1.0
    q[:, 0] = [0.0, 0.0, 0.0, 1.0]
    q[:, -1] = [0.0, 0.0, 0.0, -1.0]
    q[0, :] = q[-1, :] = [1.0, 0.0, 0.0, 0.0]
    g = np.arange(na * nb).reshape(na, nb)
    write = np.zeros((na, nb), dtype=bool)
    write[1:-1, 1:-1] = True
    gd, gq = d.reshape(-1, 3).copy(), q.reshape(-1, 4).copy()
    S.patch_level(gd, gq, True, *S.level_pack([(g, s, 1, write)]), np.zeros(0), np.zeros((0, 3)))
    dr, qr = d.copy(), q.copy()
    oracles.tfi_patch(dr, qr, s, lead=1)
    np.testing.assert_allclose(gq.reshape(na, nb, 4), qr, rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.linalg.norm(gq, axis=1), 1.0, rtol=0, atol=1e-13)


def test_fade_and_rebase_against_scipy_slerp():
    """Two-level write-back: Q <- slerp(1, Q, damp) (scipy's Slerp as the oracle, either
    hemisphere) and K <- K + rot(Q_faded, shift)."""
    rng = np.random.default_rng(4)
    n = 200
    q = _wxyz(Rotation.random(n, random_state=5))
    f = rng.uniform(-0.2, 1.2, n)
    f[:5] = [0.0, 1.0, 0.5, 1e-9, 1.0 - 1e-9]
    shift = rng.normal(size=(n, 3))
    shift[:10] = 0.0
    k = rng.normal(size=(n, 3))
    r = np.empty(3)
    fc = np.clip(f, 0.0, 1.0)
    for m in range(n):
        qm, km = q[m].copy(), k[m].copy()
        S.fade_and_rebase.py_func(qm, f[m], shift[m], km, r)
        key = Rotation.from_quat([[0, 0, 0, 1], np.r_[q[m, 1:], q[m, 0]]])
        want = Slerp([0.0, 1.0], key)([fc[m]])
        assert np.isclose(abs(np.dot(qm, _wxyz(want)[0])), 1.0, rtol=0, atol=1e-14)
        assert abs(np.linalg.norm(qm) - 1.0) < 1e-14
        np.testing.assert_allclose(km, k[m] + want.apply(shift[m])[0], rtol=0, atol=1e-14)
    # the compiled kernel (inlined into _patch_level / _fill_gaps) is the same function
    qm, km = q[7].copy(), k[7].copy()
    S.fill_gaps(km[None].repeat(3, 0), np.stack([np.array([1.0, 0.0, 0.0, 0.0]), qm, qm]), np.array([0]), np.array([1]),
                 np.array([0, 1]), np.array([2]), np.array([1.0]), True,
                 np.array([1.0, 1.0, f[7]]), np.array([[0.0] * 3, [0.0] * 3, shift[7]]))


@given(nb=st.integers(1, 4), seed=st.integers(0, 10_000))
@settings(max_examples=30, deadline=None)
def test_rigid_blend_is_the_weighted_rotation_vector(nb, seed):
    """Q = exp(sum_b phi_b v_b) (scipy's from_rotvec as the oracle), Delta = sum_b phi_b Delta_b;
    for one body Q is slerp(1, q_b, phi)."""
    rng = np.random.default_rng(seed)
    Qb = _wxyz(Rotation.random(nb, random_state=seed))
    Qb[Qb[:, 0] < 0] *= -1.0
    Db = rng.normal(size=(nb, 3))
    n = 50
    phi = rng.uniform(0.0, 1.0, (n, nb)) / nb
    phi[0] = 0.0
    idx = rng.permutation(2 * n)[:n]
    gd = np.full((2 * n, 3), 7.0)
    gq = np.full((2 * n, 4), 7.0)
    S.rigid_blend(phi, idx, Db, qa.log(Qb), gd, gq)
    rv = phi @ Rotation.from_quat(np.c_[Qb[:, 1:], Qb[:, :1]]).as_rotvec().reshape(nb, 3)
    want = _wxyz(Rotation.from_rotvec(rv))
    dots = np.abs(np.sum(gq[idx] * want, axis=1))
    np.testing.assert_allclose(dots, 1.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(gd[idx], phi @ Db, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(gq[0 if 0 not in idx else 1], gq[0 if 0 not in idx else 1])
    others = np.setdiff1d(np.arange(2 * n), idx)
    assert np.all(gd[others] == 7.0) and np.all(gq[others] == 7.0)
    if nb == 1:
        key = Rotation.from_quat([[0, 0, 0, 1], np.r_[Qb[0, 1:], Qb[0, 0]]])
        sl = _wxyz(Slerp([0.0, 1.0], key)(phi[:, 0]))
        np.testing.assert_allclose(np.abs(np.sum(gq[idx] * sl, axis=1)), 1.0, rtol=0, atol=1e-14)


def test_symmetry_fix_keeps_the_projected_position_and_twists_about_the_normal():
    rng = np.random.default_rng(2)
    n = 40
    F = rng.normal(size=(n, 3))
    X = rng.normal(size=(n, 3))
    q = _wxyz(Rotation.random(n, random_state=3))
    q[0] = [0.0, 1.0, 0.0, 0.0]            # a half turn about x: no twist about z
    carm = np.array([0.3, -0.2, 0.5])
    normal = np.tile(np.array([0.0, 0.6, 0.8]), (n, 1))
    normal[n // 2:] = [0.0, 0.0, 1.0]
    normal[0] = [0.0, 0.0, 1.0]
    point = rng.normal(size=(n, 3))
    idx = np.arange(n)
    pos0 = carm + F + qa.rotate(q, X - carm)
    want = pos0 - np.sum((pos0 - point) * normal, axis=1, keepdims=True) * normal
    F2, q2 = F.copy(), q.copy()
    S.symmetry_fix(F2, q2, True, X, carm, idx, point, normal)
    np.testing.assert_allclose(carm + F2 + qa.rotate(q2, X - carm), want, rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.cross(q2[:, 1:], normal), 0.0, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(q2, axis=1), 1.0, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(q2[0], [1.0, 0.0, 0.0, 0.0])
    # translations only: the position X + F is projected, Q untouched
    F3 = F.copy()
    S.symmetry_fix(F3, np.empty((1, 4)), False, X, np.zeros(3), idx, point, normal)
    p3 = X + F
    p3 -= np.sum((p3 - point) * normal, axis=1, keepdims=True) * normal
    np.testing.assert_allclose(X + F3, p3, rtol=0, atol=1e-13)


def test_halo_points_gather_mirror_and_mark_missing():
    X = np.arange(15.0).reshape(5, 3)
    po = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    pn = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    out = np.empty((4, 3))
    S.halo_points(X, np.array([2, -1, 3, 4]), np.array([-1, -1, 0, 1]), po, pn, out)
    np.testing.assert_array_equal(out[0], X[2])
    assert np.all(np.isnan(out[1]))
    np.testing.assert_array_equal(out[2], [-9.0, 10.0, 11.0])
    np.testing.assert_array_equal(out[3], [12.0, 2.0 - 13.0, 14.0])


def test_rigid_part_of_two_bodies_with_different_axes():
    """Two 3-D blocks side by side; the y = 0 face is one body, the y = 1 face another,
    turned about different axes.  The derived interface points get
    Q = exp(phi_1 v_1 + phi_2 v_2) with phi_b the reference patch TFI (oracles.tfi_patch)
    of each body's indicator over the interface, and walls land exactly."""
    grid, _, _, _ = G.box_pair(n=7)
    walls = ["1:jmin", "2:imin", "1:jmax", "2:imax"]
    d = Deformer(grid, walls=walls)
    sk, two = d.skeleton, d.two_level
    P = sk.points.P
    assert len(two.bodies) == 2
    lower = np.array([P[b.gids][:, 1].max() < 0.5 for b in two.bodies])
    m_low = rigid_motion(6.0, (1, 0, 0), (1.0, 0.0, 0.5))
    m_up = rigid_motion(-4.0, (0, 0, 1), (1.0, 1.0, 0.5))

    def move(p):
        return np.where((p[:, 1] < 0.5)[:, None], m_low(p), m_up(p))

    out = d.deform(move)
    rd = P.copy()
    rd[sk.points.wall] = move(P[sk.points.wall])
    fits = twolevel.fit_bodies(sk, two, rd, P.copy())
    gdelta, gq = np.zeros((sk.n_global, 3)), np.zeros((sk.n_global, 4))
    twolevel.rigid_fields(sk, two, fits, d.centre, gdelta, gq)
    v = [Rotation.from_quat(np.r_[q[1:], q[0]]).as_rotvec() for q, _ in fits]
    itf = d.connectivity.interfaces[0]
    g = sk.points.rect_gid(itf.master)
    pt = next(p for p in sk.patches.items if np.array_equal(p.gid, g))
    phis = []
    der = np.searchsorted(sk.derived, g)
    is_der = sk.derived[np.minimum(der, sk.derived.size - 1)] == g
    for k, b in enumerate(two.bodies):
        # the sides: walls 1 or 0, derived side points (segments) their own weights
        ind = np.zeros(g.shape + (3,))
        ind[..., 0] = np.isin(g, b.gids)
        ind[is_der, 0] = two.phi[der[is_der], k]
        oracles.tfi_patch(ind, None, pt.s, lead=pt.lead)
        phis.append(ind[..., 0])
    inner = (slice(1, -1), slice(1, -1))
    rv = phis[0][inner][..., None] * v[0] + phis[1][inner][..., None] * v[1]
    want = _wxyz(Rotation.from_rotvec(rv.reshape(-1, 3)))
    got = gq[g[inner].ravel()]
    np.testing.assert_allclose(np.abs(np.sum(got * want, axis=1)), 1.0, rtol=0, atol=1e-13)
    assert np.ptp(phis[0][inner]) > 0.1 and np.ptp(phis[1][inner]) > 0.1
    # walls exact; the two bodies really turned about different axes
    for b, blk in enumerate(out):
        assert np.all(np.isfinite(blk.xyz))
    assert abs(np.dot(v[0], v[1])) < 1e-6 * np.linalg.norm(v[0]) * np.linalg.norm(v[1]) + 1e-12
    np.testing.assert_allclose(out[0].xyz[:, 0], move(grid[0].xyz[:, 0].reshape(-1, 3)).reshape(
        grid[0].xyz[:, 0].shape), rtol=0, atol=1e-13)
    assert lower.sum() == 1


@settings(max_examples=20, deadline=None)
@given(nv=st.integers(1, 40), ns=st.integers(1, 60), seed=st.integers(0, 10_000))
def test_vertex_blend_rows_match_numpy_and_any_subset(nv, ns, seed):
    """The free vertices' blend row by row: Δ equal to the product ``w @ X[src]`` (numpy), the
    quaternions to the hemisphere-aligned normalised mean written with numpy; any subset of
    rows (one MPI rank's part) gives those rows' bits exactly."""
    from types import SimpleNamespace
    rng = np.random.default_rng(seed)
    G = ns + nv + 5
    src = rng.permutation(G)[:ns]
    w = rng.random((nv, ns)) ** 3
    w /= w.sum(axis=1, keepdims=True)
    ref = np.argmax(w, axis=1)
    decay = rng.random(nv)
    X = rng.standard_normal((G, 3))
    Q = rng.standard_normal((G, 4))
    Q /= np.linalg.norm(Q, axis=1, keepdims=True)
    vx = SimpleNamespace(idw=(src, w, decay, ref))
    d = S.vertex_blend(vx, X)
    np.testing.assert_allclose(d, w @ X[src], rtol=0, atol=1e-14)
    q = S.vertex_q(vx, Q, decay)
    qs = Q[src]
    sign = np.where(qs[ref] @ qs.T >= 0.0, 1.0, -1.0)
    qbar = (w * sign) @ qs
    qbar /= np.linalg.norm(qbar, axis=1, keepdims=True)
    ident = np.tile([1.0, 0.0, 0.0, 0.0], (nv, 1))
    want = qa.slerp(ident, qbar, decay)
    np.testing.assert_allclose(np.abs(np.sum(q * want, axis=1)), 1.0, rtol=0, atol=1e-12)
    rows = np.flatnonzero(rng.random(nv) < 0.5)
    sub = SimpleNamespace(idw=(src, np.ascontiguousarray(w[rows]), decay[rows], ref[rows]))
    assert S.vertex_blend(sub, X).tobytes() == d[rows].tobytes()
    assert S.vertex_q(sub, Q, decay[rows]).tobytes() == q[rows].tobytes()


def test_fit_parts_partition_and_fits_match_fit_rigid():
    """The rigid fits' partition holds every wall point once, in the body it belongs to; the
    fits from its per-part sums agree with :func:`tfi_quat.fit.fit_rigid` on each body's
    points (two bodies); the walls are pulled back by each body's fit; a subset of parts
    (one MPI rank's) gives those parts' sums with the same bits."""
    from tfi_quat.fit import fit_rigid
    grid, _, _, _ = G.box_pair(n=7)
    d = Deformer(grid, walls=["1:jmin", "2:imin", "1:jmax", "2:imax"])
    sk, two = d.skeleton, d.two_level
    P = sk.points.P
    wall = sk.points.wall
    ptr, gids = two.part_ptr, two.part_gids
    assert np.array_equal(np.sort(gids), np.sort(wall))
    for m in range(two.part_body.size):
        assert np.isin(gids[ptr[m]:ptr[m + 1]], two.bodies[two.part_body[m]].gids).all()
    rd = P.copy()
    m_low = rigid_motion(6.0, (1, 0, 0), (1.0, 0.0, 0.5), translate=(0.1, 0.0, 0.0))
    rd[wall] = m_low(P[wall]) + 1e-3 * np.sin(7.0 * P[wall])
    y = P.copy()
    fits = twolevel.fit_bodies(sk, two, rd, y)
    for body, (q, t) in zip(two.bodies, fits):
        q0, t0 = fit_rigid(P[body.gids], rd[body.gids], body.axis, body.tproj)
        assert abs(abs(float(q @ q0)) - 1.0) < 1e-13
        np.testing.assert_allclose(t, t0, rtol=0, atol=1e-12)
        np.testing.assert_allclose(y[body.gids], qa.rotate(qa.conjugate(q), rd[body.gids] - t),
                                   rtol=0, atol=0)
    allp = twolevel.fit_sums(sk, two, rd, np.arange(two.part_body.size))
    some = np.arange(1, two.part_body.size, 2)
    assert twolevel.fit_sums(sk, two, rd, some).tobytes() == allp[some].tobytes()
