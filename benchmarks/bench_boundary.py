"""Benchmark: boundary quaternions (tfi_quat.boundary.boundary_motion) on a large wall.

A ``n x n`` wing-like patch (cambered, twisted) is bent, rotated and
translated; ``boundary_motion`` is timed over several repeats after one
untimed call (numba compilation / cache load).  Prints points per second.

Usage::

    python3 benchmarks/bench_boundary.py [--points 1000000] [--repeat 5] [--threads N]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from tfi_quat import quaternion as Q  # noqa: E402
from tfi_quat._jit import threads, use_threads  # noqa: E402
from tfi_quat.boundary import boundary_motion  # noqa: E402


def wall(n: int):
    """Undeformed and deformed ``(n, n, 3)`` wall: wrapped airfoil-like sheet, bent and rotated."""
    u = np.linspace(0.0, 2.0 * np.pi, n)[:, None]
    v = np.linspace(0.0, 1.0, n)[None, :]
    x = 0.5 * (1.0 + np.cos(u)) * (1.0 - 0.4 * v)
    y = 0.06 * np.sin(u) * (1.0 - 0.4 * v) + 0.02 * np.sin(np.pi * x)
    z = 3.0 * v + 0.0 * u
    ru = np.stack(np.broadcast_arrays(x, y, z), axis=-1)
    # bending about the x axis growing along the span, then a rigid rotation + translation
    bend = 0.3 * (ru[..., 2] / 3.0) ** 2
    rd = ru.copy()
    rd[..., 1] = ru[..., 1] * np.cos(bend) - ru[..., 2] * np.sin(bend)
    rd[..., 2] = ru[..., 1] * np.sin(bend) + ru[..., 2] * np.cos(bend)
    q = Q.from_axis_angle([0.2, 0.3, 1.0], np.radians(25.0))
    rd = Q.rotate(q, rd) + np.array([0.1, -0.2, 0.05])
    return np.ascontiguousarray(ru), np.ascontiguousarray(rd)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--points", type=int, default=1_000_000, help="wall points (a square patch)")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--threads", type=int, default=0, help="threads (0: all, tfi_quat._jit.THREADS)")
    a = p.parse_args(argv)
    with use_threads(a.threads or None):
        return _run(a)


def _run(a) -> int:
    n = max(3, int(round(np.sqrt(a.points))))
    ru, rd = wall(n)
    t = time.perf_counter()
    boundary_motion(ru, rd)
    first = time.perf_counter() - t
    # reference, timed alternately in the same run: one streaming numpy pass over the
    # same points (the displacement rd - ru: reads 48 and writes 24 bytes per point)
    disp = np.empty_like(ru)
    np.subtract(rd, ru, out=disp)
    times = []
    cpu = []
    ref = []
    for _ in range(a.repeat):
        t = time.perf_counter()
        c = time.process_time()
        q, d = boundary_motion(ru, rd)
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
        t = time.perf_counter()
        np.subtract(rd, ru, out=disp)
        ref.append(time.perf_counter() - t)
    best = min(times)
    med = float(np.median(times))
    npts = n * n
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"wall {n} x {n} = {npts} points, threads {threads()}, "
          f"first call {first:.3f} s (compile or cache load)")
    print(f"boundary_motion: best {best * 1e3:.1f} ms, median {med * 1e3:.1f} ms, "
          f"{npts / best / 1e6:.1f} M points/s best, {npts / med / 1e6:.1f} M points/s median")
    print(f"reference rd - ru (numpy, one pass): best {min(ref) * 1e3:.1f} ms; "
          f"boundary_motion / reference = {best / min(ref):.1f}")
    print(f"CPU time (all threads) best {min(cpu) * 1e3:.1f} ms = {min(cpu) / npts * 1e9:.0f} ns per point; "
          f"load average {load:.1f} on {os.cpu_count()} CPUs")
    print(f"check: max |q| - 1 = {np.abs(np.linalg.norm(q, axis=-1) - 1).max():.1e}, "
          f"finite {bool(np.isfinite(q).all() and np.isfinite(d).all())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
