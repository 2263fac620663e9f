"""The Deformer front: options, the two formulations' steps, the result grid.

Set-up (once per grid) builds the frozen :class:`~.skeleton.Skeleton` and, for
the two-level formulation, its :class:`~.twolevel.TwoLevel` parts; a step
(:meth:`Deformer.deform`) reads them, fills the boundary fields level by level
(:mod:`.stages`) and runs one fused TFI kernel per block.

Methods (``docs/deformer.md`` has the derivation and the measurements):

``method="two-level"`` (default)
    The wall motion of each wall body is split into the rigid motion that
    fits it best and a residual deformation (:mod:`.twolevel`).  Rigid
    motions are reproduced exactly, near-wall grid lines turn with the wall,
    and small irregularities of the fitted wall rotations are not carried
    over long lever arms into thin far-field cells.
``method="samareh"``
    The memo's update ``R_d = c + Δ(x) + rot(Q(x), R_u - c)``, Δ and Q
    interpolated from the boundaries (Hermite blending by default).

``method="tfi"``
    The classic baseline: the same hierarchy with Q ≡ 1 and Δ the
    displacement.

The old spellings ``method="quaternion"`` and ``formulation=`` are accepted
with a :class:`DeprecationWarning` (:func:`resolve_method`).
"""

from __future__ import annotations

import functools
import math
import os
import threading
import time
import warnings
from concurrent import futures
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .. import quaternion as qa
from .._jit import SERIAL_BELOW, serial_below, threads, use_threads
from ..errors import CaseError, DeformationError
from ..grid import Block, Grid
from ..quality import CellCheck, check_block, check_reference
from ..spec import as_patch_specs
from . import buffers, stages, twolevel
from .skeleton import BLENDINGS, FIXED, WALL, ArclengthParams, boundary_points, build_skeleton
from .walls import WallInput, other_targets

__all__ = ["Deformer", "rigid_motion", "StepTimings", "deformer_from_case", "METHODS",
           "resolve_method"]

_ORIGIN = np.zeros(3)
_IDENT = np.array([1.0, 0.0, 0.0, 0.0])

#: the deformation methods: quaternion TFI in the two-level formulation (default) or in the
#: memo's (Samareh's) form, and plain TFI of displacements
METHODS = ("two-level", "samareh", "tfi")
_FORMULATIONS = ("two-level", "samareh")


def resolve_method(method: str = "two-level", formulation: str | None = None) -> str:
    """The method (one of :data:`METHODS`) for ``method`` and the deprecated ``formulation``.

    ``method="quaternion"`` (deprecated) means ``formulation`` or ``"two-level"``;
    ``formulation`` (deprecated) replaces a quaternion method (``"two-level"``,
    ``"samareh"``, ``"quaternion"``) and is ignored with ``"tfi"``, as before.  Each
    deprecated spelling warns with a :class:`DeprecationWarning`.
    """
    if formulation is not None:
        warnings.warn("Deformer(formulation=...) is deprecated; give method='two-level', "
                      "'samareh' or 'tfi'", DeprecationWarning, stacklevel=3)
        if formulation not in _FORMULATIONS:
            raise CaseError(f"formulation must be one of {', '.join(map(repr, _FORMULATIONS))}, "
                            f"got {formulation!r}")
    if method == "quaternion":
        warnings.warn("Deformer(method='quaternion') is deprecated; give method='two-level' (the "
                      "default) or method='samareh'", DeprecationWarning, stacklevel=3)
        return formulation or "two-level"
    if method not in METHODS:
        raise CaseError(f"method must be one of {', '.join(map(repr, METHODS))}, got {method!r}")
    if formulation is not None and method != "tfi":
        return formulation
    return method


def rigid_motion(rotate_deg: float = 0.0, axis=(0.0, 0.0, 1.0), about=(0.0, 0.0, 0.0),
                 translate=(0.0, 0.0, 0.0)) -> Callable[[np.ndarray], np.ndarray]:
    """A callable moving points ``(n, 3)`` by a rotation about a point, then a translation.

    ``x -> about + rot(axis, angle)(x - about) + translate``.
    """
    axis = np.asarray(axis, dtype=np.float64)
    n = np.linalg.norm(axis)
    if not np.isfinite(n) or n == 0.0:
        raise CaseError(f"rotation axis {tuple(axis)} has no direction")
    half = math.radians(float(rotate_deg)) / 2.0
    q = np.concatenate([[math.cos(half)], axis / n * math.sin(half)])
    about = np.asarray(about, dtype=np.float64)
    translate = np.asarray(translate, dtype=np.float64)

    def move(points: np.ndarray) -> np.ndarray:
        return about + qa.rotate(q, np.asarray(points, dtype=np.float64) - about) + translate

    return move


@dataclass
class StepTimings:
    """Seconds spent in each stage of the last :meth:`Deformer.deform` call.

    ``walls``: wall targets, rigid fits, wall quaternions; ``skeleton``:
    vertices and segments; ``faces``: patches, symmetry and boundary
    positions; ``volumes``: the block kernels, the copy of boundary points
    and into the ``out`` buffers; ``check``: the cell check (``check=``).
    """

    walls: float = 0.0
    skeleton: float = 0.0
    faces: float = 0.0
    volumes: float = 0.0
    check: float = 0.0

    @property
    def total(self) -> float:
        return self.walls + self.skeleton + self.faces + self.volumes + self.check


