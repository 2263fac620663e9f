"""The command line end to end: warm ``tfi-quat deform`` against warm ``tfi-quat convert``.

Both commands read the same Plot3D file and write a grid of the same size,
so ``convert`` is the natural reference: what ``deform`` costs beyond it is
its own work (connectivity, set-up, the step, the volume-ratio check).  The
grid is the shipped NACA 0012 C-grid (``grids/naca0012_c_257x65.x``)
extruded along z to as many planes as ``--points`` asks (300 planes, 5.0 M
points by default), one block, with its wake cut; the wall is ``1:kmin``
and the motion a rotation of ``--rotate`` degrees about the z axis.

Each command runs as a fresh subprocess (``python -m tfi_quat.cli``), once
to warm up (numba caches, the page cache), then ``--repeat`` times each,
alternating; the best of each and their ratio are printed (target
``deform <= 2.0 x convert``), wall time and CPU time (user + system, all
threads: on a loaded machine the steadier of the two).  ``--root PATH``
also times ``deform`` of another checkout (the code before a change) in the
same rounds.  ``--profile`` adds one ``deform`` under cProfile (the tfi_quat
functions and imports above ``--min-ms``) and the CLI's own set-up / step
line.

The package's bytecode is compiled first (``compileall``, for ``--root`` too),
as an installed package has it: where ``PYTHONDONTWRITEBYTECODE`` is set no
run would write it, and every run would compile the sources it imports
(about 0.2 s of CPU more for ``deform``'s modules than for ``convert``'s).

    python benchmarks/bench_cli.py                       # 5 M points, best of 5
    python benchmarks/bench_cli.py --points 2e5 --repeat 2 --profile
    python benchmarks/bench_cli.py --json out.json       # the table as JSON too
    python benchmarks/bench_cli.py --root /tmp/old-checkout   # and deform of another copy
"""

from __future__ import annotations

import argparse
import compileall
import json
import os
import pstats
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SECTION = ROOT / "grids" / "naca0012_c_257x65.x"


def extruded_grid(points: float, span: float = 10.0):
    """The shipped C-grid stacked along z to ``round(points / 16 705)`` planes (at least 2)."""
    import tfi_quat as tq
    sec = tq.read(SECTION)[0].xyz[:, :, 0, :2]
    ni, nj = sec.shape[:2]
    nk = max(2, int(round(points / (ni * nj))))
    xyz = np.empty((ni, nj, nk, 3), order="F")
    xyz[..., :2] = sec[:, :, None, :]
    xyz[..., 2] = np.linspace(0.0, span, nk)[None, None, :]
    return tq.Grid([tq.Block(xyz, name="c_grid_extruded")], 3)


def _cli(*args) -> list[str]:
    return [sys.executable, "-m", "tfi_quat.cli", *args]


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


#: the last command's system seconds and minor page faults (first touches of new memory)
LAST = {"sys": 0.0, "minflt": 0}


