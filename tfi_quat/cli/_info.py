"""``tfi-quat info GRID``: what a grid file holds.

Prints the detected file variant, ndim, the blocks with their dimensions and
point counts, the total number of points, the bounding box, the shortest and
longest cell edge, and whether the grid has IBLANK (CGNS: also the bases,
boundary conditions and connectivity records); ``--json`` prints the same
as one JSON object.

Also home of the input options shared with ``convert`` (:func:`add_input_args`,
:func:`read_input`) and of the variant description (:func:`describe_variant`).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
from pathlib import Path

import numpy as np

from .. import read
from .._jit import jit
from ..errors import GridFormatError, TfiQuatError
from ..grid import Grid
from ..io import TARGETS

HELP = "describe a grid file: variant, blocks, points, bounding box, cell edge lengths"
DESCRIPTION = """\
Describe a grid file: the detected variant (Plot3D: encoding, byte order,
precision, ndim, single/multi-block, IBLANK, record layout, integer size;
HDF5: layout version and compression), ndim, each block's dimensions and
points, the total points, the bounding box, the shortest and longest cell
edge, and IBLANK yes/no.  CGNS files also list their bases (marking the one
read), boundary conditions (name, type, kind, zone, face, range), 1-to-1
records and other connectivity records (kept on rewriting, not used).  Plot3D files whose variant cannot be detected
unambiguously can be described with the variant options below."""



# ----------------------------------------------------------------------------- errors

def one_line(message: str) -> str:
    """Fold a multi-line message into one line ("...Closest: a; b")."""
    out = ""
    for line in (ln.strip() for ln in message.splitlines()):
        if line:
            out += (line if not out else (" " if out.endswith(":") else "; ") + line)
    return out


@contextlib.contextmanager
def one_line_errors():
    """Re-raise a multi-line TfiQuatError with its message on one line (the CLI prints one line)."""
    try:
        yield
    except TfiQuatError as exc:
        msg = str(exc)
        if "\n" not in msg:
            raise
        try:
            folded = type(exc)(one_line(msg))
        except Exception:  # an error class with another signature: leave it as it is
            raise exc from None
        raise folded from exc


# ----------------------------------------------------------------------------- input options

def add_input_args(parser: argparse.ArgumentParser, prefix: str = "") -> None:
    """Add the input options: format, Plot3D variant overrides, ``--allow-nonfinite``.

    ``prefix`` ("" for ``info``, ``"in-"`` for ``convert``) is put in front
    of every option name; the destinations are the same either way.
    """
    p = f"--{prefix}"
    g = parser.add_argument_group(
        "input", "the format is taken from the file contents (HDF5 signature) or extension; "
        "Plot3D variant options override automatic detection")
    g.add_argument(f"{p}format", dest="in_format", choices=("plot3d", "hdf5", "cgns"),
                   help="input file format")
    g.add_argument("--from", dest="in_target", choices=TARGETS,
                   help="the file was written for this solver (tfi-quat convert --for): read exactly "
                        "its variant and undo its index mapping")
    g.add_argument(f"{p}base", dest="in_base", metavar="NAME",
                   help="CGNS: the base to read (default the first; info lists them)")
    g.add_argument(f"{p}encoding", dest="in_encoding", choices=("ascii", "binary", "fortran"),
                   help="Plot3D: ASCII, C-stream binary or Fortran unformatted")
    g.add_argument(f"{p}endian", dest="in_endian", choices=("big", "little"),
                   help="Plot3D: byte order")
    g.add_argument(f"{p}precision", dest="in_precision", choices=("single", "double"),
                   help="Plot3D: float32 or float64 coordinates")
    g.add_argument(f"{p}ndim", dest="in_ndim", type=int, choices=(2, 3),
                   help="Plot3D: 2-D (x, y) or 3-D (x, y, z) file")
    ib = g.add_mutually_exclusive_group()
    ib.add_argument(f"{p}iblank", dest="in_iblank", action="store_const", const=True,
                    help="Plot3D: the file has IBLANK arrays")
    ib.add_argument(f"{p}no-iblank", dest="in_iblank", action="store_const", const=False,
                    help="Plot3D: the file has no IBLANK arrays")
    mb = g.add_mutually_exclusive_group()
    mb.add_argument(f"{p}single-block", dest="in_multiblock", action="store_const", const=False,
                    help="Plot3D: single-block file (no block-count line)")
    mb.add_argument(f"{p}multi-block", dest="in_multiblock", action="store_const", const=True,
                    help="Plot3D: multi-block file (starts with the block count)")
    g.add_argument(f"{p}records", dest="in_records", choices=("block", "coordinate"),
                   help="Plot3D Fortran: one record per block or per coordinate array")
    g.add_argument(f"{p}int-size", dest="in_int_size", type=int, choices=(4, 8),
                   help="Plot3D: bytes per header integer and IBLANK value")
    g.add_argument(f"{p}marker-size", dest="in_marker_size", type=int, choices=(4, 8),
                   help="Plot3D Fortran: bytes per record marker")
    g.add_argument("--allow-nonfinite", action="store_true",
                   help="accept NaN or infinite coordinates")


#: (destination, option suffix, Plot3DFormat field, value map)
_INPUT_OVERRIDES = (
    ("in_encoding", "encoding", "encoding", None),
    ("in_endian", "endian", "endian", {"big": ">", "little": "<"}),
    ("in_precision", "precision", "precision", {"single": 4, "double": 8}),
    ("in_ndim", "ndim", "ndim", None),
    ("in_iblank", "iblank", "iblank", None),
    ("in_multiblock", "single-block", "multiblock", None),
    ("in_records", "records", "records", None),
    ("in_int_size", "int-size", "int_size", None),
    ("in_marker_size", "marker-size", "marker_size", None),
)


def input_overrides(args) -> dict:
    """Plot3D reader overrides (Plot3DFormat field names) from the parsed input options."""
    out = {}
    for dest, _, fieldname, values in _INPUT_OVERRIDES:
        v = getattr(args, dest, None)
        if v is not None:
            out[fieldname] = values[v] if values else v
    return out


def input_format(path, explicit: str | None) -> str | None:
    """The input's format: explicit, else HDF5 by signature, else by extension (plot3d if unknown)."""
    if explicit:
        return explicit
    from ..io import format_for
    from ..io.hdf5 import is_hdf5
    if is_hdf5(path):
        try:
            by_name = format_for(path).name
        except GridFormatError:
            by_name = None
        return "cgns" if by_name == "cgns" else "hdf5"
    try:
        return format_for(path).name
    except GridFormatError:
        return "plot3d"  # Plot3D files come with many extensions; detection checks the contents