class _Work:
    """Boundary-sized buffers a step reuses (a step holds the Deformer's lock).  Entries a step
    never writes keep their values here: fixed points ``Δ = 0``, ``Q = 1``, ``K = c`` and
    their undeformed position; non-wall rows of ``rd`` and ``y``."""

    def __init__(self, P: np.ndarray, c: np.ndarray | None):
        self.rd = P.copy()                          # wall targets
        self.y = P.copy()                           # two-level: pulled-back residual targets
        self.K = None if c is None else c.copy()    # two-level: K (Q = 1: position c + A = P)
        self.ql = np.zeros((P.shape[0], 4))         # two-level: residual Q
        self.ql[:, 0] = 1.0
        self.gd = np.zeros((P.shape[0], 3))         # Δ (Samareh's form)
        self.qg = self.ql.copy()                    # Q (Samareh's form)
        self.pos = P.copy()                         # boundary positions


class Deformer:
    """Deform a multiblock volume grid when its walls move.

    Parameters
    ----------
    grid : Grid or path
        The reference (undeformed) grid, or its file (read whole; with
        ``comm``, each rank reads its blocks).  It is kept by reference and
        never modified; do not modify it while the Deformer is in use.
    walls, symmetry, fixed : sequence of PatchSpec or "BLOCK:FACE[:A1-A2,B1-B2]"
        Boundary patches by kind (1-based text, 0-based PatchSpec).  A whole
        face given as a wall is reduced by the interfaces on it.  Faces not
        given are ``fixed``, or keep their kinds in ``connectivity`` (the
        grid's own included).
    connectivity : tfi_quat.topology.Connectivity, optional
        Interfaces and patches (e.g. loaded from JSON or an ``.nmf``).  Default:
        the grid's own (``grid.connectivity``, read from a CGNS file with its
        boundary conditions and 1-to-1 interfaces), else found with
        :func:`tfi_quat.topology.connect`.  When given (or taken from the grid)
        with ``walls``/``symmetry``/``fixed``, those kinds are applied to it
        face part by face part (:func:`tfi_quat.topology.classify`); the rest
        keeps its kinds.  The grid's own connectivity is always re-classified
        so: boundary parts it leaves out get the kinds :func:`~tfi_quat.topology.connect`
        gives them.
    method : {"two-level", "samareh", "tfi"}
        ``two-level`` (default) and ``samareh``: interpolate translations and
        rotations (quaternion TFI), the rotations acting in the two-level
        formulation or in the memo's update (see the module docstring and
        ``docs/deformer.md``); ``tfi``: the classic baseline, displacements
        only.  ``"quaternion"`` is a deprecated spelling of ``"two-level"``.
    formulation : {"two-level", "samareh"}, optional
        Deprecated: give ``method`` instead (it replaces ``method`` unless
        that is ``"tfi"``).
    centre : array_like (3,), optional
        Rotation centre ``c`` of the Samareh update (the whole update for
        ``"samareh"``, the rigid part for ``"two-level"``).  Default: the
        centroid of the undeformed wall points (it moves with the problem,
        docs/method.md §3.6).
    tol : float, optional
        Coincidence tolerance for merging boundary points; default
        1e-10 x the grid's bounding-box diagonal.
    blending : {"hermite", "linear"}, optional
        Blending function of ``"samareh"`` and ``"tfi"`` applied to the
        normalised arclength ``s``: ``hermite`` (default) ``3 s^2 - 2 s^3``,
        ``linear`` Soni's original.  The two-level formulation always uses its
        wall-layer blending (:mod:`tfi_quat.blending`).
    rotation_length : float, optional
        ``method="two-level"``: thickness of the wall layer in which residual
        (non-rigid) wall rotations act.  Default:
        :data:`tfi_quat.deform.twolevel.ROTATION_LENGTH_FRACTION` x the walls' size (twice the largest
        distance of a wall point from their centroid).
    idw_power : float
        Exponent of the inverse-distance weights of free vertices.
    max_idw_sources : int
        At most this many (evenly sampled) wall points serve as sources of the
        vertex blend.
    threads : int, optional
        The most threads the Deformer's compiled kernels use, in its own calls
        only (set-up, :meth:`deform`, :meth:`velocity`); the setting of the
        calling thread is restored after each.  Default: all
        (``numba.config.NUMBA_NUM_THREADS``; more are capped to that).  In a
        coupled run give the Deformer the cores the flow solver leaves idle
        while it waits for the grid, e.g. ``threads=1`` when every core runs
        a solver rank, so that the two do not compete.
    dup_tol : float
        The array form of :meth:`deform`: copies of one wall point (a point
        listed more than once) may differ by at most this distance (default
        0: they must be equal); the first copy given is used.
    comm : mpi4py.MPI.Intracomm, optional
        Deform distributed over the ranks of ``comm`` (``grid``: a file path or
        a Grid of the rank's own blocks; ``blocks``: their global 0-based
        numbers, None for a balanced partition): each rank deforms its own
        blocks, bit for bit as a serial run (:mod:`tfi_quat.deform.distributed`,
        ``docs/mpi.md``).  Needs the ``mpi`` extra.
    blocks : sequence of int, optional
        With ``comm``: the blocks this rank owns.
    """

    def __new__(cls, *args, comm=None, **kw):
        if comm is not None and cls is Deformer:
            from .distributed import DistributedDeformer
            return super().__new__(DistributedDeformer)
        return super().__new__(cls)

    def __init__(self, grid: Grid, walls=(), symmetry=(), fixed=(), connectivity=None,
                 method: str = "two-level", formulation: str | None = None, centre=None,
                 tol: float | None = None, blending: str | None = None,
                 rotation_length: float | None = None, idw_power: float = 3.0,
                 max_idw_sources: int = 2000, dup_tol: float = 0.0, threads: int | None = None,
                 comm=None, blocks=None):
        from .shell import ShellGrid
        if comm is None and blocks is not None:
            raise CaseError("blocks= goes with comm= (a distributed deformation)")
        if isinstance(grid, (str, os.PathLike)):
            from .. import io
            grid = io.read(grid)
        shell = isinstance(grid, ShellGrid)     # the distributed set-up (.distributed)
        if not (shell or isinstance(grid, Grid)):
            raise CaseError(f"grid must be a tfi_quat.Grid or a file path, got {type(grid).__name__}")
        method = resolve_method(method, formulation)
        two = method == "two-level"
        if blending is not None and blending not in BLENDINGS:
            raise CaseError(f"blending must be one of {', '.join(BLENDINGS)}, got {blending!r}")
        if blending is not None and two:
            raise CaseError("blending applies to method='samareh' and method='tfi'; the "
                            "two-level method blends with its wall layer (rotation_length)")
        if rotation_length is not None:
            try:
                rotation_length = float(rotation_length)
            except (TypeError, ValueError):
                raise CaseError(f"rotation_length must be a positive number, got "
                                f"{rotation_length!r}") from None
            if not (rotation_length > 0.0 and math.isfinite(rotation_length)):
                raise CaseError(f"rotation_length must be a positive number, got {rotation_length!r}")
            if not two:
                raise CaseError("rotation_length applies to method='two-level' only")
        try:
            dup_tol = float(dup_tol)
        except (TypeError, ValueError):
            dup_tol = math.nan
        if not (math.isfinite(dup_tol) and dup_tol >= 0.0):
            raise CaseError(f"dup_tol must be a finite number >= 0, got {dup_tol!r}")
        #: the largest distance allowed between copies of one wall point (:meth:`deform`)
        self.dup_tol = dup_tol
        #: the most threads the Deformer's own calls use (None: all)
        self.threads = _check_threads(threads)
        cap = functools.partial(use_threads, self.threads)
        t0 = time.perf_counter()
        #: the reference blocks this Deformer deforms (all, or under MPI the rank's own)
        self.grid = grid.local if shell else grid
        #: their global 0-based block numbers
        self.blocks = grid.own if shell else tuple(range(len(grid)))
        self._all = grid
        self.ndim = grid.ndim
        self.method = method
        self._use_q = method != "tfi"
        self.blending = None if two else (blending or "hermite")
        _check_block_sizes(grid)
        walls = as_patch_specs(walls, "walls")
        symmetry = as_patch_specs(symmetry, "symmetry")
        fixed = as_patch_specs(fixed, "fixed")
        from .. import topology
        own = connectivity is None and grid.connectivity is not None
        if own:
            # the file's kinds, the given ones over them, the rest as connect() classifies it
            # (fixed, planar next to a wall: symmetry), in connect()'s patch order
            connectivity = topology.classify(grid.connectivity, grid, walls=walls, symmetry=symmetry,
                                             fixed=fixed)
        elif connectivity is None:
            with cap():
                connectivity = topology.connect(grid, walls=walls, symmetry=symmetry, fixed=fixed)
        elif walls or symmetry or fixed:
            connectivity = topology.classify(connectivity, grid, walls=walls, symmetry=symmetry,
                                             fixed=fixed)
        self.connectivity = connectivity
        lo, hi = grid.bbox()
        diag = float(np.linalg.norm(hi - lo)) or 1.0
        self._scale = diag
        self.tol = float(tol) if tol is not None else 1e-10 * diag
        if not (math.isfinite(self.tol) and self.tol >= 0.0):
            raise CaseError(f"tol must be a finite number >= 0, got {tol!r}")
        with cap():
            pts = boundary_points(grid, connectivity, self.tol, marker=not shell)
        if not pts.wall.size:
            src = ""
            if own:
                src = f" (the boundary conditions of {grid.source_path or 'the grid'} name no wall)"
            raise CaseError(f"no wall points{src}: give at least one wall patch")
        self.centre = _centre(pts, centre)
        if two:
            with cap():
                layer = twolevel.wall_layer(pts, rotation_length, diag)
            params = layer
            self.rotation_length = layer.ell
        else:
            params = ArclengthParams(BLENDINGS[self.blending])
            self.rotation_length = None
        #: the frozen skeleton (:class:`tfi_quat.deform.skeleton.Skeleton`)
        with cap():
            self.skeleton = build_skeleton(grid, connectivity, pts, params, tol=self.tol,
                                           idw_power=idw_power, max_idw_sources=max_idw_sources,
                                           own=self.blocks if shell else None,
                                           exchange=grid.exchange_plans if shell else None)
            #: the two-level parts (:class:`tfi_quat.deform.twolevel.TwoLevel`), None for the others
            self.two_level = twolevel.build_two_level(self.skeleton, layer) if two else None
        self._work = _Work(pts.P, None if self.two_level is None else self.two_level.c)
        self._lock = threading.RLock()     # re-entrant: jvp/vjp hold it and build the linearisation
        #: the wall copies and the checks of the array form (:class:`.walls.WallInput`)
        self.walls = WallInput(grid, self.skeleton, dup_tol)
        self._scratch = buffers.Scratch(self.grid)
        self._check_seconds = 0.0
        #: per block, the reference of the checks (:func:`tfi_quat.quality.check_reference`: the
        #: sign of its volumes), made by the first check (a pass over the block) and kept:
        #: later checks skip the reference volumes
        self._check_refs = [None] * len(grid)
        self._check_thread = None
        #: the check of the last :meth:`deform` call (:class:`tfi_quat.quality.CellCheck`, also
        #: of one that raised for invalid cells), or None when it was not checked
        self.quality = None
        self.setup_seconds = time.perf_counter() - t0
        self.timings = StepTimings()
        #: the global wall targets (G, 3) of the last :meth:`deform` (the reference before
        #: any): the point its derivatives are linearised at (O(surface); updated in place)
        self.last_targets = pts.P.copy()
        self._linear = None

    @property
    def n_global(self) -> int:
        """The number of distinct boundary points."""
        return self.skeleton.n_global

    def wall_points(self) -> np.ndarray:
        """Undeformed positions ``(n, 3)`` of the (distinct) wall points, in the order
        :meth:`deform` passes them to a motion callable."""
        pts = self.skeleton.points
        return pts.P[pts.wall].copy()

    def surface_ids(self) -> np.ndarray:
        """Block and point indices of every wall point copy, in the solver's terms.

        Returns
        -------
        ndarray, int64, shape (n, 4)
            Rows ``(block, i, j, k)``, 0-based: the points of the wall patches
            in the order of ``self.connectivity.patches``, each patch's points
            in Fortran order of its running indices (the first fastest).  A
            point shared by several patches or blocks (a wall edge, an
            interface crossing a wall) appears once per copy.  2-D grids have
            ``k = 0``.  :meth:`surface_points` gives their coordinates.
        """
        return self.walls.surface()[0].copy()

    def surface_points(self) -> np.ndarray:
        """Undeformed coordinates ``(n, 3)`` of the wall point copies, in
        :meth:`surface_ids` order."""
        from .shell import boundary_values
        return boundary_values(self._all, self.walls.surface()[0])

    def new_grid(self, order: str = "F", separate: bool = False):
        """Buffers for :meth:`deform`'s ``out`` (and :meth:`velocity`'s), holding a copy of
        the reference coordinates.

        Parameters
        ----------
        order : {"F", "C"}
            Memory order of each block's arrays.
        separate : bool
            Three arrays ``x, y, z`` of shape ``(ni, nj, nk)`` per block
            (as Fortran solvers keep them) instead of one ``(ni, nj, nk, 3)``.

        Returns
        -------
        Grid or list
            ``order="F"``, not separate: a Grid (its blocks are Fortran
            ``(ni, nj, nk, 3)`` arrays, which :meth:`deform` writes with no
            copy).  Otherwise a list with per block an array
            ``(ni, nj, nk, 3)`` in ``order``, or a tuple ``(x, y, z)``.
        """
        return buffers.new_buffers(self.grid, order, separate)

    def deform(self, moved, *, ids=None, displacement: bool = False, out=None, check=False,
               callback: Callable[[int, int], None] | None = None) -> Grid:
        """Deform the grid for new wall positions.

        Parameters
        ----------
        moved : ndarray, callable, Grid or mapping
            * an array ``xs`` (n, 3): the new position (``displacement``:
              the displacement) of every wall point copy, in the order of
              :meth:`surface_ids`, or with ``ids`` of the copies ``ids``;
            * a callable ``f(points (n, 3)) -> (n, 3)`` giving the new
              position of each wall point (see :meth:`wall_points`);
            * a Grid with the reference's dimensions whose wall points hold
              the new positions (other points are ignored);
            * a mapping ``PatchSpec or "B:FACE[:range]" -> array (na, nb, 3)``
              covering every wall point.
        ids : array_like of int, shape (m, 4), optional
            With an array ``xs`` (m, 3): the ``(block, i, j, k)`` (0-based)
            of the point each row moves, in any order (a solver's own wall
            list).  Every distinct wall point must be given at least once;
            a point may be listed several times (once per block that holds
            it, say): its copies must agree within ``dup_tol``
            (:class:`Deformer`) and the first is used.  Any copy of a wall
            point counts, also one :meth:`surface_ids` does not list (a
            block touching the wall at an edge only).
        displacement : bool
            With an array: its rows are displacements from the reference
            positions (:meth:`surface_points`) instead of positions.
        out : Grid or list, optional
            Buffers the step writes into instead of making a new grid (a
            coupled solver's own arrays; :meth:`new_grid` makes them): a
            Grid with the reference's dimensions, or a list with, per
            block, an array ``(ni, nj, nk, 3)`` float64 in Fortran or C
            order (any strides), or a tuple of three ``(ni, nj, nk)``
            arrays ``x, y, z`` (2-D grids: ``nk = 1``; give a
            ``(ni, nj)`` array as its view ``a[:, :, None]``).  They are
            checked (shape, dtype, writeable, not the reference) before
            anything is written; the step allocates nothing the size of
            the grid.  Fortran-ordered ``(ni, nj, nk, 3)`` arrays (a
            Grid's blocks) are written by the compiled kernels directly;
            the other layouts go, block by block, through one scratch
            array the size of the largest block that the Deformer keeps,
            and are copied from it (the kernels are compiled for Fortran
            arrays only: a specialisation per layout would add its
            compile time to every cold start, and the x, y, z triple
            cannot be one array).
        check : {False, True, "raise"}
            Check every cell of the result against the reference as each
            block is made (:func:`tfi_quat.quality.check_block`: the
            smallest corner-Jacobian ratio, negative and negative-Jacobian
            cells, their first locations): one more pass over each block
            while it is in memory, allocating nothing grid-sized; it costs
            about 0.4 of a bare step's CPU time on the 501 k-point wing
            (``timings.check``).  With two threads or more, blocks small
            enough to run on one thread are checked on a second thread while
            the next block is made (same report).  The report
            (:class:`tfi_quat.quality.CellCheck`) is the result grid's
            ``quality`` and the Deformer's :attr:`quality`.  ``"raise"``:
            a :class:`DeformationError` naming the first invalid cells when
            a cell is negative or has a corner ratio <= 0; with ``out``, the
            step then computes into a scratch grid that the Deformer keeps
            (made on the first such call: memory the size of the grid) and
            copies it into ``out`` only when the grid is valid, so that the
            buffers are left unchanged by a failed step.
        callback : callable(done, total), optional
            Called after each block kernel (progress reporting).

        Returns
        -------
        Grid or None
            Without ``out``: a new grid with the reference's
            ``source_format`` and ``connectivity`` (so ``write(path, out,
            like=reference)`` writes the reference's file variant, a CGNS
            file with its boundary conditions).  With ``out`` a Grid: that
            grid; with a list of Fortran-ordered arrays: a Grid whose
            blocks view them; with other layouts: None (the values are in
            ``out``).  The reference is not modified; every call starts
            from it, so repeated steps do not drift.  Every form and
            every ``out`` layout gives the same bits; the array form
            gives bit for bit the grid of a callable returning the same
            positions.

        Raises
        ------
        DeformationError
            Bad input, before anything is computed: wrong shapes, ids out of
            range or not on a wall (the message names the row), wall points
            not covered (it names how many and one), copies of a point that
            disagree (it names both and their distance), non-finite values.
        """
        with self._lock, use_threads(self.threads):
            t0 = time.perf_counter()
            if not (check is False or check is True or check == "raise"):
                raise DeformationError(f"check must be False, True or 'raise', got {check!r}")
            self.quality = None
            dests = None if out is None else buffers.check_out(self.grid, out)
            if isinstance(moved, np.ndarray):
                rd = self.walls.array_targets(moved, ids, bool(displacement), self._work.rd)
            else:
                if ids is not None or displacement:
                    raise DeformationError("ids= and displacement= go with an array of wall points "
                                           f"(n, 3) as the first argument, got {type(moved).__name__}")
                rd = self._other_targets(moved)
            np.copyto(self.last_targets, rd)      # in place: a step allocates nothing
            self._linear = None
            if self.two_level is not None:
                passes, ts, t1, t3 = self._two_level_fields(rd)
            else:
                passes, ts, t1, t3 = self._samareh_fields(rd)
            self._check_seconds = 0.0
            try:
                grid = self._volumes(passes, dests, out, callback, check)
            finally:
                t4 = time.perf_counter()
                tc = self._check_seconds
                self.timings = StepTimings(walls=t1 - t0, skeleton=ts, faces=t3 - t1 - ts,
                                           volumes=t4 - t3 - tc, check=tc)
            return grid

    def linearisation(self):
        """The boundary level's linearisation at :attr:`last_targets`
        (:class:`tfi_quat.deform.dskeleton.Linearisation`), built on first use after a step."""
        from .dskeleton import linearise
        with self._lock, use_threads(self.threads):
            if self._linear is None:
                self._linear = linearise(self, self.last_targets)
                self._share_passes(self._linear)
            return self._linear

    def _share_passes(self, lin):
        """Where the linearisation's pass values are those the step left in its buffers (same
        bits: linearised at the step's targets), hold the buffers instead of copies (the next
        step drops the linearisation before it writes them)."""
        w = self._work
        kept = [w.K, w.ql, w.gd, w.qg]
        values = []
        for p in lin.values:
            p = list(p)
            for i in (0, 1):
                for b in kept:
                    if (p[i] is not None and b is not None and b.shape == p[i].shape
                            and np.array_equal(b, p[i])):
                        p[i] = b
                        break
            values.append(tuple(p))
        lin.values = values

    def linear_passes(self):
        """The volume passes ``(Δ or K, Q, centre, tables)`` at the linearisation point (the
        last step's targets): always both passes for ``"two-level"`` (residual, then rigid),
        one for the others (``Q`` None for ``"tfi"``).  O(surface) arrays held by the
        linearisation (:meth:`linearisation`; where they are the step's own, its buffers):
        do not modify them; valid until the next step."""
        return self.linearisation().values

    def _samareh_fields(self, rd):
        """Samareh's update (``"samareh"``; ``"tfi"`` without Q): the hierarchy of (Δ, Q) on the
        boundary points; returns the volume pass (:meth:`_volumes`)."""
        sk = self.skeleton
        wall, rows = sk.step_walls()
        c = self.centre
        P = sk.points.P
        w = self._work
        gdelta, gq, pos = w.gd, w.qg, w.pos
        if self._use_q:
            qw = self._wall_quaternions(rd, c)[rows]
            gq[wall] = qw
            # the translation follows from the merged rotation: c + delta + rot(q, ru - c) = rd
            gdelta[wall] = rd[wall] - c - qa.rotate(qw, P[wall] - c)
        else:
            gq = None
            gdelta[wall] = rd[wall] - P[wall]
        t1 = time.perf_counter()
        stages.vertex_stage(sk, gdelta, gq)
        stages.segment_stage(sk, gdelta, gq)
        ts = time.perf_counter() - t1
        stages.patch_stage(sk, gdelta, gq)
        stages.symmetry_stage(sk, gdelta, gq, c)
        der = sk.derived
        if gq is not None:
            pos[der] = P[der]
            stages.positions_global(gdelta, gq, c, der, pos)
        else:
            pos[der] = P[der] + gdelta[der]
        # symmetry points on their plane, walls exact (fixed points are never written: they
        # keep the buffer's undeformed position)
        stages.onto_symmetry(sk, pos)
        pos[wall] = rd[wall]
        t3 = time.perf_counter()
        return [(gdelta, gq, c, None)], ts, t1, t3

    def _two_level_fields(self, rd):
        """The residual motion (:func:`twolevel.local_fields`) where the walls deform, then
        the bodies' rigid motions (:func:`twolevel.rigid_fields`) where they move; returns
        the volume passes (:meth:`_volumes`)."""
        sk = self.skeleton
        two = self.two_level
        wall = sk.step_walls()[0]
        P = sk.points.P
        w = self._work
        fits = twolevel.fit_bodies(sk, two, rd, w.y, self._gather_parts, self._y_rows)
        y = w.y
        tiny = 1e-14 * self._scale
        rigid = any(np.max(np.abs(q - _IDENT)) > 1e-15 or np.max(np.abs(t)) > tiny for q, t in fits)
        local, qwall = self._residual_quaternions(y, tiny)
        t1 = time.perf_counter()
        ts = 0.0
        pos = w.pos
        if local:
            ts += twolevel.local_fields(sk, two, y, qwall, w.K, w.ql, pos)
        else:
            pos[sk.derived] = P[sk.derived]
        if rigid:
            twolevel.rigid_fields(sk, two, fits, self.centre, w.gd, w.qg)
            stages.positions_global(w.gd, w.qg, self.centre, sk.derived, pos)
        stages.onto_symmetry(sk, pos)
        pos[wall] = rd[wall]
        t3 = time.perf_counter()
        # the residual motion about the arms' base points, or the reference copied; then the
        # rigid motion in place
        passes = [(w.K, w.ql, _ORIGIN, two.base) if local else None]
        if rigid:
            passes.append((w.gd, w.qg, self.centre, None))
        return passes, ts, t1, t3

    def _volumes(self, passes, dests, out, callback, check):
        """The block kernels of a step's ``passes`` (each ``(Δ or K, Q, centre, base tables)``
        applied to the previous one's result, the first to the reference; None: copy the
        reference), every boundary copy from the positions, into the buffers ``dests``
        (:func:`.buffers.check_out`; None: new arrays), each block checked after it is made when
        ``check``; returns the result grid."""
        sk = self.skeleton
        grid = self.grid
        pos = self._work.pos
        total = len(grid) * sum(p is not None for p in passes)
        done = 0
        arrays = []
        # check="raise" into buffers: every block into the kept scratch first, so that a
        # folded grid leaves the buffers as they were
        hold = check == "raise" and dests is not None
        # with two threads or more, a block small enough to run on one thread is checked on
        # the second while the next block is made (the same computation, the same report)
        overlap = bool(check) and threads() > 1
        reports = []
        try:
            for n, (b, blk) in enumerate(zip(self.blocks, grid)):
                dest = None if dests is None else dests[n]
                # a layout the kernels do not write: through the block scratch (reused by
                # the next block)
                via_scratch = dest is not None and not hold and not buffers.is_kernel_array(dest)
                if dest is None:
                    dst = np.empty_like(blk.xyz, order="F")
                elif hold:
                    dst = self._scratch.grid()[n]
                elif via_scratch:
                    dst = self._scratch.block(n)
                else:
                    dst = dest
                base = blk.xyz
                for p in passes:
                    if p is None:
                        np.copyto(dst, base)
                    else:
                        gd, gq, c, tables = p
                        stages.volume(sk, self._all, b, base, gd, gq, c, dst,
                                      None if tables is None else tables[b])
                        done += 1
                        if callback is not None:
                            callback(done, total)
                    base = dst
                local, gid = sk.scatter[b]
                stages.scatter_rows(pos, gid, local, dst.reshape(-1, 3, order="F"))
                if sk.ndim == 2:
                    dst[..., 2] = 0.0
                if check:
                    if overlap and not via_scratch and blk.npoints < SERIAL_BELOW:
                        reports.append(self._checker().submit(self._check_one, b, blk, dst))
                    else:
                        tc = time.perf_counter()
                        reports.append(self._check_one(b, blk, dst))
                        self._check_seconds += time.perf_counter() - tc
                if via_scratch:
                    buffers.copy_out(dst, dest)
                arrays.append(dst if dest is None else dest)
        finally:
            # every check finished (or failed) before the buffers are used or the step ends;
            # timings.check: the checks on this thread and the wait for the others
            if overlap:
                tc = time.perf_counter()
                futures.wait([r for r in reports if isinstance(r, futures.Future)])
                reports[:] = [r.result() if isinstance(r, futures.Future) else r for r in reports]
                self._check_seconds += time.perf_counter() - tc
        report = self._report(list(zip(self.blocks, reports)), check)
        self.quality = report
        if check == "raise" and not report.ok:
            raise DeformationError(f"the deformed grid has invalid cells: {report}" +
                                   ("; the out buffers are unchanged" if hold else ""))
        if hold:
            for n, dest in enumerate(dests):
                buffers.copy_out(self._scratch.grid()[n], dest)
        if isinstance(out, Grid):
            result = out
        elif not all(buffers.is_kernel_array(a) for a in arrays):
            return None
        else:
            blocks = [Block(a, blk.iblank, blk.name, allow_nonfinite=True)
                      for a, blk in zip(arrays, grid)]
            result = Grid(blocks, grid.ndim, source_format=grid.source_format,
                          connectivity=grid.connectivity)
        result.quality = report
        return result

    def _check_one(self, b, blk, dst):
        """:func:`tfi_quat.quality.check_block` of block ``b`` (its reference made once and kept)."""
        with serial_below(blk.npoints):
            if self._check_refs[b] is None:
                self._check_refs[b] = check_reference(blk.xyz, self.skeleton.ndim)
            return check_block(dst, self._check_refs[b], self.skeleton.ndim, b)

    def _checker(self):
        """The thread that checks small blocks while the next one is made (made on first use;
        idle, it waits without spinning)."""
        if self._check_thread is None:
            self._check_thread = futures.ThreadPoolExecutor(1, thread_name_prefix="tfi-quat-check")
        return self._check_thread

    #: the rigid fits' collective (:func:`twolevel.fit_bodies`' ``gather``; None: serial)
    _gather_parts = None
    #: per wall body, the points of the residual targets a step needs (None: all)
    _y_rows = None

    def _other_targets(self, moved):
        """The wall targets of the input forms other than an array (:func:`.walls.other_targets`)."""
        return other_targets(self.skeleton, self._all, moved, self._work.rd)

    def _residual_quaternions(self, y, tiny):
        """``(local, qwall)``: whether the residual targets ``y`` move a wall point by more
        than ``tiny``, and then their merged wall quaternions (else None)."""
        sk = self.skeleton
        wall = sk.points.wall
        local = bool(np.max(np.abs(y[wall] - sk.points.P[wall]), initial=0.0) > tiny)
        return local, (self._wall_quaternions(y, self.centre) if local else None)

    def _wall_quaternions(self, rd, centre):
        """The merged wall quaternions of the walls moved to ``rd`` (under MPI: each wall patch
        computed by one rank and exchanged, :mod:`.distributed`)."""
        return stages.wall_quaternions(self.skeleton, rd, centre)

    def _report(self, reports, check):
        """The check of a step from ``(block, report)`` per own block (under MPI: of all
        ranks' blocks, :mod:`.distributed`)."""
        return CellCheck.merge(r for _, r in reports) if check else None

    def velocity(self, prev, cur, dt: float, out=None):
        """Grid-point velocities of a step, ``(cur - prev) / dt``, for ALE flow solvers.

        Parameters
        ----------
        prev, cur : Grid or list
            The grid before and after the step, in any layout :meth:`deform`
            writes (``out=``): Grids, or lists with per block an array
            ``(ni, nj, nk, 3)`` or a tuple of three ``(ni, nj, nk)`` arrays
            ``x, y, z``; the two may differ in layout.  Their dimensions
            are the reference's.
        dt : float
            The time step, finite and not 0.
        out : Grid or list, optional
            Where the velocities go (as :meth:`deform`'s ``out``: the same
            layouts, checked the same way); may be ``cur`` itself.  Default:
            new arrays in the layout of ``cur`` (a Grid's blocks: a list of
            Fortran-ordered ``(ni, nj, nk, 3)`` arrays).

        Returns
        -------
        Grid or list
            ``out`` when given, else the new list.  Each value is computed as
            ``(cur - prev) / dt`` (a subtraction, then a division: the bits
            numpy gives for that expression), with no temporaries the size
            of the grid.
        """
        try:
            dt = float(dt)
        except (TypeError, ValueError):
            dt = math.nan
        if not (math.isfinite(dt) and dt != 0.0):
            raise DeformationError(f"dt must be a finite number other than 0, got {dt!r}")
        with use_threads(self.threads):
            a = buffers.layout(self.grid, prev, "prev")
            c = buffers.layout(self.grid, cur, "cur")
            if out is None:
                out = [tuple(np.empty_like(p) for p in blk) if isinstance(blk, tuple) else
                       np.empty_like(blk) for blk in c]
                o = out
            else:
                o = buffers.check_out(self.grid, out)
            for b in range(len(self.grid)):
                for x0, x1, v in zip(buffers.parts(a[b]), buffers.parts(c[b]), buffers.parts(o[b])):
                    np.subtract(x1, x0, out=v)
                    np.divide(v, dt, out=v)
            return out

    def jvp(self, dxs, ids=None, *, at=None, out=None):
        """The tangent of the deformation: how the grid moves when the wall points move by ``dxs``.

        The forward product of the Jacobian of :meth:`deform` (volume grid as a function of
        the wall points), linearised at the wall positions of the last :meth:`deform`
        (the reference before any), or at ``at``.  ``docs/derivatives.md`` has the details.

        Parameters
        ----------
        dxs : array_like, shape (n, 3)
            A tangent of the wall points: one row per wall point copy in
            :meth:`surface_ids` order, or with ``ids`` the copies ``ids`` (as in
            :meth:`deform`: every wall point at least once; the first row given
            for a point counts, the others are ignored).  2-D grids: z = 0.
        ids : array_like of int, shape (n, 4), optional
            ``(block, i, j, k)`` (0-based) of each row of ``dxs`` (and of ``at``).
        at : array_like, shape (n, 3), optional
            Wall point positions (the array form of :meth:`deform`, rows as
            ``dxs``) to linearise at instead; they stay the linearisation point
            until the next :meth:`deform` or ``at``.
        out : Grid or list, optional
            Buffers for the result, in any layout :meth:`deform` writes.

        Returns
        -------
        list of ndarray, or ``out``
            Per block the tangent of its coordinates, Fortran ``(ni, nj, nk, 3)``
            (a slave point of an interface: its master's, as every boundary copy).

        Raises
        ------
        DeformationError
            Bad input (shapes, ids, non-finite values, as :meth:`deform`), or blocks
            where the forward map takes its rotation-vector fallback (blended
            rotations near 180 degrees apart), which the derivatives do not cover.
        """
        from . import dvolume
        from .dskeleton import fields_jvp
        with self._lock, use_threads(self.threads):
            if at is not None:
                self._linearise_at(at, ids)
            drd = dvolume.tangent_targets(self, dxs, ids)
            passes = self.linear_passes()
            tangents, dpos = fields_jvp(self, drd)
            res = dvolume.volume_jvp(self, passes, tangents, dpos, out)
            return res if out is None else out

    def vjp(self, dxv, *, at=None, ids=None) -> np.ndarray:
        """The adjoint of :meth:`jvp`: the gradient with respect to the wall points of
        ``<dxv, grid>``, for a bar ``dxv`` of the grid's coordinates.

        Parameters
        ----------
        dxv : Grid or list
            Per block an array ``(ni, nj, nk, 3)`` (or a tuple ``x, y, z``), in
            any layout :meth:`deform` writes.
        at, ids : optional
            As for :meth:`jvp` (``ids``: of the rows of ``at`` only).

        Returns
        -------
        ndarray, shape (n, 3)
            Rows in :meth:`surface_ids` order: ``<vjp(v), u> = <v, jvp(u)>``.  The
            first copy of a wall point gets its whole gradient, its other copies 0
            (:meth:`deform` uses the first copy).
        """
        from . import dvolume
        from .dskeleton import fields_vjp
        with self._lock, use_threads(self.threads):
            if at is not None:
                self._linearise_at(at, ids)
            passes = self.linear_passes()
            pass_bars, pos_bar = dvolume.volume_vjp(self, passes, dxv)
            rd_bar = fields_vjp(self, pass_bars, pos_bar)
            return dvolume.surface_bar(self, rd_bar)

    def _linearise_at(self, at, ids) -> None:
        rd = self.walls.array_targets(at, ids, False, self.skeleton.points.P.copy())
        self.last_targets = rd
        self._linear = None

    def summary(self) -> str:
        """A few lines describing the skeleton (for the CLI and logs)."""
        sk = self.skeleton
        k = sk.points.kind
        if self.method == "tfi":
            head = f"method tfi (plain TFI), {self.blending} blending"
        elif self.two_level is not None:
            nb = len(self.two_level.bodies)
            head = (f"method two-level (quaternion TFI), rotation length "
                    f"{self.rotation_length:.6g}, {nb} wall bod{'y' if nb == 1 else 'ies'}")
        else:
            head = f"method samareh (quaternion TFI, the memo's update), {self.blending} blending"
        lines = [
            head + f", centre ({', '.join(f'{v:.6g}' for v in self.centre)})",
            f"{self.n_global} boundary points: {int((k == WALL).sum())} wall, "
            f"{int((k == FIXED).sum())} fixed, {int((sk.points.sym_of >= 0).sum())} symmetry",
            f"{len(sk.vertices.corners)} vertices ({len(sk.vertices.free)} free), "
            f"{0 if sk.segments is None else len(sk.segments.left)} derived segments, "
            f"{len(sk.patches.items)} derived patches, {len(sk.blocks)} blocks",
        ]
        return "\n".join(lines)

    def write_surface(self, path, modes=None, names=None, *, overwrite: bool = False) -> None:
        """Write the wall as a surface file (``MODES.h5``), with or without mode shapes.

        The file holds :meth:`surface_ids`, :meth:`surface_points` and the
        mode shapes (layout: :mod:`tfi_quat.io.surface`); written without
        modes, it is the template a user fills from a structural model and
        gives to :meth:`modal` or ``tfi-quat deform --modes``.

        Parameters
        ----------
        path : str or path-like
            Target, written atomically.
        modes : array_like, float, shape (n_modes, n, 3), optional
            Mode shapes (displacement per unit amplitude) in
            :meth:`surface_ids` order; None: none (``modes`` of shape ``(0, n, 3)``).
        names : sequence of str, optional
            One name per mode.
        overwrite : bool
            Allow replacing the grid's own file (``grid.source_path``).
        """
        from ..io.surface import write_surface
        ids = self.walls.surface()[0]
        write_surface(path, ids, self.surface_points(), modes, names, ndim=self.ndim,
                      source="" if self.grid.source_path is None else str(self.grid.source_path),
                      overwrite=overwrite, protect=[self.grid.source_path])

    def modal(self, modes):
        """A modal wall motion: a callable ``amplitudes -> deformed Grid``.

        Parameters
        ----------
        modes : array_like (n_modes, n, 3), str / path-like, or SurfaceFile
            Mode shapes (displacement per unit amplitude) in
            :meth:`surface_ids` order, or a surface file (``MODES.h5``,
            :meth:`write_surface`; its rows in any order, matched by their ids),
            or such a file already read (:func:`tfi_quat.io.surface.read_surface`).

        Returns
        -------
        tfi_quat.deform.modal.ModalMotion
            ``motion(amplitudes, **kw)`` deforms the grid for the wall points
            moved by ``Σ a_m φ_m`` (``kw`` as :meth:`deform`'s).

        Raises
        ------
        GridFormatError
            A surface file that cannot be read (named, with the dataset).
        DeformationError
            Ids that are not this Deformer's wall point copies (each exactly
            once), points that are not this grid's, non-finite shapes, copies
            of one point whose shapes differ by more than ``dup_tol``, no modes.
        """
        from .modal import ModalMotion, surface_modes
        ids, gid = self.walls.surface()
        shapes, names, where = surface_modes(modes, ids, self.surface_points(), self._all)
        wall_pos = np.full(self.n_global, -1, dtype=np.int64)
        wall = self.skeleton.points.wall
        wall_pos[wall] = np.arange(wall.size)
        return ModalMotion(self, shapes, names, wall_pos[gid], source=where)


