"""Deformer benchmark: set-up and one step on the multiblock wing, split by stage.

Prints the grid size, set-up seconds, the step time split into walls /
skeleton / faces / volumes, points per second end to end, and the peak memory
of a step relative to the grid's coordinates (tracemalloc: numpy allocations).

    python benchmarks/bench_deform.py --scale 1      # the shipped wing size (~0.5 M points)
    python benchmarks/bench_deform.py --scale 2.7    # ~10 M points
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np

from tfi_quat import generate as gen
from tfi_quat.deform import Deformer


def beam(span, tip=0.1, twist=5.0):
    """Beam bending (sections rotate with the slope) plus linear twist about the quarter chord."""
    def move(p):
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        eta = np.clip(y / span, 0.0, None)
        wz = tip * span * eta ** 2
        phi = np.arctan(2.0 * tip * eta)
        th = np.radians(twist) * eta
        x0 = x - 0.25
        xt = x0 * np.cos(th) + z * np.sin(th) + 0.25
        zt = -x0 * np.sin(th) + z * np.cos(th)
        return np.stack([xt, y - zt * np.sin(phi), wz + zt * np.cos(phi)], -1)
    return move


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scale", type=float, default=1.0, help="resolution factor per direction")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    f = args.scale

    def odd4(n):            # ni must satisfy (ni - 1) % 4 == 0
        n = int(round(n))
        return n + (-(n - 1)) % 4

    t0 = time.perf_counter()
    grid = gen.wing(ni=odd4(129 * f), nj=int(49 * f), nk_wing=int(41 * f), nk_cap=max(5, int(9 * f)),
                    nk_out=int(25 * f))
    tg = time.perf_counter() - t0
    bp = gen.boundary_patches("wing", grid)
    span = float(grid[1].xyz[..., 1].max())
    npts = grid.npoints
    coord_bytes = npts * 24
    print(f"wing: {len(grid)} blocks, {npts / 1e6:.2f} M points ({coord_bytes / 1e6:.0f} MB coordinates), "
          f"generated in {tg:.1f} s")
    for method, form in (("quaternion", "samareh"), ("quaternion", "local"), ("tfi", "samareh")):
        t0 = time.perf_counter()
        d = Deformer(grid, walls=bp["walls"], symmetry=bp["symmetry"], fixed=bp["fixed"], method=method,
                     formulation=form)
        setup = time.perf_counter() - t0
        move = beam(span)
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
        label = method if method == "tfi" else f"{method} ({form})"
        print(f"\n{label}: set-up {setup:.2f} s ({setup / dt:.1f} steps)")
        print(f"  step {dt:.3f} s = {npts / dt / 1e6:.1f} M points/s end to end")
        for stage in ("walls", "skeleton", "faces", "volumes"):
            v = getattr(tm, stage)
            print(f"    {stage:9s} {v:.4f} s  {100 * v / tm.total:5.1f} %")
        print(f"  peak memory allocated during a step: {peak / 1e6:.0f} MB = "
              f"{peak / coord_bytes:.2f} x the coordinates (the reference grid itself not counted)")


if __name__ == "__main__":
    main()
