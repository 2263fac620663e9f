"""Plot3D I/O throughput against numpy's own file I/O on the same bytes.

Reads and writes a 3-D multi-block grid (binary float64, C stream and
Fortran unformatted) and an ASCII grid, and prints points/s and GB/s next to
``np.fromfile`` / ``ndarray.tofile`` of the same bytes measured in the same
run, plus the peak memory of a binary read (tracemalloc, in a fresh
subprocess) relative to the grid's size.  Best of ``--repeat`` runs; the
files go to ``--dir`` (default: the system temporary folder) and are deleted.

Usage::

    python benchmarks/bench_io.py                    # 20 M points binary, 1 M ASCII
    python benchmarks/bench_io.py --points 200000 --ascii-points 20000 --repeat 2
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tfi_quat import Grid  # noqa: E402
from tfi_quat.io import plot3d  # noqa: E402
from tfi_quat.io.plot3d import Plot3DFormat  # noqa: E402


def make_grid(points: int, nblocks: int = 8, seed: int = 0) -> Grid:
    """A multi-block grid of about ``points`` points (cube-like blocks of random coordinates)."""
    rng = np.random.default_rng(seed)
    per = max(1, points // nblocks)
    n = max(1, round(per ** (1 / 3)))
    blocks = []
    left = points
    for b in range(nblocks):
        nk = max(1, min(left, per) // (n * n)) if b == nblocks - 1 else max(1, per // (n * n))
        xyz = np.empty((n, n, nk, 3), order="F")
        xyz.ravel(order="K")[:] = rng.random(xyz.size)
        blocks.append(xyz)
        left -= n * n * nk
    return Grid(blocks)


def best(fn, repeat: int, setup=None) -> float:
    """Best wall time of ``repeat`` calls; ``setup`` runs untimed before each."""
    times = []
    for _ in range(repeat):
        if setup is not None:
            setup()
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def paired(fa, fb, repeat: int, setup=None) -> tuple[float, float]:
    """Best times of two operations timed alternately (so both see the same machine load)."""
    ta, tb = [], []
    for _ in range(repeat):
        for fn, acc in ((fa, ta), (fb, tb)):
            if setup is not None:
                setup()
            t0 = time.perf_counter()
            fn()
            acc.append(time.perf_counter() - t0)
    return min(ta), min(tb)


def tofile_same_bytes(grid: Grid, path: Path, fsync: bool) -> None:
    with open(path, "wb") as fh:
        for b in grid:
            b.xyz.ravel(order="K").tofile(fh)
        if fsync:
            fh.flush()
            os.fsync(fh.fileno())


def writer_only(grid: Grid, path: Path, fmt: Plot3DFormat) -> None:
    """The Plot3D byte writer into a plain file: no temporary file, rename or fsync."""
    with open(path, "wb") as fh:
        plot3d.write_header(fh, fmt, [b.dims for b in grid])
        for n, b in enumerate(grid):
            plot3d.write_block(fh, b, fmt, f"{path}: block {n + 1}")


PEAK_SCRIPT = """
import json, sys, tracemalloc
sys.path.insert(0, {root!r})
from tfi_quat.io.plot3d import read
tracemalloc.start()
g = read({path!r})
cur, peak = tracemalloc.get_traced_memory()
size = sum(b.xyz.nbytes + (b.iblank.nbytes if b.iblank is not None else 0) for b in g)
print(json.dumps({{"peak": peak, "size": size}}))
"""


def peak_memory(path: Path) -> float:
    out = subprocess.run([sys.executable, "-c", PEAK_SCRIPT.format(root=str(ROOT), path=str(path))],
                         check=True, capture_output=True, text=True).stdout
    d = json.loads(out.strip().splitlines()[-1])
    return d["peak"] / d["size"]


def row(name, seconds, points, nbytes, ref=None):
    ratio = f"{ref / seconds:6.2f}x" if ref else "      "
    return (f"  {name:<48s} {seconds:8.3f} s {points / seconds / 1e6:9.2f} Mpt/s "
            f"{nbytes / seconds / 1e9:7.2f} GB/s {ratio}")


def fresh(*paths):
    """Untimed set-up of a write: no old target, no dirty pages queued from earlier writes."""
    def setup():
        for p in paths:
            if p.exists():
                p.unlink()
        os.sync()
    return setup


def bench_binary(grid: Grid, folder: Path, repeat: int) -> list[str]:
    lines = []
    npts = grid.npoints
    data_bytes = 24 * npts
    raw = folder / "raw.bin"
    p = folder / "grid.x"
    for fmt in (Plot3DFormat(), Plot3DFormat(encoding="fortran")):
        tag = "C binary" if fmt.encoding == "binary" else "Fortran"
        t_tofile, t_wo = paired(lambda: tofile_same_bytes(grid, raw, False),
                                lambda: writer_only(grid, p, fmt), repeat, fresh(raw, p))
        t_sync, t_w = paired(lambda: tofile_same_bytes(grid, raw, True),
                             lambda: plot3d.write(p, grid, like=fmt), repeat, fresh(raw, p))
        tofile_same_bytes(grid, raw, False)
        t_ff, t_r = paired(lambda: np.fromfile(raw, dtype="<f8"), lambda: plot3d.read(p), repeat)
        assert plot3d.detect(p) == fmt
        lines.append(row(f"{tag}: ndarray.tofile (same bytes)", t_tofile, npts, data_bytes))
        lines.append(row(f"{tag}: byte writer alone vs tofile", t_wo, npts, data_bytes, t_tofile))
        lines.append(row(f"{tag}: ndarray.tofile + fsync", t_sync, npts, data_bytes))
        lines.append(row(f"{tag}: write() (atomic, fsync) vs tofile+fsync", t_w, npts, data_bytes, t_sync))
        lines.append(row(f"{tag}: np.fromfile (same bytes)", t_ff, npts, data_bytes))
        lines.append(row(f"{tag}: read() vs fromfile", t_r, npts, data_bytes, t_ff))
        lines.append(f"  {tag}: peak memory of read() / grid size: {peak_memory(p):.3f}")
    p.unlink()
    raw.unlink()
    return lines


def bench_ascii(grid: Grid, folder: Path, repeat: int) -> list[str]:
    lines = []
    npts = grid.npoints
    p = folder / "grid.fmt"
    t_w = best(lambda: plot3d.write(p, grid, encoding="ascii"), repeat, fresh(p))
    size = p.stat().st_size
    text = p.read_bytes()
    assert plot3d.read(p) == grid, "ASCII round trip is not exact"
    t_parse, t_r = paired(lambda: np.fromstring(text, dtype=np.float64, sep=" "),
                          lambda: plot3d.read(p), repeat)
    lines.append(row("ASCII write (17 digits)", t_w, npts, size))
    lines.append(row("np.fromstring of the same text", t_parse, npts, size))
    lines.append(row("ASCII read() vs fromstring", t_r, npts, size, t_parse))
    lines.append(f"  ASCII read: {3 * npts / t_r / 1e6:.2f} M values/s (target >= 2.5), "
                 f"write: {3 * npts / t_w / 1e6:.2f} M values/s, file {size / 1e6:.1f} MB")
    p.unlink()
    return lines


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=20_000_000, help="binary grid points")
    ap.add_argument("--ascii-points", type=int, default=1_000_000, help="ASCII grid points")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--dir", default=tempfile.gettempdir())
    args = ap.parse_args(argv)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    with tempfile.TemporaryDirectory(dir=args.dir, prefix="bench_io_") as d:
        folder = Path(d)
        grid = make_grid(args.points)
        print(f"binary: {grid.npoints:,} points in {len(grid)} blocks, "
              f"{24 * grid.npoints / 1e6:.0f} MB of float64, best of {args.repeat}; "
              f"{os.cpu_count()} CPU(s), load average {load:.1f} at start")
        print(f"  {'':<48s} {'time':>10s} {'points/s':>15s} {'bytes/s':>12s} {'ratio':>7s}")
        for line in bench_binary(grid, folder, args.repeat):
            print(line)
        del grid
        agrid = make_grid(args.ascii_points, nblocks=4, seed=1)
        print(f"ASCII: {agrid.npoints:,} points in {len(agrid)} blocks")
        for line in bench_ascii(agrid, folder, args.repeat):
            print(line)


if __name__ == "__main__":
    main()
