"""Regenerate the sample grids and their case files in this folder, or check them.

    python grids/make_grids.py [NAME ...]           # rewrite the grids, case files, SHA256SUMS
    python grids/make_grids.py --check [NAME ...]   # regenerate in memory and compare

Each entry of :data:`SAMPLES` records the generator, its parameters, the
motion written to the case file and a one-line purpose; ``tests/test_generate.py``
regenerates the small grids from these records and compares them with the
shipped files (the wing, ~2 s to generate, is checked there for its stated
properties; ``--check`` compares it too).
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent

#: name -> (generator, parameters, motion for the case file or None, purpose)
SAMPLES = {
    "naca0012_c_257x65": (
        "airfoil", dict(naca="0012", topology="C", ni=257, nj=65, first_spacing=1e-5, farfield=20.0),
        dict(rotate=10.0, axis=[0.0, 0.0, 1.0], about=[0.25, 0.0, 0.0], translate=[0.0, 0.05, 0.0]),
        "the memo's figure 4 case: viscous C-grid, rigid pitch and plunge of the airfoil"),
    "naca4412_o_257x65": (
        "airfoil", dict(naca="4412", topology="O", ni=257, nj=65, first_spacing=1e-5, farfield=20.0),
        dict(rotate=-8.0, axis=[0.0, 0.0, 1.0], about=[0.25, 0.0, 0.0]),
        "cambered section, periodic O-grid seam"),
    "cylinder_o_129x65": (
        "cylinder", dict(ni=129, nj=65, radius=0.5, first_spacing=1e-4, farfield=20.0),
        dict(translate=[0.0, 0.1, 0.0]),
        "analytic O-grid, rigid translation"),
    "channel_bump_129x49": (
        "channel", dict(ni=129, nj=49, length=3.0, height=1.0, bump_height=0.1, first_spacing=1e-3),
        None,
        "single-block H-grid; wall with fixed neighbours (bump shape changes)"),
    "two_block_65x33": (
        "two-block", dict(ni=65, nj=33, length=3.0, height=1.0, bump_height=0.1, first_spacing=2e-3),
        None,
        "two blocks, interface with swapped index axes, one block with a wall"),
    "wing_ch_501k": (
        "wing", dict(naca="0012", aspect_ratio=4.0, taper=0.5, sweep=30.0, ni=129, nj=49, nk_wing=45,
                     nk_cap=9, nk_out=25, first_spacing=2e-5, farfield=15.0, span_farfield=10.0),
        dict(bend=0.15, twist=5.0, about=[0.25, 0.0, 0.0], span_axis=[0.0, 1.0, 0.0], span=1.5,
             direction=[0.0, 0.0, 1.0]),
        "3-D C-H wing: wake cuts, tip cap with collapsed edge, symmetry plane, swapped/reversed interfaces"),
}


def build(name: str):
    """Return ``(grid, case)`` of one sample (the case's grid path is ``NAME.x`` in this folder)."""
    from tfi_quat import generate as gen
    from tfi_quat.case import Case, Motion

    kind, params, motion, _ = SAMPLES[name]
    grid = gen.GENERATORS[kind](**params)
    patches = gen.boundary_patches(kind, grid, n_wake=params.get("n_wake"),
                                   topology=params.get("topology", "C"))
    case = Case(grid=HERE / f"{name}.x", motion=None if motion is None else Motion(**motion), **patches)
    return grid, case


def sha256(path) -> str:
    """Hex SHA-256 of a file."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def check(names) -> int:
    """Compare the shipped files with freshly generated ones; 0 when all agree.

    Coordinates must agree to 1e-12 of the largest coordinate (other CPUs
    may differ in the last bits of sin/cos), the case files' patches and
    motion exactly, and every file its line in ``SHA256SUMS``.
    """
    import numpy as np

    import tfi_quat
    from tfi_quat.case import load_case

    sums = dict(reversed(line.split()) for line in (HERE / "SHA256SUMS").read_text().splitlines())
    bad = 0
    for name in names or SAMPLES:
        grid, case = build(name)
        shipped = tfi_quat.read(HERE / f"{name}.x")
        problems = []
        if shipped.ndim != grid.ndim or shipped.dims != grid.dims:
            problems.append(f"dims {shipped.dims} != {grid.dims}")
        else:
            scale = max(float(np.abs(b.xyz).max()) for b in grid)
            diff = max(float(np.abs(a.xyz - b.xyz).max()) for a, b in zip(shipped, grid))
            if diff > 1e-12 * scale:
                problems.append(f"coordinates differ by {diff:.3g}")
        loaded = load_case(HERE / f"{name}.toml")
        if (loaded.walls, loaded.symmetry, loaded.fixed, loaded.motion) != \
                (case.walls, case.symmetry, case.fixed, case.motion):
            problems.append("case file differs")
        if sums.get(f"{name}.x") != sha256(HERE / f"{name}.x"):
            problems.append("SHA256SUMS differs")
        print(f"{name}: {'ok' if not problems else '; '.join(problems)}")
        bad += bool(problems)
    return 1 if bad else 0


def main(names) -> int:
    import tfi_quat
    from tfi_quat.case import save_case

    if names and names[0] == "--check":
        return check(names[1:])
    for name in names or SAMPLES:
        grid, case = build(name)
        tfi_quat.write(HERE / f"{name}.x", grid, overwrite=True)
        save_case(HERE / f"{name}.toml", case)
        print(f"{name}: {len(grid)} block(s), {grid.npoints} points")
    lines = [f"{sha256(HERE / f'{n}.x')}  {n}.x" for n in SAMPLES if (HERE / f"{n}.x").exists()]
    (HERE / "SHA256SUMS").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(HERE.parent))      # the checkout's tfi_quat, installed or not
    sys.exit(main(sys.argv[1:]))
