"""Grid generators: cell validity, wall orthogonality, exact cuts and interfaces, determinism."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

import tfi_quat
from tfi_quat import Grid, GridValueError
from tfi_quat import generate as gen
from tfi_quat.case import load_case

from _cells import cell_volumes, corner_jacobians
from conftest import sheared_box


# ----------------------------------------------------------------- test helpers
def wall_normals_2d(w, closed):
    """Unit normals of a clockwise wall curve (n, 2): central differences, rotated +90 deg."""
    if closed:
        q = w[:-1]
        t = np.roll(q, -1, axis=0) - np.roll(q, 1, axis=0)
        t = np.concatenate([t, t[:1]])
    else:
        t = np.gradient(w, axis=0)
    n = np.stack([-t[:, 1], t[:, 0]], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def deviations_2d(xy, lo, hi, closed, layers=10):
    """Angles (deg, 0..180) between the j-line segments of the first ``layers``
    layers and the outward wall normal, shape (hi - lo + 1, layers)."""
    n = wall_normals_2d(xy[:, 0], closed)[lo:hi + 1]
    d = xy[lo:hi + 1, 1:layers + 1] - xy[lo:hi + 1, :layers]
    cross = n[:, None, 0] * d[..., 1] - n[:, None, 1] * d[..., 0]
    dot = n[:, None, 0] * d[..., 0] + n[:, None, 1] * d[..., 1]
    return np.degrees(np.arctan2(np.abs(cross), dot))


def max_deviation_2d(xy, lo, hi, closed, layers=10):
    """Largest angle (deg) between the j-lines of the first ``layers`` layers and the wall normal."""
    return float(deviations_2d(xy, lo, hi, closed, layers).max())


def wing_wall_deviations(grid, n_wake=None, layers=10):
    """Angles (deg) between the first ``layers`` j-line segments off the wing's
    wall (blocks 1 and 2 joined along k) and the wall normal, shape
    (wall points round the section, layers, span stations).

    The normal is the cross product of central differences along i and k
    over the joined wall, the root mirrored in the symmetry plane y = 0 and
    one-sided at the cap's last (collapsed) station; it is computed here,
    independently of the generator.
    """
    b1, b2 = grid[0].xyz, grid[1].xyz
    x = np.concatenate([b1, b2[:, :, 1:]], axis=2)
    lo, hi = gen.wing_wall_range(x.shape[0], n_wake)
    w = x[:, 0]
    ghost = w[:, 1].copy()
    ghost[:, 1] *= -1.0
    wk = np.concatenate([ghost[:, None], w], axis=1)
    tk = np.concatenate([wk[:, 2:] - wk[:, :-2], (w[:, -1] - w[:, -2])[:, None]], axis=1)
    ti = np.gradient(w, axis=0)
    n = np.cross(tk, ti)
    with np.errstate(invalid="ignore"):
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
    e = x[lo:hi + 1, 1:layers + 1] - x[lo:hi + 1, :layers]
    cr = np.linalg.norm(np.cross(n[lo:hi + 1, None], e), axis=-1)
    dt = np.einsum("ikc,ijkc->ijk", n[lo:hi + 1], e)
    return np.degrees(np.arctan2(cr, dt))


def xy_of(grid, b=0):
    return grid[b].xyz[:, :, 0, :2]


# ----------------------------------------------------------------- basic pieces
def test_geometric_spacing():
    s = gen.geometric_spacing(64, 20.0, 1e-5)
    assert s.shape == (65,) and s[0] == 0.0 and s[-1] == 20.0
    d = np.diff(s)
    assert d[0] == pytest.approx(1e-5, rel=1e-9)
    ratio = d[1:] / d[:-1]
    assert np.allclose(ratio, ratio[0], rtol=1e-9) and ratio[0] > 1.0
    shrink = np.diff(gen.geometric_spacing(10, 1.0, 0.3))
    assert shrink[0] == pytest.approx(0.3) and np.all(np.diff(shrink) < 0)
    with pytest.raises(GridValueError, match="first spacing"):
        gen.geometric_spacing(4, 1.0, 2.0)


@pytest.mark.parametrize("n,total,first", [(64, 20.0, 1e-5), (64, 20.0, 1e-7), (48, 15.0, 1e-4), (8, 1.0, 0.05)])
def test_tanh_spacing(n, total, first):
    s = gen.tanh_spacing(n, total, first)
    assert s.shape == (n + 1,) and s[0] == 0.0 and s[-1] == total
    d = np.diff(s)
    assert d[0] == pytest.approx(first, rel=1e-12)
    ratio = d[1:] / d[:-1]
    # smooth: the ratio is largest at the wall and falls towards 1
    assert np.all(ratio > 1.0) and np.all(np.diff(ratio) < 0) and ratio[-1] < 1.0 + 4.0 / n
    g = np.diff(gen.geometric_spacing(n, total, first))
    assert ratio[0] > g[1] / g[0] and d[-1] < g[-1]
    with pytest.raises(GridValueError, match="below the mean spacing"):
        gen.tanh_spacing(10, 1.0, 0.1)


def test_naca4_sections():
    x = np.linspace(0.0, 1.0, 201)
    xu, yu, xl, yl = gen.naca4("0012", x)
    assert yu[-1] == 0.0 and yl[-1] == 0.0 and xu[-1] == 1.0
    assert np.max(yu - yl) == pytest.approx(0.12, abs=2e-4)
    xu, yu, xl, yl = gen.naca4("0012", x, blunt_te=True)
    assert yu[-1] - yl[-1] == pytest.approx(2 * 0.6 * (0.2969 - 0.126 - 0.3516 + 0.2843 - 0.1015), rel=1e-12)
    xu, yu, xl, yl = gen.naca4("4412", x)
    camber = 0.5 * (yu + yl)
    assert camber.max() == pytest.approx(0.04, abs=5e-4)
    assert x[np.argmax(camber)] == pytest.approx(0.4, abs=0.02)
    for bad in ("12", "abcd", "0000", "4012"):
        with pytest.raises(GridValueError, match="naca"):
            gen.naca4(bad, x)


def test_cell_volumes_exact_for_affine_grids():
    a = np.array([[2.0, 0.3, 0.1], [0.2, 1.5, 0.0], [0.0, 0.4, 1.0]])
    i, j, k = np.meshgrid(np.arange(4.0), np.arange(3.0), np.arange(5.0), indexing="ij")
    xyz = np.asfortranarray(np.stack([i, j, k], axis=-1) @ a.T)
    v = cell_volumes(xyz)
    assert v.shape == (3, 2, 4) and np.allclose(v, np.linalg.det(a), rtol=1e-12)
    assert np.all(cell_volumes(xyz[::-1]) < 0)
    box = sheared_box(6, 5, 4)
    # the sheared box's cells are bilinear; their volumes are positive and sum to the box volume
    assert np.all(cell_volumes(box) > 0)
    flat = np.zeros((3, 2, 1, 3))
    flat[..., 0] = np.arange(3.0)[:, None, None] * 2.0
    flat[..., 1] = np.arange(2.0)[None, :, None] * 0.5
    assert np.allclose(cell_volumes(flat), 1.0)


# ----------------------------------------------------------------- airfoils
AIRFOIL_CASES = [
    ("0012", "C", 1e-5, False, 257, 65),
    ("0012", "C", 1e-6, False, 129, 49),
    ("0012", "C", 1e-4, False, 257, 65),
    ("4412", "C", 1e-5, False, 129, 41),
    ("4412", "C", 1e-4, False, 193, 65),
    ("2408", "C", 3e-5, False, 97, 33),
    ("6409", "C", 1e-6, False, 257, 97),
    ("0021", "C", 1e-4, False, 129, 49),
    ("0006", "C", 1e-5, False, 193, 65),
    ("0012", "O", 1e-5, False, 129, 41),
    ("4412", "O", 1e-6, False, 257, 65),
    ("6409", "O", 1e-4, False, 193, 65),
    ("0012", "O", 1e-5, True, 129, 41),
    ("4415", "O", 1e-4, True, 97, 33),
    ("0006", "O", 1e-6, True, 257, 65),
]


@pytest.mark.parametrize("naca,topo,fs,blunt,ni,nj", AIRFOIL_CASES)
def test_airfoil_quality(naca, topo, fs, blunt, ni, nj):
    g = gen.airfoil(naca, topo, ni=ni, nj=nj, first_spacing=fs, blunt_te=blunt)
    assert isinstance(g, Grid) and g.ndim == 2 and g.dims == [(ni, nj, 1)]
    xy = xy_of(g)
    area = cell_volumes(g[0].xyz)
    assert area.min() > 0.0, f"{(area <= 0).sum()} non-positive cells"
    # every quad convex and none degenerate: each corner angle in (5.7, 174.3) deg
    assert corner_jacobians(g[0].xyz).min() > 0.1
    lo, hi = gen.airfoil_wall_range(ni, topo)
    closed = topo == "O"
    assert max_deviation_2d(xy, lo, hi, closed) <= 0.5
    # first cell height is first_spacing all along the wall
    h = np.linalg.norm(xy[lo:hi + 1, 1] - xy[lo:hi + 1, 0], axis=-1)
    assert np.allclose(h, fs, rtol=1e-9)
    # far field at 15-20 chords (and not beyond 30)
    r = np.linalg.norm(xy[:, -1] - [0.5, 0.0], axis=-1)
    assert r.min() > 14.0 and r.max() < 30.0
    # the wall is the airfoil: chord 1 from (0, 0)
    w = xy[lo:hi + 1, 0]
    assert np.any(np.all(w == 0.0, axis=1))                      # leading edge at the origin
    assert blunt or np.any(np.all(w == [1.0, 0.0], axis=1))      # sharp trailing edge at (1, 0)
    assert -1e-3 < w[:, 0].min() and w[:, 0].max() < 1.0 + 1e-3
    # clustering at the leading and trailing edges
    ds = np.linalg.norm(np.diff(w, axis=0), axis=-1)
    ile = np.argmin(w[:, 0])
    assert ds[ile] < 0.5 * ds.mean() and min(ds[0], ds[-1]) < 0.5 * ds.mean()


@pytest.mark.parametrize("naca,topo,fs,blunt", [("0012", "C", 1e-6, False), ("4412", "C", 1e-4, False),
                                               ("2415", "O", 1e-5, True), ("6409", "O", 1e-6, False)])
def test_tanh_stretched_airfoils(naca, topo, fs, blunt):
    ni, nj = 193, 65
    g = gen.airfoil(naca, topo, ni=ni, nj=nj, first_spacing=fs, blunt_te=blunt, stretching="tanh")
    x = g[0].xyz[:, :, 0, :2]
    assert corner_jacobians(g[0].xyz).min() > 0.1
    lo, hi = gen.airfoil_wall_range(ni, topo)
    assert max_deviation_2d(x, lo, hi, topo == "O") <= 0.5
    # the wall-normal distribution is the tanh one (straight lines near the wall)
    dist = gen.tanh_spacing(nj - 1, 20.0, fs)
    h = np.linalg.norm(x[lo + 5, 1:11] - x[lo + 5, 0], axis=-1)
    assert np.allclose(h, dist[1:11], rtol=1e-9)
    with pytest.raises(GridValueError, match="stretching must be one of 'geometric', 'tanh'"):
        gen.airfoil(naca, topo, stretching="cosine")


@pytest.mark.parametrize("naca,nb", [("0012", 4), ("0024", 2), ("4412", 6)])
def test_blunt_o_grid_base(naca, nb):
    ni = 129
    g = gen.airfoil(naca, "O", ni=ni, nj=41, first_spacing=1e-5, blunt_te=True, n_base=nb)
    x = g[0].xyz[:, :, 0, :2]
    # i = 1 is the middle of the base; the base runs down to the lower corner
    # (i = 1 + nb) and back from the upper one (i = ni - nb), a straight segment
    xu, yu, xl, yl = gen.naca4(naca, np.array([1.0]), blunt_te=True)
    corner_l, corner_u = np.array([xl[0], yl[0]]), np.array([xu[0], yu[0]])
    base = np.concatenate([x[ni - 1 - nb:-1, 0], x[:nb + 1, 0]])      # upper corner -> lower corner
    assert np.allclose(base[0], corner_u, atol=1e-15) and np.allclose(base[-1], corner_l, atol=1e-15)
    t = (base - corner_u) @ (corner_l - corner_u) / np.sum((corner_l - corner_u) ** 2)
    assert np.allclose(base, corner_u + t[:, None] * (corner_l - corner_u), atol=1e-15)
    assert np.allclose(np.diff(t), 1.0 / (2 * nb))                    # evenly spaced, going down
    assert np.allclose(x[0, 0], 0.5 * (corner_u + corner_l), atol=1e-15)
    assert np.linalg.norm(corner_u - corner_l) > 2e-3                 # really blunt
    assert np.array_equal(x[0], x[-1])
    # the base and its corners too leave the wall orthogonally
    assert max_deviation_2d(x, 0, ni - 1, True) <= 0.5


def test_blunt_c_grid_is_refused():
    # a one-block C-grid's cut would meet the base in right-angle corners of the
    # domain; the first version returned inside-out or arrowhead cells there
    # for most parameters, so blunt trailing edges are O-grid only
    with pytest.raises(GridValueError, match="blunt_te=True needs topology 'O'"):
        gen.airfoil("0012", "C", blunt_te=True)


@pytest.mark.parametrize("naca", ["4412", "6409"])
def test_c_grid_trailing_edge_limit(naca):
    # the documented limit of the straight near-wall layers: next to a
    # C-grid's trailing edge (a concave corner of the wall curve) the lines
    # from the surface and the wake converge; here (cambered, 257 x 65, first
    # cell 1e-4, ten layers 2.3e-3 thick against a trailing-edge spacing of
    # 6e-4) the two or so points next to the edge bend in the last layers;
    # every other point stays orthogonal
    ni = 257
    g = gen.airfoil(naca, "C", ni=ni, nj=65, first_spacing=1e-4)
    assert corner_jacobians(g[0].xyz).min() > 0.1
    lo, hi = gen.airfoil_wall_range(ni, "C")
    dev = deviations_2d(g[0].xyz[:, :, 0, :2], lo, hi, False)
    i_bad, layer_bad = np.nonzero(dev > 0.5)
    assert i_bad.size > 0                                 # the limit is real
    te_dist = np.minimum(i_bad, (hi - lo) - i_bad)        # intervals from the trailing edge
    assert te_dist.max() <= 3 and layer_bad.min() >= 7


def test_small_c_grids_do_not_fold():
    # regression: coarse C-grids used to fold cells at the trailing-edge junction
    for ni, nj, fs in ((33, 9, 1e-5), (65, 17, 1e-4), (49, 13, 1e-3), (97, 25, 1e-3), (65, 17, 1e-3)):
        g = gen.airfoil("0012", "C", ni=ni, nj=nj, first_spacing=fs)
        assert cell_volumes(g[0].xyz).min() > 0.0, (ni, nj, fs)
        assert corner_jacobians(g[0].xyz).min() > 0.0, (ni, nj, fs)


def test_c_grid_wake_cut_is_bit_identical():
    ni, nj, nw = 129, 41, 30
    g = gen.airfoil("4412", "C", ni=ni, nj=nj, n_wake=nw)
    x = g[0].xyz
    lo, hi = gen.airfoil_wall_range(ni, "C", nw)
    assert (lo, hi) == (nw, ni - 1 - nw)
    assert np.array_equal(x[:lo + 1, 0], x[hi:, 0][::-1])
    # and only the cut: the first layer off it separates
    assert not np.any(np.all(x[:lo, 1] == x[hi + 1:, 1][::-1], axis=-1))
    # the wake cut lies on y = 0 behind the trailing edge at x = 1
    assert np.all(x[:lo + 1, 0, 0, 1] == 0.0) and x[lo, 0, 0, 0] == 1.0


def test_o_grid_seam_is_bit_identical():
    for blunt in (False, True):
        x = gen.airfoil("2412", "O", ni=97, nj=33, blunt_te=blunt)[0].xyz
        assert np.array_equal(x[0], x[-1])


def test_folded_cells_are_reported_not_returned():
    xyz = np.zeros((4, 3, 1, 3), order="F")
    xyz[..., 0] = np.arange(4.0)[:, None, None]
    xyz[..., 1] = np.arange(3.0)[None, :, None]
    assert gen._checked(Grid([xyz], ndim=2), "test") is not None
    xyz[2, 1, 0, 0] = -0.5                     # pull a point back over two neighbours
    with pytest.raises(GridValueError, match=r"test: 2 folded .* block 1, first at cell \(2, 1\)"):
        gen._checked(Grid([xyz], ndim=2), "test")


def test_corner_jacobians_catch_what_volumes_miss():
    # an arrowhead quad: positive area (by its diagonals) but a reflex corner
    q = np.zeros((2, 2, 1, 3), order="F")
    q[0, 0, 0, :2], q[1, 0, 0, :2], q[0, 1, 0, :2], q[1, 1, 0, :2] = [0, 0], [2, 0], [0, 2], [0.4, 0.4]
    assert cell_volumes(q)[0, 0] > 0.0 and corner_jacobians(q)[0, 0] < 0.0
    with pytest.raises(GridValueError, match="1 folded or degenerate"):
        gen._checked(Grid([q], ndim=2), "arrow")
    # the unit square: every corner angle 90 deg
    q[1, 1, 0, :2] = [2, 2]
    assert corner_jacobians(q)[0, 0] == pytest.approx(1.0)
    # a hexahedron with one corner pushed through the opposite face: its
    # tetrahedral volume stays positive, one corner Jacobian does not
    i, j, k = np.meshgrid([0.0, 1.0], [0.0, 1.0], [0.0, 1.0], indexing="ij")
    h = np.asfortranarray(np.stack([i, j, k], axis=-1))
    assert corner_jacobians(h)[0, 0, 0] == pytest.approx(1.0)
    h[1, 1, 1] = [0.3, 0.3, 0.3]
    assert cell_volumes(h)[0, 0, 0] > 0.0 and corner_jacobians(h)[0, 0, 0] < 0.0
    with pytest.raises(GridValueError, match="hex: 1 folded"):
        gen._checked(Grid([h], ndim=3), "hex")


def test_small_wings_do_not_fold():
    # regression: coarse wings used to twist hexahedra near the tip (3-D normal correction
    # larger than the span spacing)
    for ni, nj, fs in ((33, 13, 1e-3), (49, 17, 1e-4), (33, 21, 1e-5)):
        assert_wing_cells_valid(gen.wing(ni=ni, nj=nj, nk_wing=5, nk_cap=3, nk_out=4, first_spacing=fs))


@pytest.mark.parametrize("kind,kw", [
    ("airfoil", dict(naca="4412", topology="C", ni=97, nj=33, first_spacing=1e-4)),
    ("airfoil", dict(naca="2415", topology="O", ni=97, nj=33, blunt_te=True)),
    ("airfoil", dict(naca="0012", topology="C", ni=33, nj=9)),
    ("wing", dict(ni=33, nj=21, nk_wing=5, nk_cap=3, nk_out=4, sweep=40.0)),
])
def test_compiled_marcher_is_the_numpy_one(monkeypatch, kind, kw):
    # the compiled sub-step kernel repeats the numpy reference operation for
    # operation: the grids are bit-identical
    fast = gen.GENERATORS[kind](**kw)
    monkeypatch.setattr(gen, "_COMPILED", False)
    ref = gen.GENERATORS[kind](**kw)
    assert all(a.xyz.tobytes() == b.xyz.tobytes() for a, b in zip(fast, ref))


def test_airfoil_is_deterministic():
    a = gen.airfoil("4412", "C", ni=97, nj=33)
    b = gen.airfoil("4412", "C", ni=97, nj=33)
    assert a == b and a is not b


@pytest.mark.parametrize("kw,match", [
    (dict(topology="X"), "topology"),
    (dict(ni=128), "odd"),
    (dict(ni=5), ">= 9"),
    (dict(ni=129.0), "ni must be an integer"),
    (dict(nj=2), "nj must be >= 3"),
    (dict(first_spacing=0.1), "first_spacing"),
    (dict(first_spacing=-1.0), "first_spacing"),
    (dict(first_spacing="small"), "first_spacing must be a number"),
    (dict(farfield=1.0), "farfield"),
    (dict(farfield=float("nan")), "farfield"),
    (dict(wake_length=0.0), "wake_length"),
    (dict(n_wake=63, ni=129), "even"),
    (dict(n_wake=0), "n_wake must be >= 1"),
    (dict(naca="00120"), "naca"),
    (dict(naca=12), "naca"),
    (dict(naca="0000"), "thickness"),
    (dict(smoothing=0.9), "smoothing"),
    (dict(smoothing="lots"), "smoothing must be a number"),
    (dict(n_ortho=-1), "n_ortho"),
    (dict(blunt_te="yes"), "blunt_te must be True or False"),
    (dict(topology="O", blunt_te=True, n_base=0), "n_base"),
    (dict(topology="O", n_wake=10), "n_wake applies to C-grids only"),
    (dict(topology="O", wake_length=5.0), "wake_length applies to C-grids only"),
])
def test_airfoil_rejects_bad_arguments(kw, match):
    with pytest.raises(GridValueError, match=match):
        gen.airfoil(**kw)


# ----------------------------------------------------------------- cylinder, channel, two-block
@pytest.mark.parametrize("ni,nj,fs", [(129, 65, 1e-4), (33, 17, 1e-2), (9, 5, 1e-3)])
def test_cylinder(ni, nj, fs):
    g = gen.cylinder(ni, nj, radius=0.5, first_spacing=fs, farfield=20.0)
    xy = xy_of(g)
    r = np.linalg.norm(xy, axis=-1)
    assert np.allclose(r[:, 0], 0.5, rtol=1e-14) and np.allclose(r[:, -1], 20.0, rtol=1e-14)
    assert np.allclose(r[:, 1] - 0.5, fs, rtol=1e-9)
    assert np.array_equal(xy[0], xy[-1])
    assert cell_volumes(g[0].xyz).min() > 0.0
    assert max_deviation_2d(xy, 0, ni - 1, True, layers=min(10, nj - 1)) <= 1e-5


@pytest.mark.parametrize("kw", [dict(), dict(ni=33, nj=17, bump_height=0.3), dict(bump_height=0.0),
                                dict(ni=65, nj=33, first_spacing=1e-5, bump_height=0.2)])
def test_channel(kw):
    g = gen.channel(**kw)
    xy = xy_of(g)
    ni, nj = xy.shape[:2]
    h = kw.get("bump_height", 0.1)
    x = xy[:, 0, 0]
    expect = np.where((x > 1.0) & (x < 2.0), h * np.sin(np.pi * (x - 1.0)) ** 2, 0.0)
    assert np.allclose(xy[:, 0, 1], expect, atol=1e-15)
    assert np.all(xy[:, -1, 1] == 1.0)
    assert np.allclose(xy[0, :, 0], 0.0) and np.allclose(xy[-1, :, 0], 3.0)
    assert cell_volumes(g[0].xyz).min() > 0.0
    assert max_deviation_2d(xy, 0, ni - 1, False) <= 0.5


@pytest.mark.parametrize("ni,nj", [(65, 33), (17, 9), (9, 5)])
def test_two_block_interface(ni, nj):
    g = gen.two_block(ni, nj)
    assert len(g) == 2 and g.ndim == 2
    lower, upper = g[0].xyz, g[1].xyz
    nh = (nj + 1) // 2
    assert g.dims == [(ni, nh, 1), (nh, ni, 1)]
    # block 1 jmax == block 2 imax (block 2's axes are turned): bit-identical
    assert np.array_equal(lower[:, -1], upper[-1, :])
    for b in g:
        assert cell_volumes(b.xyz).min() > 0.0
    assert np.all(upper[0, :, 0, 1] == 1.0)           # block 2 imin: the upper wall
    assert max_deviation_2d(xy_of(g, 0), 0, ni - 1, False, layers=min(10, nh - 1)) <= 0.5


@pytest.mark.parametrize("fn,kw,match", [
    (gen.cylinder, dict(ni=4), "ni must be >= 5"),
    (gen.cylinder, dict(radius=0.0), "radius"),
    (gen.cylinder, dict(farfield=0.4), "farfield"),
    (gen.cylinder, dict(first_spacing=30.0), "first_spacing"),
    (gen.channel, dict(nj=2), "nj"),
    (gen.channel, dict(height=-1.0), "height"),
    (gen.channel, dict(bump_height=0.5), "bump_height"),
    (gen.channel, dict(bump_start="a"), "bump_start must be a number"),
    (gen.channel, dict(bump_start=2.5), "bump_start < bump_end"),
    (gen.channel, dict(first_spacing=0.6), "first_spacing"),
    (gen.two_block, dict(nj=32), "nj must be odd"),
    (gen.two_block, dict(bump_height=-0.1), "bump_height"),
    (gen.two_block, dict(length=0.0), "length"),
])
def test_2d_generators_reject_bad_arguments(fn, kw, match):
    with pytest.raises(GridValueError, match=match):
        fn(**kw)


def test_small_generators_are_deterministic():
    assert gen.cylinder(17, 9) == gen.cylinder(17, 9)
    assert gen.channel(17, 9) == gen.channel(17, 9)
    assert gen.two_block(17, 9) == gen.two_block(17, 9)


# ----------------------------------------------------------------- wing
SMALL_WING = dict(ni=65, nj=25, nk_wing=9, nk_cap=5, nk_out=7, first_spacing=1e-5)


@pytest.fixture(scope="module")
def small_wing():
    return gen.wing(**SMALL_WING)


def test_wing_blocks_and_volumes(small_wing):
    g = small_wing
    assert g.ndim == 3 and len(g) == 4
    # walls on the wing and its cap only; the blocks beyond the tip have none
    bp = gen.boundary_patches("wing", g)
    assert sorted({p.block for p in bp["walls"]}) == [0, 1]
    assert {p.block for p in bp["symmetry"]} == {0}
    ni, nj = SMALL_WING["ni"], SMALL_WING["nj"]
    nh = (ni + 1) // 2
    assert g.dims == [(ni, nj, 9), (ni, nj, 5), (nh, nj, 7), (7, nh, nj)]
    assert_wing_cells_valid(g)


def test_wing_interfaces_are_bit_identical(small_wing):
    b1, b2, b3, b4 = (b.xyz for b in small_wing)
    ih = (b1.shape[0] - 1) // 2
    assert np.array_equal(b1[:, :, -1], b2[:, :, 0])                     # 1 kmax = 2 kmin
    assert np.array_equal(b2[:ih + 1, :, -1], b3[:, :, 0])               # 2 kmax (part) = 3 kmin
    # 2 kmax (other part) = 4 imin with swapped axes: 4 is (k, i, j) of the original
    assert np.array_equal(b2[ih:, :, -1], b4[0])
    assert np.array_equal(b3[:, 0, :], b4[:, ::-1, 0].transpose(1, 0, 2))  # 3 jmin = 4 kmin, i reversed
    assert np.array_equal(b3[-1], b4[:, 0, :].transpose(1, 0, 2))         # 3 imax = 4 jmin, swapped


def test_wing_cuts_symmetry_and_tip(small_wing):
    b1, b2 = small_wing[0].xyz, small_wing[1].xyz
    ni = b1.shape[0]
    lo, hi = gen.wing_wall_range(ni)
    for b in (b1, b2):                                  # wake cuts
        assert np.array_equal(b[:lo + 1, 0], b[hi:, 0][::-1])
    assert np.all(b1[:, :, 0, 1] == 0.0)                # root face in the symmetry plane y = 0
    # the cap ends in a collapsed section: upper and lower surfaces coincide
    assert np.array_equal(b2[lo:hi + 1, 0, -1], b2[lo:hi + 1, 0, -1][::-1])
    assert not np.array_equal(b2[lo:hi + 1, 0, 0], b2[lo:hi + 1, 0, 0][::-1])
    semispan, x_le, chord = gen.wing_geometry()
    assert np.all(b1[:, :, -1, 1][:, 0] == pytest.approx(semispan))
    assert 3.0 <= 4.0 * semispan / (1.0 + chord(semispan)) <= 6.0   # aspect ratio (2b)^2 / S


def collapsed_edge_cells(grid):
    """Per block, the 0-based cells touching the collapsed leading edge beyond
    the wing (the cap's last station and the zero-thickness sheet)."""
    (ni, _, _), (_, _, nkc), (_, _, nko), _ = grid.dims
    ih = (ni - 1) // 2
    return [set(),
            {(ih - 1, 0, nkc - 2), (ih, 0, nkc - 2)},
            {(ih - 1, 0, k) for k in range(nko - 1)},
            {(k, 0, 0) for k in range(nko - 1)}]


def assert_wing_cells_valid(grid):
    # positive volumes; corner Jacobians positive except the exact 180-degree
    # corners where the C wraps round the collapsed edge (zero to round-off)
    for n, (b, edge) in enumerate(zip(grid, collapsed_edge_cells(grid))):
        assert cell_volumes(b.xyz).min() > 0.0, f"block {n + 1}"
        cj = corner_jacobians(b.xyz)
        assert cj.min() >= -gen.CORNER_TOL, f"block {n + 1}"
        assert {tuple(map(int, c)) for c in np.argwhere(cj <= 1e-6)} == edge, f"block {n + 1}"


#: wings over the parameter range, with a realistic wall-normal stretching
#: (nj = 41: ratio about 1.4 from first_spacing 1e-5 to 15 chords)
ORTHO_WINGS = [dict(), dict(sweep=0.0, taper=1.0, aspect_ratio=3.0),
               dict(naca="4415", sweep=45.0, taper=0.3, aspect_ratio=6.0),
               dict(first_spacing=1e-6), dict(naca="2412", first_spacing=1e-4, sweep=15.0, aspect_ratio=5.0),
               dict(stretching="tanh", first_spacing=1e-6)]


@pytest.mark.parametrize("kw", ORTHO_WINGS)
def test_wing_wall_orthogonality_and_cells(kw):
    params = {**SMALL_WING, "nj": 41, **kw}
    g = gen.wing(**params)
    assert_wing_cells_valid(g)
    dev = wing_wall_deviations(g)
    # every wall point of the wing and its cap (root and tip stations included),
    # all but the cap's last station, the collapsed edge where the wall has no normal
    assert dev.shape[2] == params["nk_wing"] + params["nk_cap"] - 1
    assert np.isfinite(dev[:, :, :-1]).all() and dev[:, :, :-1].max() <= 0.5
    # the first layer leaves the wall outwards at first_spacing
    b1 = g[0].xyz
    lo, hi = gen.wing_wall_range(params["ni"])
    h = np.linalg.norm(b1[lo:hi + 1, 1] - b1[lo:hi + 1, 0], axis=-1)
    assert np.allclose(h, params["first_spacing"], rtol=1e-9)


def test_wing_is_deterministic(small_wing):
    assert gen.wing(**SMALL_WING) == small_wing


@pytest.mark.parametrize("kw,match", [
    (dict(ni=67), "multiple of 4"), (dict(sweep=80.0), "sweep"), (dict(sweep="a"), "sweep must be a number"),
    (dict(taper=0.0), "taper"), (dict(aspect_ratio=0.5), "aspect_ratio"), (dict(nk_cap=1), "nk_cap"),
    (dict(nj=4), "nj"), (dict(naca="0000"), "thickness"), (dict(first_spacing=0.1), "first_spacing"),
    (dict(farfield=1.0), "farfield"), (dict(span_farfield=0.01), "span_farfield"),
    (dict(wake_length=0.01), "wake_length"), (dict(n_wake=40, ni=65), "n_wake"),
    (dict(smoothing=float("nan")), "smoothing")])
def test_wing_rejects_bad_arguments(kw, match):
    with pytest.raises(GridValueError, match=match):
        gen.wing(**kw)


# ----------------------------------------------------------------- boundary patches
def test_boundary_patches_resolve_and_sit_on_the_walls(small_wing):
    g = gen.airfoil("0012", "C", ni=97, nj=33)
    p = gen.boundary_patches("airfoil", g)
    (wall,) = p["walls"]
    (a0, a1), _ = wall.resolve(g).range
    x = g[0].xyz[a0:a1 + 1, 0, 0]
    assert x[0, 0] == 1.0 and x[-1, 0] == 1.0 and x[:, 0].min() == 0.0
    for key in ("walls", "symmetry", "fixed"):
        for spec in p[key]:
            spec.resolve(g)
    pw = gen.boundary_patches("wing", small_wing)
    assert [str(s) for s in pw["symmetry"]] == ["1:kmin"]
    for key in ("walls", "symmetry", "fixed"):
        for spec in pw[key]:
            spec.resolve(small_wing)
    # every wall point of the wing is on the surface block faces jmin, inside the airfoil range
    lo, hi = gen.wing_wall_range(SMALL_WING["ni"])
    assert pw["walls"][0].range[0] == (lo, hi)
    with pytest.raises(GridValueError, match="unknown generator"):
        gen.boundary_patches("sphere", g)


# ----------------------------------------------------------------- shipped grids
GRIDS = Path(__file__).resolve().parent.parent / "grids"


def _samples():
    spec = importlib.util.spec_from_file_location("make_grids", GRIDS / "make_grids.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


SAMPLES = _samples()
SMALL_SAMPLES = [n for n in SAMPLES.SAMPLES if not n.startswith("wing")]


def test_shipped_files_are_the_recorded_ones():
    sums = dict(reversed(line.split()) for line in (GRIDS / "SHA256SUMS").read_text().splitlines())
    assert set(sums) == {f"{n}.x" for n in SAMPLES.SAMPLES}
    total = 0
    for name, digest in sums.items():
        assert SAMPLES.sha256(GRIDS / name) == digest, name
        total += (GRIDS / name).stat().st_size
    assert total < 20e6
    readme = (GRIDS / "README.md").read_text()
    for n in SAMPLES.SAMPLES:
        assert f"{n}.x" in readme and f"{n}.toml" in readme


@pytest.mark.parametrize("name", SMALL_SAMPLES)
def test_shipped_small_grids_match_the_generator(name):
    shipped = tfi_quat.read(GRIDS / f"{name}.x")
    grid, case = SAMPLES.build(name)
    assert shipped.ndim == grid.ndim and shipped.dims == grid.dims
    for a, b in zip(shipped, grid):
        # equal to round-off (other CPUs may differ in the last bits of sin/cos)
        assert np.allclose(a.xyz, b.xyz, rtol=0.0, atol=1e-12 * np.abs(b.xyz).max())
    loaded = load_case(GRIDS / f"{name}.toml")
    assert loaded.grid == (GRIDS / f"{name}.x").resolve()
    assert (loaded.walls, loaded.symmetry, loaded.fixed, loaded.motion) == \
        (case.walls, case.symmetry, case.fixed, case.motion)
    loaded.check(shipped)
    for b in shipped:
        assert cell_volumes(b.xyz).min() > 0.0


def test_shipped_naca0012_is_the_memo_case():
    case = load_case(GRIDS / "naca0012_c_257x65.toml")
    assert [str(w) for w in case.walls] == ["1:jmin:65-193,1-1"]
    g = tfi_quat.read(case.grid)
    x = g[0].xyz[64:193, 0, 0]
    assert g.dims == [(257, 65, 1)] and x[:, 0].min() == 0.0 and x[0, 0] == x[-1, 0] == 1.0
    assert np.array_equal(g[0].xyz[:65, 0], g[0].xyz[192:, 0][::-1])


def test_shipped_wing_properties():
    case = load_case(GRIDS / "wing_ch_501k.toml")
    g = tfi_quat.read(case.grid)
    case = case.check(g)
    params = SAMPLES.SAMPLES["wing_ch_501k"][1]
    ni, nj = params["ni"], params["nj"]
    nh = (ni + 1) // 2
    assert g.ndim == 3 and g.dims == [(ni, nj, 45), (ni, nj, 9), (nh, nj, 25), (25, nh, nj)]
    assert 0.4e6 < g.npoints < 2e6
    assert_wing_cells_valid(g)
    b1, b2, b3, b4 = (b.xyz for b in g)
    ih = (ni - 1) // 2
    assert np.array_equal(b1[:, :, -1], b2[:, :, 0])
    assert np.array_equal(b2[:ih + 1, :, -1], b3[:, :, 0])
    assert np.array_equal(b2[ih:, :, -1], b4[0])
    assert np.array_equal(b3[:, 0, :], b4[:, ::-1, 0].transpose(1, 0, 2))
    assert np.array_equal(b3[-1], b4[:, 0, :].transpose(1, 0, 2))
    lo, hi = gen.wing_wall_range(ni)
    assert case.walls[0].range == ((lo, hi), (0, 44))
    assert np.array_equal(b1[:lo + 1, 0], b1[hi:, 0][::-1])
    assert np.all(b1[:, :, 0, 1] == 0.0)
    assert case.walls[1].range == ((lo, hi), (0, 8))
    assert [(p.block, p.face) for p in case.symmetry] == [(0, "kmin")]
    # wall orthogonality of the first 10 layers: wing and cap, root to the
    # cap's last station (the collapsed edge)
    dev = wing_wall_deviations(g)
    assert dev[:, :, :-1].max() <= 0.5
    # the geometry the README states: aspect ratio 4, taper 0.5, 30 deg sweep
    semispan, x_le, chord = gen.wing_geometry(4.0, 0.5, 30.0)
    assert b1[lo, 0, -1, 1] == semispan and abs(chord(semispan) - 0.5) < 1e-15
    assert 4.0 * semispan ** 2 / (semispan * (1.0 + chord(semispan))) == pytest.approx(4.0)


# ----------------------------------------------------------------- CLI
@pytest.fixture
def cli(monkeypatch):
    """``tfi_quat.cli.main`` with only this subcommand registered (others live elsewhere)."""
    from tfi_quat import cli as cli_mod
    monkeypatch.setattr(cli_mod, "SUBCOMMANDS", {"generate": "._generate"})
    return cli_mod.main


def test_cli_generate_airfoil_with_case(cli, tmp_path, capsys):
    out, case = tmp_path / "a.x", tmp_path / "sub" / "a.toml"
    case.parent.mkdir()
    rc = cli(["generate", "airfoil", "--naca", "4412", "--ni", "97", "--nj", "33", "-o", str(out),
              "--case", str(case)])
    assert rc == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1 and "97x33x1" in lines[0] and str(out) in lines[0]
    assert tfi_quat.read(out) == gen.airfoil("4412", "C", ni=97, nj=33)
    c = load_case(case)
    assert c.grid == out.resolve() and [str(w) for w in c.walls] == ["1:jmin:25-73,1-1"]
    assert 'grid = "../a.x"' in case.read_text()


@pytest.mark.parametrize("argv,dims", [
    (["cylinder", "--ni", "17", "--nj", "9"], [(17, 9, 1)]),
    (["channel", "--ni", "17", "--nj", "9"], [(17, 9, 1)]),
    (["two-block", "--ni", "17", "--nj", "9"], [(17, 5, 1), (5, 17, 1)]),
    (["airfoil", "--topology", "o", "--ni", "65", "--nj", "25", "--blunt-te"], [(65, 25, 1)]),
    (["airfoil", "--ni", "65", "--nj", "25", "--stretching", "tanh"], [(65, 25, 1)]),
    (["wing", "--ni", "65", "--nj", "25", "--nk-wing", "5", "--nk-cap", "3", "--nk-out", "4"],
     [(65, 25, 5), (65, 25, 3), (33, 25, 4), (4, 33, 25)]),
])
def test_cli_generate_every_kind(cli, tmp_path, capsys, argv, dims):
    out = tmp_path / "g.x"
    assert cli(["generate", *argv, "-o", str(out), "--case", str(tmp_path / "g.toml")]) == 0
    assert len(capsys.readouterr().out.strip().splitlines()) == 1
    g = tfi_quat.read(out)
    assert g.dims == dims
    load_case(tmp_path / "g.toml").check(g)


def test_cli_refuses_to_overwrite_without_force(cli, tmp_path, capsys):
    out = tmp_path / "c.x"
    out.write_bytes(b"keep")
    assert cli(["generate", "cylinder", "--ni", "9", "--nj", "5", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "exists" in err and "--force" in err and out.read_bytes() == b"keep"
    assert cli(["generate", "cylinder", "--ni", "9", "--nj", "5", "-o", str(out), "--force"]) == 0
    assert tfi_quat.read(out) == gen.cylinder(9, 5)


@pytest.mark.parametrize("argv,match", [
    (["airfoil", "--ni", "128"], "--ni must be odd, got 128"),
    (["airfoil", "--blunt-te"], "--blunt-te=True needs --topology 'O'"),
    (["airfoil", "--topology", "O", "--n-wake", "10"], "--n-wake applies to C-grids only"),
    (["airfoil", "--naca", "0000"], "--naca '0000': thickness"),
    (["channel", "--bump-height", "0.7"], "--bump-height must be in"),
    (["cylinder", "--farfield", "0.2"], "--farfield (0.2) must exceed the --radius (0.5)"),
    (["wing", "--sweep", "75"], "--sweep must be in [0, 60] degrees"),
    (["two-block", "--nj", "32"], "--nj must be odd"),
])
def test_cli_reports_bad_parameters(cli, tmp_path, capsys, argv, match):
    assert cli(["generate", *argv, "-o", str(tmp_path / "x.x")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and match in err
    assert not (tmp_path / "x.x").exists()


def test_cli_wing_wake_options(cli, tmp_path, capsys):
    out, case = tmp_path / "w.x", tmp_path / "w.toml"
    argv = ["wing", "--ni", "65", "--nj", "25", "--nk-wing", "5", "--nk-cap", "3", "--nk-out", "4",
            "--n-wake", "12", "--wake-length", "8"]
    assert cli(["generate", *argv, "-o", str(out), "--case", str(case)]) == 0
    g = tfi_quat.read(out)
    assert g == gen.wing(ni=65, nj=25, nk_wing=5, nk_cap=3, nk_out=4, n_wake=12, wake_length=8.0)
    assert [str(w) for w in load_case(case).walls] == ["1:jmin:13-53,1-5", "2:jmin:13-53,1-3"]
    # the outflow plane is 8 root chords behind the last trailing edge
    lo, _ = gen.wing_wall_range(65, 12)
    te_x = max(g[0].xyz[lo, 0, :, 0].max(), g[1].xyz[lo, 0, :, 0].max())
    assert np.allclose(g[0].xyz[0, 0, :, 0], te_x + 8.0, rtol=1e-14, atol=0.0)


# ----------------------------------------------------------------- cross-check with connectivity
def test_connectivity_finds_the_documented_interfaces(small_wing):
    from tfi_quat.topology import connect

    conn = connect(small_wing, **{k: v for k, v in gen.boundary_patches("wing", small_wing).items()})
    found = {(i.master.block, i.master.face, i.slave.block, i.slave.face, tuple(i.transform))
             for i in conn.interfaces}
    assert found == {(0, "jmin", 0, "jmin", (-1, -2, 3)), (0, "kmax", 1, "kmin", (1, 2, 3)),
                     (1, "jmin", 1, "jmin", (-1, -2, 3)), (1, "kmax", 2, "kmin", (1, 2, 3)),
                     (1, "kmax", 3, "imin", (2, 3, 1)), (2, "imax", 3, "jmin", (2, 3, 1)),
                     (2, "jmin", 3, "kmin", (-2, -3, 1))}
    kinds = {(p.spec.block, p.spec.face, p.kind) for p in conn.patches}
    assert (0, "jmin", "wall") in kinds and (1, "jmin", "wall") in kinds and (0, "kmin", "symmetry") in kinds
    tb = gen.two_block(17, 9)
    (itf,) = connect(tb).interfaces
    assert {(itf.master.block, itf.master.face), (itf.slave.block, itf.slave.face)} == \
        {(0, "jmax"), (1, "imax")}


@pytest.mark.parametrize("ni,nj,fs", [(257, 65, 1e-5), (129, 49, 1e-4)])
def test_c_grid_wake_lines_stay_normal_to_the_cut(ni, nj, fs):
    # regression: smoothing used to lean the wake-normal lines over until,
    # near the outflow, they ran almost parallel to the cut (cells that any
    # deformation folds)
    g = gen.airfoil("0012", "C", ni=ni, nj=nj, first_spacing=fs)
    x = g[0].xyz[:, :, 0, :2]
    lo, hi = gen.airfoil_wall_range(ni, "C")
    far = x[:, 0, 0] > 7.0                  # wake points more than 6 chords behind the TE
    assert far[:lo].any()
    e = np.diff(x[far], axis=1)             # along the wake-normal lines
    ang = np.degrees(np.arctan2(np.abs(e[..., 0]), np.abs(e[..., 1])))
    assert ang.max() < 5.0
    # and no layer crosses the wake cut (which positive cells alone would not show)
    for j in range(1, nj):
        y, xm = x[:, j, 1], 0.5 * (x[:-1, j, 0] + x[1:, j, 0])
        assert not np.any((np.sign(y[:-1]) != np.sign(y[1:])) & (xm > 1.0)), j