def _run(cmd, env) -> tuple[float, float, str]:
    """Wall and CPU seconds (user + system, all threads) of one command, and its stdout
    (its system time and page faults in :data:`LAST`)."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    c0 = _cpu()
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=env["PYTHONPATH"], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    LAST["sys"] = r1.ru_stime - r0.ru_stime
    LAST["minflt"] = r1.ru_minflt - r0.ru_minflt
    return wall, _cpu() - c0, proc.stdout


def profile(deform_cmd, env, work: Path, min_ms: float, top: int) -> None:
    """One ``deform`` under cProfile: the tfi_quat functions (and imports) by cumulative time."""
    out = work / "deform.prof"
    cmd = [sys.executable, "-m", "cProfile", "-o", str(out), "-m", "tfi_quat.cli", *deform_cmd[3:]]
    wall, _, stdout = _run(cmd, env)
    print(f"\nprofiled deform: {wall:.2f} s wall (cProfile adds its own overhead)")
    for line in stdout.splitlines():
        if line.startswith("set-up"):
            print("  CLI: " + line)
    st = pstats.Stats(str(out))
    rows = []
    for (fname, line, func), (cc, nc, tt, ct, callers) in st.stats.items():
        name = f"{Path(fname).name}:{line}({func})"
        ours = "tfi_quat" in fname
        imp = func == "<module>" or func == "_find_and_load"
        if (ours or imp) and ct * 1e3 >= min_ms:
            mod = fname.split("site-packages/")[-1] if "site-packages" in fname else \
                fname.replace(str(ROOT) + "/", "")
            rows.append((ct, tt, nc, f"{mod}:{line}({func})" if ours or func == "<module>" else name))
    rows.sort(reverse=True)
    print(f"  {'cumulative s':>12} {'own s':>8} {'calls':>7}  function")
    for ct, tt, nc, name in rows[:top]:
        print(f"  {ct:12.3f} {tt:8.3f} {nc:7d}  {name}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=float, default=5e6, help="grid points (planes = points / 16 705)")
    ap.add_argument("--repeat", type=int, default=5, help="timed runs of each command (after one warm-up)")
    ap.add_argument("--rotate", type=float, default=2.0, help="wall rotation about z, degrees")
    ap.add_argument("--method", default="two-level", help="deform --method")
    ap.add_argument("--profile", action="store_true", help="profile one deform run (cProfile)")
    ap.add_argument("--min-ms", type=float, default=20.0, help="profile rows of at least this many ms")
    ap.add_argument("--top", type=int, default=40, help="profile rows shown")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--root", help="also time deform of the package at ROOT (another checkout, e.g. "
                                   "the code before a change), alternating with this one's")
    args = ap.parse_args(argv)

    for root in (ROOT, Path(args.root).resolve() if args.root else None):
        if root is not None:                # warm bytecode, as an installed package has
            compileall.compile_dir(str(root / "tfi_quat"), quiet=1)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env_old = dict(os.environ, PYTHONPATH=str(Path(args.root).resolve())) if args.root else None
    with tempfile.TemporaryDirectory(prefix="bench_cli_") as tmp:
        work = Path(tmp)
        import tfi_quat as tq
        grid = extruded_grid(args.points)
        src = work / "grid.x"
        tq.write(src, grid)
        ni, nj, nk = grid[0].dims
        print(f"grid: C-grid {ni} x {nj} extruded to {nk} planes, {grid.npoints / 1e6:.2f} M points, "
              f"{src.stat().st_size / 1e6:.0f} MB; load average {os.getloadavg()[0]:.1f}")
        deform = _cli("deform", str(src), "--wall", "1:kmin", "--rotate", f"{args.rotate:g}",
                      "--axis", "0,0,1", "--method", args.method, "-o", str(work / "deformed.x"),
                      "--force", "--quiet")
        convert = _cli("convert", str(src), str(work / "converted.x"), "--force")
        t_dw, _, out = _run(deform, env)
        t_cw, _, _ = _run(convert, env)
        print(f"warm-up: deform {t_dw:.2f} s, convert {t_cw:.2f} s")
        print("  " + "\n  ".join(out.strip().splitlines()))
        if env_old is not None:
            t_ow, _, out_old = _run(deform, env_old)
            print(f"warm-up of {args.root}: deform {t_ow:.2f} s")
        td, tc, cd, cc, to, co = [], [], [], [], [], []
        sd, sc, fd, fc = [], [], [], []
        for r in range(args.repeat):
            t, c, out = _run(deform, env)
            td.append(t)
            cd.append(c)
            sd.append(LAST["sys"])
            fd.append(LAST["minflt"])
            t, c, _ = _run(convert, env)
            tc.append(t)
            cc.append(c)
            sc.append(LAST["sys"])
            fc.append(LAST["minflt"])
            old = ""
            if env_old is not None:
                t, c, _ = _run(deform, env_old)
                to.append(t)
                co.append(c)
                old = f", deform of --root {to[-1]:.3f} s ({co[-1]:.2f} s CPU)"
            print(f"run {r + 1}: deform {td[-1]:.3f} s ({cd[-1]:.2f} s CPU, {sd[-1]:.2f} s system, "
                  f"{fd[-1]} page faults), convert {tc[-1]:.3f} s ({cc[-1]:.2f} s CPU, {sc[-1]:.2f} s "
                  f"system, {fc[-1]} page faults){old}; load average {os.getloadavg()[0]:.1f}")
        setup = [line for line in out.splitlines() if line.startswith("set-up")]
        best_d, best_c = min(td), min(tc)
        print(f"best of {args.repeat}: deform {best_d:.3f} s, convert {best_c:.3f} s, "
              f"ratio {best_d / best_c:.2f} (target <= 2.0); CPU time {min(cd):.2f} s against "
              f"{min(cc):.2f} s, ratio {min(cd) / min(cc):.2f}; last deform's {setup[0] if setup else ''}")
        if to:
            print(f"--root deform: best {min(to):.3f} s, ratio {min(to) / best_c:.2f} to convert; CPU time "
                  f"{min(co):.2f} s, ratio {min(co) / min(cc):.2f}")
        if args.profile:
            profile(deform, env, work, args.min_ms, args.top)
    if args.json:
        Path(args.json).write_text(json.dumps({
            "points": grid.npoints, "dims": [ni, nj, nk], "method": args.method, "rotate": args.rotate,
            "deform_s": td, "convert_s": tc, "best_deform_s": best_d, "best_convert_s": best_c,
            "ratio": best_d / best_c, "deform_cpu_s": cd, "convert_cpu_s": cc,
            "cpu_ratio": min(cd) / min(cc), "deform_sys_s": sd, "convert_sys_s": sc,
            "deform_minflt": fd, "convert_minflt": fc, "root": args.root, "root_deform_s": to, "root_deform_cpu_s": co, "load_average": os.getloadavg()[0]}, indent=2) + "\n")


if __name__ == "__main__":
    main()
