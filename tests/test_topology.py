"""Connectivity: interfaces, transforms, patches, kinds, JSON files."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tfi_quat import ConnectivityError, Grid
from tfi_quat.spec import PatchSpec
from tfi_quat.topology import Connectivity, Interface, Patch, classify, connect, node_labels

from conftest import annulus, sheared_box


# ------------------------------------------------------------------ grids
def c_grid(nw=5, na=13, nj=4, R=4.0):
    """2-D C-grid around an ellipse: jmin = lower wake, airfoil, upper wake (cut at y = 0)."""
    xw = np.linspace(3.0, 1.0, nw)
    th = np.linspace(0.0, -2 * np.pi, na)
    inner = np.concatenate([np.stack([xw, 0 * xw], 1),
                            np.stack([np.cos(th), 0.2 * np.sin(th)], 1)[1:],
                            np.stack([xw[::-1], 0 * xw], 1)[1:]])
    outer = np.concatenate([np.stack([xw, -R + 0 * xw], 1),
                            np.stack([1.5 * R * np.cos(th) - 0.5, R * np.sin(th)], 1)[1:],
                            np.stack([xw[::-1], R + 0 * xw], 1)[1:]])
    outer[nw - 1:nw - 1 + na, 1] = np.where(np.arange(na) < na // 2, -R, R)  # keep it C-shaped
    t = np.linspace(0.0, 1.0, nj) ** 1.5
    xyz = np.zeros((len(inner), nj, 1, 3), order="F")
    xyz[:, :, 0, :2] = inner[:, None, :] + t[None, :, None] * (outer - inner)[:, None, :]
    xyz[nw - 1:nw - 1 + na, 1:, 0, :] += 0.0
    return xyz


def extrude(xyz2d, nk=3, dz=0.5):
    ni, nj = xyz2d.shape[:2]
    out = np.zeros((ni, nj, nk, 3), order="F")
    out[..., :2] = xyz2d[:, :, 0:1, :2]
    out[..., 2] = (np.arange(nk) * dz)[None, None, :]
    return out


def orient(xyz, perm, flips):
    """Permute and reverse a block's index axes (a new block of the same points)."""
    out = xyz.transpose(tuple(perm) + (3,))
    for ax, f in enumerate(flips):
        if f:
            out = np.flip(out, axis=ax)
    return np.asfortranarray(out)


def check_interfaces(grid, conn, tol=1e-9):
    """Every interface maps every master point onto a coincident slave point of its slave range."""
    for it in conn.interfaces:
        lo, hi = it.point_range
        ii = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi)], indexing="ij"),
                      -1).reshape(-1, 3)
        s = it.slave_index(ii)
        xm = grid[it.master.block].xyz[ii[:, 0], ii[:, 1], ii[:, 2]]
        xs = grid[it.slave.block].xyz[s[:, 0], s[:, 1], s[:, 2]]
        assert np.abs(xm - xs).max() <= tol, str(it)
        np.testing.assert_array_equal(it.master_index(s), ii)
        # the image is exactly the slave range on the slave face
        sp = it.slave
        from tfi_quat.grid import face_axes
        d, a, b = face_axes(sp.face)
        (c0, c1), (e0, e1) = sp.range
        assert s[:, a].min() == c0 and s[:, a].max() == c1 and s[:, b].min() == e0 and s[:, b].max() == e1


def covered_once(conn, grid):
    """Every boundary cell is covered by exactly one interface side or patch."""
    from tfi_quat.grid import face_shape
    for b, f in conn.faces():
        na, nb = face_shape(grid[b].dims, f)
        cnt = np.zeros((max(na - 1, 1), max(nb - 1, 1)), dtype=int)
        specs = [p.spec for _, p in conn.patches_on(b, f)]
        specs += [it.master if side == "master" else it.slave for _, it, side in conn.interfaces_on(b, f)]
        for s in specs:
            (a0, a1), (b0, b1) = s.range
            cnt[a0:max(a1, a0 + 1), b0:max(b1, b0 + 1)] += 1
        assert (cnt == 1).all(), (b, f, cnt)


# ----------------------------------------------------------------- 2-D
def test_c_grid_wake_cut_is_a_self_interface_and_wall_reduced():
    xyz = c_grid(nw=5, na=13)
    g = Grid([xyz])
    ni = xyz.shape[0]
    conn = connect(g, walls=["1:jmin"])
    assert conn.ndim == 2 and len(conn.interfaces) == 1
    it = conn.interfaces[0]
    assert it.is_self and it.master.face == it.slave.face == "jmin"
    assert it.master.range == ((0, 4), (0, 0))
    assert it.slave.range == ((ni - 5, ni - 1), (0, 0))
    assert it.transform == (-1, -2, 3)        # i reversed, jmin -> jmin, k -> k in 2-D
    check_interfaces(g, conn)
    walls = conn.kinds()["wall"]
    assert [p.spec.range for p in walls] == [((4, ni - 5), (0, 0))]   # the airfoil, not the cut
    assert all(p.origin == "user" for p in walls)
    covered_once(conn, g)


def test_o_grid_periodic_seam():
    g = Grid([annulus(ni=17, nj=5, theta=2 * np.pi)])
    conn = connect(g, walls=["1:jmin"])
    assert len(conn.interfaces) == 1
    it = conn.interfaces[0]
    assert (it.master.face, it.slave.face) == ("imin", "imax")
    assert it.transform == (1, 2, 3) and it.slave_begin == (16, 0, 0)
    check_interfaces(g, conn)
    assert {p.spec.face: p.kind for p in conn.patches} == {"jmin": "wall", "jmax": "fixed"}


def test_two_blocks_2d_full_and_partial_face():
    full = annulus(ni=9, nj=5)
    g = Grid([full[:5], full[4:]])
    conn = connect(g)
    assert [(i.master.face, i.slave.face, i.transform) for i in conn.interfaces] == [("imax", "imin", (1, 2, 3))]
    check_interfaces(g, conn)
    # partial: the second block only covers j = 0..2 of the first one's imax side
    g = Grid([full[:5], np.asfortranarray(full[4:, :3])])
    conn = connect(g)
    it, = conn.interfaces
    assert it.master == PatchSpec(0, "imax", ((0, 2), (0, 0))) and it.slave == PatchSpec(1, "imin", ((0, 2), (0, 0)))
    rest = [p.spec for p in conn.patches if p.spec.block == 0 and p.spec.face == "imax"]
    assert rest == [PatchSpec(0, "imax", ((2, 4), (0, 0)))]
    covered_once(conn, g)


def test_2d_reversed_block_and_transform_third_entry():
    full = annulus(ni=9, nj=5)
    b2 = np.asfortranarray(full[4:][::-1, ::-1])
    g = Grid([full[:5], b2])
    conn = connect(g)
    it, = conn.interfaces
    assert it.transform[2] == 3 and (it.master.face, it.slave.face) == ("imax", "imax")
    assert it.transform[:2] == (-1, -2)
    check_interfaces(g, conn)


