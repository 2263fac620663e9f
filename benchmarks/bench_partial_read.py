"""Partial reads against a full read of the same file.

Writes one multi-block grid (default 20 M points in 8 blocks of random
coordinates) as binary Plot3D, Fortran Plot3D, HDF5 and CGNS, then times, in
the same run and interleaved, a full ``tq.read``, ``tq.read(path,
blocks=[b])`` of one block, ``tq.read_faces(path)`` (every face of every
block, what each rank of a distributed deformation reads besides its own
blocks) and ``tq.read_faces(path, blocks=[b])`` (one block's faces: ranks
that split the face reads), and prints the ratios to the full read.  Best of ``--repeat`` runs.

By default the files sit in the page cache (they were just written): the
times are CPU and memory bound.  ``--cold`` drops each file's cached pages
before every read (``posix_fadvise(DONTNEED)``; best effort, Linux), which
is closer to a first read on a cluster's file system.

Usage::

    python benchmarks/bench_partial_read.py                  # 20 M points
    python benchmarks/bench_partial_read.py --points 2000000 --repeat 2 --cold
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import tfi_quat as tq  # noqa: E402
from tfi_quat import Grid  # noqa: E402


def make_grid(points: int, nblocks: int, seed: int = 0) -> Grid:
    """About ``points`` points in ``nblocks`` cube-like blocks of random coordinates."""
    rng = np.random.default_rng(seed)
    n = max(2, round((points / nblocks) ** (1 / 3)))
    blocks = []
    for _ in range(nblocks):
        xyz = np.empty((n, n, n, 3), order="F")
        xyz.ravel(order="K")[:] = rng.random(xyz.size)
        blocks.append(xyz)
    return Grid(blocks, 3)


def drop_cache(path: Path) -> None:
    """Ask the kernel to forget the file's cached pages (no-op where unsupported)."""
    if hasattr(os, "posix_fadvise"):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def bench(path: Path, block: int, repeat: int, cold: bool) -> dict:
    """Best times of the three reads, interleaved so that the load hits them alike."""
    cases = {"full": lambda: tq.read(path), "one block": lambda: tq.read(path, blocks=[block]),
             "faces": lambda: tq.read_faces(path),
             "faces of one": lambda: tq.read_faces(path, blocks=[block])}
    best = {k: float("inf") for k in cases}
    for _ in range(repeat):
        for name, fn in cases.items():
            if cold:
                drop_cache(path)
            t0 = time.perf_counter()
            out = fn()
            best[name] = min(best[name], time.perf_counter() - t0)
            del out
    return best


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=20_000_000)
    ap.add_argument("--blocks", type=int, default=8)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cold", action="store_true", help="drop the page cache of the file before each read")
    ap.add_argument("--formats", default="binary,fortran,hdf5,cgns")
    ap.add_argument("--dir", default=tempfile.gettempdir())
    args = ap.parse_args(argv)

    grid = make_grid(args.points, args.blocks)
    ni = grid[0].dims[0]
    face_points = sum(2 * (a * b + a * c + b * c) for a, b, c in grid.dims)
    print(f"grid: {grid.npoints:,} points in {len(grid)} blocks of {ni}^3; faces {face_points:,} points "
          f"({face_points / grid.npoints:.1%}); best of {args.repeat}, "
          f"{'cold (fadvise DONTNEED)' if args.cold else 'page cache warm'}")
    print(f"{'format':10s} {'file MB':>8s} {'full s':>8s} {'1 block s':>10s} {'ratio':>7s} "
          f"{'faces s':>8s} {'ratio':>7s} {'faces of 1 s':>13s} {'ratio':>7s}")
    specs = {"binary": ("g.x", dict(encoding="binary")), "fortran": ("g.g", dict(encoding="fortran")),
             "hdf5": ("g.h5", {}), "cgns": ("g.cgns", {})}
    with tempfile.TemporaryDirectory(dir=args.dir) as folder:
        for name in args.formats.split(","):
            fname, opts = specs[name]
            path = Path(folder) / fname
            tq.write(path, grid, **opts)
            t = bench(path, len(grid) // 2, args.repeat, args.cold)
            print(f"{name:10s} {path.stat().st_size / 1e6:8.0f} {t['full']:8.3f} {t['one block']:10.3f} "
                  f"{t['one block'] / t['full']:7.3f} {t['faces']:8.3f} {t['faces'] / t['full']:7.3f} "
                  f"{t['faces of one']:13.3f} {t['faces of one'] / t['full']:7.3f}")
            path.unlink()


if __name__ == "__main__":
    main()
