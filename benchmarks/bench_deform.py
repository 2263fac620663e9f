"""Deformer benchmark: set-up and one step on the multiblock wing, split by stage.

Prints the grid size, the set-up time (connectivity search and the rest; best of 3
builds, the first beside it), the step time split into walls / skeleton / faces /
volumes, points per second end to end, the memory a step allocates (tracemalloc
peak: the new grid and
the O(surface) tables) and the memory the Deformer keeps between steps, both
relative to the grid's coordinates.  The wall motion is the case files' beam
bend plus twist (``tfi_quat.case.Motion``).

    python benchmarks/bench_deform.py --scale 1      # the shipped wing size (~0.5 M points)
    python benchmarks/bench_deform.py --scale 2.8    # ~10 M points
"""

from __future__ import annotations

import argparse
import os
import time
import tracemalloc


from tfi_quat import generate as gen
from tfi_quat import topology
from tfi_quat.case import Motion
from tfi_quat.deform import Deformer

METHODS = ("two-level", "samareh", "tfi")


def _kept_bytes(d: Deformer) -> int:
    """Bytes a Deformer keeps per block: blending parameters, the kernels' kept tables and the
    two-level base tables."""
    n = 0
    for plan in d.skeleton.blocks:
        n += plan.s.nbytes + plan.gather.nbytes
    if d.two_level is not None:
        n += sum(t.nbytes for base in d.two_level.base for t in base)
    return n


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scale", type=float, default=1.0, help="resolution factor per direction")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--methods", default="all", help="comma list of two-level,samareh,tfi")
    args = ap.parse_args(argv)
    f = args.scale

    def odd4(n):            # ni must satisfy (ni - 1) % 4 == 0
        n = int(round(n))
        return n + (-(n - 1)) % 4

    t0 = time.perf_counter()
    grid = gen.wing(ni=odd4(129 * f), nj=int(49 * f), nk_wing=int(45 * f), nk_cap=max(5, int(9 * f)),
                    nk_out=int(25 * f))
    tg = time.perf_counter() - t0
    bp = gen.boundary_patches("wing", grid)
    npts = grid.npoints
    coord_bytes = npts * 24
    print(f"wing: {len(grid)} blocks, {npts / 1e6:.2f} M points ({coord_bytes / 1e6:.0f} MB coordinates), "
          f"generated in {tg:.1f} s; load average {os.getloadavg()[0]:.1f}")
    t0 = time.perf_counter()
    conn = topology.connect(grid, walls=bp["walls"], symmetry=bp["symmetry"], fixed=bp["fixed"])
    tc = time.perf_counter() - t0
    print(f"connectivity search {tc:.2f} s (once per grid; the Deformer does it when not given one)")
    move = Motion(bend=0.15, twist=5.0, about=(0.25, 0.0, 0.0), span_axis=(0, 1, 0), span=1.5).apply
    want = None if args.methods == "all" else set(args.methods.split(","))
    # compile (or load from numba's cache) every kernel on a small wing first, so that the
    # set-up figures below are the set-up's own work
    t0 = time.perf_counter()
    small = gen.wing(ni=33, nj=13, nk_wing=12, nk_cap=5, nk_out=7)
    sp = gen.boundary_patches("wing", small)
    for method in METHODS:
        Deformer(small, walls=sp["walls"], symmetry=sp["symmetry"], fixed=sp["fixed"], method=method).deform(move)
    print(f"warm-up on a small wing (compilation or numba cache load) {time.perf_counter() - t0:.1f} s")
    for method in METHODS:
        if want is not None and method not in want:
            continue
        # set-up: best of 3 builds, like the steps' best of N; the first build, which also
        # pays the first touch of the blending parameters' pages, is printed beside it
        setups = []
        for _ in range(3):
            d = None
            t0 = time.perf_counter()
            d = Deformer(grid, connectivity=conn, method=method)
            setups.append(time.perf_counter() - t0)
        setup = min(setups)
        d.deform(move)                                   # first call: compilation excluded
        best = None
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            d.deform(move)
            dt = time.perf_counter() - t0
            if best is None or dt < best[0]:
                best = (dt, d.timings)
        tracemalloc.start()
        d.deform(move)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        dt, tm = best
        print(f"\n{method}: set-up {setup:.2f} s = {setup / dt:.1f} steps "
              f"(+ {tc:.2f} s connectivity = {(setup + tc) / dt:.1f} steps); "
              f"first build {setups[0]:.2f} s = {setups[0] / dt:.1f} steps")
        print(f"  step {dt:.3f} s = {npts / dt / 1e6:.1f} M points/s end to end")
        for stage in ("walls", "skeleton", "faces", "volumes"):
            v = getattr(tm, stage)
            print(f"    {stage:9s} {v:.4f} s  {100 * v / tm.total:5.1f} %")
        print(f"  memory allocated during a step (peak): {peak / 1e6:.0f} MB = "
              f"{peak / coord_bytes:.2f} x the coordinates (the output grid included)")
        print(f"  kept by the Deformer between steps: {_kept_bytes(d) / 1e6:.0f} MB = "
              f"{_kept_bytes(d) / coord_bytes:.2f} x the coordinates")


if __name__ == "__main__":
    main()
