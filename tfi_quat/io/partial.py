"""Partial reads: some blocks of a grid file, or the faces of all of them.

A process that owns a few blocks of a large grid (one rank of an MPI job)
reads only those blocks' coordinates (``tfi_quat.read(path, blocks=[...])``)
plus the boundary faces of every block (:func:`tfi_quat.io.read_faces`),
which is all the O(surface) skeleton of a deformation needs.  This module
holds what the format readers share for that: the check of the requested
block numbers and :class:`GridFaces`, the faces of every block of a file.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import GridValueError
from ..grid import face_axis, face_index, face_shape, faces_of

__all__ = ["block_numbers", "GridFaces", "empty_faces", "fill_faces"]


def block_numbers(path, blocks, nblocks: int) -> list[int]:
    """Check the 0-based global block numbers ``blocks`` of a file of ``nblocks`` blocks.

    Parameters
    ----------
    path : str or path-like
        The file (named in the errors).
    blocks : iterable of int
        0-based block numbers, in the order wanted; no repeats.
    nblocks : int
        Number of blocks the file holds.

    Returns
    -------
    list of int

    Raises
    ------
    GridValueError
        ``blocks`` empty, not integers, negative, beyond the file's blocks or
        repeated, naming the file and the block.
    """
    if isinstance(blocks, (int, np.integer, str, bytes)):
        raise GridValueError(f"{path}: blocks= must be a list of 0-based block numbers, got {blocks!r}")
    try:
        items = list(blocks)
    except TypeError:
        raise GridValueError(f"{path}: blocks= must be a list of 0-based block numbers, "
                             f"got {type(blocks).__name__}") from None
    if not items:
        raise GridValueError(f"{path}: blocks= is empty: give at least one 0-based block number")
    out: list[int] = []
    for b in items:
        if isinstance(b, (bool, np.bool_)) or not isinstance(b, (int, np.integer)):
            raise GridValueError(f"{path}: block {b!r} in blocks= is not an integer block number (0-based)")
        n = int(b)
        if not 0 <= n < nblocks:
            raise GridValueError(f"{path}: block {n} out of range: the file holds {nblocks} block(s) "
                                 f"(0-based 0..{nblocks - 1})")
        if n in out:
            raise GridValueError(f"{path}: block {n} is given twice in blocks=")
        out.append(n)
    return out


def empty_faces(dims, ndim: int) -> list[np.ndarray]:
    """The face arrays of a block of ``dims``: float64 ``(na, nb, 3)`` Fortran order, z = 0 in 2-D."""
    out = []
    for f in faces_of(ndim):
        arr = np.empty(face_shape(dims, f) + (3,), dtype=np.float64, order="F")
        if ndim == 2:
            arr[..., 2] = 0.0
        out.append(arr)
    return out


def fill_faces(faces, c: int, coord: np.ndarray, ndim: int) -> None:
    """Set component ``c`` of every face array of a block from ``coord``, its ``(ni, nj, nk)`` values.

    ``coord`` is typically a view of a memory-mapped file in the file's own
    dtype and byte order: only the pages holding face values are touched,
    and each value is converted to float64 exactly (as a full read does).
    """
    for f, arr in zip(faces_of(ndim), faces):
        d, side = face_axis(f)
        idx = [slice(None)] * 3
        idx[d] = coord.shape[d] - 1 if side else 0
        arr[..., c] = coord[tuple(idx)]


@dataclass
class GridFaces:
    """The boundary faces of every block of a grid file, without the volume.

    What :func:`tfi_quat.io.read_faces` returns: enough to build the
    boundary skeleton of a deformation (walls, vertices, segments, patches)
    and a partition of the blocks, in memory proportional to the surface.

    Attributes
    ----------
    ndim : int
        2 or 3.
    dims : list of (ni, nj, nk)
        Every block's point dimensions, in file order.
    faces : list of tuple of ndarray (or None)
        ``faces[b][f]``: face ``f`` (numbered as :data:`tfi_quat.grid.FACES`;
        six in 3-D, the four imin..jmax in 2-D) of block ``b``, float64
        ``(na, nb, 3)``, bit-identical to ``Block.face(f)`` of a full read;
        None for a block not read (``read_faces(path, blocks=...)``).
    names : list of str or None
        The blocks' names, as a full read names them.
    source_path : str
    source_format : object
        The file variant (as ``Grid.source_format`` of a full read).
    connectivity : tfi_quat.topology.Connectivity or None
        What the file records (CGNS), as a full read gives it, except that
        the points of its interfaces are not checked to coincide (that needs
        the volume read); None for formats that record none.
    block_ids : tuple of int or None
        The blocks whose faces were read (``blocks=``), None for all.
    """

    ndim: int
    dims: list
    faces: list
    names: list
    source_path: str
    source_format: object = None
    connectivity: object = field(default=None, repr=False)
    block_ids: tuple | None = None

    @property
    def nblocks(self) -> int:
        """Number of blocks of the file."""
        return len(self.dims)

    @property
    def npoints(self) -> int:
        """Points of the whole grid (from the dims; the volume is not read)."""
        return sum(int(np.prod(d)) for d in self.dims)

    def face(self, b: int, face) -> np.ndarray:
        """Face ``face`` (name or number) of block ``b`` (0-based), ``(na, nb, 3)``."""
        f = face_index(face)
        if f >= len(faces_of(self.ndim)):
            raise GridValueError(f"{self.source_path}: a {self.ndim}-D grid has no face {face!r}")
        if not 0 <= int(b) < self.nblocks:
            raise GridValueError(f"{self.source_path}: block {b} out of range: the file holds "
                                 f"{self.nblocks} block(s) (0-based 0..{self.nblocks - 1})")
        faces = self.faces[int(b)]
        if faces is None:
            raise GridValueError(f"{self.source_path}: the faces of block {b} were not read "
                                 f"(read_faces with blocks={list(self.block_ids)})")
        return faces[f]
