"""``tfi-quat convert IN OUT``: rewrite a grid in another format or variant.

The output format is ``--format``, else the one OUT's extension names, else
the input's.  Plot3D to Plot3D keeps the input's variant (``like=grid``) and
the variant options change only what they name; HDF5 to HDF5 keeps the
compression and the ``/extra`` JSON; CGNS to CGNS keeps every node of the
input but the coordinates.  A CGNS output gets the input's boundary
conditions and interfaces (a CGNS input's), or those ``--connect`` finds
(:func:`tfi_quat.topology.connect`) or ``--connectivity``/``--nmf`` loads.
An existing OUT (the input included) is replaced only with ``--force``.
``--for cfl3d`` writes the grid file NASA's CFL3D reads
(:mod:`tfi_quat.io.cfl3d`); ``--from cfl3d`` reads one back.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from .. import write
from ..errors import CaseError, GridFormatError, OverwriteError
from ..io import TARGETS, format_for
from ._info import add_input_args, describe_variant, format_name, one_line_errors, read_input

HELP = "convert a grid to another format or file variant (Plot3D, HDF5, CGNS)"
DESCRIPTION = """\
Convert a grid file.  The output format is --format, else the one OUT's
extension names, else the input's.  Plot3D to Plot3D writes the input's
variant unless an option below changes it; HDF5 to HDF5 keeps the
compression and the extra JSON data; CGNS to CGNS keeps every node of the
input but the coordinates.  A CGNS output holds boundary conditions and
1-to-1 interfaces: the input's own (a CGNS input), or those --connect finds
(walls as --wall marks them, planar faces next to a wall symmetry, the rest
fixed), or a map --connectivity MAP.json or --nmf MAP.nmf gives; Plot3D and
HDF5 outputs hold none.  OUT is never replaced unless --force is given (the
input file included).  --for cfl3d writes the grid file CFL3D reads: Fortran
unformatted, float64, 4-byte little-endian markers, multi-block; a 2-D grid
as one block of two i planes in CFL3D's x-z plane (X = x, Z = y, Y = 0 and
-1), a 3-D grid as it is ('tfi-quat connect GRID --for cfl3d' prints the
matching input-deck sections); --from cfl3d reads such a file back."""

#: output options: (destination, option text, Plot3DFormat field)
_PLOT3D_OUTPUT = (
    ("encoding", "--ascii/--binary/--fortran", "encoding"),
    ("endian", "--big-endian/--little-endian", "endian"),
    ("precision", "--single/--double", "precision"),
    ("iblank", "--iblank/--no-iblank", "iblank"),
    ("records", "--records", "records"),
    ("multiblock", "--single-block/--multi-block", "multiblock"),
    ("int_size", "--int-size", "int_size"),
    ("marker_size", "--marker-size", "marker_size"),
)


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", metavar="IN", help="input grid file (Plot3D, HDF5 or CGNS)")
    parser.add_argument("output", metavar="OUT", help="output grid file")
    parser.add_argument("--format", choices=("plot3d", "hdf5", "cgns"),
                        help="output format (default: from OUT's extension, else the input's)")
    parser.add_argument("--for", dest="target", choices=TARGETS,
                        help="write the grid file this solver reads (no other output option applies)")
    parser.add_argument("-f", "--force", action="store_true",
                        help="replace OUT if it exists (even when it is the input)")
    g = parser.add_argument_group("Plot3D output", "default: the input's variant when it is "
                                  "Plot3D, else the Plot3D writer's defaults")
    enc = g.add_mutually_exclusive_group()
    for flag, value, text in (("--ascii", "ascii", "ASCII text"),
                              ("--binary", "binary", "C-stream binary"),
                              ("--fortran", "fortran", "Fortran unformatted (record markers)")):
        enc.add_argument(flag, dest="encoding", action="store_const", const=value, help=text)
    end = g.add_mutually_exclusive_group()
    end.add_argument("--big-endian", dest="endian", action="store_const", const=">",
                     help="big-endian byte order")
    end.add_argument("--little-endian", dest="endian", action="store_const", const="<",
                     help="little-endian byte order")
    prec = g.add_mutually_exclusive_group()
    prec.add_argument("--single", dest="precision", action="store_const", const=4,
                      help="float32 coordinates")
    prec.add_argument("--double", dest="precision", action="store_const", const=8,
                      help="float64 coordinates")
    ib = g.add_mutually_exclusive_group()
    ib.add_argument("--iblank", dest="iblank", action="store_const", const=True,
                    help="write IBLANK arrays")
    ib.add_argument("--no-iblank", dest="iblank", action="store_const", const=False,
                    help="write no IBLANK arrays")
    g.add_argument("--records", choices=("block", "coordinate"),
                   help="Fortran: one record per block or per coordinate array")
    mb = g.add_mutually_exclusive_group()
    mb.add_argument("--single-block", dest="multiblock", action="store_const", const=False,
                    help="single-block file (no block-count line; one-block grids only)")
    mb.add_argument("--multi-block", dest="multiblock", action="store_const", const=True,
                    help="multi-block file (block-count line)")
    g.add_argument("--int-size", type=int, choices=(4, 8),
                   help="bytes per header integer and IBLANK value")
    g.add_argument("--marker-size", type=int, choices=(4, 8),
                   help="Fortran: bytes per record marker")
    h = parser.add_argument_group("HDF5 output")
    comp = h.add_mutually_exclusive_group()
    comp.add_argument("--compress", dest="compress", action="store_const", const=True,
                      help="gzip-compress the datasets (with the shuffle filter)")
    comp.add_argument("--no-compress", dest="compress", action="store_const", const=False,
                      help="write uncompressed datasets (default, unless the input is compressed HDF5)")
    h.add_argument("--compression-level", type=int, choices=range(10), metavar="0..9",
                   help="gzip level (default 4; implies --compress)")
    c = parser.add_argument_group(
        "CGNS output", "boundary conditions and interfaces (default: a CGNS input's own); "
        "--single/--double set the coordinate precision (default float64)")
    src = c.add_mutually_exclusive_group()
    src.add_argument("--connect", action="store_true",
                     help="find the interfaces and classify the boundary (tfi-quat connect)")
    src.add_argument("--connectivity", metavar="MAP.json", help="interfaces and patches from a JSON map")
    src.add_argument("--nmf", metavar="MAP.nmf", help="interfaces and patches from a Neutral Map File")
    for kind in ("wall", "symmetry", "fixed"):
        c.add_argument(f"--{kind}", action="append", default=[], metavar="B:FACE[:RANGE]",
                       help=f"a {kind} patch, 1-based (repeatable; with --connect, --connectivity or --nmf)")
    c.add_argument("--no-auto-symmetry", action="store_true",
                   help="--connect: do not make planar faces next to a wall symmetry")
    add_input_args(parser, prefix="in-")


def _output_format(args, in_format: str, plot3d_opts: dict) -> str:
    if args.target:
        return args.target
    if args.format:
        return args.format
    try:
        return format_for(args.output).name
    except GridFormatError:
        if plot3d_opts:
            return "plot3d"
        if args.compress or args.compression_level is not None:
            return "hdf5"
        return in_format


def _check_target(args) -> None:
    out = Path(args.output)
    if out.is_dir():
        raise OverwriteError(f"{out}: is a directory")
    if args.force or not out.exists():
        return
    try:
        same = os.path.samefile(out, args.input)
    except OSError:
        same = False
    if same:
        raise OverwriteError(f"{out}: refusing to overwrite the input file (pass --force)")
    raise OverwriteError(f"{out}: file exists (pass --force to replace it)")


def run(args) -> int:
    with one_line_errors():
        return _convert(args)


def _convert(args) -> int:
    _check_target(args)
    plot3d_opts = {key: getattr(args, dest) for dest, _, key in _PLOT3D_OUTPUT
                   if getattr(args, dest) is not None}
    grid = read_input(args, args.input, prefix="in-")
    in_format = format_name(grid.source_format)
    fmt = _output_format(args, in_format, plot3d_opts)
    kw: dict = {}
    if fmt in TARGETS:      # --for, or a --from input written back to a file of no known extension
        _check_target_options(args, plot3d_opts, fmt)
        write(args.output, grid, target=fmt, overwrite=args.force)
        from ..io.cfl3d import CFL3DFormat
        planes = " (2-D: as two planes)" if grid.ndim == 2 else ""
        print(f"wrote {args.output}: {describe_variant(CFL3DFormat(grid.ndim))}, "
              f"{grid.nblocks} block(s), {grid.npoints:,} points{planes}")
        if grid.connectivity is not None:
            print(f"note: the boundary conditions and interfaces of {args.input} are not written "
                  f"(CFL3D takes them from its input deck: 'tfi-quat connect GRID --for {fmt}')")
        return 0
    if fmt == "plot3d":
        if args.compress or args.compression_level is not None:
            raise GridFormatError(f"{args.output}: --compress/--compression-level apply to HDF5 "
                                  "output only")
        if plot3d_opts.get("multiblock") is False and grid.nblocks > 1:
            raise GridFormatError(f"{args.output}: --single-block needs a one-block grid; "
                                  f"{args.input} has {grid.nblocks} blocks")
        kw.update(plot3d_opts)
    elif fmt == "hdf5":
        if plot3d_opts:
            opts = ", ".join(text for dest, text, _ in _PLOT3D_OUTPUT if getattr(args, dest) is not None)
            raise GridFormatError(f"{args.output}: {opts} apply to Plot3D output only")
        if args.compression_level is not None:
            if args.compress is False:
                raise GridFormatError(f"{args.output}: --compression-level contradicts --no-compress")
            kw.update(compression="gzip", compression_level=args.compression_level)
        elif args.compress is not None:
            kw["compression"] = "gzip" if args.compress else False
        if in_format == "hdf5":
            from ..io.hdf5 import read_extra
            extra = read_extra(args.input)
            if extra is not None:
                kw["extra_json"] = extra
    elif fmt == "cgns":
        bad = [text for dest, text, key in _PLOT3D_OUTPUT
               if key != "precision" and getattr(args, dest) is not None]
        if args.compress is not None or args.compression_level is not None:
            bad.append("--compress/--no-compress/--compression-level")
        if bad:
            raise GridFormatError(f"{args.output}: {', '.join(bad)} do not apply to CGNS output "
                                  "(--single/--double do)")
        if "precision" in plot3d_opts:
            kw["single"] = plot3d_opts["precision"] == 4
    conn = _connectivity(args, grid, fmt)
    if conn is not None:
        kw["connectivity"] = conn
    like = grid if fmt == in_format else None
    write(args.output, grid, format=fmt, like=like, overwrite=args.force, **kw)
    print(f"wrote {args.output}: {_written_variant(args.output, fmt, grid, kw)}, "
          f"{grid.nblocks} block(s), {grid.npoints:,} points")
    if fmt != "cgns" and grid.connectivity is not None:
        print(f"note: the boundary conditions and interfaces of {args.input} are not written "
              f"(a {fmt} file holds none)")
    return 0


def _check_target_options(args, plot3d_opts: dict, target: str) -> None:
    """--for fixes the output completely: refuse every other output option."""
    bad = [text for dest, text, _ in _PLOT3D_OUTPUT if getattr(args, dest) is not None]
    if args.format is not None and args.format != "plot3d":
        bad.append(f"--format {args.format}")
    if args.compress is not None or args.compression_level is not None:
        bad.append("--compress/--no-compress/--compression-level")
    if args.connect or args.connectivity or args.nmf or args.wall or args.symmetry or args.fixed \
            or args.no_auto_symmetry:
        bad.append("--connect/--connectivity/--nmf/--wall/--symmetry/--fixed/--no-auto-symmetry "
                   f"(the {target} input deck holds the boundary conditions: "
                   f"'tfi-quat connect GRID --for {target}')")
    if bad:
        raise GridFormatError(f"{args.output}: --for {target} writes one fixed variant; "
                              f"{', '.join(bad)} do not apply")


def _connectivity(args, grid, fmt: str):
    """The connectivity to write: from --connect, --connectivity or --nmf (with the kinds given),
    None for the writer's default (the grid's own)."""
    from ..spec import parse_patch_spec
    kinds = {}
    for kind in ("wall", "symmetry", "fixed"):
        specs = []
        for text in getattr(args, kind):
            try:
                specs.append(parse_patch_spec(text))
            except CaseError as exc:
                raise CaseError(f"--{kind}: {exc}") from None
        kinds[kind if kind != "wall" else "walls"] = specs
    source = ("--connect" if args.connect else f"--connectivity {args.connectivity}" if args.connectivity
              else f"--nmf {args.nmf}" if args.nmf else None)
    if source is None:
        given = [f"--{k}" for k in ("wall", "symmetry", "fixed") if getattr(args, k)]
        if args.no_auto_symmetry:
            given.append("--no-auto-symmetry")
        if given:
            raise CaseError(f"{', '.join(given)} need --connect, --connectivity or --nmf")
        return None
    if fmt != "cgns":
        raise CaseError(f"{args.output}: {source}: a {fmt} file cannot hold boundary conditions or "
                        "interfaces; write a CGNS file, or save the map with "
                        "'tfi-quat connect GRID -o MAP.json'")
    from .. import topology
    if args.no_auto_symmetry and not args.connect:
        raise CaseError("--no-auto-symmetry applies to --connect")
    if args.connect:
        return topology.connect(grid, auto_symmetry=not args.no_auto_symmetry, **kinds)
    if args.connectivity:
        conn = topology.Connectivity.from_json(args.connectivity, grid)
    else:
        conn = topology.Connectivity.from_nmf(args.nmf, grid)
    if any(kinds.values()):
        conn = topology.classify(conn, grid, **kinds)
    return conn


def _written_variant(path, fmt: str, grid, kw: dict) -> str:
    """Describe the variant just written.

    HDF5: read back from the file's metadata.  Plot3D: the variant the writer
    documents it writes: the grid's own Plot3D variant (else the defaults),
    with the options given, ``ndim`` the grid's and ``iblank`` whether the
    grid has IBLANK unless given.
    """
    if fmt == "hdf5":
        from ..io.hdf5 import info
        return describe_variant(info(path).format)
    if fmt in TARGETS:
        from ..io.cfl3d import CFL3DFormat
        return describe_variant(CFL3DFormat(grid.ndim))
    if fmt == "cgns":
        from ..io.cgns import CGNSFormat, info
        i = info(path)
        single = bool(i.zones) and i.zones[0][2] == "R4"
        return (f"{describe_variant(CGNSFormat(i.base, single))}, {len(i.bcs)} boundary condition(s), "
                f"{len(i.one_to_one)} 1-to-1 record(s)")
    from ..io.plot3d import Plot3DFormat
    base = grid.source_format if isinstance(grid.source_format, Plot3DFormat) else Plot3DFormat()
    opts = {k: v for k, v in kw.items() if k in {f for _, _, f in _PLOT3D_OUTPUT}}
    opts.setdefault("ndim", grid.ndim)
    opts.setdefault("iblank", grid.has_iblank)
    return describe_variant(base.replace(**opts))
