"""The wall in the solver's terms, and a step's wall targets from any input form.

:class:`WallInput` lists every copy of every wall point as ``(block, i, j, k)``
(the coupling interface's ``surface_ids``), maps ids given in a solver's own
order onto the Deformer's distinct boundary points, and checks what a step
is given: coverage of every wall point, copies that must agree within
``dup_tol``, finite values.  :func:`other_targets` takes the older forms (a
motion callable, a moved Grid, per-patch arrays).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ..errors import DeformationError
from ..grid import Grid, face_ijk
from ..spec import PatchSpec, parse_patch_spec
from .skeleton import WALL

__all__ = ["WallInput", "motion_targets", "other_targets", "point_keys"]


def point_keys(grid: Grid, ids: np.ndarray) -> np.ndarray:
    """Flat keys (block offset + Fortran index: the numbering of
    :class:`~tfi_quat.deform.skeleton.BoundaryPoints`) of the points ``ids`` (m, 4) int64,
    ``(block, i, j, k)`` 0-based and inside ``grid``."""
    dims = np.array(grid.dims, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(np.prod(dims, axis=1))[:-1]])
    b = ids[:, 0]
    d = dims[b]
    return offsets[b] + ids[:, 1] + d[:, 0] * (ids[:, 2] + d[:, 1] * ids[:, 3])


class WallInput:
    """The wall copies of one Deformer's grid (made on first use, then kept) and the checks
    of the array form of a step.

    ``grid``: the reference grid; ``skeleton``: its frozen skeleton; ``dup_tol``: the largest
    distance allowed between copies of one wall point.
    """

    def __init__(self, grid: Grid, skeleton, dup_tol: float):
        self.grid = grid
        self.skeleton = skeleton
        self.dup_tol = dup_tol
        self.ndim = grid.ndim
        self._surface_cache = None
        self._wall_keys = None

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """``(ids (n, 4), gid (n,))``: every wall point copy as ``(block, i, j, k)`` (wall
        patches in order, each in Fortran order) and its global point id;
        made on first use, then kept."""
        got = self._surface_cache
        if got is None:
            ids, gids = [], []
            pts = self.skeleton.points
            for wp in self.skeleton.walls.patches:
                spec = wp.spec
                ijk = face_ijk(self.grid[spec.block].dims, spec.face, spec.range)
                ijk = ijk.reshape(-1, 3, order="F")
                ids.append(np.column_stack([np.full(ijk.shape[0], spec.block, np.int64), ijk]))
                gids.append(pts.rect_gid(spec).reshape(-1, order="F").astype(np.int64))
            got = (np.concatenate(ids) if ids else np.empty((0, 4), np.int64),
                   np.concatenate(gids) if gids else np.empty(0, np.int64))
            for a in got:
                a.flags.writeable = False
            self._surface_cache = got
        return got

    def _wall_lookup(self) -> tuple[np.ndarray, np.ndarray]:
        """``(keys, gid)``: the flat keys (block offset + Fortran index) of every copy of every
        wall point, ascending, and its global id; made on first use, then kept."""
        got = self._wall_keys
        if got is None:
            pts = self.skeleton.points
            on_wall = pts.kind[pts.copies_gid] == WALL
            got = (pts.copies_key[on_wall], pts.copies_gid[on_wall])
            self._wall_keys = got
        return got

    def _copy_name(self, b: int, i: int, j: int, k: int) -> str:
        name = self.grid[b].name
        return f"(block, i, j, k) = ({b}, {i}, {j}, {k})" + (f" [{name}]" if name else "")

    def array_targets(self, xs, ids, displacement: bool, rd: np.ndarray) -> np.ndarray:
        """The array form of :meth:`Deformer.deform`: wall targets from rows of ``xs`` at the copies
        ``ids`` (None: :meth:`surface` order), checked, into the wall rows of ``rd``."""
        pts = self.skeleton.points
        xs = np.asarray(xs)
        if xs.ndim != 2 or xs.shape[1] != 3:
            raise DeformationError(f"xs must have shape (n, 3), got {xs.shape}")
        if not (np.issubdtype(xs.dtype, np.floating) or np.issubdtype(xs.dtype, np.integer)):
            raise DeformationError(f"xs must hold real numbers, got dtype {xs.dtype}")
        xs = np.asarray(xs, dtype=np.float64)
        m = xs.shape[0]
        copy_of, gid = self.rows(ids, m, "xs")
        bad = ~np.isfinite(xs)
        if bad.any():
            r = int(np.flatnonzero(bad.any(axis=1))[0])
            raise DeformationError(f"xs row {r} ({self._copy_name(*copy_of[r])}, 0-based) is not "
                                   f"finite ({int(bad.any(axis=1).sum())} such row(s))")
        # one row per distinct point, the first copy given; the others must agree with it
        order, start, first = _first_rows(gid)
        # the repeated copies (rows of xs) and the first copy of their point
        rep = np.flatnonzero(~start)
        lead = order[np.maximum.accumulate(np.where(start, np.arange(m), 0))[rep]]
        rep = order[rep]
        dist = np.sqrt(np.sum((xs[rep] - xs[lead]) ** 2, axis=1))
        over = dist > self.dup_tol
        if over.any():
            r = int(np.argmax(np.where(over, dist, -1.0)))
            a, c = int(lead[r]), int(rep[r])
            raise DeformationError(
                f"rows {a} and {c} of xs are copies of one wall point, {self._copy_name(*copy_of[a])} "
                f"and {self._copy_name(*copy_of[c])} (0-based), and differ by {dist[r]:.6g} > "
                f"dup_tol = {self.dup_tol:g} ({int(over.sum())} copy(ies) disagree with their "
                f"first; Deformer(dup_tol=...) sets the tolerance)")
        g_first = gid[first]
        self.check_covered(g_first, "xs")
        rd[g_first] = xs[first]
        if displacement:
            rd[g_first] += pts.P[g_first]
        if self.ndim == 2 and np.any(rd[pts.wall, 2] != 0.0):
            what = "displacements" if displacement else "wall points"
            raise DeformationError(f"the {what} of a 2-D grid must have z = 0")
        return rd

    def rows(self, ids, m: int, what: str) -> tuple[np.ndarray, np.ndarray]:
        """``(copy_of (m, 4), gid (m,))``: the wall point copy each of the ``m`` rows of an
        array input ``what`` stands for (``ids``; None: :meth:`surface` order) and its global
        id, checked (DeformationError naming the row)."""
        if ids is None:
            sid, gid = self.surface()
            if m != sid.shape[0]:
                raise DeformationError(
                    f"{what} has {m} rows; without ids it must have one row per wall point copy "
                    f"of surface_ids(), {sid.shape[0]} (or give ids)")
            return sid, gid
        copy_of = self._check_ids(ids, m, what)
        keys, kgid = self._wall_lookup()
        flat = point_keys(self.grid, copy_of)
        at = np.minimum(np.searchsorted(keys, flat), keys.size - 1)
        hit = keys[at] == flat
        if not hit.all():
            r = int(np.flatnonzero(~hit)[0])
            raise DeformationError(f"ids row {r}: {self._copy_name(*copy_of[r])} (0-based) is "
                                   f"not a wall point ({int((~hit).sum())} such row(s))")
        return copy_of, kgid[at]

    def first_rows(self, gid: np.ndarray) -> np.ndarray:
        """The rows that count of rows naming the global points ``gid``: the first row of each
        distinct point (the others are copies)."""
        return _first_rows(gid)[2]

    def check_covered(self, g_first: np.ndarray, what: str) -> None:
        """A DeformationError unless the global ids ``g_first`` cover every wall point."""
        pts = self.skeleton.points
        seen = np.zeros(pts.n_global, dtype=bool)
        seen[g_first] = True
        missing = pts.wall[~seen[pts.wall]]
        if missing.size:
            b, flat = self._key_to_copy(int(pts.rep_key[missing[0]]))
            raise DeformationError(f"{missing.size} wall point(s) have no row in {what}, e.g. "
                                   f"{self._copy_name(b, *flat)} (0-based)")

    def _check_ids(self, ids, m: int, what: str = "xs") -> np.ndarray:
        """``ids`` as an (m, 4) int64 array of existing points, else a DeformationError naming
        the row."""
        a = np.asarray(ids)
        if a.ndim != 2 or a.shape[1] != 4:
            raise DeformationError(f"ids must have shape (m, 4) (block, i, j, k, 0-based), got "
                                   f"{a.shape}")
        if a.shape[0] != m:
            raise DeformationError(f"ids has {a.shape[0]} rows, {what} {m}: one id per row of {what}")
        if not np.issubdtype(a.dtype, np.integer):
            raise DeformationError(f"ids must be integers, got dtype {a.dtype}")
        a = a.astype(np.int64, copy=False)
        nb = len(self.grid)
        bad = (a[:, 0] < 0) | (a[:, 0] >= nb)
        if bad.any():
            r = int(np.flatnonzero(bad)[0])
            raise DeformationError(f"ids row {r}: block {a[r, 0]} out of range 0..{nb - 1} "
                                   f"(0-based)")
        dims = np.array(self.grid.dims, dtype=np.int64)[a[:, 0]]
        bad = ((a[:, 1:] < 0) | (a[:, 1:] >= dims)).any(axis=1)
        if bad.any():
            r = int(np.flatnonzero(bad)[0])
            raise DeformationError(f"ids row {r}: {self._copy_name(*a[r])} (0-based) is outside "
                                   f"the block's {tuple(int(v) for v in dims[r])} points")
        return a

    def _key_to_copy(self, key: int) -> tuple[int, tuple[int, int, int]]:
        off = self.skeleton.points.offsets
        b = int(np.searchsorted(off, key, side="right") - 1)
        ni, nj, _ = self.grid[b].dims
        r = key - int(off[b])
        return b, (r % ni, (r // ni) % nj, r // (ni * nj))


def _first_rows(gid: np.ndarray) -> tuple:
    """``(order, start, first)``: a stable sort of the rows by ``gid``, where each point's run
    starts in it, and the first row of each distinct point."""
    order = np.argsort(gid, kind="stable")
    g_sorted = gid[order]
    start = np.ones(gid.shape[0], dtype=bool)
    start[1:] = g_sorted[1:] != g_sorted[:-1]
    return order, start, order[start]


def _check_targets(sk, X: np.ndarray) -> None:
    """The wall targets ``X`` (n_wall, 3): finite, and z = 0 on a 2-D grid."""
    bad = ~np.isfinite(X)
    if bad.any():
        raise DeformationError(f"{int(bad.any(axis=1).sum())} moved wall point(s) are not finite")
    if sk.ndim == 2 and np.any(X[:, 2] != 0.0):
        raise DeformationError("moved wall points of a 2-D grid must have z = 0")


def motion_targets(sk, moved, ref: np.ndarray | None = None) -> np.ndarray:
    """The callable form of :meth:`Deformer.deform`: ``moved`` called on (a copy of) the wall
    points (n_wall, 3) of the skeleton ``sk`` (``ref``: those points, kept contiguous by the
    caller), its result checked (shape, finite, z = 0 in 2-D) and returned C-contiguous."""
    wall = sk.points.wall
    src = sk.points.P[wall] if ref is None else ref.copy()
    new = np.ascontiguousarray(moved(src), dtype=np.float64)
    if new.shape != (wall.size, 3):
        raise DeformationError(f"the motion callable returned shape {new.shape}, expected "
                               f"({wall.size}, 3) for the {wall.size} wall points")
    _check_targets(sk, new)
    return new


def other_targets(sk, ref: Grid, moved, rd: np.ndarray) -> np.ndarray:
    """The other forms of :meth:`Deformer.deform` (a callable, a moved Grid, a mapping patch ->
    array): deformed positions of every global point, in ``rd`` (only wall rows are written)."""
    pts = sk.points
    wall = pts.wall
    if callable(moved):
        rd[wall] = motion_targets(sk, moved)
        return rd
    if isinstance(moved, Grid):
        if moved.dims != ref.dims:
            raise DeformationError(f"moved grid dimensions {moved.dims} differ from the "
                                   f"reference {ref.dims}")
        key = pts.rep_key[wall]
        blk_of = np.searchsorted(pts.offsets, key, side="right") - 1
        for b, blk in enumerate(moved):
            sel = blk_of == b
            rd[wall[sel]] = blk.xyz.reshape(-1, 3, order="F")[key[sel] - pts.offsets[b]]
    elif isinstance(moved, Mapping):
        seen = np.zeros(pts.n_global, dtype=bool)
        for k, arr in moved.items():
            spec = k if isinstance(k, PatchSpec) else parse_patch_spec(str(k))
            spec = spec.resolve(ref)
            gid = pts.rect_gid(spec)
            a = np.asarray(arr, dtype=np.float64)
            if a.shape[:-1] != gid.shape and a.shape[:-1] != (gid.size,):
                raise DeformationError(f"moved patch {spec}: array shape {a.shape}, expected "
                                       f"{gid.shape + (3,)}")
            rd[gid.ravel()] = a.reshape(-1, 3)
            seen[gid.ravel()] = True
        missing = wall[~seen[wall]]
        if missing.size:
            raise DeformationError(f"{missing.size} wall point(s) have no new position in the "
                                   f"mapping, e.g. at {tuple(np.round(pts.P[missing[0]], 6))}")
    else:
        raise DeformationError("moved must be a callable, a Grid, or a mapping patch -> array")
    _check_targets(sk, rd[wall])
    return rd
