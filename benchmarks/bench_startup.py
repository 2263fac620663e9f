"""First-run cost: ``tfi-quat demo`` cold (empty numba cache) against warm, side by side.

Each run is a fresh subprocess with its own ``NUMBA_CACHE_DIR``: the cold
run starts from an empty folder (every kernel it uses is compiled and
written there), the warm runs reuse that folder (every kernel is loaded from
it).  ``--rounds`` cold/warm pairs are run in turn, each pair with a new
cache folder, so that both sides see the same machine load; the script
prints each run's wall time and CPU time (user + system, of the child
process and its threads), the best of each side and their ratios.  On a
loaded machine the CPU ratio is the steadier figure: waiting for a core
counts in the wall time, not in the CPU time (contention for caches and
memory still inflates both).

Inside the child, numba's event API (``numba:compile``) records the CPU
time spent compiling each dispatcher (process CPU time: the compiler runs on
one thread while the others wait), including the helpers compiled on the way
(inclusive times: a kernel's time contains that of the helpers it compiled
first).  The cold run's most expensive kernels are listed (``--top``).

Usage::

    python3 benchmarks/bench_startup.py                 # 1 round, top 15 kernels
    python3 benchmarks/bench_startup.py --rounds 2 --top 25
    python3 benchmarks/bench_startup.py --root /tmp/old-checkout  # the same for another copy

``--root PATH`` runs the demo of the package at PATH (a checkout of the
repository) instead of this one, for comparing two versions.  Do not edit
the package while it runs: numba invalidates a file's cached kernels when
the file changes, and the warm run would compile again.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

try:
    import resource                 # CPU seconds of the child processes (POSIX)
except ImportError:                 # pragma: no cover
    resource = None
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# the child: record numba compile events, run the demo through the CLI, dump the events
_CHILD = r"""
import json, sys, time
t_start = time.perf_counter()
sys.path.insert(0, sys.argv[1])
from numba.core import event

class _Rec(event.Listener):
    def __init__(self):
        self.open = {}
        self.done = []
    def on_start(self, ev):
        self.open[id(ev.data["dispatcher"]), str(ev.data["args"])] = time.process_time()
    def on_end(self, ev):
        d = ev.data["dispatcher"]
        t0 = self.open.pop((id(d), str(ev.data["args"])), None)
        if t0 is not None:
            name = getattr(d.py_func, "__module__", "?") + "." + getattr(d.py_func, "__qualname__", "?")
            self.done.append((name, t0, time.process_time()))

rec = _Rec()
event.register("numba:compile", rec)
t_imp = time.perf_counter()
from tfi_quat.cli import main
t_imp = time.perf_counter() - t_imp
rc = main(["demo", "-o", sys.argv[2], "--force", "--no-figure"])
json.dump({"rc": rc, "import_s": t_imp, "compiles": rec.done,
           "total_s": time.perf_counter() - t_start}, open(sys.argv[3], "w"))
