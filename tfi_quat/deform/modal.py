"""Modal wall motion: the wall displaced by a sum of mode shapes, ``Σ a_m φ_m``.

Aeroelastic codes describe the structure by a few mode shapes ``φ_m`` on the
wall (displacement per unit amplitude) and integrate their amplitudes
``a_m(t)``.  :meth:`tfi_quat.Deformer.modal` turns the shapes (an array in
:meth:`~tfi_quat.Deformer.surface_ids` order, or a surface file written by
:meth:`~tfi_quat.Deformer.write_surface`, :mod:`tfi_quat.io.surface`) into a
:class:`ModalMotion`: a callable ``amplitudes -> deformed Grid``.

The wall displacement is linear in the amplitudes; the volume grid is not
(the Deformer's rotations).  The shapes are checked once, when the
:class:`ModalMotion` is made: their ids against the Deformer's wall (any row
order; each wall point copy exactly once), their points against the grid's,
every value finite, and the copies of one point (a wall edge, an interface
crossing the wall) agreeing within the Deformer's ``dup_tol``.  A step then
costs one small matrix product before the Deformer's own step.
"""

from __future__ import annotations

import numpy as np

from ..errors import DeformationError
from ..grid import Grid
from ..io.surface import SurfaceFile, check_names, read_surface
from .walls import point_keys

__all__ = ["ModalMotion", "surface_modes", "POINT_TOL"]

#: largest distance, relative to the grid's size, between a surface file's point and the
#: grid's (the file must describe this grid's wall)
POINT_TOL = 1e-6


def _row_name(ids: np.ndarray, r: int) -> str:
    return f"row {r} (block, i, j, k) = {tuple(int(v) for v in ids[r])}"


def _check_in_grid(ids: np.ndarray, grid: Grid, where: str) -> None:
    """A DeformationError naming the first row of ``ids`` whose block or point is not in ``grid``."""
    dims = np.array(grid.dims, dtype=np.int64)
    b = ids[:, 0]
    bad = (b < 0) | (b >= len(grid))
    if bad.any():
        r = int(np.flatnonzero(bad)[0])
        raise DeformationError(f"{where}: ids {_row_name(ids, r)} (0-based): block out of range "
                               f"(the grid has {len(grid)} blocks)")
    d = dims[b]
    bad = np.any((ids[:, 1:] < 0) | (ids[:, 1:] >= d), axis=1)
    if bad.any():
        r = int(np.flatnonzero(bad)[0])
        raise DeformationError(f"{where}: ids {_row_name(ids, r)} (0-based) lies outside block "
                               f"{int(b[r])}'s dims {tuple(int(v) for v in d[r])}")


def _permutation(ids: np.ndarray, surface: np.ndarray, grid: Grid, where: str) -> np.ndarray:
    """``perm`` with ``ids[perm] == surface``: the file's rows in surface order.

    Raises a DeformationError naming the first duplicate row, the first row that is not a
    wall point copy and the first copy missing."""
    if ids.shape != surface.shape:
        raise DeformationError(f"{where}: {ids.shape[0]} ids, expected {surface.shape[0]} (one per "
                               "wall point copy of surface_ids())")
    _check_in_grid(ids, grid, where)
    fk = point_keys(grid, ids)
    sk = point_keys(grid, surface)
    order = np.argsort(fk, kind="stable")
    fs = fk[order]
    dup = np.flatnonzero(fs[1:] == fs[:-1])
    if dup.size:
        a, c = sorted((int(order[dup[0]]), int(order[dup[0] + 1])))
        raise DeformationError(f"{where}: ids rows {a} and {c} both list (block, i, j, k) = "
                               f"{tuple(int(v) for v in ids[a])} (0-based); each wall point copy "
                               "must be listed once")
    at = np.minimum(np.searchsorted(fs, sk), fs.size - 1)
    found = fs[at] == sk
    if not found.all():
        r = int(np.flatnonzero(~found)[0])
        extra = np.setdiff1d(fk, sk)
        e = int(np.flatnonzero(fk == extra[0])[0]) if extra.size else None
        more = (f"; the file's ids {_row_name(ids, e)} is not a wall point copy"
                if e is not None else "")
        raise DeformationError(f"{where}: ids do not match the grid's wall: {int((~found).sum())} "
                               f"wall point copies are missing, e.g. (block, i, j, k) = "
                               f"{tuple(int(v) for v in surface[r])} (0-based){more}")
    return order[at]


