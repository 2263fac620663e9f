"""The Deformer on the shipped grids: docs/method.md §4, every property, on every topology.

Grids: the 2-D C-grid and O-grid airfoils and their one-cell-thick 3-D
extrusions (wall normal j, not the last index), the 2-D two-block case, the
H-grid channel, and the 3-D multiblock wing (wake cuts, tip cap with a
collapsed edge, symmetry plane, interfaces with swapped and reversed axes).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import tfi_quat as tq
from tfi_quat import quaternion as qa
from tfi_quat.case import Motion, load_case
from tfi_quat.deform import Deformer, rigid_motion
from tfi_quat.grid import face_ijk
from tfi_quat.quality import orthogonality_change, volume_ratio_summary
from tfi_quat.spec import parse_patch_spec

import _deform_grids as G

GRIDS = Path(__file__).resolve().parents[1] / "grids"
METHODS = ["two-level", "samareh", "tfi"]


def _shipped(name):
    case = load_case(GRIDS / f"{name}.toml")
    grid = tq.read(case.grid)
    return grid, [str(p) for p in case.walls], [str(p) for p in case.symmetry], [str(p) for p in case.fixed]


def _extruded(name, dz=0.05):
    grid, walls, _, fixed = _shipped(name)
    g3 = G.extrude(grid, 2, dz)
    walls3 = [w.split(",")[0] + ",1-2" if w.count(":") == 2 else w for w in walls]
    return g3, walls3, ["1:kmin", "1:kmax"], fixed


def _bump(amplitude, x0, x1):
    """Wall points move normal to the lower wall (+y) by a smooth bump on [x0, x1]."""
    def move(p):
        p = np.array(p, dtype=np.float64)
        t = np.clip((p[:, 0] - x0) / (x1 - x0), 0.0, 1.0)
        p[:, 1] += amplitude * np.sin(np.pi * t) ** 2
        return p
    return move


PITCH = rigid_motion(-20.0, (0, 0, 1), (0.25, 0.0, 0.0), (0.05, 0.08, 0.0))
WING_MOTION = Motion(bend=0.2, twist=8.0, about=(0.25, 0.0, 0.0), span_axis=(0, 1, 0), span=1.5).apply

#: name -> (builder, a motion the grid's fixed boundaries allow)
CASES = {
    "c-grid": (lambda: _shipped("naca0012_c_257x65"), PITCH),
    "o-grid": (lambda: _shipped("naca4412_o_257x65"), PITCH),
    "c-grid-3d": (lambda: _extruded("naca0012_c_257x65"), PITCH),
    "o-grid-3d": (lambda: _extruded("naca4412_o_257x65"), PITCH),
    "two-block": (lambda: _shipped("two_block_65x33"), _bump(0.04, 1.0, 2.0)),
    "channel": (lambda: _shipped("channel_bump_129x49"), _bump(0.12, 1.0, 2.0)),
    "wing": (lambda: _shipped("wing_ch_501k"), WING_MOTION),
}

_cache: dict = {}


def _case(name):
    if name not in _cache:
        _cache[name] = CASES[name][0]()
    return _cache[name]


def _deformer(name, method="two-level", **kw):
    key = (name, method, tuple(sorted(kw.items())))
    if key not in _cache:
        grid, walls, sym, fixed = _case(name)
        _cache[key] = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed, method=method, **kw)
    return _cache[key]


def _scale(grid):
    lo, hi = grid.bbox()
    return float(np.linalg.norm(hi - lo))


def _copies(d):
    """Per global boundary point, every (block, flat index) copy of it."""
    out = []
    for b, (local, gid) in enumerate(d.skeleton.scatter):
        out.append((b, local, gid))
    return out


# ----------------------------------------------------------------------------- properties 1, 4, 8
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name", sorted(CASES))
def test_walls_fixed_symmetry_interfaces(name, method):
    """Walls exact (1), interface and cut copies bit-identical (4), fixed at rest and symmetry
    points in their plane (8); no negative cells for the two-level formulation and plain TFI."""
    grid, walls, sym, fixed = _case(name)
    d = _deformer(name, method)
    move = CASES[name][1]
    out = d.deform(move)
    scale = _scale(grid)
    P = d.skeleton.points.P
    kinds = d.skeleton.points.kind
    seen = {}
    for b, local, gid in _copies(d):
        x = out[b].xyz.reshape(-1, 3, order="F")[local]
        ref = grid[b].xyz.reshape(-1, 3, order="F")[local]
        w = kinds[gid] == 3
        np.testing.assert_allclose(x[w], move(ref[w]), rtol=0, atol=1e-12 * scale)
        f = kinds[gid] == 2
        assert np.array_equal(x[f], ref[f]), "fixed points moved"
        for g, xx in zip(gid, x):               # every copy of a global point: the same bits
            prev = seen.setdefault(int(g), xx.tobytes())
            assert prev == xx.tobytes(), f"copies of boundary point {P[g]} differ"
    assert len(seen) == d.n_global
    for itf in d.connectivity.interfaces:       # through the connectivity's own index maps
        m = itf.master
        mi = face_ijk(grid[m.block].dims, m.face, m.range).reshape(-1, 3)
        si = np.asarray(itf.slave_index(mi)).reshape(-1, 3)
        a = out[m.block].xyz[mi[:, 0], mi[:, 1], mi[:, 2]]
        bb = out[itf.slave.block].xyz[si[:, 0], si[:, 1], si[:, 2]]
        assert np.array_equal(a, bb), f"interface {itf} not bit-identical"
    for spec in sym:
        p = parse_patch_spec(spec).resolve(grid)
        ijk = face_ijk(grid[p.block].dims, p.face, p.range).reshape(-1, 3)
        before = grid[p.block].xyz[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
        after = out[p.block].xyz[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
        c = before.mean(0)
        _, _, vt = np.linalg.svd(before - c, full_matrices=False)   # (n, n) U not wanted
        np.testing.assert_allclose((after - c) @ vt[-1], 0.0, atol=1e-12 * scale)
    if method != "samareh":
        assert volume_ratio_summary(out, grid)["negative"] == 0


# ----------------------------------------------------------------------------- property 2
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name", sorted(CASES))
def test_zero_motion_returns_the_grid(name, method):
    grid = _case(name)[0]
    out = _deformer(name, method).deform(lambda p: p)
    for blk, ref in zip(out, grid):
        np.testing.assert_allclose(blk.xyz, ref.xyz, rtol=0, atol=1e-13 * _scale(grid))


# ----------------------------------------------------------------------------- property 3
@pytest.mark.parametrize("method", ["two-level", "samareh"])
@pytest.mark.parametrize("name", sorted(CASES))
def test_rigid_motion_of_every_boundary_is_rigid_everywhere(name, method):
    grid, _, _, _ = _case(name)
    faces = ("imin", "imax", "jmin", "jmax") + (("kmin", "kmax") if grid.ndim == 3 else ())
    every = [f"{b + 1}:{f}" for b in range(len(grid)) for f in faces]
    d = Deformer(grid, walls=every, method=method)
    if grid.ndim == 3:
        move = rigid_motion(35.0, (0.2, 0.3, 1.0), (0.5, -0.2, 0.1), (0.3, 0.1, 0.05))
    else:
        move = rigid_motion(35.0, (0, 0, 1), (0.5, -0.2, 0.0), (0.3, 0.1, 0.0))
    out = d.deform(move)
    for blk, ref in zip(out, grid):
        np.testing.assert_allclose(blk.xyz, move(ref.xyz.reshape(-1, 3)).reshape(ref.xyz.shape),
                                   rtol=0, atol=1e-10 * _scale(grid))


# ----------------------------------------------------------------------------- property 5
def _transform(grid, f):
    return tq.Grid([tq.Block(f(b.xyz.reshape(-1, 3, order="F")).reshape(b.xyz.shape, order="F"),
                             name=b.name) for b in grid], grid.ndim)


@pytest.mark.parametrize("method", ["two-level", "samareh"])
@pytest.mark.parametrize("name", ["c-grid", "c-grid-3d", "two-block", "wing"])
def test_moving_the_whole_problem_moves_the_result(name, method):
    grid, walls, sym, fixed = _case(name)
    move = CASES[name][1]
    base = _deformer(name, method).deform(move)
    T = np.array([3.0, -2.0, 0.0 if grid.ndim == 2 else 1.5])
    if grid.ndim == 2:
        R = np.array([np.cos(0.6), 0.0, 0.0, np.sin(0.6)])
    else:
        R = qa.normalize([0.8, 0.3, -0.4, 0.2])
    for f, finv in ((lambda p: p + T, lambda p: p - T),
                    (lambda p: qa.rotate(R, p), lambda p: qa.rotate(qa.conjugate(R), p))):
        g2 = _transform(grid, f)
        out = Deformer(g2, walls=walls, symmetry=sym, fixed=fixed,
                       method=method).deform(lambda p: f(move(finv(p))))
        for a, b in zip(out, base):
            np.testing.assert_allclose(a.xyz.reshape(-1, 3, order="F"), f(b.xyz.reshape(-1, 3, order="F")),
                                       rtol=0, atol=1e-9 * _scale(grid))


# ----------------------------------------------------------------------------- property 6
@pytest.mark.parametrize("angle", [10.0, 30.0, 45.0])
@pytest.mark.parametrize("name", ["c-grid", "o-grid", "c-grid-3d"])
@pytest.mark.parametrize("method", ["two-level", "samareh"])
def test_near_wall_orthogonality_under_rigid_rotation(name, angle, method):
    """<= 0.1 deg change in the first 5 layers; plain TFI turns them by about the angle."""
    grid, walls, _, _ = _case(name)
    move = rigid_motion(-angle, (0, 0, 1), (0.25, 0.0, 0.0), (0.0, 0.05, 0.0))
    q = _deformer(name, method).deform(move)
    t = _deformer(name, "tfi").deform(move)
    oq = orthogonality_change(q, grid, walls, 5)
    ot = orthogonality_change(t, grid, walls, 5)
    assert oq["max"] <= 0.1, oq
    assert ot["mean"] > 0.8 * angle, ot
    assert volume_ratio_summary(q, grid)["negative"] == 0


def test_non_rigid_wall_motions_keep_the_near_wall_angles():
    """Camber plus pitch of the C-grid, a growing bump in the channel: the two-level
    formulation keeps the first layers' angles to the wall far better than plain TFI."""
    from tfi_quat.demo import DemoMotion
    for name, move, bound in (("c-grid", DemoMotion(), 0.5), ("channel", _bump(0.12, 1.0, 2.0), 1.5)):
        grid, walls, _, _ = _case(name)
        q = orthogonality_change(_deformer(name).deform(move), grid, walls, 5)
        t = orthogonality_change(_deformer(name, "tfi").deform(move), grid, walls, 5)
        assert q["max"] <= bound and q["mean"] <= 0.05 * t["mean"], (name, q, t)


