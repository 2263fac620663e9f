"""The Deformer against the properties of docs/method.md §4, on several grid shapes."""

from __future__ import annotations

import numpy as np
import pytest

from tfi_quat import CaseError, DeformationError, Grid
from tfi_quat import quaternion as qa
from tfi_quat.deform import Deformer, rigid_motion
from tfi_quat.quality import negative_cells

import _deform_grids as G

FORMULATIONS = ["two-level", "samareh"]

CASES = {
    "o-grid": G.o_grid,
    "two-block": G.two_block_o,
    "channel": G.channel,
    "o-grid-3d": G.o_grid_3d,
    "box-pair": G.box_pair,
}


@pytest.fixture(scope="module", params=sorted(CASES))
def case(request):
    grid, walls, sym, fixed = CASES[request.param]()
    return request.param, grid, walls, sym, fixed


def _scale(grid):
    lo, hi = grid.bbox()
    return float(np.linalg.norm(hi - lo))


def _wall_mask(deformer, grid):
    """Per block, a boolean (ni, nj, nk) mask of wall points."""
    out = []
    for b, blk in enumerate(grid):
        m = np.zeros(blk.dims, dtype=bool)
        for p in deformer.connectivity.patches:
            if p.kind != "wall" or p.spec.block != b:
                continue
            from tfi_quat.deform import _face_ijk
            ijk = _face_ijk(blk.dims, p.spec.face, p.spec.range).reshape(-1, 3)
            m[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
        out.append(m)
    return out


def _motion_for(name):
    if name == "channel":
        # the bump grows; the wall ends stay where the fixed side boundaries hold them
        return lambda p: p + np.stack([0 * p[:, 0], 0.08 * np.exp(-8.0 * p[:, 0] ** 2), 0 * p[:, 0]], -1)
    if name == "box-pair":
        return rigid_motion(4.0, (1, 0, 0), (1.0, 0.0, 0.5), (0.0, 0.01, 0.0))
    return rigid_motion(20.0, (0, 0, 1), (0.3, 0.0, 0.0), (0.2, -0.1, 0.0))


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_walls_land_exactly(case, formulation):
    name, grid, walls, sym, fixed = case
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed, formulation=formulation)
    move = _motion_for(name)
    out = d.deform(move)
    for blk, ref, m in zip(out, grid, _wall_mask(d, grid)):
        assert m.any() or name == "two-block"
        np.testing.assert_allclose(blk.xyz[m], move(ref.xyz[m]), rtol=0, atol=1e-12 * _scale(grid))
    assert not negative_cells(out, grid)


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_zero_motion_returns_the_grid(case, formulation):
    name, grid, walls, sym, fixed = case
    for method in ("quaternion", "tfi"):
        out = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed, method=method, formulation=formulation).deform(lambda p: p)
        for blk, ref in zip(out, grid):
            np.testing.assert_allclose(blk.xyz, ref.xyz, rtol=0, atol=1e-13 * _scale(grid))


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_reference_untouched_and_no_drift(case, formulation):
    name, grid, walls, sym, fixed = case
    before = grid.copy()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed, formulation=formulation)
    a = d.deform(_motion_for(name))
    d.deform(rigid_motion(40.0, (0, 0, 1)))
    b = d.deform(_motion_for(name))
    assert grid == before
    assert a == b


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_rigid_motion_of_every_boundary_is_rigid_everywhere(case, formulation):
    """docs/method.md §4, property 3: all boundaries walls, one rigid motion -> the grid moves rigidly."""
    name, grid, walls, sym, fixed = case
    faces = ("imin", "imax", "jmin", "jmax") + (("kmin", "kmax") if grid.ndim == 3 else ())
    every = [f"{b + 1}:{f}" for b in range(len(grid)) for f in faces]
    d = Deformer(grid, walls=every, formulation=formulation)
    move = rigid_motion(35.0, (0.2, 0.3, 1.0) if grid.ndim == 3 else (0, 0, 1), (0.5, -0.2, 0.1 if grid.ndim == 3 else 0.0),
                        (0.3, 0.1, 0.05 if grid.ndim == 3 else 0.0))
    out = d.deform(move)
    for blk, ref in zip(out, grid):
        np.testing.assert_allclose(blk.xyz, move(ref.xyz.reshape(-1, 3)).reshape(ref.xyz.shape),
                                   rtol=0, atol=1e-10 * _scale(grid))


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_interface_points_stay_bit_identical(formulation):
    for builder in (G.o_grid, G.two_block_o, G.box_pair):
        grid, walls, sym, fixed = builder()
        d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed, formulation=formulation)
        out = d.deform(rigid_motion(15.0, (0, 0, 1), (0.4, 0.1, 0.0), (0.1, 0.2, 0.0)))
        assert d.connectivity.interfaces, builder.__name__
        for itf in d.connectivity.interfaces:
            from tfi_quat.deform import _face_ijk
            m = itf.master
            mi = _face_ijk(grid[m.block].dims, m.face, m.range).reshape(-1, 3)
            si = np.asarray(itf.slave_index(mi)).reshape(-1, 3)
            a = out[m.block].xyz[mi[:, 0], mi[:, 1], mi[:, 2]]
            b = out[itf.slave.block].xyz[si[:, 0], si[:, 1], si[:, 2]]
            assert np.array_equal(a, b), f"{builder.__name__}: interface {m} not bit-identical"


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_fixed_patches_do_not_move_and_symmetry_stays_in_plane(formulation):
    grid, walls, sym, fixed = G.o_grid_3d()
    d = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed, formulation=formulation)
    out = d.deform(rigid_motion(25.0, (0, 0, 1), (0.2, 0.0, 0.0), (0.1, 0.3, 0.0)))
    x, r = out[0].xyz, grid[0].xyz
    assert np.array_equal(x[:, -1], r[:, -1])                      # far field fixed, bit for bit
    np.testing.assert_allclose(x[:, :, 0, 2], 0.0, atol=1e-14)     # symmetry planes z = 0 and z = 0.1
    np.testing.assert_allclose(x[:, :, 1, 2], 0.1, atol=1e-14)


