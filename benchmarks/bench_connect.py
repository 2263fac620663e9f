"""Benchmark: connectivity of a large multiblock grid (default 100 blocks, about 10 M points).

The grid is a lattice of NX x NY x NZ blocks of N^3 points cut from one smooth,
warped mapping; every block gets a random orientation (axes permuted and
reversed), so the search has to find every kind of Transform.  With
``--noise E`` every coordinate is multiplied by ``1 + E u`` (u uniform in
[-1, 1]), as in files written by other tools, whose copies of one point
agree only to ~1e-15.  Prints the time of each stage, the load average and
the peak resident memory, and checks the result (number of interfaces,
every master point mapped onto a coincident slave point).

Usage::

    python benchmarks/bench_connect.py [--blocks 5 5 4] [--n 47] [--repeat 1] [--noise 1e-15]
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from tfi_quat import Grid  # noqa: E402
from tfi_quat.topology import search  # noqa: E402


def lattice(nb=(5, 5, 4), n=47, seed=0, noise=0.0):
    rng = np.random.default_rng(seed)
    blocks = []
    u = np.linspace(0.0, 1.0, n)
    for bz in range(nb[2]):
        for by in range(nb[1]):
            for bx in range(nb[0]):
                X, Y, Z = np.meshgrid(bx + u, by + u, bz + u, indexing="ij")
                xyz = np.empty(X.shape + (3,), order="F")
                xyz[..., 0] = X + 0.1 * np.sin(0.7 * Y) * np.cos(0.3 * Z)
                xyz[..., 1] = Y + 0.1 * np.sin(0.5 * X + 0.2 * Z)
                xyz[..., 2] = Z + 0.05 * X * Y / (1 + X)
                perm = tuple(int(v) for v in rng.permutation(3))
                xyz = xyz.transpose(perm + (3,))
                for ax in range(3):
                    if rng.random() < 0.5:
                        xyz = np.flip(xyz, axis=ax)
                xyz = np.asfortranarray(xyz)
                if noise:
                    xyz *= 1 + noise * rng.uniform(-1, 1, xyz.shape)
                blocks.append(xyz)
    return Grid(blocks)


def expected_interfaces(nb):
    x, y, z = nb
    return (x - 1) * y * z + x * (y - 1) * z + x * y * (z - 1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--blocks", type=int, nargs=3, default=(5, 5, 4))
    ap.add_argument("--n", type=int, default=47)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--noise", type=float, default=0.0, help="relative noise of the coordinates (e.g. 1e-15)")
    args = ap.parse_args(argv)
    print(f"load average {os.getloadavg()[0]:.2f}")
    t0 = time.perf_counter()
    grid = lattice(tuple(args.blocks), args.n, noise=args.noise)
    t_build = time.perf_counter() - t0
    nbnd = sum(2 * (a * b + b * c + a * c) for a, b, c in grid.dims)
    print(f"grid: {len(grid)} blocks, {grid.npoints / 1e6:.2f} M points, {nbnd / 1e6:.2f} M boundary "
          f"face points (built in {t_build:.1f} s)")
    search._rectangles(np.ones((2, 2), bool))  # compile (cached) outside the timing
    search._largest_rectangle(np.ones((2, 2), bool))
    best = None
    for _ in range(args.repeat):
        t = [time.perf_counter()]
        geo = search._Geometry(grid)
        t.append(time.perf_counter())
        itfs = search._find_interfaces(geo)
        t.append(time.perf_counter())
        notes = []
        patches = search._classify(geo, itfs, [], [], [], [], "fixed", True, notes)
        t.append(time.perf_counter())
        stages = np.diff(t)
        if best is None or stages.sum() < best.sum():
            best = stages
    print(f"  boundary points, tolerances, k-d tree labels : {best[0]:7.2f} s")
    print(f"  interfaces (pairs, transforms, rectangles)   : {best[1]:7.2f} s")
    print(f"  patches (kinds, planes)                      : {best[2]:7.2f} s")
    print(f"  connect total                                : {best.sum():7.2f} s  "
          f"({grid.npoints / best.sum() / 1e6:.1f} M grid points/s, "
          f"{nbnd / best.sum() / 1e6:.2f} M boundary points/s)")
    want = expected_interfaces(args.blocks)
    print(f"  interfaces found: {len(itfs)} (expected {want}); patches: {len(patches)}")
    worst = 0.0
    for it in itfs:
        lo, hi = it.point_range
        ii = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi)], indexing="ij"),
                      -1).reshape(-1, 3)
        s = it.slave_index(ii)
        xm = grid[it.master.block].xyz[ii[:, 0], ii[:, 1], ii[:, 2]]
        xs = grid[it.slave.block].xyz[s[:, 0], s[:, 1], s[:, 2]]
        worst = max(worst, float(np.abs(xm - xs).max()))
    print(f"  largest master/slave coordinate mismatch: {worst:.3g}")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6     # kB -> GB (Linux)
    print(f"  peak resident memory (whole benchmark, grid included): {peak:.2f} GB; "
          f"load average {os.getloadavg()[0]:.2f}")
    limit = 8 * args.noise * max(float(np.abs(b.xyz).max()) for b in grid)
    return 0 if len(itfs) == want and worst <= limit else 1


if __name__ == "__main__":
    sys.exit(main())
