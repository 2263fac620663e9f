"""``tfi-quat plot GRID -o FIG.png``: pictures of a grid, its zooms, its quality."""

from __future__ import annotations

import argparse

from ..errors import CaseError, GridValueError
from ._common import add_base_arg, case_and_grid, check_output, grid_walls, read_grid, walls_arg

HELP = "draw a grid (2-D: zoom windows, reference overlaid; 3-D: wall surface and cuts) into a PNG"
DESCRIPTION = """Draw GRID into FIG (PNG, or another format matplotlib knows from the extension).

2-D: one panel per zoom window (--zoom, repeatable: all, near, le, te, or
X0,X1,Y0,Y1; default near, le, te with walls, else all), the walls in red,
the reference grid (--ref) in grey underneath (--layout overlay) or in its
own column (--layout side).  3-D: the wall surface in perspective and
constant-index cuts through the volume (--cut B:AXIS=N, 1-based, repeatable;
default two planes through the first wall's block), --zoom X0,X1,Y0,Y1 then
applies to the cuts in their projected coordinates.  --color METRIC fills
the cells with a quality metric (volume, jacobian, scaled_jacobian,
skewness, aspect_ratio, volume_ratio (needs --ref), orthogonality and
orthogonality_change (need walls; the latter --ref)) with a colour bar.
The walls: --walls, else the case file's, else a CGNS grid's own wall
boundary conditions."""


def _size(text: str):
    try:
        w, h = (int(v) for v in text.lower().replace("x", ",").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels, e.g. 1600x1000, got {text!r}") from None
    return w, h


def _zoom(text: str):
    t = text.strip().lower()
    if t in ("all", "near", "le", "te"):
        return t
    try:
        v = tuple(float(x) for x in t.split(","))
    except ValueError:
        v = ()
    if len(v) != 4:
        raise argparse.ArgumentTypeError(f"expected all, near, le, te or X0,X1,Y0,Y1, got {text!r}")
    return v


def add_args(p: argparse.ArgumentParser) -> None:
    from ..plot import COLOR_METRICS

    p.add_argument("grid", nargs="?", metavar="GRID",
                   help="grid file (Plot3D, HDF5 or CGNS); default: the case file's grid")
    p.add_argument("-o", "--output", required=True, metavar="FIG.png", help="image file to write")
    p.add_argument("--ref", metavar="REF", help="reference (undeformed) grid, same blocks and dimensions")
    p.add_argument("--walls", "--wall", dest="walls", action="extend", nargs="+", default=[],
                   metavar="B:FACE[:RANGE]", help="wall patches, 1-based")
    p.add_argument("--case", metavar="CASE.toml", help="case file: its grid and walls")
    add_base_arg(p)
    p.add_argument("--zoom", type=_zoom, action="append", metavar="WINDOW",
                   help="all, near, le, te or X0,X1,Y0,Y1 (repeatable: one panel each)")
    p.add_argument("--color", choices=COLOR_METRICS, metavar="METRIC",
                   help="colour the cells by: " + ", ".join(COLOR_METRICS))
    p.add_argument("--layout", choices=("overlay", "side"), default="overlay",
                   help="reference under the grid (overlay, default) or in its own column (side)")
    p.add_argument("--cut", action="append", default=[], metavar="B:AXIS=N",
                   help="3-D: constant-index plane, e.g. 1:k=23 (1-based, repeatable)")
    p.add_argument("--layers", type=int, default=None, metavar="K",
                   help="layers off the wall coloured by the orthogonality metrics (default: every layer)")
    p.add_argument("--size", type=_size, metavar="WxH", help="image size in pixels (default: from the panels)")
    p.add_argument("--dpi", type=int, default=100, help="dots per inch (default 100)")
    p.add_argument("--title", help="figure title (default: the file names)")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")


def run(args) -> int:
    from ..plot import grid_figure, save_figure

    case, path = case_and_grid(args)
    if args.layers is not None and args.layers < 1:
        raise CaseError(f"--layers must be >= 1, got {args.layers}")
    if args.dpi < 10:
        raise CaseError(f"--dpi must be >= 10, got {args.dpi}")
    check_output(args.output, args.force, inputs=[path, args.ref, args.case])
    walls = walls_arg(args, case)
    grid = read_grid(args, path)
    if not walls:
        walls = grid_walls(grid)
    if args.cut and grid.ndim == 2:
        raise CaseError(f"{path}: --cut {args.cut[0]}: cuts are planes through a 3-D grid; this grid is 2-D")
    ref = read_grid(args, args.ref, strict=False) if args.ref else None
    title = args.title
    if title is None:
        title = str(path)
        if ref is not None:
            grey = args.layout == "overlay" and not args.color
            title += f" ({'grey' if grey else 'reference'}: {args.ref})"
    zoom = args.zoom if args.zoom else "auto"
    try:
        fig = grid_figure(grid, ref=ref, walls=walls or None, zoom=zoom, color=args.color, layout=args.layout,
                          cuts=args.cut or None, layers=args.layers, size=args.size, dpi=args.dpi, title=title)
    except GridValueError as exc:
        raise GridValueError(f"{args.ref or path}: {exc}") from None
    except CaseError as exc:
        raise CaseError(f"{path}: {exc}") from None
    save_figure(fig, args.output, dpi=args.dpi)
    w, h = fig.get_size_inches() * args.dpi
    print(f"wrote {args.output} ({round(w)} x {round(h)} pixels)")
    return 0
