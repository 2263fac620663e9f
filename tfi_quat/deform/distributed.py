"""Distributed deformation under MPI: each rank deforms its own blocks, bit for bit as a serial run.

``Deformer(source, ..., comm=comm, blocks=None)`` makes a
:class:`DistributedDeformer` (``docs/mpi.md``):

Partition
    ``blocks``: the global 0-based block numbers this rank owns (the flow
    solver's partition), or None on every rank for
    :func:`tfi_quat.grid.partition` of the dims (the same on every rank).
    ``source``: a grid file (rank 0 reads the header and the faces of block
    0 for every block's dims, each rank then reads only its blocks,
    :func:`tfi_quat.io.read` with ``blocks=``) or a Grid of the rank's own
    blocks (``blocks`` default: its ``block_ids``, else the blocks in rank
    order).
Set-up
    Every rank sends the boundary shell of its blocks (faces, the layer next
    to each face, bounding box: :func:`.shell.shell_of`) to every rank (one
    ``allgather``) and builds the whole skeleton from the shells as the serial
    set-up builds it from the grid: same values, same operations, so every
    rank holds bit-identical skeleton values.  Only the blending parameters of
    a block need its volume: its owner computes them, and every rank receives
    their face values (a second ``allgather``), which the two-level set-up
    reads.  Nothing the size of another rank's blocks is held.
Step
    :meth:`DistributedDeformer.deform` takes every input form of the serial
    one (global block numbers in ``ids``); the wall input must be given on
    **every** rank, the same: each rank reduces it to the wall targets and
    the ranks compare a fingerprint of them (:func:`fingerprint`; one
    ``allgather`` of 16 bytes and any error).  The rigid fits: each rank sums
    the parts of the fits' partition in its wall patches, and two
    ``allgather`` calls (centroids, then covariances) give every rank all the
    parts, added in the fixed part order as a serial run adds them.  The wall
    quaternions: each rank computes those of its wall patches, one
    ``allgather``, and each rank merges them at the wall points it reads.
    Each rank then computes the free vertices, the rest of the boundary
    fields and the wall rows only where its blocks' faces read them
    (:func:`split_skeleton`), and its own blocks, and returns them (a Grid in
    the order of :attr:`blocks`).  ``check``
    reports are gathered and merged over all blocks in global order, so
    ``quality`` is the serial run's on every rank and ``check="raise"``
    raises on every rank.
Errors
    Every collective carries the ranks' errors: an error on any rank (bad
    input, a folded grid with ``check="raise"``, a file that cannot be read)
    is raised on every rank, the lowest failing rank's, and no rank waits.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from .._jit import jit
from ..errors import GridFormatError, GridValueError, ParallelError
from ..grid import Grid, partition
from ..io.mpi import agree, check_comm, from_root, portable, raise_first
from ..io.partial import block_numbers
from ..quality import CellCheck
from . import stages
from .deformer import Deformer
from .shell import ShellGrid, shell_of
from .walls import motion_targets

__all__ = ["DistributedDeformer", "fingerprint", "open_shell", "split_skeleton"]

#: collectives of one step: the wall targets, the wall quaternions, the cell checks (and, in
#: two-level steps, the rigid fits' two passes)
_STAGES = 3
_STAGES_TWO_LEVEL = 5


@jit
def fingerprint(bits, rows, out):
    """Two 64-bit lanes of a multiply-xorshift hash of the rows ``rows`` of ``bits`` (n, 3)
    uint64 (the bits of float64 points), in order: the ranks' wall targets compared (a
    check of the user's input, several times faster than a cryptographic digest)."""
    h1 = np.uint64(0x9E3779B97F4A7C15)
    h2 = np.uint64(0xC2B2AE3D27D4EB4F)
    m1 = np.uint64(0xFF51AFD7ED558CCD)
    m2 = np.uint64(0xC4CEB9FE1A85EC53)
    s = np.uint64(33)
    for n in range(rows.shape[0]):
        for c in range(3):
            x = bits[rows[n], c]
            h1 = (h1 ^ x) * m1
            h1 ^= h1 >> s
            h2 = (h2 + x) * m2
            h2 ^= h2 >> s
    out[0] = h1
    out[1] = h2


