"""Benchmark of ``tfi_quat._points`` against cKDTree on the Deformer's point sets.

1. Coincident boundary points, ``cKDTree.query_pairs`` vs ``close_pairs``.
   The point set is the one the Deformer merges in its set-up: every block
   point on any of the six faces of every block of the multiblock wing (each
   block point once), with ``tol = rtol * bounding-box diagonal`` (the
   Deformer's default ``rtol = 1e-10``).
2. Wall distances, ``cKDTree(W).query(Q, distance_upper_bound=bound)`` (the
   default tree and ``balanced_tree=False, compact_nodes=False``) vs
   ``nearest_within(W, Q, bound)``: ``W`` the Deformer's wall points, ``bound
   = 20 * rotation_length`` (its bounded query), ``Q`` the boundary points
   with a finite wall distance (``--queries near``) or all boundary points
   (``--queries all``, most of them beyond the bound).  Times include building
   the trees; nearest_within also on one thread.

The grid comes from a pickle of ``(grid, boundary_patches, connectivity)``
when there is one (default ``/tmp/prof/wing2.8.pkl``), otherwise it is
generated with ``tfi_quat.generate.wing`` at ``--scale`` (as in
``bench_deform.py``; the Deformer then searches the connectivity itself).

Prints the best of ``--repeat`` runs of each (the tfi_quat kernels after a
first, compiling call) and whether the answers are equal (section 2: the same
distances, and the same indices but at ties, where nearest_within returns the
smallest row).

    python benchmarks/bench_points.py                       # the pickle, else the wing at --scale 2.8
    python benchmarks/bench_points.py --pickle none --scale 1
    python benchmarks/bench_points.py --section nearest --queries all
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
from tfi_quat._jit import threads, use_threads  # noqa: E402
from tfi_quat._points import close_pairs, nearest_within  # noqa: E402


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


def _load(args):
    """``(grid, patches, connectivity, source, seconds)``; patches and connectivity None when generated."""
    t0 = time.perf_counter()
    if args.pickle.lower() != "none" and os.path.exists(args.pickle):
        with open(args.pickle, "rb") as fh:
            grid, bp, conn = pickle.load(fh)[:3]
        src = args.pickle
    else:
        grid, bp, conn = _wing(args.scale), None, None
        src = f"generate.wing(scale={args.scale:g})"
    return grid, bp, conn, src, time.perf_counter() - t0


def bench_pairs(grid, args) -> bool:
    P = boundary_points(grid)
    diag = float(np.linalg.norm(P.max(axis=0) - P.min(axis=0)))
    tol = args.rtol * diag
    print(f"\n1. coincident points: {len(P)} boundary points, tol = {args.rtol:g} x diagonal = {tol:.3g}")

    from scipy.spatial import cKDTree

    t0 = time.perf_counter()
    close_pairs(P, tol)
    first = time.perf_counter() - t0
    t_kd, kd = _best(lambda: cKDTree(P).query_pairs(tol, output_type="ndarray"), args.repeat)
    t_cp, cp = _best(lambda: close_pairs(P, tol), args.repeat)

    kd = kd.astype(np.int64)
    kd = kd[np.lexsort((kd[:, 1], kd[:, 0]))] if len(kd) else np.empty((0, 2), dtype=np.int64)
    equal = np.array_equal(kd, cp)
    print(f"{'':40s}{'time (best of %d)' % args.repeat:>20s}{'pairs':>10s}")
    print(f"{'cKDTree(P).query_pairs':40s}{t_kd * 1e3:17.1f} ms{len(kd):10d}")
    print(f"{'close_pairs':40s}{t_cp * 1e3:17.1f} ms{len(cp):10d}")
    print(f"speed-up {t_kd / t_cp:.1f}x; same pairs: {equal}; "
          f"close_pairs first call (compilation or cache load) {first:.2f} s")
    return equal


def wall_sets(grid, bp, conn, which: str):
    """``(W, Q, bound)`` from the Deformer's set-up: wall points, query points, 20 rotation lengths."""
    from tfi_quat.deform import WALL, Deformer

    if conn is not None:
        d = Deformer(grid, connectivity=conn)
    else:
        bp = gen.boundary_patches("wing", grid)
        d = Deformer(grid, walls=bp["walls"], symmetry=bp["symmetry"], fixed=bp["fixed"])
    P = d.skeleton.points.P
    W = np.ascontiguousarray(P[d.skeleton.points.kind == WALL])
    Q = P if which == "all" else P[np.isfinite(d.two_level.layer.dwall)]
    return W, np.ascontiguousarray(Q), 20.0 * d.rotation_length


