"""A fluid-structure coupling loop: wall displacements in, checked volume grids out, every step.

The structure is a two-mode model of the shipped wing (``grids/wing_ch_501k.x``,
501 k points, 4 blocks, symmetry plane y = 0), written in numpy: a bending
mode (the tip rises ``BEND`` chords, quadratic along the span) and a torsion
mode oscillating about the elastic axis ``x = X_AXIS`` (``TWIST`` degrees at the
tip, linear along the span).  Each step it hands over the displacement of every
wall point copy, in the Deformer's ``surface_ids()`` order, as a structural
solver would.

The loop builds the Deformer once, then per step: deforms into preallocated
buffers (``out=``, so the step allocates nothing the size of the grid),
checks the new grid in the same pass (``check=True``: smallest corner-Jacobian
ratio to the reference and negative cells), computes the grid velocities an
ALE flow solver needs (``Deformer.velocity``), and writes every ``--every``-th
grid (and the last).  It prints the time of each step and the process's
peak memory.  ``docs/coupling.md`` walks through it.

    python examples/coupling_loop.py                    # 50 steps into coupling_out/
    python examples/coupling_loop.py --steps 3 --out /tmp/loop --threads 1
"""

from __future__ import annotations

import argparse
import math
import resource
import sys
import time
from pathlib import Path

import numpy as np

import tfi_quat as tq
from tfi_quat.case import load_case
from tfi_quat.demo import sample_path

#: tip deflection of the bending mode at full amplitude (chords) and its period (s)
BEND, BEND_PERIOD = 0.15, 0.2
#: tip twist of the torsion mode (degrees, nose up) and its period (s)
TWIST, TWIST_PERIOD = 4.0, 0.05
#: chordwise position of the elastic axis (the torsion mode's axis, along y)
X_AXIS = 0.35


class TwoModeWing:
    """The structural model: wall displacements ``(n, 3)`` at time ``t`` for the points
    ``points`` (the wall as the Deformer lists it, :meth:`tfi_quat.Deformer.surface_points`).

    Bending: ``dz = a_b(t) (y / span)**2``, ``a_b = BEND (1 - cos(2 pi t / BEND_PERIOD)) / 2``.
    Torsion: each section rotated about the elastic axis ``(X_AXIS, y, 0)`` by
    ``theta(t) y / span``, ``theta = TWIST sin(2 pi t / TWIST_PERIOD)`` (nose up).
    """

    def __init__(self, points: np.ndarray):
        self.points = np.asarray(points, dtype=np.float64)
        self.span = float(self.points[:, 1].max())
        eta = self.points[:, 1] / self.span                  # 0 at the root, 1 at the tip
        self.bend_shape = np.zeros_like(self.points)          # a mode shape: per unit amplitude
        self.bend_shape[:, 2] = eta ** 2
        self.eta = eta
        self.arm_x = self.points[:, 0] - X_AXIS                # the section about the axis
        self.arm_z = self.points[:, 2]

    def amplitudes(self, t: float) -> tuple[float, float]:
        """Tip deflection (chords) and tip twist (degrees) at time ``t``."""
        bend = BEND * 0.5 * (1.0 - math.cos(2.0 * math.pi * t / BEND_PERIOD))
        twist = TWIST * math.sin(2.0 * math.pi * t / TWIST_PERIOD)
        return bend, twist

    def displacements(self, t: float) -> np.ndarray:
        """Wall displacements ``(n, 3)`` at time ``t``, rows as :attr:`points`."""
        bend, twist = self.amplitudes(t)
        theta = np.radians(twist) * self.eta                 # nose up: +theta about +y
        c, s = np.cos(theta), np.sin(theta)
        d = bend * self.bend_shape
        d[:, 0] += (c - 1.0) * self.arm_x + s * self.arm_z
        d[:, 2] += -s * self.arm_x + (c - 1.0) * self.arm_z
        return d


def peak_rss_mb() -> float:
    """The process's peak resident memory so far (MB)."""
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024.0 if sys.platform != "darwin" else kb / 1024.0 ** 2


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=50, help="time steps (default 50)")
    ap.add_argument("--dt", type=float, default=0.002, help="time step, s (default 0.002)")
    ap.add_argument("--every", type=int, default=10, help="write every N-th grid (and the last)")
    ap.add_argument("--threads", type=int, default=None,
                    help="threads of the Deformer (default: all cores; leave some to the flow solver)")
    ap.add_argument("--out", default="coupling_out", help="output folder (default coupling_out)")
    args = ap.parse_args(argv)
    if args.steps < 1 or args.every < 1 or not args.dt > 0.0:
        ap.error("--steps and --every must be >= 1, --dt > 0")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    # once: the grid, its boundaries (the shipped case file names them) and the Deformer
    t0 = time.perf_counter()
    case = load_case(sample_path("wing_ch_501k.toml"))
    grid = tq.read(case.grid)
    deformer = tq.Deformer(grid, walls=case.walls, symmetry=case.symmetry, fixed=case.fixed,
                           threads=args.threads)
    wing = TwoModeWing(deformer.surface_points())
    # the solver's buffers: this step's grid, the last one's, the grid velocities
    cur, prev, vel = deformer.new_grid(), deformer.new_grid(), deformer.new_grid()
    print(f"{grid.npoints:,} points in {len(grid)} blocks, {len(wing.points):,} wall point copies; "
          f"set-up {time.perf_counter() - t0:.2f} s, threads {args.threads or 'all'}")

    print(" step    t (s)  tip dz  twist   step (s)  min J ratio  negative")
    times = []
    for step in range(1, args.steps + 1):
        t = step * args.dt
        disp = wing.displacements(t)                         # from the structural solver
        t1 = time.perf_counter()
        grid_now = deformer.deform(disp, displacement=True, out=cur, check=True)
        deformer.velocity(prev, cur, args.dt, out=vel)
        times.append(time.perf_counter() - t1)
        report = grid_now.quality
        bend, twist = wing.amplitudes(t)
        print(f"{step:5d} {t:8.4f} {bend:7.4f} {twist:6.2f}   {times[-1]:8.4f}  "
              f"{report.min_ratio:11.4f}  {report.negative:8d}")
        if report.negative:
            print(f"step {step}: the grid folded ({report.negative} negative cells); stopping",
                  file=sys.stderr)
            return 1
        if step % args.every == 0 or step == args.steps:
            tq.write(out / f"wing_{step:04d}.x", cur, like=grid, overwrite=True)
        prev, cur = cur, prev                                # this step's grid is the next one's prev
    steady = times[1:] or times
    print(f"step: first {times[0]:.3f} s, then median {np.median(steady):.4f} s, max "
          f"{max(steady):.4f} s ({grid.npoints / np.median(steady) / 1e6:.1f} M points/s); "
          f"peak memory {peak_rss_mb():.0f} MB (coordinates {grid.npoints * 24 / 2**20:.0f} MB "
          f"per grid)")
    print(f"wrote {len(list(out.glob('wing_*.x')))} grid file(s) to {out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