def test_auto_symmetry_2d_straight_side_next_to_wall():
    # channel: bottom wall jmin; imin/imax are straight and touch the wall -> symmetry (auto)
    x, y = np.meshgrid(np.linspace(0, 2, 6), np.linspace(0, 1, 4) ** 2, indexing="ij")
    xyz = np.stack([x, y + 0.1 * np.sin(x) * (1 - y)], -1)
    conn = connect(Grid([xyz]), walls=["1:jmin"])
    kinds = {p.spec.face: (p.kind, p.origin) for p in conn.patches}
    assert kinds["imin"] == ("symmetry", "auto") and kinds["imax"] == ("symmetry", "auto")
    assert kinds["jmax"] == ("fixed", "default")
    assert sum("symmetry (auto)" in n for n in conn.notes) == 2
    p = next(p for p in conn.patches if p.spec.face == "imin")
    assert np.allclose(np.abs(p.plane[1]), [1, 0, 0])
    assert connect(Grid([xyz]), walls=["1:jmin"], auto_symmetry=False).kinds()["symmetry"] == []


# ----------------------------------------------------------------- 3-D
#: every orientation of a block: the 6 permutations of its axes x the 8 reversals (48 signed permutations)
ORIENTS_3D = [(p, f) for p in itertools.permutations(range(3)) for f in itertools.product((False, True), repeat=3)]
#: 2-D: the 8 signed permutations of i and j (k stays k)
ORIENTS_2D = [(p + (2,), f + (False,)) for p in itertools.permutations(range(2))
              for f in itertools.product((False, True), repeat=2)]


def expected_transform(perm, flips):
    """Transform from a block to ``orient(block, perm, flips)``: master axis m runs along slave
    axis perm^-1(m), reversed where that axis was flipped."""
    inv = list(perm).index
    return tuple((-1 if flips[inv(m)] else 1) * (inv(m) + 1) for m in range(3))


@pytest.mark.parametrize("split", [0, 1, 2])
@pytest.mark.parametrize("perm,flips", ORIENTS_3D)
def test_every_orientation_3d_gives_its_transform(perm, flips, split):
    """All 48 orientations x 3 interface directions, coordinates perturbed at 1e-15."""
    rng = np.random.default_rng(100 * split + ORIENTS_3D.index((perm, flips)))
    big = sheared_box(7, 6, 5)
    cut = [3, 2, 2][split]
    lo = [slice(None)] * 3
    hi = [slice(None)] * 3
    lo[split] = slice(0, cut + 1)
    hi[split] = slice(cut, None)
    a = np.asfortranarray(big[tuple(lo)])
    b = orient(big[tuple(hi)], perm, flips)
    b = np.asfortranarray(b * (1 + 1e-15 * rng.uniform(-1, 1, b.shape)))
    g = Grid([a, b])
    conn = connect(g)
    it, = conn.interfaces
    assert it.master.block == 0 and it.master.face == ("imax", "jmax", "kmax")[split]
    assert it.transform == expected_transform(perm, flips)
    check_interfaces(g, conn, tol=1e-13)
    covered_once(conn, g)


@pytest.mark.parametrize("split", [0, 1])
@pytest.mark.parametrize("perm,flips", ORIENTS_2D)
def test_every_orientation_2d_gives_its_transform(perm, flips, split):
    rng = np.random.default_rng(10 * split + ORIENTS_2D.index((perm, flips)))
    full = annulus(ni=9, nj=7)
    a = np.asfortranarray(full[:5] if split == 0 else full[:, :4])
    b = orient(full[4:] if split == 0 else full[:, 3:], perm, flips)
    b = np.asfortranarray(b * (1 + 1e-15 * rng.uniform(-1, 1, b.shape)))
    g = Grid([a, b])
    conn = connect(g)
    it, = conn.interfaces
    assert it.transform == expected_transform(perm, flips) and it.transform[2] == 3
    check_interfaces(g, conn, tol=1e-13)
    covered_once(conn, g)


def test_partial_faces_on_both_sides():
    """Two boxes whose faces overlap in the middle of each (offsets in both running indices)."""
    big = sheared_box(9, 11, 9)
    a = np.asfortranarray(big[:5, 0:8, 1:6])
    b = orient(big[4:, 3:11, 3:9], (2, 0, 1), (True, False, True))
    g = Grid([a, b])
    conn = connect(g, walls=["1:imax"])
    it, = conn.interfaces
    assert it.master == PatchSpec(0, "imax", ((3, 7), (2, 4)))
    assert it.transform == expected_transform((2, 0, 1), (True, False, True))
    check_interfaces(g, conn, tol=0.0)
    covered_once(conn, g)
    # the wall is what is left of 1:imax, an L shape, in rectangles
    cells = np.zeros((7, 4), int)
    cells[3:7, 2:4] += 1
    for p in conn.patches:
        if p.kind == "wall":
            (a0, a1), (b0, b1) = p.spec.range
            cells[a0:a1, b0:b1] += 1
    assert (cells == 1).all()


def cone(n=9, nk=1):
    """A square of indices (u, v) wrapped round its corner (0, 1): side imin is glued to side jmax.

    ``r = u + 1 - v``, ``theta = 2 pi u / r`` put (0, t) and (1 - t, 1) on the ray theta = 0 at the
    same radius; extruded in z (slightly warped) when ``nk > 1``.
    """
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    r = u + 1 - v
    th = 2 * np.pi * np.divide(u, r, out=np.zeros_like(u), where=r > 0)
    th[:, -1] = 2 * np.pi
    xyz = np.zeros((n, n, nk, 3), order="F")
    xyz[..., 0] = (r * np.cos(th))[..., None]
    xyz[..., 1] = (r * np.sin(th))[..., None]
    if nk > 1:
        xyz[..., 2] = np.linspace(0, 1, nk)[None, None, :] + 0.1 * xyz[..., 0] ** 2
    return xyz


@pytest.mark.parametrize("nk", [1, 4])
def test_self_match_of_two_faces_of_one_block_with_swapped_axes(nk):
    """The seam of the cone includes its centre, a block point on both faces (regression: the
    last cell of each side was left out as a patch)."""
    n = 9
    g = Grid([cone(n, nk)])
    conn = connect(g, walls=["1:jmin"])
    it, = conn.interfaces
    assert it.is_self and (it.master.face, it.slave.face) == ("imin", "jmax")
    assert it.transform == (2, -1, 3)
    assert it.master.range == it.slave.range == ((0, n - 1), (0, nk - 1))
    check_interfaces(g, conn, tol=1e-12)
    covered_once(conn, g)


