"""The coupling interface against issue 16's targets: step cost, threads, allocation, scale.

Four measurements, each side by side in one run (on a busy machine only
such ratios mean anything):

``wing``
    On the shipped 501 k-point wing (``grids/wing_ch_501k.x`` and its case
    file), the wall moved by the two-mode model of ``examples/coupling_loop.py``:
    a *coupled* step (``deform(xs, ids=..., out=buffer, check=True)``, the rows
    in a solver's own order: a fixed random permutation of ``surface_ids()``)
    against a *bare* step (``deform(xs)``: new grid, no check), alternating,
    ``--repeat`` times each; the ratio of the medians (target <= 1.3).  Each
    option alone (``ids=``, ``out=``, ``check=True``) runs in the same rounds,
    to show where the difference goes; CPU times (``process_time``) beside
    the wall times, the steadier figure on a busy machine.  The
    coupled result must be bit-identical to the callable form on the same
    surface (``deform(lambda p: ...)``), and is checked.
``threads``
    CPU time (``time.process_time``: all threads of the process) of one step
    with ``Deformer(threads=2)`` against ``threads=1``, alternating; the
    ratio of the medians (target <= 1.3: no threads spinning).  ``--load N``
    runs N busy processes meanwhile (the loaded case).
``alloc``
    ``tracemalloc``'s peak during one step with ``out=`` (after a warm-up
    step), against the grid's coordinate bytes (target < 5 %); a step
    without ``out=`` beside it.
``scale``
    The shipped NACA 0012 C-grid extruded along z (wall ``1:kmin``, the
    walls rotated 2 deg about z; the grid of ``bench_cli.py``) at 5 M and
    50 M points (``--quick``: 0.2 M and 2 M), each size in a child process
    so that each peak is its own: the step rate with ``out=`` (no check; one
    checked step is timed after, for information; target: 50 M
    at least 0.8x the 5 M rate) and the child's peak resident memory over
    the coordinate bytes (target <= 3.5x at 50 M; "above start" subtracts
    the memory of the process before the grid was made: Python, numpy,
    numba and the compiled kernels).

    python benchmarks/bench_coupling.py                  # all four, full sizes
    python benchmarks/bench_coupling.py --quick          # small sizes, fewer repeats
    python benchmarks/bench_coupling.py --only wing,threads --load 2
    python benchmarks/bench_coupling.py --json           # also benchmarks/results/DATE-coupling.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import importlib.util
import json
import os
import resource
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent
SECTIONS = ("wing", "threads", "alloc", "scale")


def _example():
    """``examples/coupling_loop.py`` as a module (its structural model)."""
    spec = importlib.util.spec_from_file_location("coupling_loop", ROOT / "examples" / "coupling_loop.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def wing_deformer(**kw):
    import tfi_quat as tq
    from tfi_quat.case import load_case
    from tfi_quat.demo import sample_path
    case = load_case(sample_path("wing_ch_501k.toml"))
    grid = tq.read(case.grid)
    return tq.Deformer(grid, walls=case.walls, symmetry=case.symmetry, fixed=case.fixed, **kw)


def _same(a, b) -> bool:
    return len(a) == len(b) and all(np.array_equal(x.xyz, y.xyz) for x, y in zip(a, b))


def bench_wing(repeat: int, t: float = 0.03) -> dict:
    """Coupled step (ids, out=, check=True) against a bare step, alternating."""
    ex = _example()
    d = wing_deformer()
    wing = ex.TwoModeWing(d.surface_points())
    xs = d.surface_points() + wing.displacements(t)
    perm = np.random.default_rng(16).permutation(xs.shape[0])
    ids, sxs = d.surface_ids()[perm], xs[perm]              # the solver's own order
    buf = d.new_grid()

    def callable_form(p):
        # the same model on the distinct wall points: the same positions, point by point
        return p + ex.TwoModeWing(p).displacements(t)

    ref = d.deform(callable_form)
    got = d.deform(sxs, ids=ids, out=buf, check=True)
    identical = _same(got, ref) and _same(d.deform(xs), ref)
    # each option alone too (same alternation), to tell where a coupled step's cost goes
    cases = {"bare": lambda: d.deform(xs),
             "ids": lambda: d.deform(sxs, ids=ids),
             "out": lambda: d.deform(xs, out=buf),
             "check": lambda: d.deform(xs, check=True),
             "coupled": lambda: d.deform(sxs, ids=ids, out=buf, check=True)}
    times = {k: [] for k in cases}
    cpu = {k: [] for k in cases}
    for _ in range(repeat):
        for k, step in cases.items():
            c0, t0 = time.process_time(), time.perf_counter()
            step()
            times[k].append(time.perf_counter() - t0)
            cpu[k].append(time.process_time() - c0)
    return {"points": d.grid.npoints, "wall_copies": int(xs.shape[0]), "bare_s": times["bare"],
            "coupled_s": times["coupled"], "ids_s": times["ids"], "out_s": times["out"],
            "check_s": times["check"], "cpu_s": cpu,
            "ratio": float(np.median(times["coupled"]) / np.median(times["bare"])),
            "cpu_ratio": float(np.median(cpu["coupled"]) / np.median(cpu["bare"])),
            "bit_identical_to_callable": bool(identical)}

def bench_threads(repeat: int, load: int) -> dict:
    """CPU time per step with threads=2 against threads=1 (alternating), under ``load`` busy
    processes."""
    ex = _example()
    d1 = wing_deformer(threads=1)
    d2 = wing_deformer(threads=2)
    xs = d1.surface_points() + ex.TwoModeWing(d1.surface_points()).displacements(0.03)
    bufs = {1: d1.new_grid(), 2: d2.new_grid()}
    for n, d in ((1, d1), (2, d2)):
        d.deform(xs, out=bufs[n], check=True)         # warm
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(load)]
    cpu = {1: [], 2: []}
    wall = {1: [], 2: []}
    try:
        time.sleep(0.2 if load else 0.0)
        for _ in range(repeat):
            for n, d in ((1, d1), (2, d2)):
                c0, t0 = time.process_time(), time.perf_counter()
                d.deform(xs, out=bufs[n], check=True)
                cpu[n].append(time.process_time() - c0)
                wall[n].append(time.perf_counter() - t0)
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()
    same = _same(bufs[1], bufs[2])
    return {"load": load, "cpu_1_s": cpu[1], "cpu_2_s": cpu[2], "wall_1_s": wall[1],
            "wall_2_s": wall[2], "cpu_ratio": float(np.median(cpu[2]) / np.median(cpu[1])),
            "wall_ratio": float(np.median(wall[2]) / np.median(wall[1])),
            "threads_bit_identical": bool(same)}


def bench_alloc() -> dict:
    """tracemalloc's peak during one step with out= and one without."""
    ex = _example()
    d = wing_deformer()
    xs = d.surface_points() + ex.TwoModeWing(d.surface_points()).displacements(0.03)
    buf = d.new_grid()
    d.deform(xs, out=buf, check=True)           # warm: caches and scratch made
    coord = d.grid.npoints * 24
    peaks = {}
    for name, kw in (("out", {"out": buf, "check": True}), ("new_grid", {"check": True})):
        tracemalloc.start()
        d.deform(xs, **kw)
        peaks[name] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return {"coordinate_bytes": coord, "peak_out_bytes": peaks["out"],
            "peak_new_bytes": peaks["new_grid"], "fraction_out": peaks["out"] / coord,
            "fraction_new": peaks["new_grid"] / coord}


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _current_rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def scale_child(points: float, repeat: int) -> dict:
    """In a child process: the extruded C-grid of ``points`` points, steps with out=."""
    import tfi_quat as tq
    from tfi_quat.deform import rigid_motion
    sys.path.insert(0, str(HERE))
    from bench_cli import extruded_grid
    # the kernels compiled (loaded from the cache) first, so that the start includes them
    small = wing_like_warmup()
    del small
    start = _current_rss_mb()
    mem = {}

    def mark(stage):
        mem[stage] = {"rss_mb": _current_rss_mb(), "peak_mb": _rss_mb()}

    t0 = time.perf_counter()
    grid = extruded_grid(points)
    mark("grid")
    d = tq.Deformer(grid, walls=["1:kmin"])
    setup = time.perf_counter() - t0
    mark("deformer")
    xs = rigid_motion(2.0, axis=(0, 0, 1), about=(0.25, 0, 0))(d.surface_points())
    buf = d.new_grid()
    mark("buffer")
    steps = []
    for _ in range(repeat + 1):
        t1 = time.perf_counter()
        d.deform(xs, out=buf)
        steps.append(time.perf_counter() - t1)
    mark("steps")
    coord = grid.npoints * 24
    peak = _rss_mb()
    # one checked step for information (not in the peak above)
    t1 = time.perf_counter()
    d.deform(xs, out=buf, check=True)
    checked = time.perf_counter() - t1
    mark("checked step")
    return {"points": grid.npoints, "dims": list(grid[0].dims), "setup_s": setup,
            "step_s": steps[1:], "first_step_s": steps[0], "checked_step_s": checked,
            "rate_mpts": grid.npoints / float(np.median(steps[1:])) / 1e6,
            "peak_rss_mb": peak, "start_rss_mb": start, "coordinate_mb": coord / 2**20,
            "peak_over_coords": peak * 2**20 / coord,
            "above_start_over_coords": (peak - start) * 2**20 / coord, "memory": mem}