def _check_block_sizes(grid: Grid) -> None:
    if grid.ndim == 3:
        for b, blk in enumerate(grid):
            if min(blk.dims) < 2:
                raise CaseError(f"block {b + 1}: a 3-D volume block needs at least 2 points in "
                                f"each direction, got {blk.dims}")
    else:
        for b, blk in enumerate(grid):
            if min(blk.dims[:2]) < 2:
                raise CaseError(f"block {b + 1}: a 2-D block needs at least 2 points in i and j, "
                                f"got {blk.dims[:2]}")


def _check_threads(threads) -> int | None:
    if threads is None:
        return None
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise CaseError(f"threads must be a whole number >= 1 or None (all), got {threads!r}")
    return int(threads)


def _centre(pts, centre) -> np.ndarray:
    if centre is None:
        return pts.P[pts.kind == WALL].mean(axis=0)
    c = np.asarray(centre, dtype=np.float64).reshape(-1)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise CaseError(f"centre must be 3 finite numbers, got {centre!r}")
    return c


def deformer_from_case(case, grid: Grid | None = None, **kw) -> Deformer:
    """Build a :class:`Deformer` from a :class:`tfi_quat.case.Case` (walls, symmetry, fixed; a case
    for a CGNS grid may give none and take the file's)."""
    from .. import io
    if grid is None:
        grid = io.read(case.grid)
    return Deformer(grid, walls=case.walls, symmetry=case.symmetry, fixed=case.fixed, **kw)