def test_face_matching_itself_shifted_is_no_interface():
    """A sector wound round three times: jmin matches itself shifted by one turn and by two; the
    master and slave ranges of the first overlap (regression: it was taken), only the second is
    an interface."""
    m, nj = 4, 4
    th = np.linspace(0, 6 * np.pi, 3 * m + 1)[:, None]
    r = np.linspace(1, 2, nj)[None, :]
    xyz = np.zeros((3 * m + 1, nj, 1, 3), order="F")
    xyz[:, :, 0, 0] = r * np.cos(th)
    xyz[:, :, 0, 1] = r * np.sin(th)
    g = Grid([xyz])
    conn = connect(g)
    assert conn.overlaps() == []
    assert [it.master.range for it in conn.interfaces if it.master.face == "jmin"] == [((0, 4), (0, 0))]
    check_interfaces(g, conn)
    covered_once(conn, g)


def test_disc_centre_collapsed_to_a_point_2d():
    """Polar disc: i round the centre (seam imin-imax through the centre), jmin one point."""
    ni, nj = 13, 5
    th = np.linspace(0, 2 * np.pi, ni)[:, None]
    r = np.linspace(0, 1, nj)[None, :] ** 1.2
    xyz = np.zeros((ni, nj, 1, 3), order="F")
    xyz[:, :, 0, 0] = r * np.cos(th)
    xyz[:, :, 0, 1] = r * np.sin(th)
    g = Grid([xyz])
    conn = connect(g, walls=["1:jmax"])
    it, = conn.interfaces
    assert (it.master.face, it.slave.face) == ("imin", "imax") and it.master.range == ((0, nj - 1), (0, 0))
    check_interfaces(g, conn)
    jmin = [p for _, p in conn.patches_on(0, "jmin")]
    assert len(jmin) == 1 and jmin[0].collapsed and jmin[0].kind == "free"
    covered_once(conn, g)


def test_three_blocks_around_one_edge():
    blocks = []
    n = 5
    s, t = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    for m in range(3):
        a0, a1 = 2 * np.pi * m / 3, 2 * np.pi * (m + 1) / 3
        P0 = np.array([np.cos(a0), np.sin(a0)])
        P1 = np.array([np.cos(a1), np.sin(a1)])
        Q = 1.3 * (P0 + P1)
        xy = (s * (1 - t))[..., None] * P0 + (s * t)[..., None] * Q + ((1 - s) * t)[..., None] * P1
        xyz = np.zeros((n, n, 4, 3), order="F")
        xyz[..., :2] = xy[:, :, None, :]
        xyz[..., 2] = np.linspace(0, 1, 4)[None, None, :] + 0.1 * xyz[..., 0] ** 2
        blocks.append(xyz)
    g = Grid(blocks)
    conn = connect(g)
    pairs = sorted((i.master.block, i.master.face, i.slave.block, i.slave.face) for i in conn.interfaces)
    assert pairs == [(0, "imin", 1, "jmin"), (0, "jmin", 2, "imin"), (1, "imin", 2, "jmin")]
    assert all(i.master.range == ((0, 4), (0, 3)) for i in conn.interfaces)
    check_interfaces(g, conn)
    covered_once(conn, g)


@pytest.mark.parametrize("ndim", [2, 3])
def test_lattice_of_blocks_meeting_at_corners(ndim):
    """2 x 2 (x 2) blocks in random orientations: four (eight) blocks share the centre point."""
    rng = np.random.default_rng(7)
    n = 4
    u = np.linspace(0, 1, n)
    blocks = []
    for bz in range(2 if ndim == 3 else 1):
        for by in range(2):
            for bx in range(2):
                if ndim == 3:
                    X, Y, Z = np.meshgrid(bx + u, by + u, bz + u, indexing="ij")
                else:
                    X, Y = np.meshgrid(bx + u, by + u, indexing="ij")
                    X, Y, Z = X[..., None], Y[..., None], 0 * X[..., None]
                xyz = np.stack([X + 0.1 * np.sin(Y), Y + 0.1 * X * X, Z + 0.05 * X * Y * (ndim == 3)], -1)
                perm = rng.permutation(3) if ndim == 3 else np.array([*rng.permutation(2), 2])
                flips = rng.random(3) < 0.5
                flips[2] &= ndim == 3
                blocks.append(orient(xyz, tuple(int(v) for v in perm), tuple(bool(f) for f in flips)))
    g = Grid(blocks)
    assert g.ndim == ndim
    conn = connect(g)
    assert len(conn.interfaces) == (12 if ndim == 3 else 4)
    check_interfaces(g, conn, tol=0.0)
    covered_once(conn, g)
    for it in conn.interfaces:
        assert it.master.range == ((0, n - 1), (0, n - 1 if ndim == 3 else 0))
        key = lambda s: (s.block, ["imin", "imax", "jmin", "jmax", "kmin", "kmax"].index(s.face))  # noqa: E731
        assert key(it.master) < key(it.slave)
        if ndim == 2:
            assert it.transform[2] == 3


def test_node_labels_identify_points_shared_by_edge_only_neighbours():
    # quadrants 0 and 2 of a 2 x 2 lattice touch at the centre point only
    full = annulus(ni=9, nj=9, theta=np.pi / 2)
    g = Grid([np.asfortranarray(full[:5, :5]), np.asfortranarray(full[4:, :5]),
              np.asfortranarray(full[4:, 4:]), np.asfortranarray(full[:5, 4:])])
    lab = node_labels(g)
    assert lab[(0, "imax")].shape == (5, 1)
    centre = {int(lab[(0, "imax")][4, 0]), int(lab[(2, "imin")][0, 0]), int(lab[(1, "jmax")][0, 0]),
              int(lab[(3, "jmin")][4, 0])}
    assert len(centre) == 1
    assert lab[(0, "imax")][3, 0] != lab[(0, "imax")][4, 0]
    n_distinct = len(np.unique(np.concatenate([v.ravel() for v in lab.values()])))
    # the outer boundary of the 9 x 9 points (32) and the two inner lines (9 + 9 - 1 - 4)
    assert n_distinct == max(int(v.max()) for v in lab.values()) + 1 == 45
    assert len(connect(g).interfaces) == 4


def test_face_with_two_interfaces_and_a_patch():
    big = sheared_box(8, 9, 3)
    a = np.asfortranarray(big[:5])
    b = np.asfortranarray(big[4:, 0:4])
    c = orient(big[4:, 5:9], (1, 0, 2), (False, True, False))
    g = Grid([a, b, c])
    conn = connect(g, walls=["1:imax"])
    on = conn.interfaces_on(0, "imax")
    assert sorted(it.master.range for _, it, _ in on) == [((0, 3), (0, 2)), ((5, 8), (0, 2))]
    rest = [p for _, p in conn.patches_on(0, "imax")]
    assert [(p.spec.range, p.kind) for p in rest] == [(((3, 5), (0, 2)), "wall")]
    check_interfaces(g, conn)
    covered_once(conn, g)
    fm = conn.face_map(0, "imax")
    assert fm.interface.shape == (9, 3)
    assert (fm.interface[4, :] == -1).all() and (fm.patch[3:6, :] >= 0).all()
    assert (fm.role[:4] == 1).all() and (fm.interface[:3] >= 0).all()


