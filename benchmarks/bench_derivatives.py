"""Deformer.jvp and Deformer.vjp against a deform step, side by side (issue 18's targets).

On the shipped 501 k-point wing (``grids/wing_ch_501k.x`` and its case file,
two-level method, the wall moved by the two-mode model of
``examples/coupling_loop.py``) and, with ``--big``, the 10 M-point benchmark
grid of ``bench_deform.py`` (the NACA 0012 C-grid extruded along z): after one
step, ``--repeat`` rounds of a bare step ``deform(xs)``, ``jvp(u)`` and
``vjp(v)``, alternating, with their medians and ratios (targets: jvp <= 2x,
vjp <= 3x a step).  The first derivative call after a step also builds the
boundary level's linearisation (once per step): its time is reported apart
(``first jvp``), and the memory that linearisation keeps (``tracemalloc``:
what stays allocated after the call, against the coordinate bytes; target
<= 1x).  Then the accuracy on that grid: the V curve of ``jvp`` against
central differences of ``deform`` (its best point: target <= 1e-6) and the
dot-product test (target <= 1e-10).  On a busy machine only the ratios mean
anything.

    python benchmarks/bench_derivatives.py                # the wing
    python benchmarks/bench_derivatives.py --big          # and the 10 M-point grid
    python benchmarks/bench_derivatives.py --repeat 3 --threads 1
"""

from __future__ import annotations

import argparse
import gc
import importlib.util
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent


def _example():
    spec = importlib.util.spec_from_file_location("coupling_loop", ROOT / "examples" / "coupling_loop.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def wing_case(threads):
    import tfi_quat as tq
    from tfi_quat.case import load_case
    from tfi_quat.demo import sample_path
    case = load_case(sample_path("wing_ch_501k.toml"))
    grid = tq.read(case.grid)
    d = tq.Deformer(grid, walls=case.walls, symmetry=case.symmetry, fixed=case.fixed,
                    threads=threads)
    wing = _example().TwoModeWing(d.surface_points())
    xs = d.surface_points() + wing.displacements(0.03)
    u = wing.displacements(0.01)
    return "wing 501k", d, xs, u


def big_case(threads, points=1e7):
    import tfi_quat as tq
    from tfi_quat.deform import rigid_motion
    sys.path.insert(0, str(HERE))
    from bench_cli import extruded_grid
    grid = extruded_grid(points)
    d = tq.Deformer(grid, walls=["1:kmin"], threads=threads)
    P = d.surface_points()
    xs = rigid_motion(2.0, axis=(0, 0, 1), about=(0.25, 0, 0))(P)
    xs[:, 1] += 0.002 * np.sin(6.0 * P[:, 0])
    u = np.zeros_like(P)
    u[:, 1] = 0.01 * np.cos(4.0 * P[:, 0])
    return f"C-grid {grid.npoints / 1e6:.1f} M", d, xs, u


def run(name, d, xs, u, repeat):
    coord = d.grid.npoints * 24
    d.deform(xs)                                # compile / warm the step
    d.jvp(u)                                    # compile the derivative kernels
    d.vjp([np.ones(b.xyz.shape) for b in d.grid])
    v = [np.random.default_rng(0).standard_normal(b.xyz.shape) for b in d.grid]
    # the linearisation: the first derivative call after a step builds it
    g = d.deform(xs)
    del g
    gc.collect()
    tracemalloc.start()
    m0 = tracemalloc.get_traced_memory()[0]
    t0 = time.perf_counter()
    J = d.jvp(u)
    first = time.perf_counter() - t0
    del J
    gc.collect()
    kept = tracemalloc.get_traced_memory()[0] - m0
    tracemalloc.stop()
    times = {"deform": [], "jvp": [], "vjp": []}
    for _ in range(repeat):
        for k, f in (("deform", lambda: d.deform(xs)), ("jvp", lambda: d.jvp(u)),
                     ("vjp", lambda: d.vjp(v))):
            if k == "jvp":
                d.jvp(u)                        # the linearisation of this step: built once
            t0 = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t0)
    med = {k: float(np.median(t)) for k, t in times.items()}
    print(f"\n{name}: {d.grid.npoints} points, {len(d.grid)} blocks, method {d.method}, "
          f"threads {d.threads or 'all'}")
    print(f"  deform step         {med['deform']:8.3f} s")
    print(f"  jvp                 {med['jvp']:8.3f} s   {med['jvp'] / med['deform']:5.2f} x step"
          f"   (target <= 2)")
    print(f"  vjp                 {med['vjp']:8.3f} s   {med['vjp'] / med['deform']:5.2f} x step"
          f"   (target <= 3)")
    print(f"  first jvp of a step {first:8.3f} s   {first / med['deform']:5.2f} x step"
          f"   (builds the linearisation)")
    print(f"  linearisation kept  {kept / 2**20:8.1f} MB  {kept / coord:5.2f} x coordinates"
          f"   (target <= 1)")
    # accuracy on this grid: the V curve of jvp against central differences, the dot test
    d.deform(xs)
    J = d.jvp(u)
    g = d.vjp(v)
    scale = max(float(np.abs(j).max()) for j in J)
    curve = []
    for h in (1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8):
        gp = d.deform(xs + h * u)
        gm = d.deform(xs - h * u)
        curve.append((h, max(float(np.abs((a.xyz - b.xyz) / (2 * h) - j).max())
                             for a, b, j in zip(gp, gm, J)) / scale))
        del gp, gm
    d.deform(xs)
    rhs = sum(float(np.sum(a * b)) for a, b in zip(v, J))
    dot = abs(float(np.sum(g * u)) - rhs) / abs(rhs)
    print("  jvp vs central differences of deform (max error / max |jvp|):")
    print("    " + "  ".join(f"h={h:.0e}: {e:.1e}" for h, e in curve))
    print(f"  best {min(e for _, e in curve):.1e} (target <= 1e-6); dot-product test "
          f"|<vjp(v),u> - <v,jvp(u)>| / |<v,jvp(u)>| = {dot:.1e} (target <= 1e-10)")
    return med, first, kept / coord


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--big", action="store_true", help="also the 10 M-point grid")
    ap.add_argument("--big-points", type=float, default=1e7)
    a = ap.parse_args(argv)
    run(*wing_case(a.threads), a.repeat)
    if a.big:
        run(*big_case(a.threads, a.big_points), max(1, a.repeat // 2))


if __name__ == "__main__":
    main()
