"""The memo's experiment, measured: plain TFI, quaternion TFI and RBF side by side.

Runs, in one process and one run, on the shipped grids:

* the NACA 0012 C-grid ``grids/naca0012_c_257x65`` (walls and fixed
  boundaries from its case file): rigid rotations of the airfoil by 5, 15,
  30, 45 and 60 deg nose-up about the quarter chord (0.25, 0, 0) plus a
  translation (0, 0.05, 0), and the camber-like bending of :class:`tfi_quat.demo.DemoMotion`
  (camber 0.08 alone, and with the demo's pitch and translation);
* the 3-D wing ``grids/wing_ch_501k`` (walls, symmetry and fixed boundaries
  from its case file): beam bending and twist (:class:`tfi_quat.case.Motion`,
  span 1.5 = the half-span, about the quarter chord), tip deflection 10 % and
  20 % of the span, twist 5 and 10 deg;

each with four methods:

``plain TFI``           ``Deformer(..., method="tfi")``
``quaternion two-level`` ``Deformer(...)`` (the default, ``method="two-level"``)
``quaternion samareh``  ``Deformer(..., method="samareh")`` (the memo's update)
``RBF``                 :class:`RBFBaseline` below: ``scipy.interpolate.RBFInterpolator``,
                        thin-plate spline, displacements, centres on the walls and
                        the far field

and measures for each the orthogonality change of the first 5 grid layers off
the walls (max, mean; also per wall patch, at interior wall points, and for
the motion itself applied to every point), the smallest cell-volume ratio to
the reference, the number of negative cells and the time per step.  It
prints Markdown tables, and with ``--out DIR`` writes
``DIR/reproduction.json`` (every number, the machine load and the RBF
set-up) and the figures of ``docs/reproduction.md``.

Timing: the Deformers are built once; after a warm-up step the methods are
timed in turn, round after round, the TFI methods with 1 and with all
threads (on a loaded machine a parallel region waits for the busy core, which
costs a small grid ~30 ms a step); the best is kept.  RBF: fit + evaluation
per step (it is refitted to every step's wall displacements).

    PYTHONPATH=. python3 benchmarks/bench_reproduction.py --out docs/figures   # 2.5-7 minutes on 2 cores
    PYTHONPATH=. python3 benchmarks/bench_reproduction.py --quick              # smoke run, < 1 minute

``--quick`` runs two C-grid pitches and one wing case with fewer repeats and
fewer RBF centres on the wing (every second wall point: it then folds cells);
its numbers are not the documented ones.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy
from scipy.interpolate import RBFInterpolator
from scipy.spatial import cKDTree

import tfi_quat as tq
from tfi_quat import _jit
from tfi_quat._jit import use_threads
from tfi_quat.case import Motion, load_case
from tfi_quat.deform import Deformer, rigid_motion
from tfi_quat.demo import DemoMotion
from tfi_quat.grid import FACES, Block, Grid
from tfi_quat.quality import orthogonality_change, volume_ratio_summary, wall_orthogonality

ROOT = Path(__file__).resolve().parents[1]
C_GRID = "naca0012_c_257x65"
WING = "wing_ch_501k"
LAYERS = 5

#: Deformer keyword arguments of the three TFI methods, in table order
DEFORMERS = {
    "plain TFI": {"method": "tfi"},
    "quaternion two-level": {},
    "quaternion samareh": {"method": "samareh"},
}
RBF = "RBF"
METHODS = (*DEFORMERS, RBF)
#: thread counts the TFI methods are timed with (one, and all: tfi_quat._jit.THREADS)
THREADS = tuple(sorted({1, _jit.THREADS}))


# ------------------------------------------------------------------ the cases
@dataclass
class CaseSpec:
    """One wall motion on one grid."""

    grid: str            # grid name under grids/
    label: str           # short label (table, JSON)
    describe: str        # the motion in words
    motion: object       # callable (n, 3) -> (n, 3)
    rigid: bool          # a rigid motion of the wall (target 1 applies up to 45 deg)
    angle: float = 0.0   # rigid rotation angle, degrees


def c_grid_cases(quick: bool) -> list[CaseSpec]:
    """Rigid pitch + plunge of the airfoil, and camber-like bending (DemoMotion)."""
    out = []
    for a in ((30.0, 60.0) if quick else (5.0, 15.0, 30.0, 45.0, 60.0)):
        # nose up: clockwise in the x-y plane (x downstream, y up), as the demo's pitch
        out.append(CaseSpec(C_GRID, f"pitch {a:g}",
                            f"pitched {a:g} deg nose-up about (0.25, 0), translated (0, 0.05)",
                            rigid_motion(a, axis=(0, 0, -1), about=(0.25, 0, 0), translate=(0, 0.05, 0)),
                            True, a))
    if not quick:
        for m in (DemoMotion(camber=0.08, pitch=0.0, translate=(0.0, 0.0, 0.0)), DemoMotion()):
            label = "camber 0.08" + (f", pitch {m.pitch:g}" if m.pitch else "")
            out.append(CaseSpec(C_GRID, label, m.describe(), m, False))
    return out


def wing_cases(quick: bool) -> list[CaseSpec]:
    """Beam bending (tip deflection ``bend``, span 1.5) and twist about the quarter-chord line."""
    out = []
    for bend, twist in (((0.15, 10.0),) if quick else ((0.15, 5.0), (0.15, 10.0), (0.3, 10.0))):
        m = Motion(bend=bend, twist=twist, about=(0.25, 0, 0), span_axis=(0, 1, 0), span=1.5,
                   direction=(0, 0, 1))
        out.append(CaseSpec(WING, f"bend {bend:g}, twist {twist:g}",
                            f"tip deflected {bend:g} (= {bend / 1.5:.0%} of the span 1.5) along +z and "
                            f"twisted {twist:g} deg (nose up), both growing as (y/1.5)^2; beam kinematics",
                            m.apply, False))
    return out


# ------------------------------------------------------------------ patch points
def patch_index(grid: Grid, spec) -> tuple[int, np.ndarray]:
    """Block and flat point indices (Fortran order, i fastest) of a resolved patch."""
    dims = grid[spec.block].dims
    d, side = divmod(FACES.index(spec.face), 2)
    run = [m for m in range(3) if m != d]
    (a0, a1), (b0, b1) = spec.range
    ijk = [None, None, None]
    ijk[d] = np.array([dims[d] - 1 if side else 0])
    ijk[run[0]] = np.arange(a0, a1 + 1)
    ijk[run[1]] = np.arange(b0, b1 + 1)
    i, j, k = np.meshgrid(*ijk, indexing="ij")
    return spec.block, (i + dims[0] * (j + dims[1] * k)).ravel()


def thinned_index(grid: Grid, spec, stride: int) -> tuple[int, np.ndarray]:
    """:func:`patch_index` keeping every ``stride``-th point along both face indices (ends kept)."""
    b, flat = patch_index(grid, spec)
    (a0, a1), (b0, b1) = spec.range
    na, nb = a1 - a0 + 1, b1 - b0 + 1

    def keep(n):
        k = np.zeros(n, dtype=bool)
        k[::stride] = True
        k[-1] = True
        return k
    mask = keep(na)[:, None] & keep(nb)[None, :]
    # patch_index orders the points as the meshgrid of the block axes: the face's first running
    # index is the lower block axis, so its points are (na, nb) in C order
    return b, flat[mask.ravel()]


def points_of(grid: Grid, index: list) -> np.ndarray:
    """Coordinates (n, 3) of ``[(block, flat indices), ...]``."""
    return np.concatenate([grid[b].xyz.reshape(-1, 3, order="F")[f] for b, f in index])


def unique_rows(p: np.ndarray, tol: float) -> np.ndarray:
    """Indices of ``p`` (n, d) with every point closer than ``tol`` to an earlier one left out."""
    drop = np.zeros(len(p), dtype=bool)
    for a, b in cKDTree(p).query_pairs(tol, output_type="ndarray"):
        drop[max(a, b)] = True
    return np.flatnonzero(~drop)


# ------------------------------------------------------------------ the RBF baseline
class RBFBaseline:
    """Radial-basis-function mesh deformation with ``scipy.interpolate.RBFInterpolator``.

    The displacement of every grid point is interpolated from centres on the
    boundaries of the reference grid: thin-plate spline kernel ``r^2 log r``
    with a degree-1 polynomial (scipy's default for it), no smoothing, so the
    centres are reproduced to round-off.

    Centres: every wall point (its displacement to the moved wall) and the
    points of the fixed (far-field) patches (zero displacement), the fixed
    ones thinned by taking every ``stride``-th point along both indices of
    each face (face ends kept), ``stride`` the smallest that leaves at most
    ``max_far`` of them; coincident points are merged.

    A symmetry plane (``symmetry_mode``): ``"mirror"`` (default) adds the
    mirror image of every centre with the mirrored displacement, so the
    interpolant is symmetric and its displacement has no component normal
    to the plane there (to round-off; symmetry-plane points are not centres
    and move freely in the plane); ``"project"`` leaves the centres alone
    and projects the symmetry-plane points back on the plane afterwards.
    Either way the symmetry points are finally put on the plane (the
    out-of-plane motion removed is recorded in ``last``); then, as the
    Deformer does, fixed points are put back at rest and wall points exactly
    at their targets (wall beats fixed beats symmetry).  2-D grids are
    interpolated in (x, y).

    Parameters
    ----------
    ref : Grid
        The reference grid.
    walls, symmetry, fixed : list of PatchSpec, resolved (explicit ranges)
    max_far : int
        At most this many fixed-boundary centres.
    wall_stride : int
        Thin the wall centres too (``--quick`` only; 1 = every wall point).
    chunk : int
        Bound on (points per evaluation chunk) x (centres): the evaluation
        matrix of one chunk has at most this many float64 entries.
    symmetry_mode : {"mirror", "project"}
        One symmetry plane at most with ``"mirror"``.
    """

    def __init__(self, ref: Grid, walls, symmetry, fixed, max_far: int = 1000, wall_stride: int = 1,
                 chunk: int = 1 << 23, symmetry_mode: str = "mirror"):
        t0 = time.perf_counter()
        self.ref = ref
        self.nd = ref.ndim
        lo, hi = ref.bbox()
        self.tol = 1e-9 * float(np.linalg.norm(hi - lo))
        self.walls = [patch_index(ref, s) for s in walls]
        self.fixed = [patch_index(ref, s) for s in fixed]
        self.symmetry = [(patch_index(ref, s), self._plane(points_of(ref, [patch_index(ref, s)])))
                         for s in symmetry]
        # wall centres
        widx = [thinned_index(ref, s, wall_stride) for s in walls]
        wpts = points_of(ref, widx)
        keep = unique_rows(wpts[:, :self.nd], self.tol)
        self.wall_centres = wpts[keep]
        # fixed centres, thinned
        nfixed = sum(len(f) for _, f in self.fixed)
        stride = 1
        while True:
            fidx = [thinned_index(ref, s, stride) for s in fixed]
            fpts = points_of(ref, fidx)
            allp = np.concatenate([self.wall_centres, fpts])
            keep = unique_rows(allp[:, :self.nd], self.tol)
            keep = keep[keep >= len(self.wall_centres)] - len(self.wall_centres)
            if len(keep) <= max_far:
                break
            stride += 1
        self.far_stride = stride
        self.far_centres = fpts[keep]
        self.n_fixed_points = nfixed
        self.centres = np.concatenate([self.wall_centres, self.far_centres])
        self.symmetry_mode = symmetry_mode if self.symmetry else "none"
        self.mirror = None
        if self.symmetry_mode == "mirror":
            if len(self.symmetry) > 1:
                raise ValueError("symmetry_mode='mirror' handles one symmetry plane")
            c, n = self.symmetry[0][1]
            img = self.centres - 2.0 * ((self.centres - c) @ n)[:, None] * n
            allp = np.concatenate([self.centres, img])
            keep = unique_rows(allp[:, :self.nd], self.tol)
            self.mirror = keep[keep >= len(self.centres)] - len(self.centres)   # images kept
            self.centres = np.concatenate([self.centres, img[self.mirror]])
            self.plane = (c, n)
        self.points = np.concatenate([b.xyz.reshape(-1, 3, order="F") for b in ref])
        self.offsets = np.cumsum([0] + [b.npoints for b in ref])
        self.chunk_rows = max(1, chunk // len(self.centres))
        self.setup_seconds = time.perf_counter() - t0
        self.last: dict = {}

    @staticmethod
    def _plane(p: np.ndarray):
        """(point, unit normal) of the best plane through ``p`` (n, 3)."""
        c = p.mean(axis=0)
        n = np.linalg.svd(p - c, full_matrices=False)[2][-1]
        return c, n

    def describe(self) -> dict:
        """The centre set, for the JSON and the docs."""
        return {"wall_centres": int(len(self.wall_centres)), "far_centres": int(len(self.far_centres)),
                "fixed_points": int(self.n_fixed_points), "far_stride": int(self.far_stride),
                "centres": int(len(self.centres)), "symmetry": self.symmetry_mode,
                "mirrored_centres": 0 if self.mirror is None else int(len(self.mirror)),
                "kernel": "thin_plate_spline", "degree": 1,
                "smoothing": 0.0, "chunk_rows": int(self.chunk_rows), "points": int(len(self.points))}

    def deform(self, motion) -> Grid:
        """The deformed grid for a wall motion (callable on points (n, 3)); timings in ``last``."""
        nd = self.nd
        t0 = time.perf_counter()
        nw = len(self.wall_centres)
        disp = np.zeros((len(self.centres), 3))
        disp[:nw] = np.asarray(motion(self.wall_centres)) - self.wall_centres
        if self.mirror is not None:
            n = self.plane[1]
            d = disp[self.mirror]
            disp[len(disp) - len(self.mirror):] = d - 2.0 * (d @ n)[:, None] * n
        disp = disp[:, :nd]
        interp = RBFInterpolator(self.centres[:, :nd], disp, kernel="thin_plate_spline", smoothing=0.0,
                                 degree=1)
        t1 = time.perf_counter()
        out = self.points.copy()
        x = self.points[:, :nd]
        for a in range(0, len(x), self.chunk_rows):
            out[a:a + self.chunk_rows, :nd] += interp(x[a:a + self.chunk_rows])
        t2 = time.perf_counter()
        blocks = [out[self.offsets[b]:self.offsets[b + 1]] for b in range(len(self.ref))]
        off_plane = 0.0
        for (b, f), (c, n) in self.symmetry:
            h = (blocks[b][f] - c) @ n
            off_plane = max(off_plane, float(np.abs(h).max()))
            blocks[b][f] -= h[:, None] * n
        for b, f in self.fixed:
            blocks[b][f] = self.ref[b].xyz.reshape(-1, 3, order="F")[f]
        for b, f in self.walls:
            blocks[b][f] = motion(self.ref[b].xyz.reshape(-1, 3, order="F")[f])
        grid = Grid([Block(np.asfortranarray(p.reshape(blk.dims + (3,), order="F")), blk.iblank, blk.name,
                           allow_nonfinite=True) for p, blk in zip(blocks, self.ref)], self.ref.ndim)
        t3 = time.perf_counter()
        self.last = {"fit_s": t1 - t0, "evaluate_s": t2 - t1, "finish_s": t3 - t2, "total_s": t3 - t0,
                     "symmetry_off_plane_removed": off_plane}
        return grid


# ------------------------------------------------------------------ checks
def boundary_errors(out: Grid, ref: Grid, walls, symmetry, fixed, motion) -> dict:
    """Largest distance of wall points from their targets, of fixed points from rest, of
    symmetry points from their plane."""
    def pts(g, idx):
        return g[idx[0]].xyz.reshape(-1, 3, order="F")[idx[1]]
    w = max((float(np.abs(pts(out, i) - motion(pts(ref, i))).max()) for i in map(lambda s: patch_index(ref, s), walls)),
            default=0.0)
    f = max((float(np.abs(pts(out, i) - pts(ref, i)).max()) for i in map(lambda s: patch_index(ref, s), fixed)),
            default=0.0)
    s = 0.0
    for spec in symmetry:
        i = patch_index(ref, spec)
        c, n = RBFBaseline._plane(pts(ref, i))
        s = max(s, float(np.abs((pts(out, i) - c) @ n).max()))
    return {"wall_error": w, "fixed_moved": f, "symmetry_off_plane": s}


def measure(out: Grid, ref: Grid, walls) -> dict:
    """Orthogonality change of the first layers (all walls, and per wall patch), volume ratio, negative cells."""
    oc = orthogonality_change(out, ref, walls, LAYERS)
    vr = volume_ratio_summary(out, ref)
    per = {}
    if len(walls) > 1:
        for w in walls:
            o = orthogonality_change(out, ref, [w], LAYERS)
            per[str(w)] = [float(o["max"]), float(o["mean"])]
    # the same over the interior points of the wall patches: their edges (trailing edge, root, tip
    # junction, the wing's collapsed tip edge) have one-sided or degenerate wall normals
    a0 = wall_orthogonality(ref, walls, LAYERS)
    a1 = wall_orthogonality(out, walls, LAYERS)
    ch = np.concatenate([np.abs(b - a)[1:-1, 1:-1].ravel() if a.shape[1] > 2 else np.abs(b - a)[1:-1].ravel()
                         for a, b in zip(a0, a1)])
    return {"ortho_max": float(oc["max"]), "ortho_mean": float(oc["mean"]), "min_ratio": float(vr["min_ratio"]),
            "min_ratio_at": [int(v) for v in vr["where"]], "negative": int(vr["negative"]),
            "ortho_by_patch": per, "ortho_interior": [float(np.nanmax(ch)), float(np.nanmean(ch))]}


def motion_field(ref: Grid, motion) -> Grid:
    """The wall motion applied to every grid point (not a deformation method: it moves the far field too).

    Its near-wall orthogonality change is what a method that reproduces the
    motion's own displacement field near the wall (displacement
    interpolation, e.g. RBF) inherits."""
    blocks = []
    for blk in ref:
        p = motion(blk.xyz.reshape(-1, 3, order="F"))
        blocks.append(Block(np.asfortranarray(p.reshape(blk.dims + (3,), order="F")), blk.iblank, blk.name))
    return Grid(blocks, ref.ndim)


def uptime() -> str:
    try:
        with open("/proc/loadavg") as fh:
            return " ".join(fh.read().split()[:3])
    except OSError:
        return "n/a"


# ------------------------------------------------------------------ the run
def run_grid(name: str, cases: list[CaseSpec], repeats: int, rbf_repeats: int, rbf_kw: dict, log,
             keep=None) -> dict:
    """Every case of one grid with every method.

    Returns a dict with the reference ``ref``, the ``case``, the table
    ``rows``, the RBF centre set ``rbf`` and ``grids[case label][method]``
    for the cases in ``keep`` (all when None), for the figures.
    """
    ref = tq.read(ROOT / "grids" / f"{name}.x")
    case = load_case(ROOT / "grids" / f"{name}.toml").check(ref)
    walls, sym, fixed = case.walls, case.symmetry, case.fixed
    deformers, setup = {}, {}
    for label, kw in DEFORMERS.items():
        t = time.perf_counter()
        deformers[label] = Deformer(ref, walls=walls, symmetry=sym, fixed=fixed, **kw)
        setup[label] = time.perf_counter() - t
    rbf = RBFBaseline(ref, walls, sym, fixed, **rbf_kw)
    setup[RBF] = rbf.setup_seconds
    log(f"{name}: {ref.npoints} points; set-up (s): "
        + ", ".join(f"{k} {v:.2f}" for k, v in setup.items())
        + f"; RBF centres {rbf.describe()}")
    rows, grids = [], {}
    for cs in cases:
        # the methods timed in turn, round after round (best of each kept), so that a burst of
        # load on the shared machine does not fall on the repeats of one method only; the
        # TFI methods with one thread and with all (THREADS), see the module docstring
        for d in deformers.values():
            d.deform(cs.motion)                          # warm-up
        best = {label: dict.fromkeys(THREADS, np.inf) for label in deformers}
        best[RBF] = {0: np.inf}
        outs = {}
        for r in range(max(repeats, rbf_repeats)):
            if r < repeats:
                for nt in THREADS:
                    for label, d in deformers.items():
                        t = time.perf_counter()
                        with use_threads(nt):
                            out = d.deform(cs.motion)
                        best[label][nt] = min(best[label][nt], time.perf_counter() - t)
                        outs[label] = (out, min(best[label].values()), {"step_s_threads": dict(best[label])})
            if r < rbf_repeats:
                t = time.perf_counter()
                out = rbf.deform(cs.motion)
                if time.perf_counter() - t < best[RBF][0]:
                    best[RBF][0] = time.perf_counter() - t
                    outs[RBF] = (out, best[RBF][0], dict(rbf.last))
        for label, (out, t, extra) in outs.items():
            row = {"grid": name, "case": cs.label, "motion": cs.describe, "rigid": cs.rigid, "angle": cs.angle,
                   "method": label, "step_s": t, "setup_s": setup[label], **measure(out, ref, walls),
                   **boundary_errors(out, ref, walls, sym, fixed, cs.motion), **extra}
            rows.append(row)
            log(f"  {cs.label:22s} {label:22s} ortho {row['ortho_max']:9.4f} / {row['ortho_mean']:8.4f}  "
                f"ratio {row['min_ratio']:9.4f}  neg {row['negative']:6d}  {1e3 * t:10.2f} ms")
        rbf_t = outs[RBF][1]
        field = measure(motion_field(ref, cs.motion), ref, walls)
        for row in rows[-len(outs):]:
            row["rbf_over_this"] = rbf_t / row["step_s"]
            row["motion_field_ortho"] = [field["ortho_max"], field["ortho_mean"]]
        log(f"  {cs.label:22s} {'(motion as a field)':22s} ortho {field['ortho_max']:9.4f} / "
            f"{field['ortho_mean']:8.4f}")
        if keep is None or cs.label in keep:
            grids[cs.label] = {k: v[0] for k, v in outs.items()}
    return {"ref": ref, "case": case, "rows": rows, "grids": grids, "rbf": rbf.describe()}


# ------------------------------------------------------------------ tables
def table(rows: list[dict]) -> str:
    """Markdown: one line per case and method."""
    def fmt(t):
        return f"{1e3 * t:.2f} ms" if t < 1.0 else f"{t:.1f} s"
    head = ("| case | method | orthogonality change, 5 layers: max / mean (deg) | smallest volume ratio "
            "| negative cells | time per step (best) | with " + " / ".join(map(str, THREADS))
            + " threads | RBF time / this |")
    lines = [head, "|---|---|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        ts = fmt(r["step_s"])
        per = " / ".join(fmt(v) for v in r["step_s_threads"].values()) if "step_s_threads" in r else ""
        ts += f" | {per}"
        ratio = "" if r["method"] == RBF else f"{r['rbf_over_this']:.0f}x"
        lines.append(f"| {r['case']} | {r['method']} | {r['ortho_max']:.3f} / {r['ortho_mean']:.4f} | "
                     f"{r['min_ratio']:.3f} | {r['negative']} | {ts} | {ratio} |")
    return "\n".join(lines)


def patch_table(rows: list[dict]) -> str:
    """Markdown: orthogonality change per wall patch (grids with several), at interior wall points,
    and of the motion applied to every point."""
    patches = list(rows[0]["ortho_by_patch"])      # empty for a single wall patch
    cols = [f"{p}: max / mean (deg)" for p in patches] + ["interior wall points: max / mean",
                                                          "motion as a field: max / mean"]
    lines = ["| case | method | " + " | ".join(cols) + " |", "|---|---|" + "---|" * len(cols)]
    for r in rows:
        vals = [r["ortho_by_patch"][p] for p in patches] + [r["ortho_interior"], r["motion_field_ortho"]]
        lines.append(f"| {r['case']} | {r['method']} | " + " | ".join(f"{v[0]:.3f} / {v[1]:.4f}" for v in vals)
                     + " |")
    return "\n".join(lines)


def targets(rows: list[dict]) -> dict:
    """The issue's three targets, per quaternion formulation."""
    res = {}
    by = {}
    for r in rows:
        by.setdefault((r["grid"], r["case"]), {})[r["method"]] = r
    for q in ("quaternion two-level", "quaternion samareh"):
        t1 = [(c, m[q]["ortho_max"]) for c, m in by.items() if m[q]["rigid"] and m[q]["angle"] <= 45.0]
        t2 = [(c, m[q]["negative"]) for c, m in by.items() if m[RBF]["negative"] == 0]
        t3 = [(c, m[q]["rbf_over_this"], m[q]["ortho_max"] <= m[RBF]["ortho_max"],
               m[q]["ortho_mean"] <= m[RBF]["ortho_mean"]) for c, m in by.items()]
        res[q] = {
            "1_ortho_le_0.1_up_to_45": {"met": all(v <= 0.1 for _, v in t1), "worst": max(v for _, v in t1)
                                        if t1 else None, "cases": [[*c, v] for c, v in t1]},
            "2_no_negative_where_rbf_has_none": {"met": all(v == 0 for _, v in t2),
                                                 "cases": [[*c, v] for c, v in t2]},
            "3_100x_faster_at_equal_or_better_orthogonality": {
                "met": all(s >= 100 and omax and omean for _, s, omax, omean in t3),
                "cases": [[*c, s, omax, omean] for c, s, omax, omean in t3]},
        }
    return res