"""


def run_demo(pkg_root: Path, cache: Path, work: Path) -> dict:
    """One demo in a fresh process with ``NUMBA_CACHE_DIR=cache``; wall time and compile events."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), TFI_QUAT_CACHE="1", TFI_QUAT_JIT="1")
    env.pop("PYTHONPATH", None)
    res_file = work / "events.json"
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN) if resource else None
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _CHILD, str(pkg_root), str(work / "out"), str(res_file)],
                          cwd=pkg_root, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    cpu = float("nan")
    if resource:
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    if proc.returncode != 0:
        raise SystemExit(f"demo failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    data = json.loads(res_file.read_text())
    data["wall_s"] = wall
    data["cpu_s"] = cpu
    return data


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=1, help="cold/warm pairs (default 1)")
    ap.add_argument("--warm", type=int, default=2, help="warm runs per pair, best kept (default 2)")
    ap.add_argument("--top", type=int, default=15, help="kernels listed by compile time (default 15)")
    ap.add_argument("--root", type=Path, default=None, help="run the package at this checkout instead")
    ap.add_argument("--json", type=Path, default=None, metavar="PATH",
                    help="also write the figures (runs, ratio, cold run's kernels) to this file")
    args = ap.parse_args(argv)
    pkg = (args.root or ROOT).resolve()
    if not (pkg / "tfi_quat" / "__init__.py").exists():
        raise SystemExit(f"{pkg}: no tfi_quat package there")
    cold, warm, last_cold = [], [], None
    cold_cpu, warm_cpu = [], []
    for r in range(args.rounds):
        with tempfile.TemporaryDirectory(prefix="bench-startup-") as tmp:
            tmp = Path(tmp)
            (tmp / "cache").mkdir()
            c = run_demo(pkg, tmp / "cache", tmp)
            cold.append(c["wall_s"])
            cold_cpu.append(c["cpu_s"])
            last_cold = c
            print(f"round {r + 1}: cold {c['wall_s']:7.2f} s, CPU {c['cpu_s']:7.2f} s (import "
                  f"{c['import_s']:.2f} s, {len(c['compiles'])} compilations)", flush=True)
            for _ in range(args.warm):
                w = run_demo(pkg, tmp / "cache", tmp)
                warm.append(w["wall_s"])
                warm_cpu.append(w["cpu_s"])
                print(f"round {r + 1}: warm {w['wall_s']:7.2f} s, CPU {w['cpu_s']:7.2f} s (import "
                      f"{w['import_s']:.2f} s, {len(w['compiles'])} compilations)", flush=True)
                for name, t0, t1 in w["compiles"]:
                    print(f"    compiled when warm: {name} ({t1 - t0:.2f} s)")
    bc, bw = min(cold), min(warm)
    print(f"\npackage: {pkg}")
    print(f"cold (best of {len(cold)}): {bc:.2f} s   warm (best of {len(warm)}): {bw:.2f} s   "
          f"ratio cold/warm: {bc / bw:.1f}x")
    cc, cw = min(cold_cpu), min(warm_cpu)
    print(f"CPU seconds: cold {cc:.2f}   warm {cw:.2f}   ratio {cc / cw:.1f}x (steadier than the "
          f"wall times on a loaded machine: a descheduled process uses no CPU)")
    comp = last_cold["compiles"]
    outer = _outermost(comp)
    agg: dict = {}
    for name, t0, t1 in comp:
        n, t, o = agg.get(name, (0, 0.0, 0.0))
        agg[name] = (n + 1, t + (t1 - t0), o + (t1 - t0 if (name, t0, t1) in outer else 0.0))
    print(f"\ncold run: {len(comp)} compilations of {len(agg)} dispatchers, "
          f"{sum(t1 - t0 for _, t0, t1 in outer):.1f} CPU s compiling in all (outermost events)")
    print("inclusive: with the helpers compiled inside it; outermost: the part of it that was "
          "not inside another compilation")
    print(f"{'dispatcher (CPU seconds)':60s} {'n':>3s} {'inclusive s':>11s} {'outermost s':>11s}")
    top = sorted(agg.items(), key=lambda kv: -kv[1][1])[:args.top]
    for name, (n, t, o) in top:
        print(f"{name[-60:]:60s} {n:3d} {t:11.2f} {o:11.2f}")
    if args.json is not None:
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
        args.json.write_text(json.dumps({
            "package": str(pkg), "cold_s": cold, "warm_s": warm, "ratio": bc / bw,
            "cold_cpu_s": cold_cpu, "warm_cpu_s": warm_cpu, "cpu_ratio": cc / cw,
            "compilations": len(comp), "compile_s": sum(t1 - t0 for _, t0, t1 in outer),
            "load_end": load,
            "kernels": [{"dispatcher": name, "n": n, "inclusive_s": t, "outermost_s": o}
                        for name, (n, t, o) in top]}, indent=2) + "\n")
    return 0


def _outermost(comp) -> set:
    """The compile events not nested inside another (their times sum to the total)."""
    ev = [tuple(e) for e in comp]
    return {e for e in ev if not any(o is not e and o[1] <= e[1] and e[2] <= o[2] and o != e
                                     for o in ev)}


if __name__ == "__main__":
    sys.exit(main())