def test_collapsed_axis_face_and_periodic_seam_3d():
    # O-grid around the z axis: i radial from the axis (imin collapsed to a line), j around
    ni, nj, nk = 4, 9, 3
    r = np.linspace(0, 1, ni)[:, None, None]
    th = np.linspace(0, 2 * np.pi, nj)[None, :, None]
    z = np.linspace(0, 1, nk)[None, None, :]
    xyz = np.zeros((ni, nj, nk, 3), order="F")
    xyz[..., 0] = r * np.cos(th) + 0 * z
    xyz[..., 1] = r * np.sin(th) + 0 * z
    xyz[..., 2] = z + 0.05 * r ** 2 + 0 * th
    g = Grid([xyz])
    conn = connect(g, walls=["1:imax"])
    it, = conn.interfaces
    assert (it.master.face, it.slave.face) == ("jmin", "jmax")
    assert it.master.range == ((0, 3), (0, 2))       # the axis row i = 0 included
    check_interfaces(g, conn)
    imin = [p for _, p in conn.patches_on(0, "imin")]
    assert len(imin) == 1 and imin[0].collapsed and imin[0].kind == "free" and imin[0].origin == "collapsed"
    assert any("collapsed" in n for n in conn.notes)
    covered_once(conn, g)


def test_axis_faces_of_two_half_o_blocks_are_not_an_interface():
    """Two halves of an O-grid round the z axis: both imin faces lie on the axis (a line)."""
    ni, nj, nk = 4, 5, 3
    blocks = []
    for t0 in (0.0, np.pi):
        r = np.linspace(0, 1, ni)[:, None, None]
        th = np.linspace(t0, t0 + np.pi, nj)[None, :, None]
        z = np.linspace(0, 1, nk)[None, None, :]
        xyz = np.zeros((ni, nj, nk, 3), order="F")
        xyz[..., 0] = r * np.cos(th) + 0 * z
        xyz[..., 1] = r * np.sin(th) + 0 * z
        xyz[..., 2] = z + 0.05 * r ** 2 + 0 * th
        blocks.append(xyz)
    g = Grid(blocks)
    conn = connect(g, walls=["1:imax", "2:imax"])
    pairs = sorted((it.master.block, it.master.face, it.slave.block, it.slave.face) for it in conn.interfaces)
    assert pairs == [(0, "jmax", 1, "jmin"), (0, "jmin", 1, "jmax")]
    assert all(it.master.range == ((0, ni - 1), (0, nk - 1)) for it in conn.interfaces)   # axis rows included
    check_interfaces(g, conn)
    col = sorted((p.spec.block, p.spec.face) for p in conn.patches if p.collapsed)
    assert col == [(0, "imin"), (1, "imin")]
    covered_once(conn, g)


def test_pole_faces_of_two_blocks_are_not_an_interface():
    # two pyramids with their imin faces collapsed onto the same apex
    ni, nj, nk = 4, 3, 3
    s = np.linspace(0, 1, ni)[:, None, None, None]
    jj, kk = np.meshgrid(np.linspace(-1, 1, nj), np.linspace(-1, 1, nk), indexing="ij")
    base = np.stack([jj, kk, np.ones_like(jj)], -1)[None]
    up = np.asfortranarray(s * base + 0 * s)
    down = np.asfortranarray(up * np.array([1, 1, -1]))
    g = Grid([up, down])
    conn = connect(g, walls=["1:imax", "2:imax"])
    assert conn.interfaces == []
    col = [p for p in conn.patches if p.collapsed]
    assert sorted((p.spec.block, p.spec.face) for p in col) == [(0, "imin"), (1, "imin")]
    covered_once(conn, g)


def test_float_noise_of_1e15_still_matches():
    rng = np.random.default_rng(1)
    big = sheared_box(9, 5, 4)
    a = np.asfortranarray(big[:5])
    b = orient(big[4:], (2, 0, 1), (True, False, True))
    b = np.asfortranarray(b * (1 + 1e-15 * rng.standard_normal(b.shape)))
    g = Grid([a, b])
    conn = connect(g)
    assert len(conn.interfaces) == 1
    check_interfaces(g, conn, tol=1e-13)
    # a real gap (1e-5 against a spacing of about 0.25) is not matched
    b2 = np.asfortranarray(b + 1e-5)
    assert connect(Grid([a, b2])).interfaces == []


@pytest.mark.parametrize("make", [lambda: c_grid(), lambda: extrude(c_grid(), nk=3),
                                  lambda: annulus(ni=17, nj=5, theta=2 * np.pi), lambda: cone(9, 4)],
                         ids=["c-grid", "c-grid-3d", "o-grid", "cone"])
def test_self_matches_survive_1e15_noise(make):
    xyz = make()
    rng = np.random.default_rng(5)
    noisy = np.asfortranarray(xyz * (1 + 1e-15 * rng.uniform(-1, 1, xyz.shape)))
    exact = connect(Grid([xyz]), walls=["1:jmin"])
    conn = connect(Grid([noisy]), walls=["1:jmin"])
    assert conn == exact and len(conn.interfaces) == 1
    check_interfaces(Grid([noisy]), conn, tol=1e-13)


def test_round_off_of_large_coordinates_with_tiny_spacing_still_matches():
    # spacing ~3e-9 at coordinates ~1e3: rtol x spacing (3e-15) is below the round-off (~1e-12)
    rng = np.random.default_rng(2)
    big = np.repeat(sheared_box(9, 5, 1), 4, axis=2)
    big[..., 2] += 3e-9 * np.arange(4)          # a 3e-9 thick layer
    big += 1000.0
    a = np.asfortranarray(big[:5])
    b = orient(big[4:], (1, 0, 2), (False, True, False))
    b = np.asfortranarray(b * (1 + 1e-15 * rng.uniform(-1, 1, b.shape)))
    g = Grid([a, b])
    conn = connect(g)
    assert len(conn.interfaces) == 1 and conn.interfaces[0].master.range == ((0, 4), (0, 3))
    check_interfaces(g, conn, tol=3e-12)
    assert not any(p.collapsed for p in conn.patches)      # 3e-9 edges are not merged


def test_extruded_c_grid_auto_symmetry_and_user_kinds():
    xyz = extrude(c_grid(), nk=3)
    g = Grid([xyz])
    conn = connect(g, walls=["1:jmin"], fixed=["1:jmax"])
    it, = conn.interfaces
    assert it.transform == (-1, -2, 3) and it.master.range == ((0, 4), (0, 2))
    check_interfaces(g, conn)
    kinds = {(p.spec.face, p.kind, p.origin) for p in conn.patches}
    assert ("kmin", "symmetry", "auto") in kinds and ("kmax", "symmetry", "auto") in kinds
    assert ("jmax", "fixed", "user") in kinds and ("imin", "fixed", "default") in kinds
    k = next(p for p in conn.patches if p.spec.face == "kmin")
    assert np.allclose(k.plane[1], [0, 0, 1])
    # the user may classify the planes; then they are not touched
    conn2 = connect(g, walls=["1:jmin"], fixed=["1:kmin", "1:kmax"])
    assert {p.kind for p in conn2.patches if p.spec.face in ("kmin", "kmax")} == {"fixed"}
    covered_once(conn2, g)