# ------------------------------------------------------------------ figures
def save_small(fig, path: Path, dpi: int, colors: int = 64) -> None:
    """:func:`tfi_quat.plot.save_figure`, then the PNG reduced to a palette of ``colors``
    (grid-line pictures need few colours; the files get 3-4x smaller)."""
    from PIL import Image

    from tfi_quat.plot import save_figure

    save_figure(fig, path, dpi=dpi)
    with Image.open(path) as im:
        small = im.convert("RGB").quantize(colors=colors, method=Image.Quantize.MEDIANCUT)
    small.save(path, optimize=True)


def _subtitle(r: dict) -> str:
    return (f"orthogonality change max {r['ortho_max']:.2f} deg\n"
            f"min volume ratio {r['min_ratio']:.2f}, {r['negative']} negative cells")


def c_grid_figure(res: dict, label: str, path: Path, dpi: int) -> None:
    """Memo figure 4 layout: plain TFI, quaternion two-level and RBF; near field, LE and TE zooms."""
    from tfi_quat.plot import plot_compare

    show = ("plain TFI", "quaternion two-level", RBF)
    rows = {r["method"]: r for r in res["rows"] if r["case"] == label}
    grids = {m: res["grids"][label][m] for m in show}
    fig = plot_compare(grids, ref=res["ref"], walls=res["case"].walls, windows=["near", "le", "te"],
                       layout="overlay", subtitles={m: _subtitle(rows[m]) for m in show}, figsize=(13.5, 12.0),
                       suptitle=f"NACA 0012 C-grid 257 x 65, wall {rows[show[0]]['motion']}\n"
                                f"(grey: reference grid, red: deformed wall)")
    save_small(fig, path, dpi)