def _numbers(blocks, where: str) -> list[int]:
    """The 0-based block numbers of a rank's Grid (a file's: :func:`tfi_quat.io.partial.block_numbers`)."""
    if isinstance(blocks, (int, np.integer, str, bytes)):
        raise GridValueError(f"{where}: blocks= must be a list of 0-based block numbers, got {blocks!r}")
    out = []
    for b in blocks:
        if isinstance(b, (bool, np.bool_)) or not isinstance(b, (int, np.integer)) or b < 0:
            raise GridValueError(f"{where}: block {b!r} in blocks= is not a 0-based block number")
        if int(b) in out:
            raise GridValueError(f"{where}: block {int(b)} is given twice in blocks=")
        out.append(int(b))
    return out


def _check_cover(where: str, owned: list, nblocks: int) -> None:
    """Every block 0 .. nblocks-1 owned by exactly one rank (``owned``: each rank's list)."""
    owner = {}
    for rank, nums in enumerate(owned):
        for b in nums:
            if b in owner:
                raise GridValueError(f"{where}: block {b} (0-based) is owned by rank {owner[b]} and "
                                     f"rank {rank}")
            owner[b] = rank
    missing = [b for b in range(nblocks) if b not in owner]
    if missing or len(owner) != nblocks:
        first = missing[0] if missing else max(owner)
        raise GridValueError(f"{where}: the ranks' blocks= must cover blocks 0..{nblocks - 1} once "
                             f"each; block {first} (0-based) is owned by no rank")


def _local_from_path(path, comm, blocks):
    """``(local Grid, own, nblocks, connectivity)`` of a file: rank 0 reads the dims, each rank
    its blocks.  Collective; errors agreed."""
    from .. import io
    exc = info = None
    if comm.rank == 0:
        try:
            faces = io.read_faces(path, blocks=[0])
            info = (faces.dims, faces.connectivity)
        except Exception as e:      # noqa: BLE001  (raised on every rank)
            exc = e
    dims, conn = from_root(comm, exc, info)
    exc = own = None
    try:
        if blocks is None:
            own = partition(dims, comm.size)[comm.rank]
        else:
            own = block_numbers(path, blocks, len(dims))
    except Exception as e:          # noqa: BLE001
        exc = e
    gathered = comm.allgather((portable(exc), own))
    raise_first(comm, [e for e, _ in gathered], exc)
    _check_cover(str(path), [o for _, o in gathered], len(dims))
    exc = local = None
    try:
        local = io.read(path, blocks=own)
    except Exception as e:          # noqa: BLE001
        exc = e
    agree(comm, exc)
    return local, own, len(dims), conn


def _local_from_grid(grid, comm, blocks):
    """``(grid, own, nblocks, None)`` for a Grid of the rank's own blocks.  Collective."""
    exc = own = None
    try:
        if not isinstance(grid, Grid):
            raise GridValueError(f"the source must be a grid file or a Grid of this rank's blocks, "
                                 f"got {type(grid).__name__}")
        if blocks is None:
            blocks = getattr(grid, "block_ids", None)
        own = None if blocks is None else _numbers(blocks, f"rank {comm.rank}")
        if own is not None and len(own) != len(grid):
            raise GridValueError(f"rank {comm.rank}: blocks= lists {len(own)} block number(s) for "
                                 f"a grid of {len(grid)} block(s)")
    except Exception as e:          # noqa: BLE001
        exc = e
    gathered = comm.allgather((portable(exc), own, None if exc else len(grid)))
    raise_first(comm, [g[0] for g in gathered], exc)
    given = [g[1] is not None for g in gathered]
    if any(given) and not all(given):
        raise GridValueError("blocks= given on some ranks but not on others; give it on every "
                             "rank or on none")
    if not all(given):              # rank order: rank 0's blocks first
        starts = np.cumsum([0] + [g[2] for g in gathered])
        own = list(range(int(starts[comm.rank]), int(starts[comm.rank + 1])))
        owned = [list(range(int(starts[r]), int(starts[r + 1]))) for r in range(comm.size)]
    else:
        owned = [g[1] for g in gathered]
    nblocks = sum(g[2] for g in gathered)
    _check_cover("distributed Deformer", owned, nblocks)
    return grid, own, nblocks, None