def _box_with_bulge(eps, n=6):
    """Unit box, wall jmin; its imin face (x = 0) bulges out by eps at its centre."""
    u = np.linspace(0, 1, n)
    X, Y, Z = np.meshgrid(u, u, u, indexing="ij")
    bump = eps * np.sin(np.pi * Y) * np.sin(np.pi * Z) * (1 - X)
    return Grid([np.asfortranarray(np.stack([X - bump, Y, Z], -1))])


@pytest.mark.parametrize("tol", [None, 0.1])
def test_auto_symmetry_planar_relative_to_the_patch_size(tol):
    from tfi_quat.topology import PLANE_RTOL
    assert PLANE_RTOL == 1e-6
    flat = connect(_box_with_bulge(1e-8), walls=["1:jmin"], tol=tol)
    p, = [p for _, p in flat.patches_on(0, "imin")]
    assert (p.kind, p.origin) == ("symmetry", "auto")
    np.testing.assert_allclose(p.plane[1], [1, 0, 0], atol=1e-6)
    # a bulge of 1e-4 of the face is not a plane, whatever the matching tolerance
    bent = connect(_box_with_bulge(1e-4), walls=["1:jmin"], tol=tol)
    p, = [p for _, p in bent.patches_on(0, "imin")]
    assert (p.kind, p.origin) == ("fixed", "default")
    # a user symmetry patch on it is kept, with a note
    sym = connect(_box_with_bulge(1e-4), walls=["1:jmin"], symmetry=["1:imin"], tol=tol)
    p, = [p for _, p in sym.patches_on(0, "imin")]
    assert p.kind == "symmetry" and p.plane is None
    assert any("1:imin" in s and "not planar" in s for s in sym.notes)


def test_auto_symmetry_needs_a_shared_point_with_a_wall():
    g = _box_with_bulge(0.0)
    # the wall is part of jmin away from imin: imin does not touch it
    conn = connect(g, walls=["1:jmin:3-6,1-6"])
    # (the rest of jmin is coplanar with the wall and touches it: symmetry too)
    assert sorted(p.spec.face for p in conn.patches if p.origin == "auto") == ["imax", "jmin", "kmax", "kmin"]
    assert not any("1:imin" in s for s in conn.notes)
    # a wall on another block counts: the touching point is shared across the interface
    big = np.asfortranarray(g[0].xyz)
    g2 = Grid([np.asfortranarray(big[:3]), np.asfortranarray(big[2:])])
    conn2 = connect(g2, walls=["2:jmin"])
    auto = sorted((p.spec.block, p.spec.face) for p in conn2.patches if p.origin == "auto")
    assert (0, "jmin") in auto and (0, "imin") not in auto
    notes = [s for s in conn2.notes if s.startswith("symmetry (auto)")]
    assert len(notes) == len(auto) and "-0" not in " ".join(notes)


# ---------------------------------------------------------------- errors
def test_user_patch_errors_name_block_face_and_range():
    g = Grid([sheared_box(5, 4, 3)])
    with pytest.raises(ConnectivityError, match=r"wall 1:imin:1-3,1-3 overlaps wall 1:imin"):
        connect(g, walls=["1:imin", "1:imin:1-3,1-3"])
    with pytest.raises(ConnectivityError,
                       match=r"fixed 1:kmin:2-3,1-2 overlaps symmetry 1:kmin:1-5,1-4 on block 1 face kmin"):
        connect(g, fixed=["1:kmin:2-3,1-2"], symmetry=["1:kmin"])
    with pytest.raises(ConnectivityError, match=r"wall 3:imin.*1 block"):
        connect(g, walls=["3:imin"])
    with pytest.raises(ConnectivityError, match=r"fixed 1:jmax:1-9,1-3.*exceeds"):
        connect(g, fixed=["1:jmax:1-9,1-3"])
    with pytest.raises(ConnectivityError, match=r"no area"):
        connect(g, walls=["1:jmax:1-5,2-2"])
    with pytest.raises(ConnectivityError, match=r"top"):
        connect(g, walls=["1:top"])
    with pytest.raises(ConnectivityError, match="no k faces"):
        connect(Grid([annulus()]), walls=["1:kmin"])
    with pytest.raises(ConnectivityError, match="default kind"):
        connect(g, default="moving")


def test_user_patch_on_an_interface_is_noted():
    g = Grid([c_grid()])
    conn = connect(g, walls=["1:jmin:1-5"])
    assert any("lies entirely on interfaces" in n for n in conn.notes)
    assert conn.kinds()["wall"] == []
    # a range reaching into the wake cut is reduced, with a note; a whole face silently
    conn = connect(g, walls=["1:jmin:3-19"])
    assert [p.spec.range for p in conn.kinds()["wall"]] == [((4, 16), (0, 0))]
    assert conn.notes == ["wall 1:jmin:3-19,1-1 is partly on interfaces: only its part off them is wall"]
    conn = connect(g, walls=["1:jmin"])
    assert [p.spec.range for p in conn.kinds()["wall"]] == [((4, 16), (0, 0))] and conn.notes == []


def test_interface_validates_its_transform():
    m = PatchSpec(0, "imax", ((0, 3), (0, 2)))
    s = PatchSpec(1, "imin", ((0, 3), (0, 2)))
    it = Interface(m, s, (1, 2, 3), (4, 0, 0), (0, 0, 0))
    assert it.point_range_donor == ((0, 0, 0), (0, 3, 2))
    with pytest.raises(ConnectivityError, match="signed permutation"):
        Interface(m, s, (1, 1, 3), (4, 0, 0), (0, 0, 0))
    with pytest.raises(ConnectivityError, match="not onto the slave range"):
        Interface(m, s, (1, 3, 2), (4, 0, 0), (0, 0, 0))
    with pytest.raises(ConnectivityError, match="first corner"):
        Interface(m, s, (1, 2, 3), (4, 1, 0), (0, 1, 0))
    r = it.reversed()
    assert r.master == s and r.slave == m and r.transform == (1, 2, 3)
    with pytest.raises(ConnectivityError, match="unknown kind"):
        Patch(m, "moving")


def test_connectivity_checks_grid_dims():
    g = Grid([sheared_box(5, 4, 3)])
    conn = connect(g)
    conn.check(g)
    with pytest.raises(ConnectivityError, match="block 1: connectivity is for 5 x 4 x 3"):
        conn.check(Grid([sheared_box(5, 4, 4)]))
    with pytest.raises(ConnectivityError, match="exceeds"):
        Connectivity([], [Patch(PatchSpec(0, "imin", ((0, 9), (0, 2))), "wall")], 3, [(5, 4, 3)])