def _section(g: Grid, k: int) -> np.ndarray:
    """Wall section of the wing block (block 1, j = 0, i 33-97 1-based) at station ``k``, (65, 3)."""
    return g[0].xyz[32:97, 0, k]


def wing_figure(res: dict, label: str, path: Path, dpi: int, k_cut: int = 44, vmax: float = 15.0) -> None:
    """Wing: the wall coloured by the orthogonality change of its first layer of cells (top) and
    the tip section of the wing block coloured by volume ratio (bottom), one column per method."""
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    from tfi_quat.plot import _cmap, _colorbar, _norm, cell_values, plot_cut, plot_wall_3d

    ref, walls = res["ref"], res["case"].walls
    rows = {r["method"]: r for r in res["rows"] if r["case"] == label}
    grids = res["grids"][label]
    cut_k = min(k_cut, ref[0].dims[2] - 1)
    from tfi_quat.plot import Cut
    cut = Cut(0, "k", cut_k)
    fig = Figure(figsize=(3.6 * len(grids), 7.2), layout="constrained")
    gs = fig.add_gridspec(2, len(grids), height_ratios=[1.1, 0.8])
    onorm = Normalize(0.0, vmax)
    ortho = {m: cell_values(g, "orthogonality_change", ref=ref, walls=walls, layers=1) for m, g in grids.items()}
    ratio = {m: cell_values(g, "volume_ratio", ref=ref) for m, g in grids.items()}
    # the tip section's near field, the same window in every column
    sec = np.concatenate([_section(g, cut_k) for g in grids.values()])
    lo, hi = sec[:, [0, 2]].min(axis=0), sec[:, [0, 2]].max(axis=0)
    pad = 0.6 * float(np.max(hi - lo))
    win = (lo[0] - pad, hi[0] + pad, lo[1] - pad, hi[1] + pad)
    shown = []
    for m, g in grids.items():
        p = g[0].xyz[:, :, cut_k]
        inside = ((p[:-1, :-1, 0] >= win[0]) & (p[:-1, :-1, 0] <= win[1])
                  & (p[:-1, :-1, 2] >= win[2]) & (p[:-1, :-1, 2] <= win[3]))
        shown.append(np.asarray(ratio[m][0])[:, :, min(cut_k, ref[0].dims[2] - 2)][inside])
    rnorm = _norm("volume_ratio", shown)
    top, bottom = [], []
    wall_mappable = cut_mappable = None
    for c, (m, g) in enumerate(grids.items()):
        r = rows[m]
        ax3 = fig.add_subplot(gs[0, c], projection="3d")
        # seen from above (+z): the planform, upper surface
        colls = plot_wall_3d(ax3, g, walls, values=ortho[m], cmap=_cmap("orthogonality_change"), norm=onorm,
                             linewidth=0.05, elev=90.0, azim=-90.0)
        ax3.set_zticks([])
        ax3.set_zlabel("")
        ax3.set_ylabel("")
        ax3.set_box_aspect((1.0, 1.0, 0.02), zoom=1.3)     # x and y to the same scale; z is edge-on
        wall_mappable = wall_mappable or colls[0]
        ax3.set_title(f"{m}\n{_subtitle(r)}", fontsize=8)
        top.append(ax3)
        ax = fig.add_subplot(gs[1, c])
        out = plot_cut(ax, g, cut, values=ratio[m], cmap=_cmap("volume_ratio"), norm=rnorm, window=win,
                       coords=(0, 2), linewidth=0.3)
        cut_mappable = cut_mappable or out["mesh"]
        s = _section(g, cut_k)
        ax.plot(s[:, 0], s[:, 2], color="tab:red", lw=1.0, zorder=4)
        y = float(ref[0].xyz[32, 0, cut_k, 1])
        ax.set_title(f"section y = {y:.2f} (block 1, k = {cut_k + 1})", fontsize=8)
        bottom.append(ax)
    cb = fig.colorbar(wall_mappable, ax=top, shrink=0.5, aspect=40, location="right", extend="max")
    cb.set_label(f"change of the first layer's angle to the wall normal (deg; {vmax:g}+ saturated)", fontsize=7)
    cb.ax.tick_params(labelsize=7)
    _colorbar(fig, cut_mappable, "volume_ratio", ax=bottom, shrink=0.5, aspect=40, location="right")
    fig.suptitle(f"wing {WING} (root chord 1, half-span 1.5), {rows[RBF]['motion']}\n"
                 f"top: upper surface seen from above (x right, span y up); bottom: the wing block's "
                 f"last section, next to the tip cap", fontsize=9)
    save_small(fig, path, dpi, colors=128)


