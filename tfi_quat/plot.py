"""Pictures of grids with matplotlib: 2-D grids and zoom windows, reference and
deformed grids overlaid or side by side (the memo's figure 4 layout), cells
coloured by a quality metric, and for 3-D grids the wall surface and cuts
through the volume along constant-index planes.

Figures are :class:`matplotlib.figure.Figure` objects made without pyplot, so
the library needs no display and never changes the user's backend; saving a
PNG uses matplotlib's Agg renderer.  The drawing functions take an axes
(``plot_grid_2d(ax, grid, ...)``) and return what they added, so they
compose into any figure; :func:`plot_compare` and :func:`grid_figure` build
whole figures, :func:`save_figure` writes one atomically.

Block and cell indices are 0-based here, as everywhere in the Python API.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import CaseError, GridValueError
from .grid import Grid, face_axes, face_cells, face_ijk, face_layer
from .spec import resolve_patch_specs

__all__ = ["COLOR_METRICS", "Cut", "parse_cut", "cell_values", "wall_points", "zoom_windows",
           "plot_grid_2d", "plot_walls_2d", "plot_cells_2d", "plot_metric_2d", "plot_compare",
           "plot_wall_3d", "plot_cut", "default_cuts", "grid_figure", "save_figure"]

#: metrics cells can be coloured by (:func:`cell_values`)
COLOR_METRICS = ("volume", "jacobian", "scaled_jacobian", "skewness", "aspect_ratio", "volume_ratio",
                 "orthogonality", "orthogonality_change")

_LABELS = {
    "volume": "cell volume", "jacobian": "smallest corner Jacobian", "scaled_jacobian": "scaled Jacobian",
    "skewness": "equiangle skewness", "aspect_ratio": "aspect ratio",
    "volume_ratio": "volume ratio (grid / reference)",
    "orthogonality": "angle to the wall normal (deg)",
    "orthogonality_change": "change of the angle to the wall normal (deg)",
}
_CMAPS = {"volume_ratio": "RdBu", "skewness": "magma_r", "orthogonality": "magma_r",
          "orthogonality_change": "magma_r", "scaled_jacobian": "viridis"}

REF_COLOR = "0.78"        # the reference grid, under the deformed one
INVERTED_COLOR = "lime"   # cells with a volume ratio <= 0
RATIO_SPAN = 10.0         # volume-ratio colours span at most 1/10 .. 10
GRID_COLOR = "k"
WALL_COLOR = "tab:red"

# zoom windows of an airfoil wall, as fractions of the chord
LE_HALF = 0.04
TE_HALF = 0.06
NEAR_PAD = 0.35


# ------------------------------------------------------------------ data
def cell_values(grid: Grid, metric: str, ref: Grid | None = None, walls=None, layers: int | None = None) -> list:
    """Per-cell values of a metric, one array per block (shaped as
    :func:`tfi_quat.quality.cell_volumes`).

    Parameters
    ----------
    grid : Grid
    metric : str
        One of :data:`COLOR_METRICS`: the cell metrics of
        :func:`tfi_quat.quality.cell_metrics`, or ``orthogonality`` /
        ``orthogonality_change`` (:func:`tfi_quat.quality.cell_orthogonality`:
        cells of the first ``layers`` layers off the walls, NaN elsewhere).
    ref : Grid, optional
        Needed by ``volume_ratio`` and ``orthogonality_change``.
    walls : patch specs, optional
        Needed by ``orthogonality`` and ``orthogonality_change``.
    layers : int, optional
        Layers off the wall of the orthogonality metrics (default: every
        layer, so the picture shows how far from the wall the lines turn).

    Raises
    ------
    CaseError
        Unknown metric, or a metric without the reference or walls it needs.
    """
    from .quality import cell_metrics, cell_orthogonality

    if metric not in COLOR_METRICS:
        raise CaseError(f"unknown metric {metric!r}: expected one of {', '.join(COLOR_METRICS)}")
    if metric in ("volume_ratio", "orthogonality_change") and ref is None:
        raise CaseError(f"metric {metric!r} needs a reference grid (--ref)")
    if metric.startswith("orthogonality"):
        if not walls:
            raise CaseError(f"metric {metric!r} needs wall patches (--walls or --case)")
        if layers is None:
            layers = max(max(b.dims) for b in grid) - 1
        return cell_orthogonality(grid, walls, layers, ref=ref if metric == "orthogonality_change" else None)
    _check_ref(grid, ref)
    return [cell_metrics(b, grid.ndim, ref=None if ref is None else ref[n])[metric] for n, b in enumerate(grid)]


def _check_ref(grid: Grid, ref: Grid | None) -> None:
    if ref is None:
        return
    if len(ref) != len(grid) or ref.ndim != grid.ndim or ref.dims != grid.dims:
        raise GridValueError(f"the reference grid ({len(ref)} block(s), {ref.ndim}-D, {ref.dims}) does not "
                             f"match the grid ({len(grid)} block(s), {grid.ndim}-D, {grid.dims})")


def wall_points(grid: Grid, walls) -> list:
    """Points of each wall patch, ``(na, nb, 3)`` arrays (2-D walls: ``nb == 1``)."""
    out = []
    for spec in resolve_patch_specs(grid, walls, "walls"):
        ijk = face_ijk(grid[spec.block].dims, spec.face, spec.range)
        out.append(grid[spec.block].xyz[ijk[..., 0], ijk[..., 1], ijk[..., 2]])
    return out


def _square(cx, cy, half):
    return (cx - half, cx + half, cy - half, cy + half)


def zoom_windows(grid: Grid, walls, le: float = LE_HALF, te: float = TE_HALF, pad: float = NEAR_PAD) -> dict:
    """Zoom windows ``(x0, x1, y0, y1)`` on the first wall of a 2-D grid, as for an airfoil.

    ``"near field"``: the walls' bounding box grown by ``pad`` times its
    largest side; ``"trailing edge"``: a square of half-width ``te`` chords
    about the middle of the first wall's end points (where a C- or O-grid
    airfoil wall starts and ends); ``"leading edge"``: half-width ``le``
    chords about the wall point farthest from it.  The chord is that
    distance.  The windows follow the wall wherever it moved.
    """
    pts = [w.reshape(-1, 3)[:, :2] for w in wall_points(grid, walls)]
    if not pts:
        raise CaseError("zoom windows need at least one wall patch")
    w = pts[0]
    allp = np.concatenate(pts)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    p = pad * float(np.max(hi - lo))
    tep = 0.5 * (w[0] + w[-1])
    d = np.linalg.norm(w - tep, axis=1)
    lep = w[int(np.argmax(d))]
    chord = float(d.max()) or float(np.max(hi - lo)) or 1.0
    return {"near field": (lo[0] - p, hi[0] + p, lo[1] - p, hi[1] + p),
            "leading edge": _square(lep[0], lep[1], le * chord),
            "trailing edge": _square(tep[0], tep[1], te * chord)}


def _bounds(grid: Grid):
    lo, hi = grid.bbox()
    return (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))


def _check_window(window, what="window"):
    try:
        x0, x1, y0, y1 = (float(v) for v in window)
    except (TypeError, ValueError):
        raise CaseError(f"{what}: expected (x0, x1, y0, y1), got {window!r}") from None
    if not (x0 < x1 and y0 < y1) or not all(map(math.isfinite, (x0, x1, y0, y1))):
        raise CaseError(f"{what}: expected x0 < x1 and y0 < y1, got {window!r}")
    return x0, x1, y0, y1


# ------------------------------------------------------------------ 2-D drawing
def _lines_in(x: np.ndarray, window, every: int) -> list:
    """Grid lines of one 2-D block ``x`` (ni, nj, 2) with a segment that enters ``window``."""
    segs = []
    for axis in (0, 1):
        lines = x if axis == 1 else x.transpose(1, 0, 2)      # lines[n] runs along the other index
        lines = lines[::every] if lines.shape[0] > 1 else lines
        if window is None:
            segs += list(lines)
            continue
        x0, x1, y0, y1 = window
        a, b = lines[:, :-1], lines[:, 1:]
        if lines.shape[1] < 2:
            continue
        hit = ((np.minimum(a[..., 0], b[..., 0]) <= x1) & (np.maximum(a[..., 0], b[..., 0]) >= x0) &
               (np.minimum(a[..., 1], b[..., 1]) <= y1) & (np.maximum(a[..., 1], b[..., 1]) >= y0))
        segs += [lines[n] for n in np.flatnonzero(hit.any(axis=1))]
    return segs


def _set_window(ax, window, equal=True):
    if window is not None:
        ax.set_xlim(window[0], window[1])
        ax.set_ylim(window[2], window[3])
    if equal:
        ax.set_aspect("equal", adjustable="box")


def _style(ax, xlabel="x", ylabel="y"):
    ax.tick_params(labelsize=7)
    ax.set_xlabel(xlabel, fontsize=8, labelpad=1)
    ax.set_ylabel(ylabel, fontsize=8, labelpad=1)


def _check_2d(grid: Grid, what: str):
    if not isinstance(grid, Grid):
        raise GridValueError(f"{what}: expected a Grid, got {type(grid).__name__}")
    if grid.ndim != 2:
        raise GridValueError(f"{what}: needs a 2-D grid, got a {grid.ndim}-D one (use plot_cut or plot_wall_3d)")


def plot_grid_2d(ax, grid: Grid, *, window=None, color=GRID_COLOR, linewidth: float = 0.45, every: int = 1,
                 blocks=None, label: str | None = None, zorder: float = 2):
    """Draw the grid lines of a 2-D grid.

    Parameters
    ----------
    ax : matplotlib Axes
    grid : Grid (2-D)
    window : (x0, x1, y0, y1), optional
        Draw only the lines that enter it, and set the axes to it (equal
        scales either way).
    color, linewidth, zorder : matplotlib styles
    every : int
        Draw every n-th line of each family (dense grids).
    blocks : sequence of int, optional
        0-based blocks to draw (default all).
    label : str, optional
        Legend label (on the first block's lines).

    Returns
    -------
    list of LineCollection, one per block
    """
    from matplotlib.collections import LineCollection

    _check_2d(grid, "plot_grid_2d")
    if window is not None:
        window = _check_window(window)
    every = max(1, int(every))
    out = []
    for n, blk in enumerate(grid):
        if blocks is not None and n not in blocks:
            continue
        segs = _lines_in(blk.xyz[:, :, 0, :2], window, every)
        lc = LineCollection(segs, colors=color, linewidths=linewidth, zorder=zorder,
                            label=label if not out else None)
        ax.add_collection(lc)
        out.append(lc)
    if window is None:
        ax.autoscale_view()
    _set_window(ax, window)
    return out


def plot_walls_2d(ax, grid: Grid, walls, *, color=WALL_COLOR, linewidth: float = 1.2, zorder: float = 4):
    """Draw the wall patches of a 2-D grid as curves; returns the Line2D list."""
    out = []
    for w in wall_points(grid, walls):
        (ln,) = ax.plot(w[:, 0, 0], w[:, 0, 1], color=color, lw=linewidth, zorder=zorder)
        out.append(ln)
    return out


def _cells_in(p: np.ndarray, window) -> np.ndarray:
    """Mask (na-1, nb-1) of the cells of a point sheet ``p`` (na, nb, 2) whose centre lies in ``window``."""
    c = 0.25 * (p[:-1, :-1] + p[1:, :-1] + p[:-1, 1:] + p[1:, 1:])
    if window is None:
        return np.ones(c.shape[:2], dtype=bool)
    x0, x1, y0, y1 = window
    return (c[..., 0] >= x0) & (c[..., 0] <= x1) & (c[..., 1] >= y0) & (c[..., 1] <= y1)


def _log_or_nan(x):
    """log(x) where x > 0, NaN elsewhere (no warning)."""
    x = np.asarray(x, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(x > 0.0, np.log(np.where(x > 0.0, x, 1.0)), np.nan)


def _cmap(metric: str | None):
    """The colour map of a metric; volume ratio: inverted cells (ratio <= 0) in bright green."""
    import matplotlib

    cm = matplotlib.colormaps[_CMAPS.get(metric, "viridis")]
    return cm.with_extremes(bad=INVERTED_COLOR) if metric == "volume_ratio" else cm


def _colorbar(fig, mappable, metric: str, **kw):
    """A colour bar labelled with the metric (volume ratio: log ticks, arrows beyond the range)."""
    if metric == "volume_ratio":
        kw["extend"] = "both"
    cb = fig.colorbar(mappable, **kw)
    label = _LABELS[metric]
    if metric == "volume_ratio":
        lo, hi = mappable.norm.vmin, mappable.norm.vmax
        # ratios r and 1/r, the three widest that fit
        steps = [r for r in (1.01, 1.02, 1.05, 1.1, 1.2, 1.5, 2.0, 5.0, 10.0) if r <= hi * (1 + 1e-9)][-3:]
        ticks = sorted([1.0] + steps + [1.0 / r for r in steps if 1.0 / r >= lo * (1 - 1e-9)])
        cb.set_ticks(ticks, labels=[f"{t:.3g}" for t in ticks])
        label += "; green: <= 0 (inverted)"
    cb.set_label(label, fontsize=8)
    cb.ax.tick_params(labelsize=7)
    return cb


def _norm(metric: str, values: list, vmin=None, vmax=None):
    """A colour normalisation shared by every panel showing ``metric``."""
    from matplotlib.colors import FuncNorm, LogNorm, Normalize

    finite = [v[np.isfinite(v)] for v in values]
    allv = np.concatenate(finite) if finite else np.zeros(0)
    if allv.size == 0:
        return Normalize(0.0, 1.0)
    lo = float(allv.min()) if vmin is None else float(vmin)
    hi = float(allv.max()) if vmax is None else float(vmax)
    if metric == "volume_ratio":
        # log scale symmetric about 1, at most 10x either way (arrows beyond); ratios <= 0
        # (inverted cells) have no logarithm and take the colour map's "bad" colour
        pos = allv[allv > 0.0]
        if pos.size == 0:
            return Normalize(lo, hi)
        # the 99th percentile of |log ratio|: a few extreme cells do not wash the rest out
        span = min(max(float(np.percentile(np.abs(np.log(pos)), 99.0)), math.log(1.05)), math.log(RATIO_SPAN))
        return FuncNorm((_log_or_nan, np.exp), vmin=math.exp(-span), vmax=math.exp(span))
    if metric in ("aspect_ratio", "volume", "jacobian") and lo > 0.0 and hi / lo > 100.0:
        return LogNorm(lo, hi)
    if metric in ("skewness", "orthogonality", "orthogonality_change") and vmin is None:
        lo = 0.0
    if hi <= lo:
        hi = lo + (abs(lo) or 1.0) * 1e-6
    return Normalize(lo, hi)


def plot_cells_2d(ax, grid: Grid, values: list, *, cmap="viridis", norm=None, window=None, zorder: float = 1):
    """Fill the cells of a 2-D grid with colours from per-cell ``values``.

    Parameters
    ----------
    values : list of ndarray
        One per block, shape (ni-1, nj-1) or (ni-1, nj-1, 1); NaN cells are
        left transparent.
    cmap : str or Colormap
    norm : matplotlib Normalize, optional
        Default: linear over the finite values.

    Returns
    -------
    list of QuadMesh, one per block; ``mesh.get_array()`` holds the values.
    """
    from matplotlib.colors import Normalize

    _check_2d(grid, "plot_cells_2d")
    if len(values) != len(grid):
        raise GridValueError(f"values: {len(values)} array(s) for {len(grid)} block(s)")
    if norm is None:
        finite = np.concatenate([np.asarray(v)[np.isfinite(v)] for v in values])
        norm = Normalize(*(finite.min(), finite.max())) if finite.size else Normalize(0, 1)
    out = []
    for n, (blk, v) in enumerate(zip(grid, values)):
        x = blk.xyz[:, :, 0, :2]
        c = np.asarray(v, dtype=np.float64).reshape(x.shape[0] - 1, x.shape[1] - 1)
        mesh = ax.pcolormesh(x[..., 0], x[..., 1], np.ma.masked_invalid(c), cmap=cmap, norm=norm,
                             shading="flat", zorder=zorder, rasterized=True)
        out.append(mesh)
    _set_window(ax, None if window is None else _check_window(window))
    return out


def plot_metric_2d(ax, grid: Grid, metric: str, *, ref: Grid | None = None, walls=None, layers: int | None = None,
                   window=None, cmap=None, norm=None, lines: bool = True, colorbar: bool = True):
    """Cells of a 2-D grid coloured by a quality metric, grid lines on top, a colour bar.

    Returns
    -------
    (list of QuadMesh, Colorbar or None)
    """
    values = cell_values(grid, metric, ref=ref, walls=walls, layers=layers)
    if norm is None:      # the colour scale of the cells shown
        win = None if window is None else _check_window(window)
        norm = _norm(metric, [v[..., 0][_cells_in(b.xyz[:, :, 0, :2], win)] for b, v in zip(grid, values)])
    meshes = plot_cells_2d(ax, grid, values, cmap=cmap or _cmap(metric), norm=norm, window=window)
    if lines:
        plot_grid_2d(ax, grid, window=window, color="0.15", linewidth=0.25)
    cb = _colorbar(ax.figure, meshes[0], metric, ax=ax, shrink=0.85) if colorbar else None
    return meshes, cb


def _windows(grid: Grid, walls, windows):
    """[(name, window or None)] from "auto", a list of names/tuples, or one tuple."""
    if windows is None or windows == "auto":
        windows = _auto_windows(grid, walls)
    elif isinstance(windows, tuple) or (isinstance(windows, list) and windows and
                                        all(isinstance(v, (int, float)) for v in windows)):
        windows = [tuple(windows)]
    out = []
    zooms = None
    for w in windows:
        if isinstance(w, str):
            key = {"le": "leading edge", "te": "trailing edge", "near": "near field"}.get(w, w)
            if key == "all":
                out.append(("whole grid", _pad(_bounds(grid), 0.02)))
                continue
            if key not in ("leading edge", "trailing edge", "near field"):
                raise CaseError(f"unknown zoom window {w!r}: expected all, near, le, te or (x0, x1, y0, y1)")
            if not walls:
                raise CaseError(f"zoom window {w!r} needs wall patches (--walls or --case)")
            zooms = zooms or zoom_windows(grid, walls)
            out.append((key, zooms[key]))
        else:
            out.append(("x {:.4g}..{:.4g}, y {:.4g}..{:.4g}".format(*_check_window(w, "zoom")),
                        _check_window(w, "zoom")))
    return out


def _auto_windows(grid: Grid, walls) -> list:
    """near, le, te for an airfoil wall (closed and thin); else the whole grid, and the
    near field too when the walls are small in it."""
    if not walls:
        return ["all"]
    pts = wall_points(grid, walls)
    w = pts[0].reshape(-1, 3)[:, :2]
    te = 0.5 * (w[0] + w[-1])
    d = np.linalg.norm(w - te, axis=1)
    chord = float(d.max())
    if chord > 0.0 and np.linalg.norm(w[0] - w[-1]) <= 1e-2 * chord:
        u = (w[int(np.argmax(d))] - te) / chord
        thickness = float(np.ptp((w - te) @ np.array([-u[1], u[0]])))
        if thickness <= 0.4 * chord:
            return ["near field", "leading edge", "trailing edge"]
    allw = np.concatenate([p.reshape(-1, 3)[:, :2] for p in pts])
    x0, x1, y0, y1 = _bounds(grid)
    if float(np.max(np.ptp(allw, axis=0))) < 0.3 * max(x1 - x0, y1 - y0):
        return ["all", "near field"]
    return ["all"]


def _pad(window, f):
    x0, x1, y0, y1 = window
    p = f * max(x1 - x0, y1 - y0)
    return (x0 - p, x1 + p, y0 - p, y1 + p)


def plot_compare(grids, ref: Grid | None = None, walls=None, windows="auto", *, layout: str = "overlay",
                 color: str | None = None, layers: int | None = None, subtitles: dict | None = None,
                 suptitle: str | None = None, figsize=None, transpose: bool | None = None):
    """The memo's figure 4 layout: one column per grid, one row per zoom window.

    Parameters
    ----------
    grids : Grid or dict of label -> Grid
        The grids to show (e.g. ``{"plain TFI": g1, "quaternion TFI": g2}``),
        left to right; all 2-D with the same blocks.
    ref : Grid, optional
        The reference grid.  ``layout="overlay"``: drawn in light grey under
        every grid (not under cells coloured by a metric); ``"side"``: in its
        own first column.
    walls : patch specs, optional
        Drawn in red; the zoom windows follow each column's own wall.
    windows : "auto", list, or (x0, x1, y0, y1)
        Rows: names ``"all"`` (whole grid), ``"near"``, ``"le"``,
        ``"te"`` (:func:`zoom_windows`) or explicit windows.  ``"auto"``:
        near field, leading and trailing edge when walls are given, else the
        whole grid.
    layout : {"overlay", "side"}
    color : str, optional
        A metric of :data:`COLOR_METRICS` to colour the cells by, with one
        colour scale (and colour bar) over the cells the panels show.
    layers : int, optional
        Layers of the orthogonality metrics (default: every layer).
    subtitles : dict of label -> str, optional
        Extra text under the first row's title of that column.
    suptitle : str, optional
    figsize : (width, height) inches, optional
    transpose : bool, optional
        Windows along a row instead of a column; default: when there is a
        single column.

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure

    if isinstance(grids, Grid):
        grids = {"grid": grids}
    if not grids:
        raise CaseError("plot_compare: no grid to draw")
    if layout not in ("overlay", "side"):
        raise CaseError(f"layout: expected 'overlay' or 'side', got {layout!r}")
    for label, g in grids.items():
        _check_2d(g, f"grid {label!r}")
        _check_ref(g, ref)
    columns = dict(grids)
    if ref is not None and layout == "side":
        columns = {"reference": ref, **columns}
    values = {}
    norm = None
    if color is not None:
        for label, g in columns.items():
            # the reference column is not coloured by a metric relative to itself
            if not (g is ref and color in ("volume_ratio", "orthogonality_change")):
                values[label] = cell_values(g, color, ref=ref, walls=walls, layers=layers)
    rows = {label: _windows(g, walls, windows) for label, g in columns.items()}
    # the overviews show one region in every column; the zooms follow each column's wall
    for r, (where, _) in enumerate(next(iter(rows.values()))):
        if where in ("near field", "whole grid"):
            wins = np.array([rows[label][r][1] for label in rows])
            union = (wins[:, 0].min(), wins[:, 1].max(), wins[:, 2].min(), wins[:, 3].max())
            for label in rows:
                rows[label][r] = (where, union)
    if color is not None:
        # one colour scale over the cells the panels show
        shown = []
        for label, vs in values.items():
            for blk, v in zip(columns[label], vs):
                inside = np.zeros(v.shape[:2], dtype=bool)
                for _, win in rows[label]:
                    inside |= _cells_in(blk.xyz[:, :, 0, :2], win)
                shown.append(v[..., 0][inside])
        norm = _norm(color, shown)
    nrow = len(next(iter(rows.values())))
    ncol = len(columns)
    if transpose is None:
        transpose = ncol == 1 and nrow > 1
    shape = (ncol, nrow) if transpose else (nrow, ncol)
    # 5 inches per panel across (8 for a single panel), the height from the window's shape
    pw = 8.0 if nrow * ncol == 1 else 5.0

    def tall(win):
        # the axes box is ~0.7 in narrower than the panel (tick labels); title and x label ~0.75 in
        return (pw - 0.7) * min(1.6, max(0.3, (win[3] - win[2]) / (win[1] - win[0]))) + 0.75
    heights = [max(tall(rows[label][r][1]) for label in rows) for r in range(nrow)]
    if figsize is None:
        if transpose:
            figsize = (pw * nrow, max(heights) * ncol + 0.5 + (0.8 if color else 0.0))
        else:
            figsize = (pw * ncol + (1.0 if color else 0.0), sum(heights) + 0.5)
    fig = Figure(figsize=figsize, layout="constrained")
    axes = fig.subplots(*shape, squeeze=False,
                        gridspec_kw=None if transpose else {"height_ratios": heights})
    mesh = None
    for c, (label, g) in enumerate(columns.items()):
        for r, (where, win) in enumerate(rows[label]):
            ax = axes[c, r] if transpose else axes[r, c]
            if label in values:
                m = plot_cells_2d(ax, g, values[label], cmap=_cmap(color), norm=norm, window=win)
                mesh = mesh or m[0]
            if ref is not None and layout == "overlay" and g is not ref and label not in values:
                plot_grid_2d(ax, ref, window=win, color=REF_COLOR, linewidth=0.5, zorder=1.5)
            if color is None:
                plot_grid_2d(ax, g, window=win, color=GRID_COLOR, linewidth=0.45)
            else:
                plot_grid_2d(ax, g, window=win, color="0.15", linewidth=0.25)
            if walls:
                plot_walls_2d(ax, g, walls)
            _style(ax)
            title = f"{label}: {where}"
            if r == 0 and subtitles and label in subtitles:
                title += "\n" + subtitles[label]
            ax.set_title(title, fontsize=9)
    if mesh is not None:
        _colorbar(fig, mesh, color, ax=axes.ravel().tolist(), shrink=0.6, aspect=40,
                  location="bottom" if transpose else "right")
    if suptitle:
        fig.suptitle(suptitle, fontsize=9)
    return fig


# ------------------------------------------------------------------ 3-D
@dataclass(frozen=True)
class Cut:
    """A constant-index plane of one block (0-based): ``axis`` "i", "j" or "k" at ``index``."""

    block: int
    axis: str
    index: int

    def __str__(self) -> str:
        return f"{self.block + 1}:{self.axis}={self.index + 1}"


def parse_cut(text: str) -> Cut:
    """``"B:AXIS=N"`` (1-based, e.g. ``"1:k=23"``) -> :class:`Cut` (0-based)."""
    try:
        b, rest = str(text).split(":", 1)
        axis, n = rest.split("=", 1)
        block, index = int(b) - 1, int(n) - 1
        axis = axis.strip().lower()
    except ValueError:
        raise CaseError(f"cut {text!r}: expected BLOCK:AXIS=N, e.g. 1:k=23 (1-based)") from None
    if axis not in ("i", "j", "k") or block < 0 or index < 0:
        raise CaseError(f"cut {text!r}: expected BLOCK:AXIS=N with AXIS i, j or k and BLOCK, N >= 1")
    return Cut(block, axis, index)


def _plane(grid: Grid, cut: Cut) -> np.ndarray:
    if not 0 <= cut.block < len(grid):
        raise CaseError(f"cut {cut}: the grid has {len(grid)} block(s)")
    d = "ijk".index(cut.axis)
    dims = grid[cut.block].dims
    if not 0 <= cut.index < dims[d]:
        raise CaseError(f"cut {cut}: block {cut.block + 1} has {cut.axis} = 1..{dims[d]}")
    idx = [slice(None)] * 3
    idx[d] = cut.index
    return grid[cut.block].xyz[tuple(idx)]            # (na, nb, 3)


def _projection(p: np.ndarray):
    """The two coordinates (indices into xyz) along which the points spread most, in order."""
    ext = np.ptp(p.reshape(-1, 3), axis=0)
    return tuple(sorted(np.argsort(ext)[::-1][:2]))


def _cut_values(values: list, cut: Cut) -> np.ndarray:
    """The cells of the layer on a cut's upper side (lower side for the last plane), (na-1, nb-1)."""
    d = "ijk".index(cut.axis)
    vals = np.asarray(values[cut.block])
    idx = [slice(None)] * 3
    idx[d] = min(cut.index, vals.shape[d] - 1)
    return vals[tuple(idx)]


def _wall_face_values(grid: Grid, spec, vals: np.ndarray) -> np.ndarray:
    """The cells on a wall patch, (na-1, nb-1), from one block's per-cell values."""
    return vals[face_cells(grid[spec.block].dims, spec.face, spec.range)]


def _wall_values(grid: Grid, walls, values: list) -> np.ndarray:
    return np.concatenate([_wall_face_values(grid, s, np.asarray(values[s.block])).ravel()
                           for s in resolve_patch_specs(grid, walls, "walls")])


def plot_cut(ax, grid: Grid, cut: Cut, *, ref: Grid | None = None, values: list | None = None, cmap="viridis",
             norm=None, window=None, coords=None, linewidth: float = 0.4):
    """Draw a constant-index plane of a 3-D block, projected on two coordinates.

    Parameters
    ----------
    cut : Cut
    ref : Grid, optional
        Its same plane drawn in light grey underneath (not under coloured cells).
    values : list of ndarray, optional
        Per-cell values of the whole grid (:func:`cell_values`); the cells
        of the layer on the plane's upper side (lower side for the last
        plane) are filled with their colours.
    coords : (int, int), optional
        Coordinates to project on (0 = x, 1 = y, 2 = z); default the two
        along which the plane spreads most.
    window : (u0, u1, v0, v1), optional, in those coordinates.

    Returns
    -------
    dict with ``lines`` (LineCollection), ``mesh`` (QuadMesh or None), ``coords``
    """
    from matplotlib.collections import LineCollection

    if grid.ndim != 3:
        raise GridValueError("plot_cut: needs a 3-D grid (use plot_grid_2d for 2-D grids)")
    p = _plane(grid, cut)
    u, v = coords if coords is not None else _projection(p)
    mesh = None
    if values is not None:
        mesh = ax.pcolormesh(p[..., u], p[..., v], np.ma.masked_invalid(_cut_values(values, cut)), cmap=cmap,
                             norm=norm, shading="flat", zorder=1, rasterized=True)
    if ref is not None and values is None:
        pr = _plane(ref, cut)
        ax.add_collection(LineCollection(_lines_in(pr[..., [u, v]], window, 1), colors=REF_COLOR,
                                         linewidths=linewidth + 0.1, zorder=1.5))
    lc = LineCollection(_lines_in(p[..., [u, v]], window, 1), colors=GRID_COLOR,
                        linewidths=linewidth if values is None else 0.25, zorder=2)
    ax.add_collection(lc)
    if window is None:
        ax.autoscale_view()
    _set_window(ax, None if window is None else _check_window(window))
    _style(ax, "xyz"[u], "xyz"[v])
    return {"lines": lc, "mesh": mesh, "coords": (u, v)}


def default_cuts(grid: Grid, walls) -> list:
    """Two sections through the first wall: the planes of its block across the
    wall's second running index at its middle and at its end (for a wing
    with its span along that index: mid-span and tip).  Without walls: the
    middle k- and j-planes of block 1."""
    specs = resolve_patch_specs(grid, walls, "walls") if walls else []
    if not specs:
        dims = grid[0].dims
        return [Cut(0, "k", dims[2] // 2), Cut(0, "j", dims[1] // 2)]
    s = specs[0]
    axis = "ijk"[face_axes(s.face)[2]]
    b0, b1 = s.range[1]
    return [Cut(s.block, axis, (b0 + b1) // 2), Cut(s.block, axis, b1)]


def _wall_in_cut(grid: Grid, walls, cut: Cut):
    """Points (n, 3) of the walls of the cut's block that lie in the cut plane (None if none)."""
    if not walls:
        return None
    pts = []
    for spec, w in zip(resolve_patch_specs(grid, walls, "walls"), wall_points(grid, walls)):
        if spec.block != cut.block:
            continue
        d, *run = face_axes(spec.face)
        axis = "ijk".index(cut.axis)
        if axis in run:
            r = run.index(axis)
            lo, hi = spec.range[r]
            if lo <= cut.index <= hi:
                pts.append(w[cut.index - lo] if r == 0 else w[:, cut.index - lo])
        elif cut.index == face_layer(grid[spec.block].dims, spec.face):
            pts.append(w.reshape(-1, 3))
    return np.concatenate(pts) if pts else None


def plot_wall_3d(ax, grid: Grid, walls, *, values: list | None = None, cmap="viridis", norm=None,
                 edgecolor="0.25", linewidth: float = 0.15, elev: float = 25.0, azim: float = -60.0):
    """Draw the wall patches of a 3-D grid as a surface on a 3-D axes.

    Parameters
    ----------
    ax : mpl_toolkits.mplot3d Axes3D (``fig.add_subplot(projection="3d")``)
    walls : patch specs
    values : list of ndarray, optional
        Per-cell values of the whole grid; each wall face takes the value of
        the cell it bounds.  Default: a grey surface shaded by its normals.

    Returns
    -------
    list of Poly3DCollection, one per wall; with ``values``, ``get_array()``
    holds the wall faces' values.
    """
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    if grid.ndim != 3:
        raise GridValueError("plot_wall_3d: needs a 3-D grid")
    specs = resolve_patch_specs(grid, walls, "walls")
    if not specs:
        raise CaseError("plot_wall_3d: no wall patch given (--walls or --case)")
    out = []
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for spec, w in zip(specs, wall_points(grid, walls)):
        quads = np.stack([w[:-1, :-1], w[1:, :-1], w[1:, 1:], w[:-1, 1:]], axis=2)   # (na-1, nb-1, 4, 3)
        verts = quads.reshape(-1, 4, 3)
        lo = np.minimum(lo, w.reshape(-1, 3).min(axis=0))
        hi = np.maximum(hi, w.reshape(-1, 3).max(axis=0))
        if values is not None:
            fv = _wall_face_values(grid, spec, np.asarray(values[spec.block])).reshape(-1)
            coll = Poly3DCollection(verts, cmap=cmap, norm=norm, edgecolors=edgecolor, linewidths=linewidth)
            coll.set_array(np.ma.masked_invalid(fv))
        else:
            n = np.cross(quads[:, :, 2] - quads[:, :, 0], quads[:, :, 3] - quads[:, :, 1]).reshape(-1, 3)
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
            light = np.array([-0.4, -0.5, 0.75])
            shade = 0.55 + 0.4 * np.abs(n @ (light / np.linalg.norm(light)))
            fc = np.clip(shade, 0, 1)[:, None] * np.array([0.85, 0.87, 0.92])
            coll = Poly3DCollection(verts, facecolors=fc, edgecolors=edgecolor, linewidths=linewidth)
        ax.add_collection3d(coll)
        out.append(coll)
    mid = 0.5 * (lo + hi)
    half = 0.5 * float(np.max(hi - lo)) or 1.0
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=elev, azim=azim)
    ax.set_xlabel("x", fontsize=8)
    ax.set_ylabel("y", fontsize=8)
    ax.set_zlabel("z", fontsize=8)
    ax.tick_params(labelsize=6)
    return out


# ------------------------------------------------------------------ whole figures
def grid_figure(grid: Grid, ref: Grid | None = None, walls=None, *, zoom="auto", color: str | None = None,
                layout: str = "overlay", cuts=None, layers: int | None = None, size=None, dpi: int = 100,
                title: str | None = None):
    """The figure of ``tfi-quat plot``: a 2-D grid in zoom windows, or a 3-D grid's
    wall surface and cuts.

    Parameters
    ----------
    grid : Grid
    ref : Grid, optional
        The reference (undeformed) grid: overlaid in grey, or its own column
        with ``layout="side"``.
    walls : patch specs, optional
    zoom : "auto", list of names or windows, or (x0, x1, y0, y1)
        2-D: the windows of :func:`plot_compare`.  3-D: one window applied
        to every cut (in the cut's projected coordinates), or "auto" (whole).
    color : str, optional
        Metric to colour cells by (:data:`COLOR_METRICS`).
    cuts : list of Cut or "B:AXIS=N" strings, optional
        3-D: the planes to draw (default :func:`default_cuts`).
    size : (width, height) pixels, optional
        Default: from the number of panels.
    dpi : int
    title : str, optional

    Returns
    -------
    matplotlib.figure.Figure, ``size`` pixels at ``dpi`` when saved with that dpi
    """
    from matplotlib.figure import Figure

    if not isinstance(grid, Grid):
        raise GridValueError(f"grid: expected a Grid, got {type(grid).__name__}")
    if size is not None:
        w, h = (int(v) for v in size)
        if w < 100 or h < 100:
            raise CaseError(f"size: at least 100 x 100 pixels, got {w} x {h}")
        figsize = (w / dpi, h / dpi)
    else:
        figsize = None
    if grid.ndim == 2:
        fig = plot_compare({"grid" if ref is None else "deformed": grid}, ref=ref, walls=walls, windows=zoom,
                           layout=layout, color=color, layers=layers, figsize=figsize, suptitle=title)
        return fig
    _check_ref(grid, ref)
    cuts = [parse_cut(c) if isinstance(c, str) else c for c in (cuts or default_cuts(grid, walls))]
    for c in cuts:
        _plane(grid, c)
    win = None
    if zoom not in (None, "auto", "all"):
        if isinstance(zoom, list) and len(zoom) == 1:
            zoom = zoom[0]
        if isinstance(zoom, str):
            raise CaseError(f"zoom {zoom!r}: a 3-D figure takes an explicit window U0,U1,V0,V1 for its cuts")
        win = _check_window(zoom, "zoom")
    values = cell_values(grid, color, ref=ref, walls=walls, layers=layers) if color else None
    # each cut: its projection and window (the near field of the wall's section in it)
    views = []
    for c in cuts:
        cwin, coords = win, None
        w = _wall_in_cut(grid, walls, c)
        if w is not None:
            coords = _projection(_plane(grid, c))
            if cwin is None:
                lo, hi = w[:, coords].min(axis=0), w[:, coords].max(axis=0)
                p = NEAR_PAD * float(np.max(hi - lo))
                cwin = (lo[0] - p, hi[0] + p, lo[1] - p, hi[1] + p)
        views.append((c, w, cwin, coords))
    norm = None
    if values is not None:
        # one colour scale over what is drawn: the wall faces and the cut cells in their windows
        shown = [_wall_values(grid, walls, values)] if walls else []
        for c, _, cwin, coords in views:
            p = _plane(grid, c)
            uv = coords if coords is not None else _projection(p)
            shown.append(_cut_values(values, c)[_cells_in(p[..., list(uv)], cwin)])
        norm = _norm(color, shown)
    cmap = _cmap(color)
    has_wall = bool(walls)
    ncut = len(cuts)
    # the wall in perspective on the left, spanning the rows; the cuts stacked on the right
    if figsize is None:
        figsize = ((6.5 if has_wall else 0.0) + 6.5, max(5.0, 2.9 * ncut) + (0.8 if color else 0.0) + 0.4)
    fig = Figure(figsize=figsize, layout="constrained")
    gs = fig.add_gridspec(ncut, 2 if has_wall else 1)
    mappable = None
    axes = []
    if has_wall:
        ax3 = fig.add_subplot(gs[:, 0], projection="3d")
        colls = plot_wall_3d(ax3, grid, walls, values=values, cmap=cmap, norm=norm)
        ax3.set_title("wall surface" + (f" (coloured by the {color.replace('_', ' ')} of the wall cells)"
                                        if color else ""), fontsize=9)
        if values is not None:
            mappable = colls[0]
        axes.append(ax3)
    for n, (c, w, cwin, coords) in enumerate(views):
        ax = fig.add_subplot(gs[n, 1 if has_wall else 0])
        res = plot_cut(ax, grid, c, ref=ref, values=values, cmap=cmap, norm=norm, window=cwin, coords=coords)
        if w is not None:
            ax.plot(w[:, res["coords"][0]], w[:, res["coords"][1]], color=WALL_COLOR, lw=1.2, zorder=4)
        if res["mesh"] is not None:
            mappable = mappable or res["mesh"]
        ax.set_title(f"cut: block {c.block + 1}, {c.axis} = {c.index + 1}", fontsize=9)
        axes.append(ax)
    if mappable is not None:
        _colorbar(fig, mappable, color, ax=axes, shrink=0.5, aspect=40, location="bottom")
    if title:
        fig.suptitle(title, fontsize=9)
    return fig


def save_figure(fig, path, dpi: int = 100, overwrite: bool = True) -> None:
    """Write ``fig`` as a PNG (or any format matplotlib knows from the extension), atomically.

    The image has ``fig``'s size in inches times ``dpi`` pixels (no tight
    bounding box, so the requested size is the size written).
    """
    from pathlib import Path

    from .errors import OverwriteError
    from .io._atomic import atomic_output

    target = Path(path)
    if target.exists() and not overwrite:
        raise OverwriteError(f"{target}: exists; refusing to overwrite it (use --force)")
    fmt = target.suffix.lstrip(".").lower() or "png"
    with atomic_output(target) as fh:
        fig.savefig(fh, format=fmt, dpi=dpi)
