"""Quality benchmark: the full report of tfi_quat.quality on a >= 10 M-point grid.

The grid is synthetic: a box of ``--blocks`` blocks (stacked along x), each
warped smoothly (so no cell is a rectangle and every metric has work to do);
the reference is the same box unwarped, the walls are every block's jmin face.
Three reports are timed (best of ``--repeat``): cell metrics alone, with the
reference (volume ratio), and with reference and walls (orthogonality and its
change over ``--layers`` layers), beside two streaming references measured in
the same run, alternately with the report (wall time, and the process CPU
time over all threads per point, which the other users of a shared machine
disturb less):

- ``copy``: numpy ``np.copyto`` of every block's coordinates (24 bytes read
  and 24 written per point);
- ``sum``: a parallel numba pass that reads every coordinate once (24 bytes
  per point), the least a quality pass over the grid must do.

    python benchmarks/bench_quality.py                  # ~10.5 M points
    python benchmarks/bench_quality.py --points 2e6     # smaller
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from tfi_quat import Block, Grid
from tfi_quat._jit import numba, threads
from tfi_quat.quality import quality_report


# the reference: a numba parallel loop (the package's own kernels run on its thread pool)
@numba.njit(parallel=True, fastmath=True, nogil=True)   # a reduction numba may vectorise
def _stream_sum(x, out):
    nk = x.shape[2]
    for k in numba.prange(nk):
        s = 0.0
        for d in range(3):
            for j in range(x.shape[1]):
                for i in range(x.shape[0]):
                    s += x[i, j, k, d]
        out[k] = s


def make_grid(points: float, blocks: int):
    """(warped grid, reference box, walls) with about ``points`` points."""
    per = points / blocks
    # block shape ni : nj : nk = 1.2 : 0.9 : 1
    n = (per / (1.2 * 0.9)) ** (1.0 / 3.0)
    ni, nj, nk = int(round(1.2 * n)), int(round(0.9 * n)), int(round(n))
    ref, warped = [], []
    for b in range(blocks):
        i = np.linspace(b, b + 1.0, ni)[:, None, None]
        j = np.linspace(0.0, 0.75, nj)[None, :, None] ** 1.5     # clustered towards the wall (jmin)
        k = np.linspace(0.0, 0.8, nk)[None, None, :]
        box = np.empty((ni, nj, nk, 3), order="F")
        box[..., 0] = i
        box[..., 1] = j
        box[..., 2] = k
        w = np.empty_like(box)
        w[..., 0] = i + 0.05 * np.sin(2.0 * np.pi * j) * np.cos(np.pi * k)
        w[..., 1] = j + 0.04 * np.sin(np.pi * i) * (1.0 - j) + 0.02 * k * i
        w[..., 2] = k + 0.03 * np.sin(np.pi * (i + j))
        ref.append(Block(box))
        warped.append(Block(w))
    walls = [f"{b + 1}:jmin" for b in range(blocks)]
    return Grid(warped, ndim=3), Grid(ref, ndim=3), walls


def timed(fn):
    """(wall seconds, process CPU seconds over all threads) of one call."""
    c0 = time.process_time()
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0, time.process_time() - c0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=float, default=10.5e6, help="grid points (default 10.5 M)")
    ap.add_argument("--blocks", type=int, default=4)
    ap.add_argument("--layers", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    grid, ref, walls = make_grid(args.points, args.blocks)
    npts = grid.npoints
    print(f"grid: {len(grid)} blocks {' + '.join('x'.join(map(str, b.dims)) for b in grid)}, "
          f"{npts / 1e6:.2f} M points ({npts * 24 / 1e6:.0f} MB coordinates), made in "
          f"{time.perf_counter() - t0:.1f} s; threads {threads()}, "
          f"{os.cpu_count()} CPUs")
    print(f"load average before: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")

    t0 = time.perf_counter()
    small = Grid([Block(b.xyz[:4, :4, :4]) for b in grid], ndim=3)
    quality_report(small, ref=Grid([Block(b.xyz[:4, :4, :4]) for b in ref], ndim=3), walls=walls)
    print(f"first call on a tiny grid (numba compile or cache load): {time.perf_counter() - t0:.2f} s")

    copies = [np.empty_like(b.xyz) for b in grid]
    sums = [np.empty(b.dims[2]) for b in grid]
    for c, b in zip(copies, grid):         # touch the pages once
        np.copyto(c, b.xyz)

    def copy():
        for c, b in zip(copies, grid):
            np.copyto(c, b.xyz)

    def stream():
        for s, b in zip(sums, grid):
            _stream_sum(b.xyz, s)

    cases = [("report: cell metrics", lambda: quality_report(grid)),
             ("report: + reference (volume ratio)", lambda: quality_report(grid, ref=ref)),
             (f"report: + reference + walls ({args.layers} layers)",
              lambda: quality_report(grid, ref=ref, walls=walls, layers=args.layers))]
    stream()
    for _, fn in cases:
        fn()
    times = {"copy": [], "sum": []}
    times.update({name: [] for name, _ in cases})
    for _ in range(args.repeat):            # alternate, so every figure sees the same load
        times["copy"].append(timed(copy))
        times["sum"].append(timed(stream))
        for name, fn in cases:
            times[name].append(timed(fn))
    t_sum = min(t for t, _ in times["sum"])
    print(f"\n{'what':52s} {'best s':>7s} {'median s':>8s} {'M points/s':>10s} {'x read':>7s} "
          f"{'CPU ns/point':>12s}")
    for name, ts in times.items():
        label = {"copy": "numpy copyto of the coordinates (48 B/point)",
                 "sum": "numba parallel read of the coordinates (24 B/point)"}.get(name, name)
        b = min(t for t, _ in ts)
        cpu = min(c for _, c in ts)
        print(f"{label:52s} {b:7.3f} {np.median([t for t, _ in ts]):8.3f} {npts / b / 1e6:10.1f} "
              f"{b / t_sum:7.1f} {1e9 * cpu / npts:12.1f}")
    rep = quality_report(grid, ref=ref, walls=walls, layers=args.layers)
    print(f"\nload average after: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print(f"(the report found {rep.negative} negative cells, skewness max {rep.metrics['skewness'].max:.3f}, "
          f"volume ratio {rep.metrics['volume_ratio'].min:.3f}..{rep.metrics['volume_ratio'].max:.3f}, "
          f"orthogonality change max {rep.orthogonality['change_max']:.2f} deg)")


if __name__ == "__main__":
    main()
