"""HDF5 grid I/O throughput against ``ndarray.tofile`` / ``np.fromfile`` of the same bytes.

Writes and reads a 3-D multiblock grid (default 20 M points, float64) with
``tfi_quat.io.hdf5`` uncompressed and gzip-compressed, and in the same run
writes and reads the same coordinate bytes with plain numpy.  ``write()``
is durable (temporary file, ``fsync``, rename) and is compared with
``tofile`` + ``fsync``; the HDF5 writer alone (no fsync) with plain ``tofile``.  Then times
``read_face`` (each of the six faces) and ``read_block`` on the largest
block.  Every figure is the best of ``--repeat`` runs (gzip: at most 2), run
round-robin with the numpy reference so that the ratios are fair on a shared
machine.  Reads follow the
writes, so the files are in the page cache: these are hot-cache figures
(memory and format overhead, not the disk).  Before each timed write the
target is deleted and dirty pages are flushed, so every write goes to a fresh
file (the page-cache allocation is part of the figure, the disk is not).

Usage::

    python3 benchmarks/bench_hdf5.py [--points 20000000] [--blocks 8] [--repeat 3]
                                     [--dir DIR] [--level 4] [--no-gzip]
"""

from __future__ import annotations

import argparse
import os
import resource
import platform
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tfi_quat import FACES, Block, Grid  # noqa: E402
from tfi_quat.io import hdf5  # noqa: E402


def make_grid(npoints: int, nblocks: int) -> Grid:
    """``nblocks`` near-cubic blocks of a smooth, sheared 3-D grid, about ``npoints`` in all.

    The first block is twice as large as the others (the face-read target).
    """
    share = [2.0] + [1.0] * (nblocks - 1)
    blocks = []
    for b, w in enumerate(share):
        n = int(np.ceil((npoints * w / sum(share)) ** (1.0 / 3.0)))
        ni, nj, nk = n + 8, n, max(2, n - 8)
        xyz = np.empty((ni, nj, nk, 3), order="F")
        i = np.linspace(0.0, 1.0, ni)[:, None]
        j = np.linspace(0.0, 1.0, nj)[None, :]
        for k, t in enumerate(np.linspace(0.0, 1.0, nk)):
            xyz[:, :, k, 0] = b + 2.0 * i + 0.3 * j + 0.05 * np.sin(3.0 * t)
            xyz[:, :, k, 1] = 1.5 * j + 0.2 * t + 0.02 * i * i
            xyz[:, :, k, 2] = t + 0.1 * i * j
        blocks.append(Block(xyz, name=f"block{b + 1}"))
    return Grid(blocks)