# ----------------------------------------------------------------------------- property 7
@pytest.mark.parametrize("method", ["two-level", "samareh"])
def test_one_d_derived_structure_gives_the_one_d_interpolation(method):
    """An annulus (O-grid) whose wall turns about its centre: the seam (a 1-D derived cut)
    and every other radial line move the same way, so the result has the grid's rotational
    symmetry: each line is the seam's line turned by its angle."""
    ni = 49
    grid, walls, _, fixed = G.o_grid(ni, 25)
    out = Deformer(grid, walls=walls, fixed=fixed, method=method).deform(
        rigid_motion(25.0, (0, 0, 1), (0.0, 0.0, 0.0)))
    x = out[0].xyz[:, :, 0]
    seam = x[0]
    for i in range(1, ni - 1):
        a = 2.0 * np.pi * i / (ni - 1)
        q = np.array([np.cos(a / 2), 0.0, 0.0, np.sin(a / 2)])
        np.testing.assert_allclose(x[i], qa.rotate(q, seam), rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- the wing
@pytest.mark.parametrize("bend,twist", [(0.15, 5.0), (0.15, 10.0), (0.3, 10.0)])
def test_wing_bending_and_twist_without_negative_cells(bend, twist):
    """Tip deflection 10 and 20 % of the half span with up to 10 deg of twist."""
    grid, walls, _, _ = _case("wing")
    move = Motion(bend=bend, twist=twist, about=(0.25, 0.0, 0.0), span_axis=(0, 1, 0), span=1.5).apply
    out = _deformer("wing").deform(move)
    q = volume_ratio_summary(out, grid)
    assert q["negative"] == 0 and q["min_ratio"] > 0.2, q
    oq = orthogonality_change(out, grid, walls, 5)
    ot = orthogonality_change(_deformer("wing", "tfi").deform(move), grid, walls, 5)
    assert oq["mean"] < 0.03 * ot["mean"], (oq, ot)


def test_the_memos_formulation_folds_the_bent_wing():
    """Why two-level is the default: Samareh's update carries small differences of the
    fitted wall rotations over lever arms of chords into thin cells (docs/deformer.md)."""
    grid = _case("wing")[0]
    out = _deformer("wing", "samareh").deform(WING_MOTION)
    assert volume_ratio_summary(out, grid)["negative"] > 100


# ----------------------------------------------------------------------------- walls on part of a face
def test_a_whole_face_wall_is_reduced_by_the_interfaces_on_it():
    """'1:jmin' of the C-grid means the airfoil: the wake cut on the same face stays a cut."""
    grid, walls, sym, fixed = _case("c-grid")
    a = Deformer(grid, walls=["1:jmin"], fixed=fixed)
    assert a.wall_points().shape == _deformer("c-grid").wall_points().shape
    assert a.deform(PITCH) == _deformer("c-grid").deform(PITCH)


def test_sub_face_wall_in_3d():
    """The extruded C-grid with its wall on part of jmin and only one of its k-layers fixed
    elsewhere: walls exact, the rest of the face derived."""
    grid, walls, sym, fixed = _case("c-grid-3d")
    d = Deformer(grid, walls=["1:jmin:97-161,1-2"], symmetry=sym, fixed=fixed)
    move = _bump(0.01, 0.1, 0.45)              # zero at the patch ends (x = 0.5)
    out = d.deform(move)
    x, r = out[0].xyz, grid[0].xyz
    np.testing.assert_allclose(x[96:161, 0], move(r[96:161, 0].reshape(-1, 3)).reshape(r[96:161, 0].shape),
                               atol=1e-14)
    np.testing.assert_allclose(x[160:193, 0, :, 2], r[160:193, 0, :, 2], atol=1e-15)   # in the planes
    assert volume_ratio_summary(out, grid)["negative"] == 0


# ----------------------------------------------------------------------------- connectivity files
def test_nmf_round_trip_gives_the_same_grid(tmp_path):
    grid, walls, sym, fixed = _case("wing")
    d = _deformer("wing")
    path = tmp_path / "wing.nmf"
    d.connectivity.to_nmf(path)
    conn = tq.Connectivity.from_nmf(path, grid)
    assert conn == d.connectivity
    d2 = Deformer(grid, connectivity=conn)
    assert d2.deform(WING_MOTION) == d.deform(WING_MOTION)


# ----------------------------------------------------------------------------- steps and the reference
def test_steps_start_from_the_reference_and_reuse_no_state():
    grid = _case("wing")[0]
    before = grid.copy()
    d = _deformer("wing")
    a = d.deform(WING_MOTION)
    d.deform(rigid_motion(40.0, (0, 1, 0), (0.25, 0.0, 0.0)))
    b = d.deform(WING_MOTION)
    assert a == b and grid == before
    t = d.timings
    assert t.total > 0 and min(t.walls, t.skeleton, t.faces, t.volumes) >= 0


def test_progress_callback_sees_every_kernel():
    d = _deformer("wing")
    seen = []
    d.deform(WING_MOTION, callback=lambda done, total: seen.append((done, total)))
    assert seen[-1][0] == seen[-1][1] and [s[0] for s in seen] == list(range(1, seen[-1][1] + 1))
    assert "two-level" in d.summary() and "rotation length" in d.summary()