# ------------------------------------------------------------ classify
def test_classify_applies_kinds_to_an_existing_connectivity():
    g = Grid([c_grid()])
    conn = connect(g)
    assert conn.kinds()["wall"] == []
    conn2 = classify(conn, g, walls=["1:jmin"], default="free")
    assert conn2.interfaces == conn.interfaces
    assert len(conn2.kinds()["wall"]) == 1 and {p.kind for p in conn2.patches} == {"wall", "free"}
    # kinds from the user survive a second classification
    conn3 = classify(conn2, g, fixed=["1:jmax"])
    assert {p.spec.face: p.kind for p in conn3.patches}["jmin"] == "wall"


# ----------------------------------------------------------------- JSON
def test_json_round_trip_is_1_based_cgns_style(tmp_path):
    big = sheared_box(9, 5, 4)
    g = Grid([np.asfortranarray(big[:5]), orient(big[4:], (1, 0, 2), (False, False, True))])
    conn = connect(g, walls=["1:jmin", "2:imin"])
    path = tmp_path / "map.json"
    conn.to_json(path)
    doc = json.loads(path.read_text())
    itf = doc["interfaces"][0]
    assert itf["PointRange"] == [[5, 1, 1], [5, 5, 4]]
    assert itf["Transform"] == list(conn.interfaces[0].transform)
    assert itf["PointRangeDonor"][0] == [v + 1 for v in conn.interfaces[0].slave_begin]
    back = Connectivity.from_json(path, g)
    assert back == conn
    assert [p.origin for p in back.patches] == [p.origin for p in conn.patches]
    with pytest.raises(Exception, match="exists"):
        conn.to_json(path)
    conn.to_json(path, overwrite=True)


#: the example of docs/formats.md, written by hand (only two of the patches)
HAND_JSON = """\
{
 "format": "tfi_quat.connectivity",
 "version": 1,
 "ndim": 3,
 "blocks": [
  [5, 5, 4],
  [5, 5, 4]
 ],
 "interfaces": [
  {"block": 1, "face": "imax", "donor": 2, "donor_face": "jmin", "PointRange": [[5, 1, 1], [5, 5, 4]], \
"PointRangeDonor": [[1, 1, 4], [5, 1, 1]], "Transform": [2, 1, -3]}
 ],
 "patches": [
  {"block": 1, "face": "jmin", "PointRange": [[1, 1, 1], [5, 1, 4]], "kind": "wall", "name": null, \
"collapsed": false, "origin": "user"},
  {"block": 1, "face": "kmin", "PointRange": [[1, 1, 1], [5, 5, 1]], "kind": "symmetry", "name": null, \
"collapsed": false, "origin": "auto", "plane": {"origin": [0.5375, 0.525, 0.0], "normal": [0.0, 0.0, 1.0]}}
 ],
 "notes": [
  "symmetry (auto) 1:kmin:1-5,1-5: planar, touches a wall, not classified; normal (0, 0, 1)"
 ]
}
"""


def test_hand_written_json_of_the_documented_layout(tmp_path):
    from pathlib import Path
    docs = (Path(__file__).parent.parent / "docs" / "formats.md").read_text().splitlines()
    assert all(line in docs for line in HAND_JSON.splitlines())      # the documented example
    path = tmp_path / "hand.json"
    path.write_text(HAND_JSON)
    big = sheared_box(9, 5, 4)
    g = Grid([np.asfortranarray(big[:5]), orient(big[4:], (1, 0, 2), (False, False, True))])
    conn = Connectivity.from_json(path, g)
    it, = conn.interfaces
    assert it == connect(g).interfaces[0]
    assert it.transform == (2, 1, -3) and it.slave_begin == (0, 0, 3)
    assert it.point_range_donor == ((0, 0, 3), (4, 0, 0))
    check_interfaces(g, conn, tol=0.0)
    wall, sym = conn.patches
    assert (wall.spec, wall.kind, wall.origin) == (PatchSpec(0, "jmin", ((0, 4), (0, 3))), "wall", "user")
    assert sym.kind == "symmetry" and sym.plane == ((0.5375, 0.525, 0.0), (0.0, 0.0, 1.0))
    assert conn.notes[0].startswith("symmetry (auto) 1:kmin")


def test_json_interface_that_does_not_match_the_grid(tmp_path):
    path = tmp_path / "hand.json"
    path.write_text(HAND_JSON)
    big = sheared_box(9, 5, 4)
    # block 2 without the reversed k of the documented example
    g = Grid([np.asfortranarray(big[:5]), orient(big[4:], (1, 0, 2), (False, False, False))])
    assert Connectivity.from_json(path).interfaces[0].transform == (2, 1, -3)
    with pytest.raises(ConnectivityError, match=r"hand.json:10: interface 1: .* does not match the grid: point "
                                                r"\(5, \d, \d\) of block 1 is [0-9.]+ from its partner \(\d, 1, \d\) of block 2"):
        Connectivity.from_json(path, g)
    with pytest.raises(ConnectivityError, match=r"hand.json: connectivity is for 2 block\(s\), the grid has 1"):
        Connectivity.from_json(path, Grid([g[0].xyz]))


@pytest.mark.parametrize("old,new,match", [
    ('"Transform": [2, 1, -3]', '"Transform": [2, 1, 3]', r"hand.json:10: interface 1: .*not onto the slave range"),
    ('"Transform": [2, 1, -3]', '"Transform": [2, 2, 3]', r"hand.json:10: interface 1: .*signed permutation"),
    ('"PointRange": [[5, 1, 1], [5, 5, 4]]', '"PointRange": [[5, 5, 4], [5, 1, 1]]',
     r"hand.json:10: interface 1: .*first corner .*lowest corner"),
    ('"PointRange": [[5, 1, 1], [5, 5, 4]]', '"PointRange": [[4, 1, 1], [4, 5, 4]]',
     r"hand.json:10: interface 1: PointRange .* is not on face imax of block 1 \(index i should be 5\)"),
    ('"donor": 2', '"donor": 3', r"hand.json:10: interface 1 \(donor\): block 3 does not exist"),
    ('"face": "jmin", "PointRange": [[1, 1, 1], [5, 1, 4]]', '"face": "jmin", "PointRange": [[1, 1, 1], [5, 1, 9]]',
     r"hand.json:13: patch 1: PointRange .* exceeds block 1 \(5 x 5 x 4\)"),
    ('"kind": "wall"', '"kind": "moving"', r"hand.json:13: patch 1: .*unknown kind 'moving'"),
    ('"kind": "wall", ', '', r"hand.json:13: patch 1: 'kind' is missing"),
    ('"face": "kmin", "PointRange": [[1, 1, 1], [5, 5, 1]]', '"face": "imax", "PointRange": [[5, 1, 1], [5, 3, 3]]',
     r"hand.json:14: patch 2 overlaps interface 1 master side \(line 10\) on block 1 face imax"),
    ('"ndim": 3', '"ndim": 4', r"hand.json: 'ndim' must be 2 or 3"),
    ('"version": 1', '"version": 2', r"hand.json: file version 2 is newer"),
    ('"notes": [', '"notes": [,', r"hand.json:16: not valid JSON"),
])
def test_bad_json_files_name_file_and_line(tmp_path, old, new, match):
    text = HAND_JSON
    assert old in text
    path = tmp_path / "hand.json"
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(ConnectivityError, match=match):
        Connectivity.from_json(path)


