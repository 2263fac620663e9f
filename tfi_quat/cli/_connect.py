"""``tfi-quat connect``: find interfaces and patches, print them, optionally save the map."""

from __future__ import annotations

import sys
from pathlib import Path

from ..errors import ConnectivityError
from ..io import TARGETS
from ._common import finite

HELP = "find block interfaces and boundary patches; print them; save as .json or .nmf"
DESCRIPTION = """\
Find the point-matched interfaces of a multiblock grid (coincident boundary
points, grown into maximal rectangles with a CGNS Transform) and classify the
rest of the boundary into patches.  Patches are given 1-based as
BLOCK:FACE[:A1-A2,B1-B2] (FACE = imin imax jmin jmax kmin kmax; A, B are the
face's running indices: i faces (j,k), j faces (i,k), k faces (i,j)).  A wall
given as a whole face is reduced by the interfaces on it.  Unclassified planar
patches that touch a wall become symmetry (reported in the notes).

--for cfl3d prints, instead of the table, the sections of a CFL3D input deck
for the grid file 'tfi-quat convert GRID OUT --for cfl3d' writes: grid
dimensions (LT8), boundary-condition segments (LT13-LT19: interfaces as
bctype 0, walls 1005 inviscid surface, fixed 1003 inflow/outflow, symmetry
1001, free 1002, collapsed 1013, the span faces of a 2-D grid 1002) and
the 1-1 blocking data (LT24-LT26), with the index mapping in '#' comment
lines.  --bc KIND=BCTYPE changes a kind's bctype (e.g. --bc wall=2004 for a
viscous run)."""


def add_args(parser) -> None:
    parser.add_argument("grid", metavar="GRID", help="grid file (Plot3D or HDF5)")
    parser.add_argument("--wall", action="append", default=[], metavar="B:FACE[:range]",
                        help="a wall patch (repeatable)")
    parser.add_argument("--symmetry", action="append", default=[], metavar="B:FACE[:range]",
                        help="a symmetry patch (repeatable)")
    parser.add_argument("--fixed", action="append", default=[], metavar="B:FACE[:range]",
                        help="a fixed patch (repeatable)")
    parser.add_argument("--default", choices=("fixed", "free", "wall", "symmetry"), default="fixed",
                        help="kind of the unclassified boundary (default: fixed)")
    parser.add_argument("--tol", type=finite, default=None, metavar="T",
                        help="absolute matching distance (default: RTOL x local spacing)")
    parser.add_argument("--rtol", type=finite, default=1e-6, metavar="R",
                        help="matching tolerance relative to the smallest adjacent edge (default 1e-6)")
    parser.add_argument("--no-auto-symmetry", action="store_true",
                        help="do not make planar patches next to walls symmetry")
    parser.add_argument("-o", "--output", metavar="MAP", default=None,
                        help="save the connectivity: MAP.json (CGNS-style ranges) or MAP.nmf (Neutral Map File)")
    parser.add_argument("--nmf-faces", choices=("3d", "2d"), default="3d",
                        help="face numbering of a written .nmf for a 2-D grid (default 3d: GEOLAB)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing MAP")
    parser.add_argument("--for", dest="target", choices=TARGETS,
                        help="print the solver's input-deck sections instead of the table")
    parser.add_argument("--bc", action="append", default=[], metavar="KIND=BCTYPE",
                        help="--for cfl3d: bctype of a patch kind (wall, fixed, symmetry, free, "
                             "collapsed; repeatable), e.g. wall=2004")


def connect_grid(grid, args, out=None) -> int:
    """The command on a grid already in memory (``run`` reads the grid, then calls this)."""
    from ..topology import connect
    out = sys.stdout if out is None else out
    target = None
    if args.output is not None:
        target = Path(args.output)
        if target.suffix.lower() not in (".json", ".nmf"):
            raise ConnectivityError(f"{target}: unknown map extension {target.suffix!r}: use .json or .nmf")
    bctypes = _bctypes(args)
    conn = connect(grid, tol=args.tol, rtol=args.rtol, walls=args.wall, symmetry=args.symmetry,
                   fixed=args.fixed, default=args.default, auto_symmetry=not args.no_auto_symmetry)
    if args.target is not None:
        from ..io.cfl3d import input_deck
        print(input_deck(conn, bctypes), end="", file=out)
    else:
        print(conn.table(), file=out)
    if target is not None:
        if target.suffix.lower() == ".json":
            conn.to_json(target, overwrite=args.force)
        else:
            conn.to_nmf(target, overwrite=args.force, convention=args.nmf_faces)
        # after deck sections, a '#' comment line (the sections stay pasteable)
        print(f"# wrote {target}" if args.target else f"\nwrote {target}", file=out)
    return 0


def _bctypes(args) -> dict:
    """``--bc KIND=BCTYPE`` options as a dict (only with ``--for``)."""
    if args.bc and args.target is None:
        raise ConnectivityError("--bc applies to --for cfl3d")
    out = {}
    for text in args.bc:
        kind, sep, value = text.partition("=")
        try:
            number = int(value)
        except ValueError:
            number = None
        if not sep or number is None:
            raise ConnectivityError(f"--bc {text!r}: expected KIND=BCTYPE, e.g. wall=2004")
        out[kind.strip().lower()] = number
    if args.target is not None:
        from ..io.cfl3d import bctype_table
        bctype_table(out)       # refuse a bad kind or bctype before the search
    return out


def run(args) -> int:
    from .. import read
    grid = read(args.grid)
    return connect_grid(grid, args)
