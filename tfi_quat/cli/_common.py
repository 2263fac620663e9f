"""Helpers shared by the subcommands."""

from __future__ import annotations

import argparse
import math
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