def test_classify_refuses_overlapping_patches():
    g = Grid([c_grid()])
    conn = connect(g, walls=["1:jmin"])
    bad = conn.with_patches(conn.patches + [Patch(PatchSpec(0, "jmin", ((0, 6), (0, 0))), "fixed")])
    assert bad.overlaps() == [(("master", 0), ("patch", 4))]
    assert conn.overlaps() == []
    with pytest.raises(ConnectivityError, match=r"patch 1:jmin:1-7,1-1 overlaps master 1:jmin:1-5,1-1"):
        classify(bad, g)


def test_json_errors_name_the_entry(tmp_path):
    g = Grid([annulus(ni=17, nj=5, theta=2 * np.pi)])
    doc = json.loads(json.dumps(__import__("tfi_quat.topology.files", fromlist=["x"]).to_dict(connect(g))))
    doc["interfaces"][0]["Transform"] = [2, 1, 3]
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(doc))
    with pytest.raises(ConnectivityError, match="interface 1"):
        Connectivity.from_json(p)
    p.write_text("{not json")
    with pytest.raises(ConnectivityError, match="not valid JSON"):
        Connectivity.from_json(p)
    p.write_text(json.dumps({"format": "other"}))
    with pytest.raises(ConnectivityError, match="not a tfi_quat connectivity"):
        Connectivity.from_json(p)


def test_table_lists_interfaces_patches_and_notes():
    g = Grid([extrude(c_grid(), nk=3)])
    text = connect(g, walls=["1:jmin"]).table()
    assert "interfaces" in text and "-1 -2 +3" in text and "wall" in text and "symmetry (auto)" in text


# ------------------------------------------------------------------ CLI
def _cli_args(argv):
    import argparse

    from tfi_quat.cli import _connect
    parser = argparse.ArgumentParser()
    _connect.add_args(parser)
    return parser.parse_args(argv)


def test_cli_connect_prints_table_and_writes_maps(tmp_path):
    import io

    from tfi_quat.cli._connect import connect_grid
    from tfi_quat.errors import OverwriteError
    g = Grid([extrude(c_grid(), nk=3)])
    out = io.StringIO()
    js = tmp_path / "map.json"
    assert connect_grid(g, _cli_args(["g.x", "--wall", "1:jmin", "-o", str(js)]), out) == 0
    text = out.getvalue()
    assert "1        jmin  1-5,1-3" in text and "-1 -2 +3" in text
    assert "wall      1      jmin  5-17,1-3" in text and "symmetry (auto)" in text and f"wrote {js}" in text
    assert Connectivity.from_json(js, g) == connect(g, walls=["1:jmin"])
    with pytest.raises(OverwriteError, match="exists"):
        connect_grid(g, _cli_args(["g.x", "-o", str(js)]), io.StringIO())
    connect_grid(g, _cli_args(["g.x", "-o", str(js), "--force", "--fixed", "1:kmin", "--default", "free"]),
                 io.StringIO())
    assert {p.kind for p in Connectivity.from_json(js).patches} == {"fixed", "free"}
    nmf = tmp_path / "map.nmf"
    connect_grid(g, _cli_args(["g.x", "--wall", "1:jmin", "-o", str(nmf)]), io.StringIO())
    assert Connectivity.from_nmf(nmf, g) == connect(g, walls=["1:jmin"])
    with pytest.raises(ConnectivityError, match="use .json or .nmf"):
        connect_grid(g, _cli_args(["g.x", "-o", str(tmp_path / "map.txt")]), io.StringIO())
    with pytest.raises(ConnectivityError, match="overlaps"):
        connect_grid(g, _cli_args(["g.x", "--wall", "1:jmin", "--fixed", "1:jmin:1-9,1-3"]), io.StringIO())


def test_cli_connect_run_reports_a_missing_grid(tmp_path):
    from tfi_quat.cli._connect import run
    with pytest.raises(FileNotFoundError):
        run(_cli_args([str(tmp_path / "nothing.x")]))


def test_absolute_tolerance_bridges_a_small_gap(tmp_path):
    big = sheared_box(9, 5, 4)
    a = np.asfortranarray(big[:5])
    b = np.asfortranarray(big[4:] + 1e-5)
    assert connect(Grid([a, b])).interfaces == []
    conn = connect(Grid([a, b]), tol=1e-4)
    assert len(conn.interfaces) == 1
    check_interfaces(Grid([a, b]), conn, tol=2e-5)
    # such a map saved and read back with the grid passes the reader's check (a quarter cell)
    conn.to_json(tmp_path / "gap.json")
    conn.to_nmf(tmp_path / "gap.nmf")
    assert Connectivity.from_json(tmp_path / "gap.json", Grid([a, b])) == conn
    assert Connectivity.from_nmf(tmp_path / "gap.nmf", Grid([a, b])).interfaces == conn.interfaces
    with pytest.raises(ConnectivityError, match="tol"):
        connect(Grid([a, b]), tol=-1.0)
    with pytest.raises(ConnectivityError, match="rtol"):
        connect(Grid([a, b]), rtol=0.0)


def test_json_accepts_a_2d_transform_with_two_entries(tmp_path):
    g = Grid([c_grid()])
    conn = connect(g, walls=["1:jmin"])
    from tfi_quat.topology.files import to_dict
    doc = to_dict(conn)
    assert doc["interfaces"][0]["Transform"] == [-1, -2, 3]
    doc["interfaces"][0]["Transform"] = [-1, -2]
    p = tmp_path / "two.json"
    p.write_text(json.dumps(doc))
    assert Connectivity.from_json(p, g) == conn


def test_face_map_priority_where_kinds_meet():
    g = Grid([sheared_box(5, 4, 3)])
    conn = connect(g, walls=["1:imin:1-2,1-3"], fixed=["1:imin:2-4,1-3"], auto_symmetry=False)
    fm = conn.face_map(0, "imin")
    kinds = np.array([conn.patches[i].kind for i in fm.patch.ravel()]).reshape(fm.patch.shape)
    assert (kinds[:2] == "wall").all() and (kinds[2:] == "fixed").all()   # the shared line j = 2 is wall
    assert (fm.interface == -1).all() and (fm.role == 0).all()