def surface_modes(modes, surface_ids: np.ndarray, surface_points: np.ndarray, grid: Grid):
    """Mode shapes in ``surface_ids`` order from an array or a surface file, checked.

    Parameters
    ----------
    modes : array_like (n_modes, n, 3), str / path-like, or SurfaceFile
        Shapes in ``surface_ids`` order, or a surface file, or one already read
        (:func:`tfi_quat.io.surface.read_surface`), with its rows in any order.
    surface_ids : ndarray, int64, shape (n, 4)
    surface_points : ndarray, float64, shape (n, 3)
    grid : Grid
        The reference grid (dims for the ids, size for the point tolerance).

    Returns
    -------
    shapes : ndarray, float64, shape (n_modes, n, 3)
    names : tuple of str
    where : str
        The file (or ``"modes"``), for messages.
    """
    n = surface_ids.shape[0]
    if isinstance(modes, (str, bytes, SurfaceFile)) or hasattr(modes, "__fspath__"):
        f = modes if isinstance(modes, SurfaceFile) else read_surface(modes, n_points=n)
        where = f.path
        if f.ndim != grid.ndim:
            raise DeformationError(f"{where}: written for a {f.ndim}-D grid, this grid is "
                                   f"{grid.ndim}-D")
        perm = _permutation(f.ids, surface_ids, grid, where)
        pts = f.points[perm]
        lo, hi = grid.bbox()
        tol = POINT_TOL * (float(np.linalg.norm(hi - lo)) or 1.0)
        dist = np.sqrt(np.sum((pts - surface_points) ** 2, axis=1))
        if np.max(dist, initial=0.0) > tol:
            r = int(np.argmax(dist))
            raise DeformationError(
                f"{where}: dataset /points: row {int(perm[r])} (block, i, j, k) = "
                f"{tuple(int(v) for v in surface_ids[r])} (0-based) lies {dist[r]:.3g} from the "
                f"grid's point (more than {tol:.3g}): the file describes another grid")
        shapes = np.ascontiguousarray(f.modes[:, perm])
        names = f.names
    else:
        where = "modes"
        shapes = np.asarray(modes)
        if not (np.issubdtype(shapes.dtype, np.floating) or np.issubdtype(shapes.dtype, np.integer)):
            raise DeformationError(f"modes must hold real numbers, got dtype {shapes.dtype}")
        if shapes.ndim == 2:
            shapes = shapes[None]
        if shapes.ndim != 3 or shapes.shape[1:] != (n, 3):
            raise DeformationError(f"modes must have shape (n_modes, {n}, 3) in surface_ids() "
                                   f"order, got {shapes.shape}")
        shapes = np.array(shapes, dtype=np.float64)
        bad = ~np.isfinite(shapes)
        if bad.any():
            m, r, c = (int(v) for v in np.argwhere(bad)[0])
            raise DeformationError(f"modes: {int(bad.sum())} non-finite value(s); first in mode "
                                   f"{m + 1} at {_row_name(surface_ids, r)} (0-based), "
                                   f"component {'xyz'[c]}")
        names = check_names(None, shapes.shape[0])
    if shapes.shape[0] == 0:
        raise DeformationError(f"{where}: no mode shapes (n_modes = 0): fill in the modes first "
                               "(docs/coupling.md)")
    if grid.ndim == 2 and np.any(shapes[..., 2] != 0.0):
        raise DeformationError(f"{where}: the mode shapes of a 2-D grid must have z = 0")
    return shapes, names, where


