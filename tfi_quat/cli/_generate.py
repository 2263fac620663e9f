"""``tfi-quat generate KIND [options] -o FILE [--case CASE.toml] [--force]``.

Writes a generated grid (format from the extension) and, with ``--case``, a
case file naming its walls, symmetry planes and fixed far-field faces.
"""

from __future__ import annotations

import argparse
import os
import re
from pathlib import Path

from ._common import finite

HELP = "generate a sample grid (airfoil, cylinder, channel, two-block, wing)"
DESCRIPTION = ("Generate a grid and write it; --case also writes a TOML case file describing "
               "its walls, symmetry planes and fixed boundaries (1-based ranges).")


def _stretching(p):
    p.add_argument("--stretching", choices=("geometric", "tanh"), default="geometric",
                   help="wall-normal distribution (default geometric)")


def _common(p, ni, nj, first_spacing, farfield=None):
    p.add_argument("--ni", type=int, default=ni, help=f"points in i (default {ni})")
    p.add_argument("--nj", type=int, default=nj, help=f"points in j (default {nj})")
    p.add_argument("--first-spacing", type=finite, default=first_spacing,
                   help=f"first cell size off the wall (default {first_spacing:g})")
    if farfield is not None:
        p.add_argument("--farfield", type=finite, default=farfield,
                       help=f"distance to the outer boundary (default {farfield:g})")


def add_args(parser: argparse.ArgumentParser) -> None:
    kinds = parser.add_subparsers(dest="kind", metavar="KIND", required=True)

    def kind(name, help_):
        p = kinds.add_parser(name, help=help_, description=help_)
        return p

    a = kind("airfoil", "viscous C- or O-grid round a NACA 4-digit airfoil (2-D)")
    a.add_argument("--naca", default="0012", help="4-digit NACA code (default 0012)")
    a.add_argument("--topology", choices=("C", "O"), default="C", type=str.upper)
    _common(a, 257, 65, 1e-5, 20.0)
    a.add_argument("--wake-length", type=finite, default=None,
                   help="C-grid wake length behind the trailing edge (default: farfield)")
    a.add_argument("--n-wake", type=int, default=None, help="C-grid intervals per wake side")
    a.add_argument("--blunt-te", action="store_true", help="blunt trailing edge (O-grid only)")
    a.add_argument("--n-base", type=int, default=4,
                   help="intervals on each half of a blunt base (default 4)")
    _stretching(a)

    c = kind("cylinder", "analytic O-grid round a circular cylinder (2-D)")
    _common(c, 129, 65, 1e-4, 20.0)
    c.add_argument("--radius", type=finite, default=0.5)

    for name, help_, ni, nj, fs in (("channel", "H-grid of a channel with a bump (2-D)", 129, 49, 1e-3),
                                    ("two-block", "two-block channel with a bump (2-D)", 65, 33, 2e-3)):
        h = kind(name, help_)
        _common(h, ni, nj, fs)
        h.add_argument("--length", type=finite, default=3.0)
        h.add_argument("--height", type=finite, default=1.0)
        h.add_argument("--bump-height", type=finite, default=0.1)

    w = kind("wing", "C-H multiblock grid round a swept, tapered half wing (3-D)")
    w.add_argument("--naca", default="0012")
    _common(w, 129, 49, 2e-5, 15.0)
    w.add_argument("--nk-wing", type=int, default=45)
    w.add_argument("--nk-cap", type=int, default=9)
    w.add_argument("--nk-out", type=int, default=25)
    w.add_argument("--aspect-ratio", type=finite, default=4.0)
    w.add_argument("--taper", type=finite, default=0.5)
    w.add_argument("--sweep", type=finite, default=30.0, help="leading-edge sweep, degrees")
    w.add_argument("--span-farfield", type=finite, default=10.0,
                   help="spanwise far field beyond the tip (default 10)")
    w.add_argument("--wake-length", type=finite, default=15.0,
                   help="outflow plane behind the last trailing edge (default 15)")
    w.add_argument("--n-wake", type=int, default=None, help="intervals per wake side (default (ni-1)/4)")
    _stretching(w)

    for p in (a, c, kinds.choices["channel"], kinds.choices["two-block"], w):
        p.add_argument("-o", "--output", required=True, help="grid file to write (.x, .h5, ...)")
        p.add_argument("--case", default=None, help="also write this TOML case file")
        p.add_argument("--force", action="store_true", help="overwrite existing files")


_PARAMS = {
    "airfoil": ("naca", "topology", "ni", "nj", "first_spacing", "farfield", "wake_length",
                "n_wake", "blunt_te", "n_base", "stretching"),
    "cylinder": ("ni", "nj", "first_spacing", "farfield", "radius"),
    "channel": ("ni", "nj", "first_spacing", "length", "height", "bump_height"),
    "two-block": ("ni", "nj", "first_spacing", "length", "height", "bump_height"),
    "wing": ("naca", "ni", "nj", "first_spacing", "farfield", "nk_wing", "nk_cap", "nk_out",
             "aspect_ratio", "taper", "sweep", "span_farfield", "wake_length", "n_wake", "stretching"),
}


def _as_options(message: str, names) -> str:
    """``message`` with the generator's argument names as the CLI spells them
    (``bump_height`` -> ``--bump-height``)."""
    for name in sorted(names, key=len, reverse=True):
        message = re.sub(rf"(?<![\w-]){name}\b", "--" + name.replace("_", "-"), message)
    return message


def run(args) -> int:
    from .. import generate as gen
    from ..case import Case, save_case
    from ..errors import GridValueError, OverwriteError
    from ..io import write

    out = Path(args.output)
    targets = [out] + ([Path(args.case)] if args.case else [])
    for t in targets:
        if t.exists() and not args.force:
            raise OverwriteError(f"{t}: exists (pass --force to overwrite)")
    params = {k: getattr(args, k) for k in _PARAMS[args.kind]}
    try:
        grid = gen.GENERATORS[args.kind](**params)
    except GridValueError as exc:
        raise GridValueError(_as_options(str(exc), params)) from None
    write(out, grid, overwrite=True)
    msg = f"wrote {out}: {args.kind}, {len(grid)} block(s) " + \
        ", ".join("x".join(map(str, d)) for d in grid.dims) + f", {grid.npoints} points"
    if args.case:
        patches = gen.boundary_patches(args.kind, grid, n_wake=params.get("n_wake"),
                                       topology=params.get("topology", "C"))
        save_case(args.case, Case(grid=Path(os.path.abspath(out)), **patches))
        msg += f"; case {args.case}"
    print(msg)
    return 0