def _orthogonality_change(out, ref, layers=5):
    """Max change (deg) of the angle between wall-normal grid lines (j) and the wall normal,
    over the first `layers` layers of a 2-D O-grid whose wall is jmin."""
    def angles(x):
        w = x[:, 0, 0, :2]
        t = np.roll(w, -1, axis=0) - np.roll(w, 1, axis=0)
        t[0] = t[-1] = w[1] - w[-2]
        n = np.stack([t[:, 1], -t[:, 0]], -1)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        out = []
        for j in range(layers):
            e = x[:, j + 1, 0, :2] - x[:, j, 0, :2]
            e /= np.linalg.norm(e, axis=1, keepdims=True)
            out.append(np.degrees(np.arctan2(e[:, 0] * n[:, 1] - e[:, 1] * n[:, 0], (e * n).sum(1))))
        return np.array(out)
    return np.abs(angles(out[0].xyz) - angles(ref[0].xyz)).max()


@pytest.mark.parametrize("angle", [10.0, 30.0, 45.0])
@pytest.mark.parametrize("formulation", ["samareh"])
def test_near_wall_orthogonality_kept_under_rigid_rotation(angle, formulation):
    """docs/method.md §4, property 6 on an O-grid: quaternion TFI keeps the wall angle, plain TFI does not."""
    grid, walls, sym, fixed = G.o_grid(65, 33)
    move = rigid_motion(angle, (0, 0, 1), (0.5, 0.0, 0.0), (0.3, 0.2, 0.0))
    q = Deformer(grid, walls=walls, fixed=fixed, formulation=formulation).deform(move)
    t = Deformer(grid, walls=walls, fixed=fixed, method="tfi", formulation=formulation).deform(move)
    dq = _orthogonality_change(q, grid)
    dt = _orthogonality_change(t, grid)
    assert dq <= 0.1, dq
    assert dt > 0.3 * angle, dt
    assert not negative_cells(q, grid)


def _transform_grid(grid, f):
    from tfi_quat import Block
    return Grid([Block(f(b.xyz.reshape(-1, 3, order="F")).reshape(b.xyz.shape, order="F"), name=b.name)
                 for b in grid], grid.ndim)


@pytest.mark.parametrize("name", ["o-grid", "box-pair", "o-grid-3d"])
@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_translation_and_rotation_of_the_whole_problem(name, formulation):
    """docs/method.md §4, property 5: moving the whole problem moves the result the same way."""
    grid, walls, sym, fixed = CASES[name]()
    move = _motion_for(name)
    base = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed, formulation=formulation).deform(move)
    scale = _scale(grid)
    T = np.array([3.0, -2.0, 0.0 if grid.ndim == 2 else 1.5])
    if grid.ndim == 2:
        R = np.array([np.cos(0.6), 0.0, 0.0, np.sin(0.6)])
    else:
        R = qa.normalize([0.8, 0.3, -0.4, 0.2])
    for f, finv in ((lambda p: p + T, lambda p: p - T),
                    (lambda p: qa.rotate(R, p), lambda p: qa.rotate(qa.conjugate(R), p))):
        g2 = _transform_grid(grid, f)
        if name == "o-grid-3d" and f(np.zeros(3))[2] != 0.0:
            continue
        out = Deformer(g2, walls=walls, symmetry=sym, fixed=fixed, formulation=formulation).deform(lambda p: f(move(finv(p))))
        for a, b in zip(out, base):
            np.testing.assert_allclose(a.xyz.reshape(-1, 3, order="F"),
                                       f(b.xyz.reshape(-1, 3, order="F")), rtol=0, atol=1e-9 * scale)