def test_single_precision_plot3d_file_matches_to_its_round_off(tmp_path):
    from tfi_quat.io import plot3d
    rng = np.random.default_rng(3)
    big = sheared_box(9, 5, 4) + 100.0
    a = np.asfortranarray(big[:5])
    b = orient(big[4:], (2, 1, 0), (True, False, False))
    b = np.asfortranarray(b * (1 + 1e-7 * rng.uniform(-1, 1, b.shape)))   # about one float32 ulp
    path = tmp_path / "g.x"
    plot3d.write(path, Grid([a, b]), encoding="fortran", precision=4)
    g = plot3d.read(path)
    assert g.source_format.precision == 4
    conn = connect(g)
    assert len(conn.interfaces) == 1 and conn.interfaces[0].master.range == ((0, 4), (0, 3))
    check_interfaces(g, conn, tol=1e-4)
    # the same coordinates without the file's precision are not matched to 1e-6 of the spacing
    assert connect(Grid([blk.xyz for blk in g])).interfaces == []


@pytest.mark.parametrize("ext", [".x", ".h5"])
def test_cli_main_connect_end_to_end(tmp_path, capsys, ext):
    import tfi_quat
    from tfi_quat.cli import main
    g = Grid([extrude(c_grid(), nk=3)])
    grid_path = tmp_path / f"cgrid{ext}"
    tfi_quat.write(grid_path, g)
    out_map = tmp_path / "map.nmf"
    assert main(["connect", str(grid_path), "--wall", "1:jmin", "-o", str(out_map)]) == 0
    text = capsys.readouterr().out
    assert "1 interface(s)" in text and "-1 -2 +3" in text and "symmetry (auto)" in text
    assert Connectivity.from_nmf(out_map, g) == connect(g, walls=["1:jmin"])
    # refusing to overwrite, bad patches: one line on stderr, status 2
    assert main(["connect", str(grid_path), "-o", str(out_map)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "exists" in err
    assert main(["connect", str(grid_path), "--wall", "1:jmin", "--fixed", "1:jmin:2-6,1-3"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tfi-quat connect: error: ") and "overlaps" in err
    assert main(["connect", str(grid_path), "--wall", "1:jmin", "-o", str(out_map), "--force"]) == 0


def test_cli_main_connect_errors_are_one_line_with_status_2(tmp_path, capsys):
    import tfi_quat
    from tfi_quat.cli import main
    grid_path = tmp_path / "c.x"
    tfi_quat.write(grid_path, Grid([c_grid()]))
    cases = [
        ([str(tmp_path / "missing.x")], "missing.x"),
        ([str(grid_path), "-o", str(tmp_path / "map.txt")], "unknown map extension '.txt': use .json or .nmf"),
        ([str(grid_path), "--tol", "-1"], "tol must be a finite distance"),
        ([str(grid_path), "--wall", "2:jmin"], "wall 2:jmin"),
        ([str(grid_path), "--wall", "1:kmin"], "no k faces"),
        ([str(grid_path), "--symmetry", "1:jmin:1-99"], "exceeds"),
    ]
    for argv, words in cases:
        assert main(["connect", *argv]) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("tfi-quat connect: error: ") and err.count("\n") == 1 and words in err, (argv, err)


def test_cli_main_connect_options_2d(tmp_path, capsys):
    import tfi_quat
    from tfi_quat.cli import main
    from tfi_quat.topology.nmf import read_nmf
    x, y = np.meshgrid(np.linspace(0, 2, 6), np.linspace(0, 1, 4) ** 2, indexing="ij")
    g = Grid([np.stack([x, y + 0.1 * np.sin(x) * (1 - y)], -1)])
    grid_path = tmp_path / "channel.x"
    tfi_quat.write(grid_path, g)
    assert main(["connect", str(grid_path), "--wall", "1:jmin"]) == 0
    out = capsys.readouterr().out
    assert out.count("symmetry (auto)") == 2 and "symmetry  1      imin  1-4,1-1           auto" in out
    nmf = tmp_path / "c.nmf"
    assert main(["connect", str(grid_path), "--wall", "1:jmin", "--no-auto-symmetry", "--default", "free",
                 "-o", str(nmf), "--nmf-faces", "2d"]) == 0
    out = capsys.readouterr().out
    assert "symmetry" not in out and "free      1      imin" in out and f"wrote {nmf}" in out
    back = read_nmf(nmf)
    assert {p.spec.face: p.kind for p in back.patches} == {"imin": "free", "imax": "free", "jmin": "wall",
                                                           "jmax": "free"}
    assert max(int(line.split()[2]) for line in nmf.read_text().splitlines() if line[:1] not in "# ") == 4


# ------------------------------------------------------------ connected components
@settings(max_examples=40, deadline=None)
@given(n=st.integers(0, 40), data=st.data())
def test_connected_components_match_scipy(n, data):
    """Same count and labels (numbered by each component's smallest node) as scipy's."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components as scipy_components

    from tfi_quat.topology.graph import connected_components
    m = data.draw(st.integers(0, 3 * n)) if n else 0
    i = np.array(data.draw(st.lists(st.integers(0, n - 1), min_size=m, max_size=m)) if n else [], dtype=np.int64)
    j = np.array(data.draw(st.lists(st.integers(0, n - 1), min_size=m, max_size=m)) if n else [], dtype=np.int64)
    count, labels = connected_components(n, i, j)
    if n == 0:
        assert count == 0 and labels.size == 0
        return
    want_count, want = scipy_components(coo_matrix((np.ones(m, np.int8), (i, j)), shape=(n, n)), directed=False)
    assert count == want_count
    np.testing.assert_array_equal(labels, want)


def test_connected_components_long_chains_and_bad_edges():
    from tfi_quat.topology.graph import connected_components
    rng = np.random.default_rng(5)
    p = rng.permutation(5000)
    count, labels = connected_components(5001, p[:-1], p[1:])      # one chain, randomly numbered
    assert count == 2 and np.all(labels[p] == 0) and labels[5000] == 1
    with pytest.raises(ValueError, match="outside"):
        connected_components(3, [0], [3])
    with pytest.raises(ValueError, match="length"):
        connected_components(3, [0, 1], [2])


def test_non_finite_boundary_coordinates_are_named():
    from tfi_quat import Block, GridValueError
    x = sheared_box(4, 3, 3)
    x[1, 0, 2, 0] = np.nan                               # on faces jmin and kmax
    grid = Grid([Block(x, allow_nonfinite=True)], 3)
    with pytest.raises(GridValueError, match=r"block 1 face jmin: non-finite"):
        connect(grid)


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 12), st.integers(1, 12), st.floats(0.3, 1.0), st.integers(0, 2 ** 32 - 1))
def test_small_masks_split_uncompiled_as_compiled(nr, nc, p, seed):
    """Small masks run the largest-rectangle search uncompiled (the demo compiles none): the
    same rectangle as the compiled kernel, and the split covers the mask exactly."""
    from tfi_quat.topology import search
    mask = np.random.default_rng(seed).random((nr, nc)) < p
    assert search._largest_rectangle.py_func(mask) == search._largest_rectangle(mask)
    cover = np.zeros(mask.shape, dtype=int)
    for r0, r1, c0, c1 in search._rectangles(mask):
        cover[r0:r1 + 1, c0:c1 + 1] += 1
    np.testing.assert_array_equal(cover, mask)