def open_shell(source, comm, blocks=None) -> ShellGrid:
    """The :class:`~.shell.ShellGrid` of this rank: its own blocks (read from ``source``, a path,
    or ``source`` itself, a Grid of them) and every other block's shell.  Collective."""
    if isinstance(source, (str, os.PathLike)):
        local, own, nblocks, conn = _local_from_path(source, comm, blocks)
    else:
        local, own, nblocks, conn = _local_from_grid(source, comm, blocks)
    ndim = local.ndim
    exc = mine = None
    try:
        mine = [(b, shell_of(blk, ndim)) for b, blk in zip(own, local)]
    except Exception as e:          # noqa: BLE001
        exc = e
    gathered = comm.allgather((portable(exc), ndim, mine))
    raise_first(comm, [g[0] for g in gathered], exc)
    ndims = {g[1] for g in gathered}
    if len(ndims) > 1:
        raise ParallelError(f"the ranks' grids disagree on ndim ({sorted(ndims)})")
    every = [None] * nblocks
    for _, _, part in gathered:
        for b, sh in part:
            every[b] = sh
    for b, blk in zip(own, local):
        every[b] = blk
    shell = ShellGrid(every, ndim, local, own, connectivity=conn,
                      source_format=local.source_format, source_path=local.source_path)
    shell.exchange_plans = _plan_exchange(comm, shell)
    return shell


def _plan_exchange(comm, shell):
    """The collective giving every rank the face parameters of every block (the set-up's
    :func:`tfi_quat.deform.skeleton.build_skeleton` calls it with its plans and error)."""
    nf = 2 * shell.ndim

    def exchange(plans, error):
        mine = None if error is not None else [(b, plans[b].face_s[:nf]) for b in shell.own]
        gathered = comm.allgather((portable(error), mine))
        raise_first(comm, [e for e, _ in gathered], error)
        plans = list(plans)
        for _, part in gathered:
            for b, face_s in part:
                if plans[b].face_s is None:
                    plans[b] = dataclasses.replace(plans[b], face_s=tuple(face_s))
        return plans

    return exchange


def split_skeleton(sk, two, own):
    """The skeleton (and two-level parts) restricted to what the blocks ``own`` read: the
    derived patches writing a point of their faces, the segments' gaps those patches or faces
    need (their ends in turn), the symmetry and derived points among them.

    A step on it computes every point of the own blocks' faces with the same operations, item
    by item, as on the whole skeleton (so with the same bits), and skips the rest: the
    replicated O(surface) work of a step shrinks to the rank's share of the boundary.  The
    free vertices kept are those the kept items read (each row of their blend is computed
    alone, :func:`.stages.idw_rows`); the wall rows a step fills are set by the
    :class:`DistributedDeformer` (``wall_rows``).
    """
    from .skeleton import Patches, Segments, Symmetry, Vertices
    from .stages import level_pack
    need = np.zeros(sk.n_global, dtype=bool)
    for b in own:
        for g in sk.blocks[b].face_gid:
            need[g.ravel()] = True
    # the patches are one level (each reads its sides only): keep those writing a needed point
    kept = [p for p in sk.patches.items if need[p.gid[p.write]].any()]
    for p in kept:
        need[p.gid.ravel()] = True
    patches = Patches(tuple(kept), level_pack([(p.gid, p.s, p.lead, p.write) for p in kept]),
                      int(sum(p.gid.size for p in kept)))
    segments = sk.segments
    if segments is not None:
        # a gap reads its ends, which an earlier gap may fill: walk them backwards
        left, right, ptr, pts, s = segments.arrays()
        keep = np.zeros(left.size, dtype=bool)
        for g in range(left.size - 1, -1, -1):
            if need[pts[ptr[g]:ptr[g + 1]]].any():
                keep[g] = True
                need[left[g]] = need[right[g]] = True
        sizes = np.diff(ptr)[keep]
        rows = np.repeat(keep, np.diff(ptr))
        segments = Segments(left[keep], right[keep],
                            np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
                            np.ascontiguousarray(pts[rows]), np.ascontiguousarray(s[rows]))
    # the free vertices those read (each row of the inverse-distance blend is computed alone,
    # stages.idw_rows: the same bits for any subset of rows)
    vertices = sk.vertices
    if vertices.idw is not None:
        keep = need[vertices.free]
        src, w, decay, ref = vertices.idw
        vertices = Vertices(vertices.corners, vertices.free[keep],
                            (src, np.ascontiguousarray(w[keep]), decay[keep], ref[keep])
                            if keep.any() else None)
    sym = sk.symmetry
    on = need[sym.gids]
    symmetry = Symmetry(sym.gids[on], sym.point[on], sym.normal[on])
    der = need[sk.derived]
    sk = dataclasses.replace(sk, patches=patches, segments=segments, symmetry=symmetry,
                             vertices=vertices, derived=sk.derived[der])
    if two is not None:
        two = dataclasses.replace(two, phi=np.ascontiguousarray(two.phi[der]))
    return sk, two


