"""The demo: the memo's figure 4 experiment on the shipped NACA 0012 C-grid.

The 257 x 65 viscous C-grid (``grids/naca0012_c_257x65.x``) has its wall
deformed, rotated and translated "to simulate aeroelastic deformation"
(Samareh, NASA/TM-2002-211646, figure 4): the aft part of the section is
bent down (camber), the airfoil pitched nose-up about the quarter chord and
plunged.  The volume grid is deformed by plain TFI (``method="tfi"``), by
quaternion TFI with the memo's update (``method="samareh"``) and by the
default two-level quaternion TFI (``method="two-level"``); the three grids are written, a figure like
the memo's (plain TFI left, quaternion TFI right, zooms at the leading and
trailing edges) is drawn, and a table compares near-wall orthogonality,
cell volumes and time per step.

:func:`run_demo` does it all; ``tfi-quat demo`` is its command line.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from . import quaternion as qa
from .errors import CaseError

__all__ = ["DemoMotion", "default_grid_path", "run_demo", "sample_path"]

#: the shipped grid the demo runs on
GRID_NAME = "naca0012_c_257x65"


def sample_path(name: str) -> Path:
    """Path of a shipped sample grid or case file, e.g. ``"naca0012_c_257x65.x"``.

    The sample grids (``grids/README.md``) are installed with the package
    (``tfi_quat/grids/``); in a source checkout they are read from its
    ``grids/`` folder.

    Parameters
    ----------
    name : str
        File name inside ``grids/``, with its extension.

    Returns
    -------
    pathlib.Path
        The file's path.

    Raises
    ------
    FileNotFoundError
        If no such sample is shipped (the message names the places looked in).
    """
    installed = Path(str(resources.files(__package__))) / "grids"
    checkout = Path(__file__).resolve().parents[1] / "grids"
    for folder in (installed, checkout):
        path = folder / name
        if path.is_file():
            return path
    raise FileNotFoundError(f"{name}: no such sample grid in {installed} or {checkout}")


def default_grid_path() -> Path:
    """The demo's grid, ``grids/naca0012_c_257x65.x``, as shipped (:func:`sample_path`)."""
    return sample_path(f"{GRID_NAME}.x")


@dataclass(frozen=True)
class DemoMotion:
    """The wall motion of the demo, applied in this order.

    1. camber: ``y -= camber * (max(x - x_ref, 0) / (1 - x_ref))**2``, the
       part behind ``x_ref`` bent down, ``camber`` chords at the trailing edge;
    2. pitch: rotation by ``pitch`` degrees nose-up (clockwise in the x-y
       plane) about ``(x_ref, 0, 0)``;
    3. translation by ``translate``.
    """

    camber: float = 0.08
    pitch: float = 30.0
    x_ref: float = 0.25
    translate: tuple = (0.0, 0.1, 0.0)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        p = np.array(points, dtype=np.float64)
        aft = np.maximum(p[:, 0] - self.x_ref, 0.0) / (1.0 - self.x_ref)
        p[:, 1] -= self.camber * aft * aft
        half = np.radians(self.pitch) / 2.0
        q = np.array([np.cos(half), 0.0, 0.0, -np.sin(half)])
        about = np.array([self.x_ref, 0.0, 0.0])
        return about + qa.rotate(q, p - about) + np.asarray(self.translate, dtype=np.float64)

    def describe(self) -> str:
        tx, ty, tz = self.translate
        return (f"aft part bent down {self.camber:g} chord at the trailing edge (quadratic from "
                f"x = {self.x_ref:g}), pitched {self.pitch:g} deg nose-up about ({self.x_ref:g}, 0), "
                f"translated ({tx:g}, {ty:g})")


@dataclass
class DemoResult:
    """What :func:`run_demo` measured and wrote."""

    motion: str
    rows: dict = field(default_factory=dict)      # method -> metrics
    files: list = field(default_factory=list)
    first_step_seconds: dict = field(default_factory=dict)

    def table(self) -> str:
        head = ("| method | orthogonality change, first 5 layers: max / mean (deg) | "
                "smallest volume ratio | negative cells | time per step (ms) |")
        lines = [head, "|---|---|---|---|---|"]
        for name, r in self.rows.items():
            lines.append(f"| {name} | {r['ortho_max']:.3f} / {r['ortho_mean']:.3f} | "
                         f"{r['min_ratio']:.3f} | {r['negative']} | {r['step_ms']:.2f} |")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {"motion": self.motion, "methods": self.rows, "files": [str(f) for f in self.files],
                "first_step_seconds": self.first_step_seconds}


#: table label -> (Deformer method, output file); plain TFI left as in the memo's figure 4
METHODS = {
    "plain TFI": ("tfi", "naca0012_tfi.x"),
    "quaternion TFI, memo's update": ("samareh", "naca0012_samareh.x"),
    "quaternion TFI": ("two-level", "naca0012_quaternion.x"),
}


