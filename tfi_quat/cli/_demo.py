"""``tfi-quat demo``: the memo's figure 4 experiment on the shipped C-grid."""

from __future__ import annotations

import argparse
import time

from ._common import finite

HELP = "deform the shipped NACA 0012 C-grid by plain and quaternion TFI; grids, figure, table"
DESCRIPTION = """Run the memo's figure 4 experiment (Samareh, NASA/TM-2002-211646) on
grids/naca0012_c_257x65.x: the wall bent (camber), pitched nose-up about the
quarter chord and translated; the volume grid deformed with plain TFI and
with quaternion TFI.  Writes both grids (Plot3D, like the input), demo.png
(plain TFI left, quaternion right, leading- and trailing-edge zooms),
demo.md and demo.json (near-wall orthogonality change in the first 5
layers, smallest cell-volume ratio, negative cells, time per step) into DIR."""


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", default="demo_out", metavar="DIR",
                   help="output folder (default: demo_out)")
    p.add_argument("--grid", help="reference C-grid (default: grids/naca0012_c_257x65.x); "
                                  "its case file NAME.toml gives the boundaries")
    p.add_argument("--pitch", type=finite, default=30.0, metavar="DEG", help="nose-up pitch (default 30)")
    p.add_argument("--camber", type=finite, default=0.08, metavar="C",
                   help="trailing-edge bend in chords (default 0.08)")
    p.add_argument("--no-figure", action="store_true", help="skip demo.png")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")


def run(args) -> int:
    from ..demo import DemoMotion, run_demo

    t0 = time.perf_counter()
    motion = DemoMotion(camber=args.camber, pitch=args.pitch)
    res = run_demo(args.output, grid_path=args.grid, motion=motion, overwrite=args.force,
                   figure=not args.no_figure)
    print(f"Motion: {res.motion}.")
    print(res.table())
    print("wrote " + ", ".join(str(f) for f in res.files))
    print(f"total {time.perf_counter() - t0:.1f} s (first step incl. set-up and any JIT compilation: "
          + ", ".join(f"{m} {s:.2f} s" for m, s in res.first_step_seconds.items()) + ")")
    return 0
