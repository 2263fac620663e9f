"""The caller's coordinate buffers: ``out=`` of :meth:`Deformer.deform` and
:meth:`Deformer.velocity`.

A block's buffer is a float64 ``(ni, nj, nk, 3)`` array in any memory order, or a
tuple of three ``(ni, nj, nk)`` arrays ``x, y, z``.  The volume kernels write
Fortran-ordered ``(ni, nj, nk, 3)`` arrays straight (:func:`is_kernel_array`); other
layouts receive a copy of a block made in one kept scratch (:class:`Scratch`), so
that a step allocates nothing the size of the grid in any layout.
"""

from __future__ import annotations

import numpy as np

from ..errors import CaseError, DeformationError
from ..grid import Grid

__all__ = ["Scratch", "check_out", "layout", "is_kernel_array", "parts", "copy_out", "new_buffers"]


class Scratch:
    """Fortran ``(ni, nj, nk, 3)`` arrays for the blocks of the reference grid ``ref``, made on
    first use and kept."""

    def __init__(self, ref: Grid):
        self.ref = ref
        self._flat = None
        self._grid = None

    def grid(self) -> list:
        """One Fortran (ni, nj, nk, 3) array per block (``check="raise"`` into buffers), made
        on first use and kept."""
        if self._grid is None:
            self._grid = [np.empty_like(blk.xyz, order="F") for blk in self.ref]
        return self._grid

    def block(self, b: int) -> np.ndarray:
        """A Fortran (ni, nj, nk, 3) array for block ``b``: a view of one buffer the size of
        the largest block, made on first use and kept (the next block's scratch reuses it)."""
        if self._grid is not None:
            return self._grid[b]
        dims = self.ref[b].dims
        n = 3 * self.ref[b].npoints
        flat = self._flat
        if flat is None:
            flat = self._flat = np.empty(3 * max(blk.npoints for blk in self.ref))
        return flat[:n].reshape(dims + (3,), order="F")


def check_out(grid: Grid, out, what: str = "out", writeable: bool = True) -> list:
    """The buffers of ``out`` per block of ``grid`` (the reference): a (ni, nj, nk, 3) float64 array or a tuple of three
    (ni, nj, nk) ones, checked (shape, dtype; with ``writeable``: writeable and not the
    reference's memory).  ``what``: the argument's name in messages."""
    nb = len(grid)
    if isinstance(out, Grid):
        if out is grid and writeable:
            raise DeformationError(f"{what} is the reference grid: give a buffer of its own "
                                   "(Deformer.new_grid())")
        if len(out) != nb:
            raise DeformationError(f"{what} has {len(out)} blocks, the grid {nb}")
        items = [blk.xyz for blk in out]
    elif isinstance(out, (list, tuple)):
        if len(out) != nb:
            raise DeformationError(f"{what} has {len(out)} entries, the grid {nb} blocks: "
                                   "one per block")
        items = list(out)
    else:
        raise DeformationError(f"{what} must be a Grid or a list with one entry per block, "
                               f"got {type(out).__name__}")
    dests = []
    for b, (item, blk) in enumerate(zip(items, grid)):
        dims = blk.dims
        if isinstance(item, np.ndarray):
            parts, want, name = [item], dims + (3,), f"{what}[{b}]"
        elif isinstance(item, (tuple, list)) and len(item) == 3:
            parts, want, name = list(item), dims, f"{what}[{b}] (x, y, z)"
        else:
            raise DeformationError(f"{what}[{b}]: expected an array (ni, nj, nk, 3) or a tuple of "
                                   f"three (ni, nj, nk) arrays x, y, z, got "
                                   f"{type(item).__name__}")
        for part in parts:
            if not isinstance(part, np.ndarray):
                raise DeformationError(f"{name}: expected numpy arrays, got "
                                       f"{type(part).__name__}")
            if part.shape != want:
                raise DeformationError(f"{name}: shape {part.shape}, expected {want} for "
                                       f"block {b} (0-based)")
            if part.dtype != np.float64:
                raise DeformationError(f"{name}: dtype {part.dtype}, expected float64")
            if writeable and not part.flags.writeable:
                raise DeformationError(f"{name}: the array is read-only")
            if writeable and np.may_share_memory(part, blk.xyz):
                raise DeformationError(f"{name}: shares memory with the reference grid")
        dests.append(item if isinstance(item, np.ndarray) else tuple(item))
    return dests


def layout(grid: Grid, coords, what: str) -> list:
    """``coords`` (a Grid or a list) as per-block arrays or (x, y, z) tuples, checked."""
    if isinstance(coords, Grid):
        if len(coords) != len(grid) or coords.dims != grid.dims:
            raise DeformationError(f"{what}: a grid of dimensions {coords.dims}, the "
                                   f"reference has {grid.dims}")
        return [blk.xyz for blk in coords]
    return check_out(grid, coords, what=what, writeable=False)


def is_kernel_array(a) -> bool:
    """Whether the volume kernels write ``a`` straight: a Fortran-ordered (ni, nj, nk, 3) array."""
    return isinstance(a, np.ndarray) and a.ndim == 4 and a.flags.f_contiguous


def parts(blk) -> tuple:
    """A block's coordinate arrays: ``(xyz,)`` or its ``(x, y, z)``, as arrays of one shape
    (a (ni, nj, nk, 3) array against x, y, z: the three component views)."""
    if isinstance(blk, tuple):
        return blk
    return tuple(blk[..., c] for c in range(3))


def copy_out(src: np.ndarray, dest) -> None:
    """A block's result (Fortran (ni, nj, nk, 3)) into the caller's layout ``dest``."""
    if isinstance(dest, np.ndarray):
        np.copyto(dest, src)
    else:
        for c in range(3):
            np.copyto(dest[c], src[..., c])


def new_buffers(ref: Grid, order: str = "F", separate: bool = False):
    """Buffers holding a copy of ``ref``'s coordinates (:meth:`Deformer.new_grid`): a Grid
    for ``order="F"`` not separate, else a list with per block an ``(ni, nj, nk, 3)`` array
    in ``order`` or a tuple ``(x, y, z)``."""
    if order not in ("F", "C"):
        raise CaseError(f"order must be 'F' or 'C', got {order!r}")
    if order == "F" and not separate:
        return ref.copy()
    out = []
    for blk in ref:
        if separate:
            out.append(tuple(np.array(blk.xyz[..., c], order=order) for c in range(3)))
        else:
            out.append(np.array(blk.xyz, order=order))
    return out
