"""Benchmark: coincident boundary points, ``cKDTree.query_pairs`` vs ``tfi_quat._points.close_pairs``.

The point set is the one the Deformer merges in its set-up: every block
point on any of the six faces of every block of the multiblock wing (each
block point once), with ``tol = rtol * bounding-box diagonal`` (the
Deformer's default ``rtol = 1e-10``).  The grid comes from a pickle of
``(grid, boundary_patches, connectivity)`` when there is one (default
``/tmp/prof/wing2.8.pkl``), otherwise it is generated with
``tfi_quat.generate.wing`` at ``--scale`` (as in ``bench_deform.py``).

Prints the best of ``--repeat`` runs of each (close_pairs after a first,
compiling call), the pair counts and whether the two pair sets are equal.

    python benchmarks/bench_points.py                       # the pickle, else the wing at --scale 2.8
    python benchmarks/bench_points.py --pickle none --scale 1
"""

from __future__ import annotations

import argparse
import os
import pickle
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from tfi_quat import generate as gen  # noqa: E402
from tfi_quat._jit import numba  # noqa: E402
from tfi_quat._points import close_pairs  # noqa: E402


def _wing(scale: float):
    def odd4(n):            # ni must satisfy (ni - 1) % 4 == 0
        n = int(round(n))
        return n + (-(n - 1)) % 4

    f = scale
    return gen.wing(ni=odd4(129 * f), nj=int(49 * f), nk_wing=int(45 * f), nk_cap=max(5, int(9 * f)),
                    nk_out=int(25 * f))


def boundary_points(grid) -> np.ndarray:
    """Every block point on a face of its block (xyz[0], xyz[-1], xyz[:, 0], ...), once per block."""
    pts = []
    for blk in grid:
        x = blk.xyz
        on_face = np.zeros(x.shape[:3], dtype=bool)
        on_face[[0, -1]] = True
        on_face[:, [0, -1]] = True
        on_face[:, :, [0, -1]] = True
        pts.append(x[on_face])
    return np.ascontiguousarray(np.concatenate(pts), dtype=np.float64)


def _best(fn, repeat):
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pickle", default="/tmp/prof/wing2.8.pkl",
                    help="pickle of (grid, bp, conn); 'none' to always generate")
    ap.add_argument("--scale", type=float, default=2.8, help="wing resolution factor when generating")
    ap.add_argument("--rtol", type=float, default=1e-10, help="tol relative to the bounding-box diagonal")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    if args.pickle.lower() != "none" and os.path.exists(args.pickle):
        with open(args.pickle, "rb") as fh:
            grid = pickle.load(fh)[0]
        src = args.pickle
    else:
        grid = _wing(args.scale)
        src = f"generate.wing(scale={args.scale:g})"
    tg = time.perf_counter() - t0
    P = boundary_points(grid)
    diag = float(np.linalg.norm(P.max(axis=0) - P.min(axis=0)))
    tol = args.rtol * diag
    print(f"grid: {src} ({tg:.1f} s), {len(grid)} blocks, {grid.npoints / 1e6:.2f} M points; "
          f"{len(P)} boundary points, tol = {args.rtol:g} x diagonal = {tol:.3g}")
    print(f"load average {os.getloadavg()[0]:.1f}, {os.cpu_count()} CPUs, numba threads {numba.get_num_threads()}")

    from scipy.spatial import cKDTree

    t0 = time.perf_counter()
    close_pairs(P, tol)
    first = time.perf_counter() - t0
    t_kd, kd = _best(lambda: cKDTree(P).query_pairs(tol, output_type="ndarray"), args.repeat)
    t_cp, cp = _best(lambda: close_pairs(P, tol), args.repeat)

    kd = kd.astype(np.int64)
    kd = kd[np.lexsort((kd[:, 1], kd[:, 0]))] if len(kd) else np.empty((0, 2), dtype=np.int64)
    equal = np.array_equal(kd, cp)
    print(f"\n{'':28s}{'time (best of %d)' % args.repeat:>20s}{'pairs':>10s}")
    print(f"{'cKDTree(P).query_pairs':28s}{t_kd * 1e3:17.1f} ms{len(kd):10d}")
    print(f"{'close_pairs':28s}{t_cp * 1e3:17.1f} ms{len(cp):10d}")
    print(f"speed-up {t_kd / t_cp:.1f}x; same pairs: {equal}; "
          f"close_pairs first call (compilation or cache load) {first:.2f} s")
    if not equal:
        raise SystemExit("pair sets differ")


if __name__ == "__main__":
    main()
