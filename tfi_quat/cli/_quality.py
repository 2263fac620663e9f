"""``tfi-quat quality GRID``: cell volumes, Jacobians, skewness, aspect ratio, volume ratio,
negative cells and near-wall orthogonality of a grid."""

from __future__ import annotations

import argparse
import json

from ..errors import CaseError, GridValueError
from ._common import add_base_arg, case_and_grid, finite, grid_walls, non_negative_int, read_grid, walls_arg

HELP = "grid quality: volumes, Jacobians, skewness, aspect ratio, negative cells, near-wall orthogonality"
DESCRIPTION = """Measure the quality of GRID: per block and over the grid, the min, mean and
max of the cell volume (area in 2-D), the smallest corner Jacobian and scaled
Jacobian, the equiangle skewness and the aspect ratio; the negative cells
(volume <= 0), the cells with a corner Jacobian <= 0 and the degenerate ones,
each with the first few (block, i, j, k), 1-based.  With --ref (the grid before
deformation) also the cell volume ratio GRID / REF.  With walls (--walls, or
the case file's, else a CGNS grid's own wall boundary conditions) the angle
between the wall normal and the first --layers grid lines off the wall, and
with --ref its change.  Definitions:
docs/quality.md.  Exit status 0, or 1 with --fail-on-negative when a cell
has a volume <= 0; 2 on bad input."""


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("grid", nargs="?", metavar="GRID",
                   help="grid file (Plot3D, HDF5 or CGNS); default: the case file's grid")
    p.add_argument("--ref", metavar="REF", help="the grid before deformation (same blocks and dimensions)")
    p.add_argument("--walls", "--wall", dest="walls", action="extend", nargs="+", default=[],
                   metavar="B:FACE[:RANGE]", help="wall patches, 1-based (e.g. 1:jmin:65-193)")
    p.add_argument("--case", metavar="CASE.toml", help="case file: its grid and walls")
    add_base_arg(p)
    p.add_argument("--layers", type=int, default=5, metavar="K",
                   help="grid lines off the wall measured per wall point (default 5)")
    p.add_argument("--rtol", type=finite, default=1e-12,
                   help="degenerate cell: |volume| <= RTOL * (longest edge)^3 (default 1e-12)")
    p.add_argument("--locations", type=non_negative_int, default=10, metavar="N",
                   help="list the first N bad cells of each kind (default 10)")
    p.add_argument("--json", action="store_true", help="print one JSON object (indices 1-based)")
    p.add_argument("--fail-on-negative", action="store_true",
                   help="exit with status 1 when a cell has a volume <= 0 (for CI scripts)")


def run(args) -> int:
    from ..quality import quality_report

    case, path = case_and_grid(args)
    if args.layers < 1:
        raise CaseError(f"--layers must be >= 1, got {args.layers}")
    if args.rtol < 0:
        raise CaseError(f"--rtol must be >= 0, got {args.rtol:g}")
    walls = walls_arg(args, case)
    where = args.case if (case is not None and not args.walls) else "--walls"
    grid = read_grid(args, path)
    if not walls:
        walls, where = grid_walls(grid), f"the wall boundary conditions of {path}"
    ref = read_grid(args, args.ref, strict=False) if args.ref else None
    try:
        report = quality_report(grid, ref=ref, walls=walls or None, layers=args.layers, rtol=args.rtol,
                                max_locations=args.locations)
    except GridValueError as exc:
        raise GridValueError(f"{args.ref}: does not match {path}: {exc}") from None
    except CaseError as exc:
        raise CaseError(f"{where}: {exc} (grid {path})") from None
    if args.json:
        d = {"grid": str(path), "reference": None if args.ref is None else str(args.ref)}
        d.update(report.to_dict(one_based=True))
        print(json.dumps(d, indent=2, allow_nan=False))
    else:
        print(f"{path}" + (f" against reference {args.ref}" if args.ref else ""))
        print(report.summary())
    if args.fail_on_negative and report.negative:
        return 1
    return 0
