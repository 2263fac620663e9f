"""``tfi-quat deform``: deform a grid for moved walls and write the result."""

from __future__ import annotations

import argparse
import os
import sys
import time

from ..errors import CaseError
from . import EXIT_CHECK
from ._common import (add_base_arg, case_and_grid, check_output, file_format, finite, output_like,
                      read_grid, vector)

#: negative cells listed in the summary line
_SHOW = 3

#: tfi_quat.deform.METHODS, spelled out so the CLI starts without numba
METHODS = ("two-level", "samareh", "tfi")

HELP = "deform a volume grid when its walls move (quaternion TFI or plain TFI)"
DESCRIPTION = """Deform GRID for a wall motion and write the deformed grid to OUT.

The walls, symmetry planes and fixed boundaries come from the grid file
itself when it records them (CGNS: its boundary conditions and 1-to-1
interfaces), from --case, --nmf or --connectivity, and from
--wall/--symmetry/--fixed (BLOCK:FACE[:A1-A2,B1-B2], 1-based), which
override the others face part by face part; faces not named are fixed.
The wall motion is either a moved grid
(--moved, same dimensions, only its wall points are used) or a rigid motion
of the walls (--rotate/--axis/--about/--translate), or mode shapes on the
walls with their amplitudes (--modes MODES.h5 --amplitudes A1,A2,...; the
file's template is written by --write-surface, docs/coupling.md), or the
case file's [motion].  Prints the number of negative cells and the smallest cell-volume
ratio to the reference at the end.  A deformed grid with negative cells is
not written (exit status 1, the count and the first cells on stderr)
unless --allow-negative is given.  OUT is written in the input's format and
variant unless its extension names another format; a CGNS input gives a
CGNS output with every node of the input but the coordinates, another
input written to a .cgns file gets the boundaries the deformation used."""


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("grid", nargs="?",
                   help="reference grid (Plot3D, HDF5 or CGNS); default: the case file's grid")
    p.add_argument("--case", help="case file (TOML) with grid, walls, symmetry, fixed, motion")
    p.add_argument("--nmf", help="Neutral Map File with interfaces and boundary kinds")
    p.add_argument("--connectivity", help="connectivity JSON written by 'tfi-quat connect'")
    p.add_argument("--wall", action="append", default=[], metavar="B:FACE[:RANGE]", help="wall patch")
    p.add_argument("--symmetry", action="append", default=[], metavar="B:FACE[:RANGE]",
                   help="symmetry patch")
    p.add_argument("--fixed", action="append", default=[], metavar="B:FACE[:RANGE]", help="fixed patch")
    p.add_argument("--moved", help="grid whose wall points hold the new wall positions")
    p.add_argument("--rotate", type=finite, metavar="DEG", help="rotate the walls by DEG degrees")
    p.add_argument("--axis", type=vector, default=None, metavar="X,Y,Z", help="rotation axis (default 0,0,1)")
    p.add_argument("--about", type=vector, default=None, metavar="X,Y,Z",
                   help="point on the rotation axis (default 0,0,0)")
    p.add_argument("--translate", type=vector, default=None, metavar="X,Y,Z", help="translate the walls")
    p.add_argument("--modes", metavar="MODES.h5",
                   help="mode shapes on the walls (a surface file, docs/coupling.md); the walls move "
                        "by the sum of the --amplitudes times the shapes")
    p.add_argument("--amplitudes", type=amplitudes, metavar="A1,A2,...",
                   help="one amplitude per mode of --modes")
    p.add_argument("--write-surface", metavar="SURF.h5",
                   help="write the walls (their point ids and coordinates, no modes) as the template "
                        "of a --modes file, and stop (no deformation, no -o)")
    p.add_argument("--method", choices=METHODS + ("quaternion",), metavar="{" + ",".join(METHODS) + "}",
                   help="quaternion TFI in the two-level formulation (default) or in the memo's "
                        "update (samareh), or plain TFI of displacements (tfi); docs/deformer.md")
    p.add_argument("--formulation", choices=METHODS[:2], help=argparse.SUPPRESS)   # deprecated
    p.add_argument("--rotation-length", type=finite, metavar="L",
                   help="two-level: thickness of the wall layer where non-rigid wall rotations act "
                        "(default 1%% of the walls' size)")
    p.add_argument("-o", "--output", help="deformed grid file (default: the case file's output)")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")
    p.add_argument("--allow-negative", action="store_true",
                   help="write the deformed grid even when it has negative cells (exit status 0)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_base_arg(p)


def amplitudes(text: str) -> tuple[float, ...]:
    """``A1,A2,...``: one or more finite numbers (an argparse type)."""
    out = []
    for part in text.split(","):
        try:
            out.append(finite(part.strip()))
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(f"expected finite numbers A1,A2,..., got {text!r}") from None
    return tuple(out)


def _check_modes(args):
    """--modes and --amplitudes go together, without another motion; the file is read (and
    checked) before the set-up and returned (:class:`tfi_quat.io.surface.SurfaceFile`; None
    without --modes)."""
    if args.amplitudes is not None and not args.modes:
        raise CaseError("--amplitudes goes with --modes MODES.h5")
    if not args.modes:
        return None
    if args.amplitudes is None:
        raise CaseError(f"--modes {args.modes}: give the amplitudes (--amplitudes A1,A2,...)")
    if args.moved or any(v is not None for v in (args.rotate, args.axis, args.about, args.translate)):
        raise CaseError("give either --modes or --moved or --rotate/--axis/--about/--translate, "
                        "not more than one")
    from ..io.surface import read_surface
    surface = read_surface(args.modes)
    if surface.n_modes != len(args.amplitudes):
        raise CaseError(f"{args.modes}: {surface.n_modes} mode(s), but {len(args.amplitudes)} "
                        "amplitude(s) given")
    return surface


def _motion(args, case):
    from ..case import unit_vector
    from ..deform import rigid_motion
    given = any(v is not None for v in (args.rotate, args.axis, args.about, args.translate))
    if args.modes:
        values = ", ".join(f"{a:g}" for a in args.amplitudes)
        return None, f"walls moved by the modes of {args.modes}, amplitudes {values}"
    if args.moved and given:
        raise CaseError("give either --moved or --rotate/--axis/--about/--translate, not both")
    if args.moved:
        return read_grid(args, args.moved, strict=False), f"walls from {args.moved}"
    if given:
        rot = args.rotate or 0.0
        axis = tuple(float(v) for v in unit_vector(args.axis, "--axis")) if args.axis else (0.0, 0.0, 1.0)
        about = args.about or (0.0, 0.0, 0.0)
        tr = args.translate or (0.0, 0.0, 0.0)
    elif case is not None and case.motion is not None:
        m = case.motion
        return m.apply, "walls moved by the case file's motion: " + m.describe()
    else:
        raise CaseError("no wall motion: give --moved, --rotate/--translate, or a case file with [motion]")
    desc = f"walls rotated {rot:g} deg about axis {tuple(axis)} through {tuple(about)}, translated {tuple(tr)}"
    return rigid_motion(rot, axis, about, tr), desc


def _method(args) -> str:
    """``--method``, with the old ``--method quaternion`` and ``--formulation X`` (deprecated, a
    note on stderr) mapped as the library maps them."""
    method = args.method or "two-level"
    if args.method == "quaternion":
        method = args.formulation or "two-level"
        print(f"tfi-quat deform: --method quaternion is deprecated; use --method {method}",
              file=sys.stderr)
    elif args.formulation is not None:
        if args.method not in (None, "tfi", args.formulation):
            raise CaseError(f"--method {args.method} and --formulation {args.formulation} disagree; "
                            "give --method only")
        if args.method is None:
            method = args.formulation
        print(f"tfi-quat deform: --formulation is deprecated; use --method {method}", file=sys.stderr)
    return method


class _Progress:
    def __init__(self, enabled: bool):
        self.enabled = enabled and sys.stderr.isatty()

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled or total < 2:
            return
        width = 30
        fill = int(width * done / total)
        sys.stderr.write(f"\r  volumes [{'#' * fill}{'.' * (width - fill)}] {done}/{total}")
        if done == total:
            sys.stderr.write("\n")
        sys.stderr.flush()


def run(args) -> int:
    from .. import io
    from .._jit import warm_up_in_background
    from ..spec import parse_patch_spec

    comm = mpi_world()
    if comm is not None:
        return _run_mpi(args, comm)
    case, path = case_and_grid(args)
    inputs = [path, args.moved, args.case, args.nmf, args.connectivity, args.modes]
    surface = None
    if args.write_surface:
        if args.output or args.modes or args.moved or args.amplitudes is not None:
            raise CaseError("--write-surface writes the walls only: give no -o, --modes, "
                            "--amplitudes or --moved")
        out = args.write_surface
    else:
        out = args.output or (case.output if case is not None else None)
        if out is None:
            raise CaseError("no output file: give -o OUT")
        surface = _check_modes(args)
    check_output(out, args.force, inputs=inputs)
    if args.nmf and args.connectivity:
        raise CaseError("give --nmf or --connectivity, not both")
    walls = [parse_patch_spec(w) for w in args.wall]
    sym = [parse_patch_spec(w) for w in args.symmetry]
    fixed = [parse_patch_spec(w) for w in args.fixed]
    # numba's set-up runs while the grid is read (the read holds no lock numba needs)
    warm_up_in_background()
    grid = read_grid(args, path)
    from ..deform import Deformer
    from ..quality import volume_ratio_summary
    conn = None
    if args.nmf or args.connectivity:
        from ..topology import Connectivity
        conn = Connectivity.from_nmf(args.nmf, grid) if args.nmf else Connectivity.from_json(args.connectivity, grid)
    if case is not None and not (walls or sym or fixed):
        walls, sym, fixed = list(case.walls), list(case.symmetry), list(case.fixed)
    # none given, no map: a CGNS grid's own connectivity (Deformer's default), else connect()
    moved, desc = (None, "") if args.write_surface else _motion(args, case)
    t0 = time.perf_counter()
    method = _method(args)
    kw = {}
    if method == "two-level" and args.rotation_length is not None:
        kw["rotation_length"] = args.rotation_length
    if args.rotation_length is not None and "rotation_length" not in kw:
        raise CaseError("--rotation-length applies to --method two-level")
    deformer = Deformer(grid, walls=walls, symmetry=sym, fixed=fixed, connectivity=conn,
                        method=method, **kw)
    t1 = time.perf_counter()
    if args.write_surface:
        deformer.write_surface(out, overwrite=args.force)
        n = deformer.surface_ids().shape[0]
        print(f"wrote {out}: {n} wall point copies ({deformer.wall_points().shape[0]} distinct), "
              f"their ids and coordinates, no modes; add /modes (n_modes, {n}, 3) for --modes "
              "(docs/coupling.md)")
        return 0
    progress = _Progress(not args.quiet and grid.npoints > 2_000_000)
    if args.modes:
        result = deformer.modal(surface)(args.amplitudes, callback=progress)
    else:
        result = deformer.deform(moved, callback=progress)
    t2 = time.perf_counter()
    q = volume_ratio_summary(result, grid)
    print(f"{desc}; method {method}")
    print(f"set-up {t1 - t0:.3f} s, step {t2 - t1:.3f} s ({grid.npoints / max(t2 - t1, 1e-12) / 1e6:.1f} M points/s)")
    where = ""
    if q["where"] is not None:
        b, i, j, k = q["where"]
        where = f" at block {b + 1} cell ({i + 1}, {j + 1}, {k + 1})"
    negative = f"{q['negative']} negative cells{_first_cells(result, grid) if q['negative'] else ''}"
    if q["negative"] and not args.allow_negative:
        print(f"tfi-quat deform: {negative}, smallest volume ratio {q['min_ratio']:.4g}{where}; "
              f"{out} not written (--allow-negative writes it)", file=sys.stderr)
        return EXIT_CHECK
    like = output_like(out, grid)
    boundaries = {}
    if like is None and result.connectivity is None and file_format(out) == "cgns":
        boundaries["connectivity"] = deformer.connectivity      # a CGNS file holds the ones used
    io.write(out, result, like=like, overwrite=args.force, **boundaries)
    print(f"wrote {out}: {negative}, smallest volume ratio {q['min_ratio']:.4g}{where}")
    return 0


def mpi_world():
    """``MPI.COMM_WORLD`` when the command runs under ``mpiexec`` with more than one rank (the
    launcher's rank count in the environment), else None; ParallelError naming the ``mpi``
    extra when mpi4py is missing."""
    size = next((os.environ[v] for v in _MPI_SIZE_VARS if v in os.environ), None)
    try:
        many = size is not None and int(size) > 1
    except ValueError:
        many = False
    if not many:
        return None
    from ..io.mpi import require_mpi
    return require_mpi().COMM_WORLD


def _moved_walls(path, deformer):
    """``--moved`` under MPI: the moved grid's wall patches, from its faces only (a mapping
    patch -> points, the form :meth:`Deformer.deform` takes)."""
    from .. import io
    faces = io.read_faces(path)
    if [tuple(d) for d in faces.dims] != deformer.dims:
        raise CaseError(f"--moved {path}: dimensions {faces.dims} differ from the grid's")
    out = {}
    for p in deformer.connectivity.patches:
        if p.kind == "wall":
            (a0, a1), (b0, b1) = p.spec.range
            out[p.spec] = faces.face(p.spec.block, p.spec.face)[a0:a1 + 1, b0:b1 + 1]
    return out


def _run_mpi(args, comm) -> int:
    """``tfi-quat deform`` under ``mpiexec -n N`` (N > 1): every rank reads and deforms its blocks
    (:class:`tfi_quat.deform.distributed.DistributedDeformer`), the output is written
    collectively, and rank 0 prints the summary reduced over the ranks.  Every error is agreed
    over the ranks (the same on each), so only rank 0 reports it."""
    from ..deform import Deformer
    from ..io.mpi import agree
    from ..quality import negative_cells, volume_ratio_summary
    from ..spec import parse_patch_spec
    if comm.rank != 0:      # one report: rank 0's (every rank meets the same errors)
        sys.stdout = sys.stderr = open(os.devnull, "w", encoding="utf-8")  # noqa: SIM115
    exc = None
    try:
        case, path = case_and_grid(args)
        if args.write_surface or args.base or args.nmf or args.connectivity:
            raise CaseError("under mpiexec, deform takes no --write-surface, --base, --nmf or "
                            "--connectivity yet: run them serially (docs/mpi.md)")
        out = args.output or (case.output if case is not None else None)
        if out is None:
            raise CaseError("no output file: give -o OUT")
        surface = _check_modes(args)
        if comm.rank == 0:
            check_output(out, args.force, inputs=[path, args.moved, args.case, args.modes])
        walls = [parse_patch_spec(w) for w in args.wall]
        sym = [parse_patch_spec(w) for w in args.symmetry]
        fixed = [parse_patch_spec(w) for w in args.fixed]
        if case is not None and not (walls or sym or fixed):
            walls, sym, fixed = list(case.walls), list(case.symmetry), list(case.fixed)
        method = _method(args)
        kw = {}
        if args.rotation_length is not None:
            if method != "two-level":
                raise CaseError("--rotation-length applies to --method two-level")
            kw["rotation_length"] = args.rotation_length
        moved, desc = (None, "") if args.moved else _motion(args, case)
    except Exception as e:      # noqa: BLE001  (every rank raises the first rank's)
        exc = e
    agree(comm, exc)
    t0 = time.perf_counter()
    deformer = Deformer(path, walls=walls, symmetry=sym, fixed=fixed, method=method, comm=comm, **kw)
    t1 = time.perf_counter()
    exc = None
    try:
        if args.moved:
            moved, desc = _moved_walls(args.moved, deformer), f"walls from {args.moved}"
    except Exception as e:      # noqa: BLE001
        exc = e
    agree(comm, exc)
    if args.modes:
        result = deformer.modal(surface)(args.amplitudes)
    else:
        result = deformer.deform(moved)
    t2 = time.perf_counter()
    # the summary of each rank's blocks, reduced: as the serial run's over all blocks
    q = volume_ratio_summary(result, deformer.grid)
    own = deformer.blocks
    where = None if q["where"] is None else (own[q["where"][0]],) + tuple(q["where"][1:])
    cells = [(own[b], ijk) for b, found in negative_cells(result, deformer.grid)
             for ijk in found[:_SHOW]] if q["negative"] else []
    parts = comm.allgather((q["negative"], q["min_ratio"], where, cells))
    negative = sum(p[0] for p in parts)
    lo = min(parts, key=lambda p: (p[1], p[2] or (0,)))
    shown = sorted((c for p in parts for c in p[3]), key=lambda c: c[0])[:_SHOW]
    at = ""
    if lo[2] is not None:
        b, i, j, k = lo[2]
        at = f" at block {b + 1} cell ({i + 1}, {j + 1}, {k + 1})"
    first = ", ".join(f"block {b + 1} cell ({', '.join(str(int(v) + 1) for v in ijk)})"
                      for b, ijk in shown)
    text = f"{negative} negative cells" + (f" (first: {first})" if first else "")
    print(f"{desc}; method {method}; {comm.size} MPI ranks")
    print(f"set-up {t1 - t0:.3f} s, step {t2 - t1:.3f} s")
    if negative and not args.allow_negative:
        print(f"tfi-quat deform: {text}, smallest volume ratio {lo[1]:.4g}{at}; "
              f"{out} not written (--allow-negative writes it)", file=sys.stderr)
        return EXIT_CHECK
    deformer.write(out, result, like=output_like(out, deformer.grid), overwrite=args.force)
    print(f"wrote {out}: {text}, smallest volume ratio {lo[1]:.4g}{at}")
    return 0


#: environment variables in which MPI launchers give the number of ranks (MPICH/Hydra, Open MPI)
_MPI_SIZE_VARS = ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE")


def _first_cells(result, grid) -> str:
    """`` (first at block B cell (i, j, k), ...)``: the first negative cells, 1-based."""
    from ..quality import negative_cells
    cells = [(b, ijk) for b, found in negative_cells(result, grid) for ijk in found[:_SHOW]][:_SHOW]
    text = ", ".join(f"block {b + 1} cell ({', '.join(str(int(v) + 1) for v in ijk)})" for b, ijk in cells)
    return f" (first: {text})" if text else ""