class DistributedDeformer(Deformer):
    """A :class:`~tfi_quat.deform.Deformer` over the ranks of ``comm``: set up from the rank's own
    blocks and every block's boundary, it deforms the rank's blocks (see the module docstring).

    Made by ``Deformer(source, ..., comm=comm, blocks=...)``; the options are the
    Deformer's (``threads`` default 1: one thread per rank).  :attr:`grid` holds the rank's
    reference blocks, :attr:`blocks` their global numbers; :meth:`write` writes a step's
    result collectively.
    """

    def __init__(self, source, walls=(), symmetry=(), fixed=(), connectivity=None, *,
                 comm=None, blocks=None, threads: int | None = None, **kw):
        check_comm(comm)
        #: the communicator
        self.comm = comm
        self._stage = self._stages = _STAGES
        shell = open_shell(source, comm, blocks)
        exc = None
        try:
            super().__init__(shell, walls=walls, symmetry=symmetry, fixed=fixed,
                             connectivity=connectivity, threads=1 if threads is None else threads,
                             **kw)
        except Exception as e:      # noqa: BLE001  (every rank raises the first rank's)
            exc = e
        agree(comm, exc)
        shell.drop_layers()
        self._own_set = frozenset(self.blocks)
        self._print = self._wall_ref = None
        #: the whole skeleton (every rank's copy is the same); :attr:`skeleton` is this rank's part
        self.full_skeleton = self.skeleton
        self.skeleton, self.two_level = split_skeleton(self.skeleton, self.two_level, self.blocks)
        self._plan_walls()

    def _plan_walls(self) -> None:
        """The wall work of this rank: its wall patches (those on its blocks), the parts of the
        rigid fits' partition in them, the wall points whose merged quaternions it reads and
        the points of the residual targets it needs (its part of the skeleton reads them, or
        its wall patches' halos)."""
        sk, two = self.skeleton, self.two_level
        own = self._own_set
        self._my_patches = [m for m, w in enumerate(sk.walls.patches) if w.spec.block in own]
        need = np.zeros(sk.n_global, dtype=bool)
        for b in self.blocks:
            for g in sk.blocks[b].face_gid:
                need[g.ravel()] = True
        for p in sk.patches.items:
            need[p.gid.ravel()] = True
        if sk.segments is not None:
            left, right, _, pts, _ = sk.segments.arrays()
            need[left] = need[right] = need[pts] = True
        if sk.vertices.idw is not None:
            need[sk.vertices.idw[0]] = True
        need[sk.symmetry.gids] = True
        wall = sk.points.wall
        rows = np.flatnonzero(need[wall])
        self.skeleton = sk = dataclasses.replace(sk, wall_rows=rows)
        self._merge = stages.merge_plan(sk, rows)
        self._merge_acc = np.zeros((wall.size, 4))      # rows it does not read: 1
        self._merge_acc[:, 0] = 1.0
        self._merge_count = np.zeros(wall.size, dtype=np.int64)
        self._wall_order = np.arange(wall.size)
        for m in self._my_patches:
            h = sk.walls.patches[m].halo.ravel()
            need[h[h >= 0]] = True
        if two is not None:
            self._plan_fits(need)
        # the wall targets it reads (a callable's are written there only)
        rows = np.flatnonzero(need[wall])
        self._target_rows = (wall[rows], rows)

    def _plan_fits(self, need) -> None:
        """The rigid fits' parts in this rank's wall patches and the points of the residual
        targets it needs (marked in ``need``)."""
        two = self.two_level
        self._stages = _STAGES_TWO_LEVEL
        self._my_parts = np.flatnonzero(np.isin(two.part_patch, self._my_patches))
        ptr, gids = two.part_ptr, two.part_gids
        self._part_rows = (np.concatenate([gids[ptr[m]:ptr[m + 1]] for m in self._my_parts])
                           if self._my_parts.size else np.zeros(0, dtype=np.int64))
        need[self._part_rows] = True
        self._y_rows = [body.gids[need[body.gids]] for body in two.bodies]

    @property
    def dims(self) -> list:
        """Every block's dims, in global order (:attr:`grid` holds this rank's blocks only)."""
        return [tuple(d) for d in self._all.dims]

    def summary(self) -> str:
        """:meth:`Deformer.summary` of the whole skeleton, and this rank's part of it."""
        part = self.skeleton
        self.skeleton = self.full_skeleton
        try:
            text = super().summary()
        finally:
            self.skeleton = part
        nseg = 0 if part.segments is None else len(part.segments.left)
        return (text + f"\nrank {self.comm.rank} of {self.comm.size}: blocks "
                f"{', '.join(str(b + 1) for b in self.blocks)}; its part: {nseg} segments, "
                f"{len(part.patches.items)} patches, {part.derived.size} derived points")

    # ------------------------------------------------------------ the step's collectives
    def _sync(self, exc, payload) -> list:
        """One collective of a step: every rank's payload, or the first rank's error raised."""
        self._stage += 1
        gathered = self.comm.allgather((portable(exc), payload))
        raise_first(self.comm, [e for e, _ in gathered], exc)
        return [p for _, p in gathered]

    def deform(self, moved, **kw):
        """:meth:`Deformer.deform` on the rank's blocks: a Grid of them (in :attr:`blocks` order),
        or what ``out`` gives.  Collective: call it on every rank with the same wall input
        (``out`` and ``callback`` are the rank's own)."""
        self._stage = 0
        try:
            return super().deform(moved, **kw)
        except Exception as exc:
            agreed = exc
            while self._stage < self._stages:    # the collectives the other ranks are in
                try:
                    self._sync(exc, None)
                except Exception as e:  # noqa: BLE001
                    agreed = e
            if agreed is exc:
                raise
            raise agreed from None

    def _other_targets(self, moved):
        """A callable's targets: its result fingerprinted as it comes (the ranks compare it)
        and written at the wall points this rank reads only; other forms as serially."""
        self._print = None
        if not callable(moved):
            return super()._other_targets(moved)
        if self._wall_ref is None:                  # the wall points, contiguous, once
            self._wall_ref = self.skeleton.points.P[self.skeleton.points.wall]
        new = motion_targets(self.skeleton, moved, self._wall_ref)
        self._print = np.zeros(2, dtype=np.uint64)
        fingerprint(new.view(np.uint64), self._wall_order, self._print)
        gids, rows = self._target_rows
        rd = self._work.rd
        rd[gids] = new[rows]
        return rd

    def _agree_targets(self, rd) -> None:
        digest = self._print
        if digest is None:      # the same value as a callable's: the wall rows in order
            digest = np.zeros(2, dtype=np.uint64)
            fingerprint(rd.view(np.uint64), self.skeleton.points.wall, digest)
        self._print = None
        digests = self._sync(None, digest.tobytes())
        differ = [r for r, d in enumerate(digests) if d != digests[0]]
        if differ:
            raise ParallelError(f"the wall motion given to deform() differs between rank 0 and "
                                f"rank {differ[0]}: give the same wall input on every rank")

    def _samareh_fields(self, rd):
        self._agree_targets(rd)
        return self._with_wall_stage(super()._samareh_fields, rd)

    def _two_level_fields(self, rd):
        self._agree_targets(rd)
        return self._with_wall_stage(super()._two_level_fields, rd)

    def _with_wall_stage(self, fields, rd):
        """``fields(rd)``, and the wall quaternions' collective when it did not need them (a
        rigid two-level step, plain TFI): every rank passes the same stages."""
        before = self._stage
        out = fields(rd)
        if self._stage == before:
            self._sync(None, None)
        return out

    def _gather_parts(self, fn, nparts: int) -> np.ndarray:
        """One pass of the rigid fits (:func:`.twolevel.fit_bodies`): each rank computes the
        parts in its wall patches, one ``allgather`` gives every rank all of them in order."""
        exc = mine = None
        try:
            mine = fn(self._my_parts)
        except Exception as e:      # noqa: BLE001  (every rank raises the first rank's)
            exc = e
        parts = self._sync(exc, None if mine is None else (self._my_parts, mine))
        out = np.empty((nparts, mine.shape[1]))
        for which, vals in parts:
            out[which] = vals
        return out

    def _residual_quaternions(self, y, tiny):
        """The serial method's ``(local, qwall)`` with one collective: the ranks' largest
        residual on their parts of the walls travel with the wall patches' quaternions."""
        sk = self.skeleton
        rows = self._part_rows
        big = float(np.max(np.abs(y[rows] - sk.points.P[rows]), initial=0.0))
        qwall, bigs = self._exchange_quaternions(y, self.centre, big)
        local = max(bigs) > tiny
        return local, (qwall if local else None)

    def _wall_quaternions(self, rd, centre):
        return self._exchange_quaternions(rd, centre, None)[0]

    def _exchange_quaternions(self, rd, centre, extra):
        """Each rank computes the quaternions of the wall patches on its blocks; all are
        exchanged (with every rank's ``extra``) and merged in the global patch order (the
        serial merge: the same bits) at the wall points this rank reads.  Returns the merged
        quaternions and the ranks' ``extra``."""
        sk = self.skeleton
        mine = self._my_patches
        exc = qs = None
        try:
            qs = stages.patch_quaternions(sk, rd, centre, mine)
        except Exception as e:      # noqa: BLE001  (every rank raises the first rank's)
            exc = e
        parts = self._sync(exc, None if qs is None else (list(zip(mine, qs)), extra))
        every = [None] * len(sk.walls.patches)
        for part, _ in parts:
            for m, q in part:
                every[m] = q
        qwall = stages.merge_wall_rows(self._merge, every, self._merge_acc, self._merge_count)
        return qwall, [e for _, e in parts]

    def _report(self, reports, check):
        parts = self._sync(None, reports if check else None)
        if not check:
            return None
        every = sorted((item for part in parts for item in part), key=lambda item: item[0])
        return CellCheck.merge(r for _, r in every)

    def jvp(self, *args, **kw):
        """Not available over MPI yet (docs/derivatives.md): raises :class:`ParallelError`."""
        raise ParallelError("Deformer.jvp is not available on a distributed Deformer (comm=) yet: "
                            "run the derivatives on a serial Deformer of the whole grid")

    def vjp(self, *args, **kw):
        """Not available over MPI yet (docs/derivatives.md): raises :class:`ParallelError`."""
        raise ParallelError("Deformer.vjp is not available on a distributed Deformer (comm=) yet: "
                            "run the derivatives on a serial Deformer of the whole grid")

    def write(self, path, grid, **kw) -> None:
        """Write a step's result (this rank's blocks) collectively: :func:`tfi_quat.io.write` with
        ``comm`` and ``blocks`` (``like`` default: the reference's file variant when ``path``
        names the reference's format)."""
        from .. import io
        if "like" not in kw and "format" not in kw:
            try:
                same = io.format_for(path).name == io.format_for(like=self.grid).name
            except GridFormatError:
                same = False
            if same:
                kw["like"] = self.grid
        io.write(path, grid, comm=self.comm, blocks=list(self.blocks), **kw)