def wing_like_warmup():
    """A small extruded grid deformed once: loads the kernels a step uses."""
    import tfi_quat as tq
    from tfi_quat.deform import rigid_motion
    from bench_cli import extruded_grid
    g = extruded_grid(5e4)
    d = tq.Deformer(g, walls=["1:kmin"])
    d.deform(rigid_motion(1.0)(d.surface_points()), out=d.new_grid(), check=True)
    return d


def bench_scale(sizes, repeat: int) -> dict:
    out = {}
    for pts in sizes:
        cmd = [sys.executable, str(Path(__file__).resolve()), "--child-scale", str(pts),
               "--repeat", str(repeat)]
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
        if proc.returncode != 0:
            raise SystemExit(f"scale child {pts:g} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
        out[f"{pts:g}"] = json.loads(proc.stdout.strip().splitlines()[-1])
    small, big = (out[f"{p:g}"] for p in sizes)
    return {"sizes": out, "rate_ratio": big["rate_mpts"] / small["rate_mpts"]}


def _med(v) -> str:
    return f"{np.median(v):.3f}"


def report(res: dict) -> None:
    print()
    print(f"{'measurement':<58} {'value':>14}  target")
    rows = []
    if "wing" in res:
        w = res["wing"]
        rows += [("wing: bare step, median s", _med(w["bare_s"]), ""),
                 ("wing: coupled step (ids, out=, check=True), median s", _med(w["coupled_s"]), ""),
                 ("wing: ids= only, out= only, check=True only, median s",
                  f"{_med(w['ids_s'])}, {_med(w['out_s'])}, {_med(w['check_s'])}", ""),
                 ("wing: coupled / bare", f"{w['ratio']:.3f}", "<= 1.3"),
                 ("wing: CPU s bare, ids=, out=, check=True, coupled",
                  ", ".join(f"{np.median(w['cpu_s'][k]):.3f}"
                            for k in ("bare", "ids", "out", "check", "coupled")), ""),
                 ("wing: CPU coupled / bare", f"{w['cpu_ratio']:.3f}", "<= 1.3"),
                 ("wing: bit-identical to the callable form", str(w["bit_identical_to_callable"]),
                  "True")]
    if "threads" in res:
        t = res["threads"]
        rows += [(f"threads=1: CPU s per step (load {t['load']})", _med(t["cpu_1_s"]), ""),
                 (f"threads=2: CPU s per step (load {t['load']})", _med(t["cpu_2_s"]), ""),
                 ("CPU ratio threads=2 / threads=1", f"{t['cpu_ratio']:.3f}", "<= 1.3"),
                 ("wall ratio threads=2 / threads=1", f"{t['wall_ratio']:.3f}", ""),
                 ("threads=1 and threads=2 bit-identical", str(t["threads_bit_identical"]), "True")]
    if "alloc" in res:
        a = res["alloc"]
        rows += [("allocated in a step with out= / coordinate bytes",
                  f"{100 * a['fraction_out']:.2f} %", "< 5 %"),
                 ("allocated in a step without out= / coordinate bytes",
                  f"{100 * a['fraction_new']:.1f} %", "")]
    if "scale" in res:
        s = res["scale"]
        for key, c in s["sizes"].items():
            rows += [(f"{c['points'] / 1e6:.1f} M points: step s (median), rate M points/s",
                      f"{np.median(c['step_s']):.3f}, {c['rate_mpts']:.1f}", ""),
                     (f"{c['points'] / 1e6:.1f} M points: peak RSS / coordinates (above start)",
                      f"{c['peak_over_coords']:.2f} ({c['above_start_over_coords']:.2f})",
                      "<= 3.5 (large)")]
        rows.append(("rate large / small", f"{s['rate_ratio']:.3f}", ">= 0.8"))
        for key, c in s["sizes"].items():
            rows.append((f"{c['points'] / 1e6:.1f} M points: one step with out= and check=True, s",
                         f"{c['checked_step_s']:.3f}", ""))
            print_mem = ", ".join(f"{k} {v['rss_mb']:.0f}/{v['peak_mb']:.0f}"
                                  for k, v in c["memory"].items())
            rows.append((f"{c['points'] / 1e6:.1f} M: MB now/peak after {print_mem}", "", ""))
    for name, value, target in rows:
        print(f"{name:<58} {value:>14}  {target}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small scale sizes (0.2 M, 2 M), fewer repeats")
    ap.add_argument("--only", default=",".join(SECTIONS), help=f"sections, of {', '.join(SECTIONS)}")
    ap.add_argument("--repeat", type=int, default=None, help="timed steps per case (default 9; quick 3)")
    ap.add_argument("--load", type=int, default=0, help="busy processes during the threads section")
    ap.add_argument("--json", nargs="?", const="", default=None, metavar="PATH",
                    help="write the results as JSON (default path benchmarks/results/DATE-coupling.json)")
    ap.add_argument("--child-scale", type=float, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    repeat = args.repeat or (3 if args.quick else 9)
    if args.child_scale is not None:
        print(json.dumps(scale_child(args.child_scale, repeat)))
        return 0
    only = [s.strip() for s in args.only.split(",") if s.strip()]
    unknown = sorted(set(only) - set(SECTIONS))
    if unknown:
        ap.error(f"unknown section(s) {', '.join(unknown)}; choose from {', '.join(SECTIONS)}")
    res = {"date": dt.date.today().isoformat(), "load_average": os.getloadavg()[0],
           "cpus": os.cpu_count(), "quick": args.quick, "repeat": repeat}
    print(f"load average {res['load_average']:.1f} on {res['cpus']} CPUs")
    if "wing" in only:
        res["wing"] = bench_wing(repeat)
        print(f"wing: coupled / bare {res['wing']['ratio']:.3f}")
    if "threads" in only:
        res["threads"] = bench_threads(repeat, args.load)
        print(f"threads: CPU ratio {res['threads']['cpu_ratio']:.3f}")
    if "alloc" in only:
        res["alloc"] = bench_alloc()
    if "scale" in only:
        sizes = (2e5, 2e6) if args.quick else (5e6, 5e7)
        res["scale"] = bench_scale(sizes, max(2, repeat // 3))
    report(res)
    if args.json is not None:
        path = Path(args.json) if args.json else HERE / "results" / f"{res['date']}-coupling.json"
        path.write_text(json.dumps(res, indent=2) + "\n")
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