def _same_nearest(W, Q, ref, out):
    """(equal, ties): same distances; same indices but at ties, where ``out``'s is the smaller."""
    (dk, ik), (d, i) = ref, out
    ik = ik.astype(np.int64)
    if not np.array_equal(dk, d):
        return False, 0
    diff = np.flatnonzero(ik != i)
    if diff.size == 0:
        return True, 0
    if np.any(ik[diff] >= len(W)) or np.any(i[diff] > ik[diff]):
        return False, diff.size

    def d2(R):
        dx = R[:, 0] - Q[diff, 0]
        dy = R[:, 1] - Q[diff, 1]
        dz = R[:, 2] - Q[diff, 2]
        return dx * dx + dy * dy + dz * dz

    return bool(np.array_equal(d2(W[ik[diff]]), d2(W[i[diff]]))), diff.size


def bench_nearest(grid, bp, conn, args) -> bool:
    t0 = time.perf_counter()
    W, Q, bound = wall_sets(grid, bp, conn, args.queries)
    ts = time.perf_counter() - t0
    print(f"\n2. wall distances: {len(W)} wall points, {len(Q)} query points ({args.queries}), "
          f"bound = 20 x rotation length = {bound:.4g} (Deformer set-up {ts:.1f} s)")

    from scipy.spatial import cKDTree

    t0 = time.perf_counter()
    nearest_within(W, Q[:10], bound)
    first = time.perf_counter() - t0
    runs = [("cKDTree(W).query", lambda: cKDTree(W).query(Q, distance_upper_bound=bound)),
            ("cKDTree(W, balanced_tree=False,", lambda: cKDTree(W, balanced_tree=False, compact_nodes=False)
             .query(Q, distance_upper_bound=bound)),
            ("nearest_within", lambda: nearest_within(W, Q, bound))]
    times, outs = [], []
    for _, fn in runs:
        t, out = _best(fn, args.repeat)
        times.append(t)
        outs.append(out)
    with use_threads(1):
        t1, out1 = _best(lambda: nearest_within(W, Q, bound), args.repeat)
    ref = outs[1]
    print(f"{'':54s}{'time (best of %d)' % args.repeat:>20s}{'within bound':>14s}{'vs best cKDTree':>17s}")
    t_kd = min(times[:2])
    labels = [runs[0][0], runs[1][0] + " compact_nodes=False)", f"nearest_within ({threads()} threads)",
              "nearest_within (1 thread)"]
    ok = True
    for label, t, out in zip(labels, times + [t1], outs + [out1]):
        equal, ties = _same_nearest(W, Q, ref, out)
        ok &= equal
        note = "" if equal else "  DIFFERENT"
        note += f"  ({ties} ties, other index)" if equal and ties else ""
        print(f"{label:54s}{t * 1e3:17.1f} ms{np.count_nonzero(np.isfinite(out[0])):14d}"
              f"{t_kd / t:16.1f}x{note}")
    print(f"same distances and indices (but at ties): {ok}; "
          f"nearest_within first call (compilation or cache load) {first:.2f} s")
    return ok


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pickle", default="/tmp/prof/wing2.8.pkl",
                    help="pickle of (grid, bp, conn); 'none' to always generate")
    ap.add_argument("--scale", type=float, default=2.8, help="wing resolution factor when generating")
    ap.add_argument("--rtol", type=float, default=1e-10, help="tol relative to the bounding-box diagonal")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--section", choices=("all", "pairs", "nearest"), default="all")
    ap.add_argument("--queries", choices=("near", "all"), default="near",
                    help="section 2: the points with a finite wall distance, or all boundary points")
    args = ap.parse_args(argv)

    grid, bp, conn, src, tg = _load(args)
    print(f"grid: {src} ({tg:.1f} s), {len(grid)} blocks, {grid.npoints / 1e6:.2f} M points")
    print(f"load average {os.getloadavg()[0]:.1f}, {os.cpu_count()} CPUs, threads {threads()}")
    ok = True
    if args.section in ("all", "pairs"):
        if not bench_pairs(grid, args):
            ok = False
            print("pair sets differ")
    if args.section in ("all", "nearest"):
        if not bench_nearest(grid, bp, conn, args):
            ok = False
            print("nearest neighbours differ")
    if not ok:
        raise SystemExit("results differ")


if __name__ == "__main__":
    main()