def read_input(args, path, prefix: str = "") -> Grid:
    """Read the input grid with the options of :func:`add_input_args`."""
    if not Path(path).exists():
        raise FileNotFoundError(2, "no such file", str(path))
    target = getattr(args, "in_target", None)
    if target is not None:
        given = [f"--{prefix}{suffix}" for dest, suffix, *_ in _INPUT_OVERRIDES
                 if getattr(args, dest, None) is not None]
        given += [f"--{prefix}{name}" for name in ("format", "base")
                  if getattr(args, f"in_{name}", None) is not None]
        if given:
            raise GridFormatError(f"{path}: --from {target} reads one fixed variant; {', '.join(given)} "
                                  "do not apply")
        return read(path, target=target, allow_nonfinite=args.allow_nonfinite)
    fmt = input_format(path, args.in_format)
    overrides = input_overrides(args)
    if fmt != "plot3d" and overrides:
        opts = ", ".join(f"--{prefix}{suffix}" for dest, suffix, *_ in _INPUT_OVERRIDES
                         if getattr(args, dest, None) is not None)
        what = {"hdf5": "an HDF5"}.get(fmt, f"a {fmt}")
        raise GridFormatError(f"{path}: is {what} file; the Plot3D input option(s) {opts} do not apply")
    base = getattr(args, "in_base", None)
    if base is not None:
        if fmt != "cgns":
            raise GridFormatError(f"{path}: is not a CGNS file; --{prefix}base applies to CGNS files only")
        overrides["base"] = base
    if args.allow_nonfinite:
        overrides["allow_nonfinite"] = True
    return read(path, format=fmt, **overrides)


