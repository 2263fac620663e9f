"""Pictures: figures for the shipped 2-D and 3-D grids, the values the colours come from,
and clear errors for bad arguments."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from matplotlib.collections import LineCollection, QuadMesh
from matplotlib.figure import Figure

import tfi_quat
from tfi_quat import Block, CaseError, Grid, GridValueError
from tfi_quat import plot as P
from tfi_quat.case import load_case
from tfi_quat.quality import cell_metrics, cell_orthogonality

GRIDS_2D = ["naca0012_c_257x65", "naca4412_o_257x65", "cylinder_o_129x65", "channel_bump_129x49",
            "two_block_65x33"]


def png_size(path):
    with open(path, "rb") as fh:
        data = fh.read(24)
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG file"
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def load(name):
    case = load_case(f"grids/{name}.toml")
    return tfi_quat.read(case.grid), case


@pytest.fixture(scope="module")
def naca():
    return load("naca0012_c_257x65")


@pytest.fixture(scope="module")
def moved(naca):
    from tfi_quat.deform import Deformer
    from tfi_quat.demo import DemoMotion
    g, case = naca
    d = Deformer(g, walls=case.walls, fixed=case.fixed, method="tfi")
    return d.deform(DemoMotion(pitch=15.0))


def meshes(fig):
    """The QuadMeshes of the panels (not the colour bar's own)."""
    return [c for ax in fig.axes if ax.get_label() != "<colorbar>" for c in ax.collections
            if isinstance(c, QuadMesh)]


@pytest.mark.parametrize("name", GRIDS_2D)
def test_2d_shipped_grids_make_pngs_of_the_requested_size(tmp_path, name):
    g, case = load(name)
    fig = P.grid_figure(g, walls=case.walls, size=(900, 400), dpi=100, title=name)
    out = tmp_path / f"{name}.png"
    P.save_figure(fig, out, dpi=100)
    assert png_size(out) == (900, 400)


def test_3d_wing_wall_and_cuts(tmp_path):
    g, case = load("wing_ch_501k")
    fig = P.grid_figure(g, walls=case.walls, color="skewness", size=(1200, 500), dpi=80)
    out = tmp_path / "wing.png"
    P.save_figure(fig, out, dpi=80)
    assert png_size(out) == (1200, 500)
    # the wall faces carry the skewness of the cells they bound (block 1, j = 0, wall range)
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection
    walls3d = [c for ax in fig.axes for c in ax.collections if isinstance(c, Poly3DCollection)]
    skew = cell_metrics(g[0])["skewness"]
    want = skew[32:96, 0, 0:44].reshape(-1)
    np.testing.assert_array_equal(np.asarray(walls3d[0].get_array()), want)
    # the cuts are the default sections: mid-span and the wall's end
    cuts = P.default_cuts(g, case.walls)
    assert [str(c) for c in cuts] == ["1:k=23", "1:k=45"]
    cut_meshes = meshes(fig)
    np.testing.assert_array_equal(np.asarray(cut_meshes[0].get_array()).ravel(), skew[:, :, 22].ravel())
    np.testing.assert_array_equal(np.asarray(cut_meshes[1].get_array()).ravel(), skew[:, :, 43].ravel())


def test_plot_cut_projects_on_the_plane_coordinates():
    g, _ = load("wing_ch_501k")
    fig = Figure()
    ax = fig.add_subplot()
    res = P.plot_cut(ax, g, P.parse_cut("1:k=23"))
    assert res["coords"] == (0, 2)          # a section of the wing: x and z
    assert isinstance(res["lines"], LineCollection) and res["mesh"] is None
    assert ax.get_xlabel() == "x" and ax.get_ylabel() == "z"


def test_metric_colours_are_the_metric_values(naca, moved):
    g, case = naca
    for metric in ("skewness", "aspect_ratio", "scaled_jacobian"):
        fig = Figure()
        ax = fig.add_subplot()
        ms, cb = P.plot_metric_2d(ax, g, metric)
        want = cell_metrics(g[0])[metric][:, :, 0]
        np.testing.assert_array_equal(np.asarray(ms[0].get_array()).reshape(want.shape), want)
        assert cb is not None and cb.ax.get_ylabel() == P._LABELS[metric]
    fig = P.plot_compare({"plain TFI": moved}, ref=g, walls=case.walls, windows=["near", "te"],
                         color="volume_ratio")
    want = cell_metrics(moved[0], ref=g[0])["volume_ratio"][:, :, 0]
    got = meshes(fig)
    assert len(got) == 2
    for m in got:
        np.testing.assert_array_equal(np.asarray(m.get_array()).reshape(want.shape), want)
    # side by side: the reference column is drawn, but not coloured by a ratio to itself
    fig = P.plot_compare({"plain TFI": moved}, ref=g, walls=case.walls, windows=["near"], layout="side",
                         color="volume_ratio")
    assert len(fig.axes) == 3 and len(meshes(fig)) == 1     # 2 panels + colour bar
    # orthogonality change: NaN (masked, transparent) away from the wall
    fig = P.plot_compare({"plain TFI": moved}, ref=g, walls=case.walls, windows=["le"],
                         color="orthogonality_change", layers=4)
    arr = meshes(fig)[0].get_array()
    want = cell_orthogonality(moved, case.walls, 4, ref=g)[0][:, :, 0]
    np.testing.assert_array_equal(np.ma.getmaskarray(arr).reshape(want.shape), np.isnan(want))
    np.testing.assert_array_equal(np.ma.filled(arr, np.nan).reshape(want.shape), want)


def test_plot_compare_layout(naca, moved):
    g, case = naca
    fig = P.plot_compare({"plain TFI": moved, "again": moved}, ref=g, walls=case.walls)
    assert len(fig.axes) == 6
    titles = [ax.get_title() for ax in fig.axes]
    assert titles[:2] == ["plain TFI: near field", "again: near field"]
    assert "again: trailing edge" in titles
    # overlay: the reference in grey under every panel, the wall on top
    ax = fig.axes[0]
    colors = {tuple(np.round(lc.get_colors()[0], 3)) for lc in ax.collections if isinstance(lc, LineCollection)}
    assert len(colors) == 2 and ax.get_aspect() == 1.0
    # near-field panels share one window; the zooms follow each grid's wall
    w = P.zoom_windows(moved, case.walls)
    assert fig.axes[4].get_xlim() == pytest.approx(w["trailing edge"][:2])


def test_zoom_windows_on_the_c_grid(naca):
    g, case = naca
    w = P.zoom_windows(g, case.walls)
    le = w["leading edge"]
    te = w["trailing edge"]
    assert le[0] < 0.0 < le[1] and le[2] < 0.0 < le[3] and le[1] - le[0] == pytest.approx(0.08, rel=1e-3)
    assert te[0] < 1.0 < te[1] and te[3] - te[2] == pytest.approx(0.12, rel=1e-3)
    near = w["near field"]
    assert near[0] < 0.0 and near[1] > 1.0


def test_window_draws_only_the_lines_that_enter_it(naca):
    g, _ = naca
    win = (0.9, 1.1, -0.05, 0.05)
    fig = Figure()
    ax = fig.add_subplot()
    (lc,) = P.plot_grid_2d(ax, g, window=win)
    x = g[0].xyz[:, :, 0, :2]

    def enters(line):
        a, b = line[:-1], line[1:]
        return bool(np.any((np.minimum(a[:, 0], b[:, 0]) <= win[1]) & (np.maximum(a[:, 0], b[:, 0]) >= win[0]) &
                           (np.minimum(a[:, 1], b[:, 1]) <= win[3]) & (np.maximum(a[:, 1], b[:, 1]) >= win[2])))
    want = sum(enters(x[i]) for i in range(x.shape[0])) + sum(enters(x[:, j]) for j in range(x.shape[1]))
    assert len(lc.get_segments()) == want < x.shape[0] + x.shape[1]
    assert ax.get_xlim() == pytest.approx(win[:2])


def test_bad_arguments(naca, moved):
    g, case = naca
    fig = Figure()
    ax = fig.add_subplot()
    with pytest.raises(CaseError, match="unknown metric 'skew'"):
        P.cell_values(g, "skew")
    with pytest.raises(CaseError, match="needs a reference"):
        P.plot_metric_2d(ax, g, "volume_ratio")
    with pytest.raises(CaseError, match="needs wall patches"):
        P.cell_values(g, "orthogonality")
    with pytest.raises(CaseError, match="x0 < x1"):
        P.plot_grid_2d(ax, g, window=(1.0, 0.0, 0.0, 1.0))
    with pytest.raises(CaseError, match="needs wall patches"):
        P.plot_compare(g, windows=["le"])
    with pytest.raises(CaseError, match="unknown zoom"):
        P.plot_compare(g, walls=case.walls, windows=["middle"])
    with pytest.raises(CaseError, match="layout"):
        P.plot_compare(g, layout="stacked")
    wing, wcase = load("wing_ch_501k")
    with pytest.raises(GridValueError, match="2-D"):
        P.plot_grid_2d(ax, wing)
    with pytest.raises(GridValueError, match="3-D"):
        P.plot_cut(ax, g, P.Cut(0, "k", 0))
    with pytest.raises(CaseError, match="k = 1..45"):
        P.grid_figure(wing, walls=wcase.walls, cuts=["1:k=46"])
    with pytest.raises(CaseError, match="BLOCK:AXIS=N"):
        P.parse_cut("1:q=3")
    with pytest.raises(GridValueError, match="does not match"):
        P.plot_compare({"x": moved}, ref=Grid([Block(g[0].xyz[:-1])], ndim=2))
    with pytest.raises(CaseError, match="100 x 100"):
        P.grid_figure(g, size=(50, 40))


def test_inverted_cells_stand_out_in_the_volume_ratio_colours():
    i, j = np.meshgrid(np.arange(5.0), np.arange(4.0), indexing="ij")
    ref = np.zeros((5, 4, 1, 3), order="F")
    ref[..., 0, 0], ref[..., 0, 1] = i, j
    x = ref.copy(order="F")
    x[2, 1, 0, :2] = (3.6, 2.7)               # folds the cells around point (2, 1)
    g, gr = Grid([Block(x)], ndim=2), Grid([Block(ref)], ndim=2)
    fig = Figure()
    ax = fig.add_subplot()
    (mesh,), cb = P.plot_metric_2d(ax, g, "volume_ratio", ref=gr)
    ratio = cell_metrics(x, ref=ref)["volume_ratio"][:, :, 0]
    assert (ratio <= 0).any()
    arr = mesh.get_array()
    np.testing.assert_array_equal(np.asarray(arr).reshape(ratio.shape), ratio)
    rgba = mesh.to_rgba(arr).reshape(ratio.shape + (4,))
    np.testing.assert_array_equal(rgba[ratio <= 0], [[0.0, 1.0, 0.0, 1.0]] * int((ratio <= 0).sum()))
    assert not np.any(np.all(rgba[ratio > 0] == (0.0, 1.0, 0.0, 1.0), axis=-1))
    assert "inverted" in cb.ax.get_ylabel()
