"""CGNS read and write throughput, side by side with the project's own HDF5 layout.

Writes and reads the same 3-D multiblock grid (default 20 M points, float64,
uncompressed) as a tfi_quat HDF5 file (``tfi_quat.io.hdf5``) and as a
CGNS/HDF5 file (``tfi_quat.io.cgns``): a new CGNS file with its boundary
conditions and 1-to-1 records, a CGNS file written like its source (the
source's tree copied, the coordinates replaced), and the reads of both
formats (the CGNS read with its connectivity, checked against the
coordinates), once with the metadata guard's verdict cached (a file read
again) and once with the guard walking the file (a first read: the file's
times are renewed, so each format's reader forks its guard, which walks that
file's metadata, exactly as on the first read of a new file; the same
process, grid and page cache for both).  Every figure is the best of
``--repeat`` runs, run round-robin so that a change of the machine's load
affects all of them alike; before each timed write the target is deleted and
dirty pages are flushed.  Reads follow the writes (hot page cache,
flushed first: the file written last is not read during its write-back).  The
goal: CGNS within 1.2x of HDF5 both ways.

Besides the wall-clock seconds, each row has its CPU seconds (this process
and the guard's child, best of the runs too): on a loaded machine the CPU
ratios move less than the wall-clock ones (writes wait for the disk, so
their CPU ratio is not the goal's measure).

Usage::

    python3 benchmarks/bench_cgns.py [--points 20000000] [--blocks 8] [--repeat 3]
                                     [--dir DIR] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_hdf5 import best_of, make_grid  # noqa: E402
from tfi_quat.io import cgns, hdf5  # noqa: E402
from tfi_quat.spec import PatchSpec  # noqa: E402
from tfi_quat.topology import Connectivity, Patch  # noqa: E402


def boundary(grid) -> Connectivity:
    """Every block face a patch (walls on block 1, the rest fixed): a ZoneBC per zone.

    The blocks of :func:`bench_hdf5.make_grid` do not abut, so there are no
    interfaces; the records are few and small either way (the coordinates
    are the bytes that count).
    """
    from tfi_quat.grid import face_shape, faces_of
    patches = []
    for n, b in enumerate(grid):
        for f in faces_of(3):
            na, nb = face_shape(b.dims, f)
            patches.append(Patch(PatchSpec(n, f, ((0, na - 1), (0, nb - 1))), "wall" if n == 0 else "fixed"))
    return Connectivity([], patches, 3, [b.dims for b in grid])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=float, default=20e6, help="grid points in all (default 20e6)")
    ap.add_argument("--blocks", type=int, default=8, help="number of blocks (default 8)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per figure, best kept (default 3)")
    ap.add_argument("--dir", default=None, help="folder for the files (default: a temporary one)")
    ap.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = ap.parse_args(argv)

    load_before = os.getloadavg()
    grid = make_grid(int(args.points), args.blocks)
    grid.connectivity = boundary(grid)
    nbytes = sum(b.xyz.nbytes for b in grid)
    print(f"grid: {grid.nblocks} blocks, {grid.npoints:,} points, {nbytes / 2**20:.0f} MiB of coordinates")
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        tmp = Path(tmp)
        h5, cg, cg_src, cg_like = tmp / "g.h5", tmp / "g.cgns", tmp / "src.cgns", tmp / "like.cgns"
        hdf5.write(h5, grid)
        cgns.write(cg, grid, keep=False)
        cgns.write(cg_src, grid, keep=False)
        source = cgns.read(cg_src)                   # a grid read from CGNS, to write like its file

        def first(read, path):
            # a new change time: the metadata guard walks the file again, as on a first read
            def run():
                os.utime(path)
                read(path)
            return run
        writes, writes_cpu = best_of({
            "hdf5 write": (lambda: hdf5.write(h5, grid), h5),
            "cgns write (new file)": (lambda: cgns.write(cg, grid, keep=False), cg),
            "cgns write (like its source)": (lambda: cgns.write(cg_like, source), cg_like),
        }, args.repeat, cpu=True)
        os.sync()  # the last file written (like.cgns) is not read while its pages are written back
        reads, reads_cpu = best_of({
            "hdf5 read": (lambda: hdf5.read(h5), None),
            "cgns read": (lambda: cgns.read(cg), None),
            "cgns read (like file)": (lambda: cgns.read(cg_like), None),
            "hdf5 first read (guard walks)": (first(hdf5.read, h5), None),
            "cgns first read (guard walks)": (first(cgns.read, cg), None),
        }, args.repeat, cpu=True)
        back = cgns.read(cg_like)
        assert all(np.array_equal(a.xyz, b.xyz) for a, b in zip(back, grid))
        sizes = {"hdf5": h5.stat().st_size, "cgns": cg.stat().st_size}

    t, c = writes | reads, writes_cpu | reads_cpu

    def ref(name):
        return "hdf5 write" if "write" in name else \
            "hdf5 first read (guard walks)" if "first" in name else "hdf5 read"
    pairs = {"write": "cgns write (new file)", "write like": "cgns write (like its source)",
             "read": "cgns read", "read like": "cgns read (like file)",
             "first read": "cgns first read (guard walks)"}
    ratios = {k: t[name] / t[ref(name)] for k, name in pairs.items()}
    cpu_ratios = {k: c[name] / max(c[ref(name)], 1e-6) for k, name in pairs.items()}
    print(f"{'':34s}{'seconds':>9s}{'GB/s':>8s}{'vs hdf5':>9s}{'cpu s':>9s}{'vs hdf5':>9s}")
    for name, sec in t.items():
        print(f"{name:34s}{sec:9.3f}{nbytes / sec / 1e9:8.2f}{sec / t[ref(name)]:9.2f}"
              f"{c[name]:9.3f}{c[name] / max(c[ref(name)], 1e-6):9.2f}")
    print("ratios (goal <= 1.2): " + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items()))
    print("CPU ratios: " + ", ".join(f"{k} {v:.2f}" for k, v in cpu_ratios.items()))
    if args.json:
        doc = {"date": datetime.date.today().isoformat(), "points": grid.npoints, "blocks": grid.nblocks,
               "bytes": nbytes, "repeat": args.repeat, "seconds": t, "ratios": ratios, "cpu_seconds": c,
               "cpu_ratios": cpu_ratios, "file_bytes": sizes,
               "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                           "platform": platform.platform(),
                           "load_average": {"before": load_before[0], "after": os.getloadavg()[0]}}}
        Path(args.json).write_text(json.dumps(doc, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
