"""Helpers shared by the subcommands."""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import CaseError, OverwriteError


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


def check_output(path, force: bool, inputs=()) -> Path:
    """Refuse an existing output file unless ``force``; never silently replace an input."""
    out = Path(os.fspath(path))
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