# ----------------------------------------------------------------------------- descriptions

def format_name(variant) -> str:
    """Registry name of the format a variant object belongs to ("plot3d", "hdf5", ...)."""
    from ..io import format_for
    try:
        return format_for(like=variant).name
    except GridFormatError:
        return "unknown"


def describe_variant(variant) -> str:
    """One line naming the format and describing the variant, e.g. ``hdf5: layout v1, uncompressed``."""
    if variant is None:
        return "unknown"
    describe = getattr(variant, "describe", None)
    text = describe() if callable(describe) else repr(variant)
    return f"{format_name(variant)}: {text}"


def variant_dict(variant) -> dict:
    """JSON-ready fields of a variant dataclass (empty when unknown)."""
    if variant is not None and dataclasses.is_dataclass(variant):
        return dataclasses.asdict(variant)
    return {}


# ----------------------------------------------------------------------------- measures

@jit
def _edge_range_kernel(xyz, out):
    """Smallest and largest squared cell-edge length of one block.

    ``xyz`` float64 ``(ni, nj, nk, 3)`` (Fortran order: i innermost);
    ``out`` float64 (2,) holds ``(min, max)`` on entry and is updated.  An
    edge joins two neighbouring points along i, j or k; NaN edges are skipped.
    """
    ni, nj, nk = xyz.shape[0], xyz.shape[1], xyz.shape[2]
    lo = out[0]
    hi = out[1]
    for k in range(nk):
        for j in range(nj):
            for i in range(ni):
                x = xyz[i, j, k, 0]
                y = xyz[i, j, k, 1]
                z = xyz[i, j, k, 2]
                if i + 1 < ni:
                    dx = xyz[i + 1, j, k, 0] - x
                    dy = xyz[i + 1, j, k, 1] - y
                    dz = xyz[i + 1, j, k, 2] - z
                    d = dx * dx + dy * dy + dz * dz
                    if d < lo:
                        lo = d
                    if d > hi:
                        hi = d
                if j + 1 < nj:
                    dx = xyz[i, j + 1, k, 0] - x
                    dy = xyz[i, j + 1, k, 1] - y
                    dz = xyz[i, j + 1, k, 2] - z
                    d = dx * dx + dy * dy + dz * dz
                    if d < lo:
                        lo = d
                    if d > hi:
                        hi = d
                if k + 1 < nk:
                    dx = xyz[i, j, k + 1, 0] - x
                    dy = xyz[i, j, k + 1, 1] - y
                    dz = xyz[i, j, k + 1, 2] - z
                    d = dx * dx + dy * dy + dz * dz
                    if d < lo:
                        lo = d
                    if d > hi:
                        hi = d
    out[0] = lo
    out[1] = hi


def edge_length_range(grid: Grid, kernel=None) -> tuple[float, float] | None:
    """Shortest and longest cell edge over all blocks.

    An edge joins two neighbouring points along i, j or k.  One compiled pass
    over each block (no temporaries).  Returns None when no block has an edge
    (every block a single point) or every edge is NaN.

    ``kernel`` replaces the compiled kernel (tests pass its ``py_func``).
    """
    kernel = _edge_range_kernel if kernel is None else kernel
    out = np.array([np.inf, -np.inf])
    for b in grid:
        if max(b.dims) > 1:
            kernel(b.xyz, out)
    if not out[0] <= out[1]:
        return None
    return math.sqrt(out[0]), math.sqrt(out[1])


def _num(v) -> float | None:
    """A float for JSON; None for NaN/inf (only with --allow-nonfinite)."""
    v = float(v)
    return v if math.isfinite(v) else None


