"""Helpers shared by the subcommands."""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

from ..errors import CaseError, GridFormatError, OverwriteError

#: registry name of the format whose files hold several bases (``--base``)
BASE_FORMAT = "cgns"


def case_and_grid(args):
    """The ``--case`` file (or None) and the grid path: ``GRID`` or the case file's grid."""
    case = None
    if getattr(args, "case", None):
        from ..case import load_case
        case = load_case(args.case)
    path = args.grid or (case.grid if case is not None else None)
    if path is None:
        raise CaseError("no grid: give GRID or --case")
    return case, path


def add_base_arg(parser) -> None:
    """Add ``--base NAME`` (dest ``base``): the CGNS base to read."""
    parser.add_argument("--base", metavar="NAME", default=None,
                        help="CGNS input: the base to read (default: the first; 'tfi-quat info' lists them)")


def file_format(path) -> str | None:
    """Registry name of a grid file's format (from its extension or HDF5 signature), None if unknown."""
    from ..io import format_for
    try:
        return format_for(path).name
    except GridFormatError:
        return None


def read_options(args, path, *, strict: bool = True) -> dict:
    """Reader keywords from the shared input options: ``{"base": NAME}`` for a CGNS file.

    ``--base`` on a file of another format is a :class:`GridFormatError`
    naming the file when ``strict`` (the command's main input), and is left
    out for it otherwise (a second input such as ``--ref``).
    """
    base = getattr(args, "base", None)
    if base is None:
        return {}
    fmt = file_format(path)
    if fmt == BASE_FORMAT:
        return {"base": base}
    if strict:
        raise GridFormatError(f"{path}: --base {base}: selects a base of a CGNS file; this is "
                              f"{'a ' + fmt if fmt else 'not a CGNS'} file")
    return {}


def read_grid(args, path, *, strict: bool = True):
    """Read a grid file with the shared input options (:func:`read_options`)."""
    from .. import io
    return io.read(path, **read_options(args, path, strict=strict))


def output_like(out, grid):
    """``like=`` for writing a grid derived from ``grid`` to ``out``: ``grid`` (its file variant,
    and for CGNS every node of its file) when ``out`` names the same format or none, else None
    (``out``'s extension chooses the format)."""
    from ..io import format_for
    try:
        source = format_for(like=grid).name
    except GridFormatError:
        return None
    target = file_format(out)
    return grid if target in (None, source) else None


def grid_walls(grid) -> list:
    """The wall patches (PatchSpec) of the grid's own connectivity (a CGNS file's walls), else []."""
    conn = getattr(grid, "connectivity", None)
    if conn is None:
        return []
    return [p.spec for p in conn.patches if p.kind == "wall"]


def check_output(path, force: bool, inputs=()) -> Path:
    """Refuse an existing output file unless ``force``; never silently replace an input."""
    out = Path(os.fspath(path))
    if out.is_dir():
        raise OverwriteError(f"{out}: is a directory")
    if out.exists() and not force:
        for p in inputs:
            if p is not None and Path(p).exists() and os.path.samefile(out, p):
                raise OverwriteError(f"{out}: is an input of this command; refusing to overwrite it "
                                     "(use --force)")
        raise OverwriteError(f"{out}: exists; refusing to overwrite it (use --force)")
    return out


def walls_arg(args, case) -> list:
    """``--walls`` patches (1-based text), else the case file's walls, else none."""
    from ..spec import parse_patch_spec
    walls = []
    for text in args.walls:
        try:
            walls.append(parse_patch_spec(text))
        except CaseError as exc:
            raise CaseError(f"--walls: {exc}") from None
    if not walls and case is not None:
        walls = list(case.walls)
    return walls


def finite(text: str) -> float:
    """argparse type: a finite number (``nan``, ``inf`` and ``1e999`` are usage errors)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def non_negative_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return v


def vector(text: str) -> tuple[float, float, float]:
    """argparse type: ``X,Y,Z``, three finite numbers."""
    parts = text.split(",")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected 3 numbers X,Y,Z, got {text!r}")
    try:
        return tuple(finite(x) for x in parts)  # type: ignore[return-value]
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected 3 finite numbers X,Y,Z, got {text!r}") from None