def test_moved_as_grid_and_as_mapping_agree_with_callable():
    grid, walls, sym, fixed = G.two_block_o()
    d = Deformer(grid, walls=walls, fixed=fixed)
    move = rigid_motion(12.0, (0, 0, 1), (0.1, 0.0, 0.0))
    a = d.deform(move)
    moved_grid = _transform_grid(grid, move)
    b = d.deform(moved_grid)
    mapping = {}
    for p in d.connectivity.patches:
        if p.kind == "wall":
            from tfi_quat.deform import _face_ijk
            ijk = _face_ijk(grid[p.spec.block].dims, p.spec.face, p.spec.range)
            pts = grid[p.spec.block].xyz[ijk[..., 0], ijk[..., 1], ijk[..., 2]]
            mapping[p.spec] = move(pts.reshape(-1, 3)).reshape(pts.shape)
    c = d.deform(mapping)
    assert a == b == c


def test_bad_inputs_are_clear_errors():
    grid, walls, sym, fixed = G.o_grid()
    with pytest.raises(CaseError, match="method"):
        Deformer(grid, walls=walls, method="spline")
    with pytest.raises(CaseError, match="no wall"):
        Deformer(grid, walls=[])
    with pytest.raises(CaseError, match="unknown face"):
        Deformer(grid, walls=["1:top"])
    for bad in (-1e-9, float("nan"), float("inf")):
        with pytest.raises(CaseError, match="tol must be"):
            Deformer(grid, walls=walls, tol=bad)
    d = Deformer(grid, walls=walls, fixed=fixed)
    with pytest.raises(DeformationError, match="shape"):
        d.deform(lambda p: p[:-1])
    with pytest.raises(DeformationError, match="not finite"):
        d.deform(lambda p: p * np.nan)
    with pytest.raises(DeformationError, match="dimensions"):
        d.deform(G.channel()[0])


def test_unknown_formulation_and_misplaced_options_are_errors():
    grid, walls, sym, fixed = G.o_grid()
    with pytest.raises(CaseError, match="formulation"):
        Deformer(grid, walls=walls, formulation="local")
    with pytest.raises(CaseError, match="blending"):
        Deformer(grid, walls=walls, blending="linear")              # two-level has its own
    with pytest.raises(CaseError, match="rotation_length"):
        Deformer(grid, walls=walls, formulation="samareh", rotation_length=0.1)
    with pytest.raises(CaseError, match="rotation_length"):
        Deformer(grid, walls=walls, rotation_length=-1.0)
    Deformer(grid, walls=walls, formulation="samareh", blending="linear")


def test_two_wall_bodies_get_their_own_rigid_fits():
    """A channel whose lower and upper walls move apart rigidly (two bodies: the side faces
    between them are fixed): each body's fit takes its own motion exactly, so the residual
    is zero; walls exact, no negative cells, the middle moves half way."""
    grid, _, _, _ = G.channel()
    d = Deformer(grid, walls=["1:jmin", "1:jmax"], fixed=["1:imin", "1:imax"])
    assert len(d._bodies) == 2

    def move(p):
        p = np.array(p, dtype=np.float64)
        lower = p[:, 1] < 0.5
        p[lower, 1] -= 0.04
        p[~lower, 1] += 0.04
        return p

    fits, y = d._fits(d._wall_targets(move))
    for q, t in fits:
        np.testing.assert_allclose(q, [1.0, 0.0, 0.0, 0.0], atol=1e-14)
        assert abs(abs(t[1]) - 0.04) < 1e-14 and abs(t[0]) < 1e-14
    np.testing.assert_allclose(y[d._wall_gids], d._P[d._wall_gids], atol=1e-14)   # no residual
    out = d.deform(move)
    x, r = out[0].xyz, grid[0].xyz
    np.testing.assert_allclose(x[:, 0, 0, 1], r[:, 0, 0, 1] - 0.04, atol=1e-14)
    np.testing.assert_allclose(x[:, -1, 0, 1], r[:, -1, 0, 1] + 0.04, atol=1e-14)
    assert not negative_cells(out, grid)
    mid = x.shape[1] // 2
    ni = x.shape[0]
    dy = x[ni // 2, mid, 0, 1] - r[ni // 2, mid, 0, 1]
    assert abs(dy) < 0.02                       # between the two walls' motions