def run_demo(outdir, grid_path=None, motion: DemoMotion | None = None, overwrite: bool = False,
             figure: bool = True, repeats: int = 5) -> DemoResult:
    """Run the demo; write the grids, figure and table into ``outdir``.

    Parameters
    ----------
    outdir : path
        Folder for ``naca0012_tfi.x``, ``naca0012_samareh.x``, ``naca0012_quaternion.x``,
        ``demo.png``, ``demo.md`` (the table) and ``demo.json``; created if
        missing.  Existing files are refused unless ``overwrite``.
    grid_path : path, optional
        The reference C-grid (default :func:`default_grid_path`); its case
        file (same name, ``.toml``) gives the walls and fixed boundaries.
    motion : DemoMotion, optional
    overwrite : bool
    figure : bool
        Draw ``demo.png`` (matplotlib).
    repeats : int
        Steps timed per method after the first; the best is reported.
    """
    from . import io
    from .case import load_case
    from .deform import Deformer
    from .quality import orthogonality_change, volume_ratio_summary

    grid_path = Path(grid_path) if grid_path is not None else default_grid_path()
    case_path = grid_path.with_suffix(".toml")
    if not grid_path.exists():
        raise CaseError(f"{grid_path}: demo grid not found")
    if not case_path.exists():
        raise CaseError(f"{case_path}: the demo grid's case file is missing")
    motion = motion or DemoMotion()
    out = Path(outdir)
    targets = [out / m[1] for m in METHODS.values()] + [out / "demo.md", out / "demo.json"]
    if figure:
        targets.append(out / "demo.png")
    if not overwrite:
        for t in targets:
            if t.exists():
                raise CaseError(f"{t}: exists; refusing to overwrite it (use --force)")
    out.mkdir(parents=True, exist_ok=True)

    ref = io.read(grid_path)
    case = load_case(case_path)
    result = DemoResult(motion.describe())
    grids = {}
    for label, (method, fname) in METHODS.items():
        t0 = time.perf_counter()
        d = Deformer(ref, walls=case.walls, symmetry=case.symmetry, fixed=case.fixed, method=method)
        moved = d.deform(motion)
        result.first_step_seconds[label] = time.perf_counter() - t0
        best = np.inf
        for _ in range(max(1, repeats)):
            t = time.perf_counter()
            moved = d.deform(motion)
            best = min(best, time.perf_counter() - t)
        q = volume_ratio_summary(moved, ref)
        oc = orthogonality_change(moved, ref, case.walls, layers=5)
        result.rows[label] = {"method": method,
                              "ortho_max": float(oc["max"]), "ortho_mean": float(oc["mean"]),
                              "min_ratio": float(q["min_ratio"]), "negative": int(q["negative"]),
                              "step_ms": 1e3 * best, "setup_s": d.setup_seconds}
        path = out / fname
        io.write(path, moved, like=ref, overwrite=overwrite)
        result.files.append(path)
        grids[label] = moved
    text = f"Motion: {result.motion}.\n\n{result.table()}\n"
    io_write_text(out / "demo.md", text, overwrite)
    io_write_text(out / "demo.json", json.dumps(result.to_dict(), indent=2, ensure_ascii=True) + "\n", overwrite)
    result.files += [out / "demo.md", out / "demo.json"]
    if figure:
        fig = demo_figure(ref, grids, case.walls, result)
        from .io._atomic import atomic_output
        with atomic_output(out / "demo.png") as fh:
            fig.savefig(fh, format="png", dpi=110)
        result.files.append(out / "demo.png")
    return result


def demo_figure(ref, grids: dict, walls, result: DemoResult | None = None):
    """The memo's figure 4 layout (:func:`tfi_quat.plot.plot_compare`): one column per
    method (plain TFI left, then the memo's quaternion update, then the default), rows: the near field, a leading-edge zoom and a
    trailing-edge zoom, the reference grid in light grey under the deformed
    one.  Zoom windows follow the deformed wall (trailing edge: the wall's end
    points; leading edge: the wall point farthest from them)."""
    from .plot import plot_compare

    subtitles, suptitle = None, None
    if result is not None:
        subtitles = {label: (f"orthogonality change (5 layers) max {row['ortho_max']:.2f} deg,\n"
                             f"min volume ratio {row['min_ratio']:.2f}") for label, row in result.rows.items()}
        suptitle = (f"NACA 0012 C-grid 257 x 65 (grey: reference grid, red: deformed wall)\n"
                    f"wall {result.motion}")
    return plot_compare(grids, ref=ref, walls=walls, windows=["near", "le", "te"], layout="overlay",
                        subtitles=subtitles, suptitle=suptitle, figsize=(5.2 * len(grids), 13.0))


def io_write_text(path: Path, text: str, overwrite: bool) -> None:
    """Write a small text file atomically (:func:`tfi_quat.io._atomic.atomic_output`)."""
    from .io._atomic import atomic_output

    if path.exists() and not overwrite:
        raise CaseError(f"{path}: exists; refusing to overwrite it (use --force)")
    with atomic_output(path, "w") as fh:
        fh.write(text)