#: Plot3DFormat field -> the ``info`` option that sets it to a value
_FIELD_OPTIONS = {
    "encoding": lambda v: f"--encoding {v}",
    "endian": lambda v: "--endian " + ("big" if v == ">" else "little"),
    "precision": lambda v: "--precision " + ("single" if v == 4 else "double"),
    "ndim": lambda v: f"--ndim {v}",
    "multiblock": lambda v: "--multi-block" if v else "--single-block",
    "iblank": lambda v: "--iblank" if v else "--no-iblank",
    "records": lambda v: f"--records {v}",
    "int_size": lambda v: f"--int-size {v}",
    "marker_size": lambda v: f"--marker-size {v}",
}


#: IBLANK values beyond this size mark a variant as implausible (real ones are small:
#: 1 field, 0 hole, 2 or -n fringe with donor grid n)
IBLANK_PLAUSIBLE = 1 << 20


def _plausible(path, variant) -> bool:
    """Whether the file read as ``variant`` has plausible IBLANK values (or none)."""
    from ..io.plot3d import read as read_plot3d
    if not variant.iblank:
        return True
    try:
        g = read_plot3d(path, format=variant, allow_nonfinite=True)
    except TfiQuatError:
        return False
    return all(int(np.abs(b.iblank.astype(np.int64)).max()) <= IBLANK_PLAUSIBLE for b in g)


def other_variants(args, path, grid: Grid) -> list[dict]:
    """The other Plot3D variants the file fits, each with the options that read it so.

    Empty for HDF5 files and for Plot3D files that fit one variant only.
    Variants whose IBLANK values would be absurd (beyond ``IBLANK_PLAUSIBLE``
    in size: coordinate bytes read as integers) are left out: a 2-D float64
    file with one block fits, byte for byte, a 3-D single-block float32 file
    with IBLANK and ``ni = 1``.
    """
    from ..io.plot3d import Plot3DFormat, detect_all
    chosen = grid.source_format
    if not isinstance(chosen, Plot3DFormat):
        return []
    fits = detect_all(path, **input_overrides(args))
    out = []
    for alt in fits:
        if alt == chosen or not _plausible(path, alt):
            continue
        # the fields that differ from the chosen variant, plus any that tell ``alt``
        # from a preferred fit sharing those
        names = [n for n in _FIELD_OPTIONS if getattr(alt, n) != getattr(chosen, n)]
        while True:
            first = next(f for f in fits if all(getattr(f, n) == getattr(alt, n) for n in names))
            if first == alt:
                break
            names.append(next(n for n in _FIELD_OPTIONS
                              if n not in names and getattr(first, n) != getattr(alt, n)))
        out.append({"variant": variant_dict(alt), "description": describe_variant(alt),
                    "options": " ".join(_FIELD_OPTIONS[n](getattr(alt, n)) for n in names)})
    return out


def summary(grid: Grid, path, also_fits=()) -> dict:
    """Everything ``info`` reports, as a JSON-ready dict.

    ``also_fits``: the other variants the file fits (:func:`other_variants`);
    listed under ``"also_fits"`` when there are any.
    """
    lo, hi = grid.bbox()
    edges = edge_length_range(grid)
    variant = grid.source_format
    return {
        "path": os.fspath(path),
        "format": format_name(variant),
        "variant": variant_dict(variant),
        "description": describe_variant(variant),
        "ndim": grid.ndim,
        "nblocks": grid.nblocks,
        "blocks": [{"block": n + 1, "name": b.name, "dims": list(b.dims), "points": b.npoints,
                    "iblank": b.iblank is not None} for n, b in enumerate(grid)],
        "points": grid.npoints,
        "bbox": {"min": [_num(v) for v in lo], "max": [_num(v) for v in hi]},
        "edge_length": None if edges is None else {"min": _num(edges[0]), "max": _num(edges[1])},
        "iblank": grid.has_iblank,
    } | ({"also_fits": list(also_fits)} if also_fits else {})


def cgns_summary(path, base: str | None) -> dict:
    """The CGNS part of ``info``: bases, zones, BCs, 1-to-1 and other connectivity records."""
    from ..io.cgns import info as cgns_info
    i = cgns_info(path, base=base)
    return {
        "base": i.base,
        "bases": [{"name": n, "cell_dim": c, "phys_dim": p, "zones": z, "read": n == i.base}
                  for n, c, p, z in i.bases],
        "bcs": i.bcs,
        "one_to_one": i.one_to_one,
        "other_connectivity": i.other_connectivity,
    }