# ------------------------------------------------------------------ main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="smoke run: fewer cases, repeats and RBF centres")
    ap.add_argument("--out", type=Path, help="folder for reproduction.json and the figures")
    ap.add_argument("--repeat", type=int, default=None, help="timed steps per TFI/quaternion method (best kept)")
    ap.add_argument("--max-far", type=int, default=1000, help="at most this many far-field RBF centres on the wing")
    ap.add_argument("--rbf-symmetry", choices=("mirror", "project"), default="mirror",
                    help="RBF on the wing's symmetry plane: mirrored centres (default) or projection afterwards")
    ap.add_argument("--dpi", type=int, default=70)
    ap.add_argument("--no-figures", action="store_true")
    args = ap.parse_args(argv)
    quick = args.quick
    repeats = args.repeat or (2 if quick else 10)

    def log(msg):
        print(msg, flush=True)

    meta = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "load_start": uptime(),
            "machine": f"{platform.machine()}, {os.cpu_count()} CPUs", "python": platform.python_version(),
            "numpy": np.__version__, "scipy": scipy.__version__, "quick": quick, "repeats": repeats}
    log(f"load average at start: {meta['load_start']}")
    t0 = time.perf_counter()
    results = {
        "c": run_grid(C_GRID, c_grid_cases(quick), repeats, 1 if quick else 3,
                      {"max_far": 10 ** 9}, log),
        "wing": run_grid(WING, wing_cases(quick), max(2, repeats // 3), 1,
                         {"max_far": 300 if quick else args.max_far, "wall_stride": 2 if quick else 1,
                          "symmetry_mode": args.rbf_symmetry}, log, keep=[wing_cases(quick)[-1].label]),
    }
    meta["load_end"] = uptime()
    meta["seconds"] = time.perf_counter() - t0
    rows = results["c"]["rows"] + results["wing"]["rows"]
    print()
    print(f"load average: {meta['load_start']} at the start, {meta['load_end']} at the end; "
          f"{meta['seconds']:.0f} s")
    for key in ("c", "wing"):
        print(f"\n{results[key]['rows'][0]['grid']}; RBF: {results[key]['rbf']}\n")
        print(table(results[key]["rows"]))
        print("\northogonality change per wall patch, at interior wall points (patch edges left out), "
              "and of the motion applied to every point:\n")
        print(patch_table(results[key]["rows"]))
    tg = targets(rows)
    print("\ntargets:", json.dumps({q: {k: v["met"] for k, v in t.items()} for q, t in tg.items()}, indent=1))
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        doc = {"meta": meta, "rbf": {k: results[k]["rbf"] for k in results}, "rows": rows, "targets": tg}
        (args.out / "reproduction.json").write_text(json.dumps(doc, indent=1) + "\n")
        if not args.no_figures:
            c_figs = [("pitch 30", "reproduction_pitch30.png"), ("pitch 60", "reproduction_pitch60.png"),
                      ("camber 0.08, pitch 30", "reproduction_camber.png")]
            for label, fname in c_figs:
                if label in results["c"]["grids"]:
                    c_grid_figure(results["c"], label, args.out / fname, args.dpi)
            wlabel = list(results["wing"]["grids"])[-1]
            wing_figure(results["wing"], wlabel, args.out / "reproduction_wing.png", args.dpi)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