def cpu_seconds() -> float:
    """CPU seconds used so far by this process and its waited-for children (the guard's)."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def best_of(fns: dict, repeat: int, cpu: bool = False):
    """Best time of each ``fns[name] = (fn, remove)`` over ``repeat`` rounds.

    The functions run round-robin (one of each per round), so a change of the
    machine's load during the run affects all of them alike and the ratios
    stay fair.  With ``remove``, that file is deleted before each run and
    dirty pages are flushed (``os.sync``), untimed: every write goes to a
    fresh file from a clean page cache.  ``cpu``: return ``(wall, cpu)``, the
    best CPU seconds (:func:`cpu_seconds`) beside the best wall-clock ones.
    """
    wall = {name: [] for name in fns}
    used = {name: [] for name in fns}
    for _ in range(repeat):
        for name, (fn, remove) in fns.items():
            if remove is not None:
                if os.path.exists(remove):
                    os.unlink(remove)
                os.sync()
            c0, t0 = cpu_seconds(), time.perf_counter()
            fn()
            wall[name].append(time.perf_counter() - t0)
            used[name].append(cpu_seconds() - c0)
    best = {name: min(t) for name, t in wall.items()}
    return (best, {name: min(t) for name, t in used.items()}) if cpu else best


def peak_ratio(fn, nbytes: int) -> float:
    """Peak traced (numpy/Python) allocation during ``fn()``, over ``nbytes``."""
    tracemalloc.start()
    try:
        fn()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return peak / nbytes


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=float, default=20e6, help="grid points in all (default 20e6)")
    ap.add_argument("--blocks", type=int, default=8, help="number of blocks (default 8)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per figure, best kept (default 3)")
    ap.add_argument("--level", type=int, default=4, help="gzip level (default 4)")
    ap.add_argument("--no-gzip", action="store_true", help="skip the compressed runs")
    ap.add_argument("--dir", default=None, help="folder for the files (default: a temporary one)")
    args = ap.parse_args(argv)

    load0 = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    grid = make_grid(int(args.points), args.blocks)
    npts = grid.npoints
    nbytes = sum(b.xyz.nbytes for b in grid)
    rows = []

    def row(name, seconds, ref=None, extra=""):
        rate = npts / seconds
        gbs = nbytes / seconds / 1e9
        ratio = "" if ref is None else f"{ref / seconds:.2f}"
        rows.append((name, f"{seconds:.3f}", f"{rate / 1e6:.1f}", f"{gbs:.2f}", ratio, extra))

    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        raw = os.path.join(tmp, "grid.raw")
        h5 = os.path.join(tmp, "grid.h5")
        gz = os.path.join(tmp, "grid_gz.h5")

        def np_write():
            with open(raw, "wb") as fh:
                for b in grid:
                    b.xyz.T.tofile(fh)

        def np_read():
            out = []
            with open(raw, "rb") as fh:
                for b in grid:
                    a = np.fromfile(fh, dtype=np.float64, count=b.npoints * 3)
                    out.append(a.reshape(b.dims + (3,), order="F"))
            return out

        def np_write_fsync():
            with open(raw, "wb") as fh:
                for b in grid:
                    b.xyz.T.tofile(fh)
                fh.flush()
                os.fsync(fh.fileno())

        def h5_writer_alone():
            # the HDF5 file as write() makes it, without the temporary file, fsync and rename
            hdf5.write_blocks(h5, grid.blocks, ndim=grid.ndim, nblocks=grid.nblocks,
                              source_path=grid.source_path, source_format=grid.source_format)

        def os_write():
            fd = os.open(raw, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            try:
                for b in grid:
                    os.write(fd, memoryview(b.xyz.T).cast("B"))
            finally:
                os.close(fd)

        level = args.level
        w = best_of({"np": (np_write, raw), "os": (os_write, raw), "h5w": (h5_writer_alone, h5),
                     "npsync": (np_write_fsync, raw), "h5": (lambda: hdf5.write(h5, grid), h5)},
                    args.repeat)
        r = best_of({"np": (np_read, None), "h5": (lambda: hdf5.read(h5), None),
                     "h5raw": (lambda: hdf5.read(h5, allow_nonfinite=True), None)}, args.repeat)
        row("np tofile (same bytes)", w["np"])
        row("np fromfile (same bytes)", r["np"])
        row("os.write (same bytes)", w["os"], w["np"])
        row("hdf5 writer alone", w["h5w"], w["np"], "no fsync")
        row("np tofile + fsync", w["npsync"])
        row("hdf5 write()", w["h5"], w["npsync"], f"vs tofile+fsync; file {os.path.getsize(h5) / nbytes:.3f}x")
        row("hdf5 read", r["h5"], r["np"], f"peak mem {peak_ratio(lambda: hdf5.read(h5), nbytes):.2f}x")
        row("hdf5 read, no NaN scan", r["h5raw"], r["np"])
        if not args.no_gzip:
            gzrep = min(args.repeat, 2)
            w = best_of({"np": (np_write_fsync, raw), "gz": (lambda: hdf5.write(
                gz, grid, compression="gzip", compression_level=level), gz)}, gzrep)
            r = best_of({"np": (np_read, None), "gz": (lambda: hdf5.read(gz), None)}, gzrep)
            row(f"hdf5 write() gzip {level}", w["gz"], w["np"],
                f"vs tofile+fsync; file {os.path.getsize(gz) / nbytes:.3f}x")
            row(f"hdf5 read gzip {level}", r["gz"], r["np"])

        big = grid[0]
        face_rows = []
        files = [("uncompressed", h5)] + ([] if args.no_gzip else [(f"gzip {args.level}", gz)])
        for label, path in files:
            t_blk = best_of({"b": (lambda: hdf5.read_block(path, 0), None)}, args.repeat)["b"]
            face_rows.append((label, "read_block", f"{t_blk * 1e3:.1f}", f"{big.xyz.nbytes / t_blk / 1e9:.2f}"))
            for face in FACES:
                t_f = best_of({"f": (lambda: hdf5.read_face(path, 0, face), None)}, args.repeat)["f"]
                fb = big.face(face).size * 8
                face_rows.append((label, face, f"{t_f * 1e3:.2f}", f"{fb / t_f / 1e9:.2f}"))

    print(f"# tfi_quat HDF5 I/O: {npts:,} points in {grid.nblocks} blocks, {nbytes / 1e9:.2f} GB float64; "
          f"best of {args.repeat} (gzip: {min(args.repeat, 2)}); hot page cache")
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cpus, "
          f"python {platform.python_version()}, numpy {np.__version__}, h5py "
          f"{__import__('h5py').version.version}, HDF5 {__import__('h5py').version.hdf5_version}; "
          f"load average {load0:.1f} at start, {os.getloadavg()[0]:.1f} at the end")
    head = ("operation", "time s", "Mpoints/s", "GB/s", "x numpy", "notes")
    widths = [max(len(r[c]) for r in rows + [head]) for c in range(len(head))]
    print("| " + " | ".join(h.ljust(w) for h, w in zip(head, widths)) + " |")
    print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for r in rows:
        print("| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |")
    print()
    print(f"# largest block {'x'.join(map(str, big.dims))} ({big.xyz.nbytes / 1e6:.0f} MB): "
          "read_block and read_face")
    head = ("file", "read", "time ms", "GB/s")
    widths = [max(len(r[c]) for r in face_rows + [head]) for c in range(len(head))]
    print("| " + " | ".join(h.ljust(w) for h, w in zip(head, widths)) + " |")
    print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for r in face_rows:
        print("| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