def _rng(r) -> str:
    return "[" + ", ".join("(" + ",".join(map(str, c)) + ")" for c in r) + "]"


def _cgns_text(c: dict) -> list[str]:
    lines = ["  bases"]
    for b in c["bases"]:
        mark = " (read)" if b["read"] else ""
        lines.append(f"    {b['name']}{mark}  cell dim {b['cell_dim']}, physical dim {b['phys_dim']}, "
                     f"{len(b['zones'])} zone(s): {', '.join(b['zones'])}")
    lines.append(f"  BCs         {len(c['bcs'])}" + (" (name, type, kind, zone, face, range 1-based)"
                                                     if c["bcs"] else ""))
    for b in c["bcs"]:
        t = b["type"]
        if b["family"]:
            t = f"{t} -> {b['family']} -> {b['resolved']}"
        lines.append(f"    {b['name']}  {t}  {b['kind']}  {b['zone']} {b['face']} {_rng(b['range'])}")
    lines.append(f"  1-to-1      {len(c['one_to_one'])} record(s)" +
                 (" (name, zone range -> donor range, Transform)" if c["one_to_one"] else ""))
    for r in c["one_to_one"]:
        lines.append(f"    {r['name']}  {r['zone']} {_rng(r['range'])} -> {r['donor']} "
                     f"{_rng(r['donor_range'])}  [{', '.join(map(str, r['transform']))}]")
    if c["other_connectivity"]:
        lines.append(f"  other connectivity  {len(c['other_connectivity'])} record(s), kept, not used")
        for r in c["other_connectivity"]:
            lines.append(f"    {r['name']}  {r['type']}  {r['zone']} -> {r['donor']}")
    return lines


def _g(v) -> str:
    return "nan" if v is None else f"{v:.6g}"


def format_text(s: dict) -> str:
    """The human-readable ``info`` report."""
    lines = [s["path"],
             f"  format      {s['description']}",
             *(f"  also fits   {a['description']} (read it so with {a['options']})"
               for a in s.get("also_fits", ())),
             f"  ndim        {s['ndim']}",
             f"  blocks      {s['nblocks']}"]
    wname = max((len(b["name"] or "") for b in s["blocks"]), default=0)
    wdims = max(len(" x ".join(map(str, b["dims"]))) for b in s["blocks"])
    wpts = max(len(f"{b['points']:,}") for b in s["blocks"])
    wnum = len(str(s["nblocks"]))
    for b in s["blocks"]:
        dims = " x ".join(map(str, b["dims"]))
        name = (b["name"] or "").ljust(wname)
        ib = "  iblank" if b["iblank"] else ""
        lines.append(f"    {b['block']:>{wnum}}  {name}  {dims:<{wdims}}  {b['points']:>{wpts},} points{ib}")
    lines.append(f"  points      {s['points']:,}")
    lo, hi = s["bbox"]["min"], s["bbox"]["max"]
    lines.append("  bbox        " + "  ".join(f"{c} [{_g(a)}, {_g(b)}]" for c, a, b in zip("xyz", lo, hi)))
    e = s["edge_length"]
    lines.append("  cell edge   " + ("n/a (single-point blocks)" if e is None else
                                     f"min {_g(e['min'])}  max {_g(e['max'])}"))
    lines.append(f"  iblank      {'yes' if s['iblank'] else 'no'}")
    if "cgns" in s:
        lines += _cgns_text(s["cgns"])
    return "\n".join(lines)


# ----------------------------------------------------------------------------- subcommand

def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("grid", metavar="GRID", help="grid file (Plot3D, HDF5 or CGNS)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    add_input_args(parser)


def run(args) -> int:
    with one_line_errors():
        grid = read_input(args, args.grid)
        s = summary(grid, args.grid, other_variants(args, args.grid, grid))
        if format_name(grid.source_format) == "cgns":
            s["cgns"] = cgns_summary(args.grid, args.in_base)
    print(json.dumps(s, indent=2) if args.json else format_text(s))
    return 0