class ModalMotion:
    """Wall motion as a sum of mode shapes: ``motion(amplitudes) -> Grid``.

    Made by :meth:`tfi_quat.Deformer.modal`; every call deforms that
    Deformer's grid for the wall displaced by ``Σ a_m φ_m``.

    Attributes
    ----------
    deformer : Deformer
    shapes : ndarray, float64, shape (n_modes, n, 3)
        The mode shapes in :meth:`~tfi_quat.Deformer.surface_ids` order (read-only).
    names : tuple of str
        One name per mode.
    source : str
        The surface file the shapes came from, or ``"modes"`` for an array.
    """

    def __init__(self, deformer, shapes: np.ndarray, names, wall_of_copy: np.ndarray,
                 source: str = "modes"):
        self.deformer = deformer
        self.source = source
        self.names = tuple(names)
        ids = deformer.surface_ids()
        n_wall = int(wall_of_copy.max(initial=-1)) + 1
        uniq, first = np.unique(wall_of_copy, return_index=True)
        if uniq.size != n_wall:
            raise DeformationError(f"{source}: the surface leaves wall points out")  # internal
        # the copies of one point must move together
        diff = shapes - shapes[:, first[wall_of_copy]]
        dist = np.sqrt(np.max(np.sum(diff * diff, axis=2), axis=0))
        tol = deformer.dup_tol
        over = dist > tol
        if over.any():
            r = int(np.argmax(dist))
            a = int(first[wall_of_copy[r]])
            raise DeformationError(
                f"{source}: {_row_name(ids, a)} and {_row_name(ids, r)} (0-based, surface_ids() "
                f"order) are copies of one wall point, and their mode shapes differ by "
                f"{dist[r]:.6g} > dup_tol = {tol:g} ({int(over.sum())} copy(ies) disagree; "
                "Deformer(dup_tol=...) sets the tolerance)")
        self.shapes = shapes
        self.shapes.flags.writeable = False
        #: the shapes on the distinct wall points, in Deformer.wall_points() order
        self._wall_shapes = np.ascontiguousarray(shapes[:, first])
        self._wall_of_copy = wall_of_copy

    @property
    def n_modes(self) -> int:
        """The number of mode shapes."""
        return int(self.shapes.shape[0])

    def _amplitudes(self, amplitudes) -> np.ndarray:
        a = np.asarray(amplitudes)
        if a.ndim == 0:
            a = a.reshape(1)
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise DeformationError(f"{self.source}: amplitudes must be real numbers, got dtype {a.dtype}")
        if a.shape != (self.n_modes,):
            raise DeformationError(f"{self.source}: {self.n_modes} amplitude(s) expected, one per mode "
                                   f"({', '.join(self.names)}), got shape {a.shape}")
        a = a.astype(np.float64)
        if not np.all(np.isfinite(a)):
            raise DeformationError(f"{self.source}: amplitudes must be finite, got {a.tolist()}")
        return a

    def wall_displacements(self, amplitudes) -> np.ndarray:
        """``Σ a_m φ_m`` on the distinct wall points, ``(n_wall, 3)`` in
        :meth:`~tfi_quat.Deformer.wall_points` order."""
        a = self._amplitudes(amplitudes)
        return np.tensordot(a, self._wall_shapes, axes=1)

    def displacements(self, amplitudes) -> np.ndarray:
        """``Σ a_m φ_m`` on every wall point copy, ``(n, 3)`` in
        :meth:`~tfi_quat.Deformer.surface_ids` order (the copies of a point equal)."""
        return self.wall_displacements(amplitudes)[self._wall_of_copy]

    def __call__(self, amplitudes, **kw) -> Grid:
        """The grid deformed for the wall displaced by ``Σ a_m φ_m``.

        Parameters
        ----------
        amplitudes : array_like, shape (n_modes,)
            One finite amplitude per mode.
        **kw
            Passed to :meth:`tfi_quat.Deformer.deform` (``out=``, ``check=``,
            ``callback=``).  The grid is bit for bit the one of the callable
            form ``deform(lambda p: p + motion.wall_displacements(a))``.

        Returns
        -------
        Grid
            What :meth:`~tfi_quat.Deformer.deform` returns.
        """
        # the array form of deform, in surface_ids() order: the copies of a point are equal
        return self.deformer.deform(self.displacements(amplitudes), displacement=True, **kw)
