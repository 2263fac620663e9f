"""Multiblock structured grid model.

A :class:`Block` holds its coordinates as one float64 array ``xyz`` of shape
``(ni, nj, nk, 3)`` in **Fortran order**: all x with i fastest, then all y, then
all z.  That is byte for byte the Plot3D whole-block layout, so binary readers
and writers move bytes without a transpose.  A 2-D block has ``nk == 1`` and
z = 0.  An optional ``iblank`` int32 array ``(ni, nj, nk)`` (Fortran order) is
carried through untouched.

A :class:`Grid` is an ordered list of blocks with a dimension ``ndim`` (2 or 3)
and, when it was read from a file, the detected file variant
(``source_format``) and path (``source_path``), so it can be written back in
the same variant and an input is never overwritten by accident.  A grid read
from a format that records its boundary conditions and block interfaces
(CGNS) also carries them as a :class:`tfi_quat.topology.Connectivity`
(``connectivity``).
"""

from __future__ import annotations

import os
from typing import Iterable, Iterator, Sequence

import numpy as np

from .errors import GridValueError

__all__ = ["Block", "Grid", "FACES", "faces_of", "face_index", "face_axis", "face_axes", "face_shape",
           "face_layer", "face_ijk", "face_cells", "partition"]

#: face names in the order used everywhere (imin=0 ... kmax=5)
FACES = ("imin", "imax", "jmin", "jmax", "kmin", "kmax")


def face_index(face: str | int) -> int:
    """Return the face number 0..5 of a face name (``"imin"`` ... ``"kmax"``) or number.

    Raises
    ------
    GridValueError
        An unknown name or a number outside 0..5.
    """
    if isinstance(face, (int, np.integer)) and not isinstance(face, bool):
        if 0 <= int(face) < 6:
            return int(face)
        raise GridValueError(f"face number {face} is out of range 0..5")
    try:
        return FACES.index(str(face).strip().lower())
    except ValueError:
        raise GridValueError(f"unknown face {face!r}: expected one of {', '.join(FACES)}") from None


# ---------------------------------------------------------------- face geometry
# Every function below takes a face as a name or a number (:func:`face_index`)
# and block dimensions ``dims = (ni, nj, nk)``.  A face's two *running*
# indices ``(a, b)`` are the block's other two indices in order:
# imin/imax -> (j, k), jmin/jmax -> (i, k), kmin/kmax -> (i, j).  Ranges are
# 0-based and inclusive: ``((a0, a1), (b0, b1))``.

def faces_of(ndim: int) -> tuple[str, ...]:
    """The boundary faces of a block of a ``ndim``-D grid: all six in 3-D, imin..jmax in 2-D."""
    return FACES if ndim == 3 else FACES[:4]


def face_axis(face: str | int) -> tuple[int, int]:
    """``(axis, side)`` of a face: the block axis normal to it (0 = i, 1 = j, 2 = k)
    and its side (0 = min, 1 = max).

    >>> face_axis("jmax")
    (1, 1)
    """
    return divmod(face_index(face), 2)


def face_axes(face: str | int) -> tuple[int, int, int]:
    """``(normal, a, b)``: the block axis normal to a face and the axes of its running indices.

    >>> face_axes("jmin")
    (1, 0, 2)
    """
    d = face_index(face) // 2
    a, b = [m for m in range(3) if m != d]
    return d, a, b


def face_shape(dims, face: str | int) -> tuple[int, int]:
    """``(na, nb)``: the number of points along a face's running indices.

    >>> face_shape((5, 4, 3), "kmax")
    (5, 4)
    """
    _, a, b = face_axes(face)
    return int(dims[a]), int(dims[b])


def face_layer(dims, face: str | int, depth: int = 0) -> int:
    """Index along the face's normal axis of the layer ``depth`` steps in from the face.

    ``depth = 0`` is the face itself (0 on a min face, ``n - 1`` on a max
    face, ``n = dims[normal]``); ``depth = 1`` the next layer inside, and so
    on.  Given the per-cell shape instead of the point dimensions it numbers
    the cell layers.

    >>> face_layer((5, 4, 3), "imax"), face_layer((5, 4, 3), "imax", 1), face_layer((5, 4, 3), "imin", 1)
    (4, 3, 1)
    """
    d, side = face_axis(face)
    return int(dims[d]) - 1 - depth if side else depth


def _check_range(dims, face, rng) -> tuple[tuple[int, int], tuple[int, int]]:
    na, nb = face_shape(dims, face)
    if rng is None:
        return (0, na - 1), (0, nb - 1)
    try:
        (a0, a1), (b0, b1) = ((int(u), int(v)) for u, v in rng)
    except (TypeError, ValueError):
        raise GridValueError(f"face {FACES[face_index(face)]}: a range is ((a0, a1), (b0, b1)), "
                             f"got {rng!r}") from None
    if not (0 <= a0 <= a1 < na and 0 <= b0 <= b1 < nb):
        raise GridValueError(f"face {FACES[face_index(face)]}: range {rng!r} is not an increasing "
                             f"range inside the face's {na} x {nb} points (0-based, inclusive)")
    return (a0, a1), (b0, b1)


def face_ijk(dims, face: str | int, rng=None) -> np.ndarray:
    """Block indices of the points of a face, or of a range of it.

    Parameters
    ----------
    dims : (ni, nj, nk)
    face : str or int
    rng : ((a0, a1), (b0, b1)), optional
        0-based inclusive range of the running indices; default the whole face.

    Returns
    -------
    ndarray, int64, shape (a1 - a0 + 1, b1 - b0 + 1, 3)
        ``out[p, q]`` is the ``(i, j, k)`` of running indices
        ``(a0 + p, b0 + q)``, so ``xyz[out[..., 0], out[..., 1], out[..., 2]]``
        is the range's part of :meth:`Block.face`.

    Raises
    ------
    GridValueError
        An unknown face, or a range that is not inside the face.
    """
    (a0, a1), (b0, b1) = _check_range(dims, face, rng)
    d, a, b = face_axes(face)
    out = np.empty((a1 - a0 + 1, b1 - b0 + 1, 3), dtype=np.int64)
    out[..., d] = face_layer(dims, face)
    out[..., a] = np.arange(a0, a1 + 1)[:, None]
    out[..., b] = np.arange(b0, b1 + 1)[None, :]
    return out


def face_cells(dims, face: str | int, rng=None, depth: int = 0) -> tuple:
    """Index of the cells next to a face (range) in a per-cell array of a block.

    Parameters
    ----------
    dims : (ni, nj, nk)
        Point dimensions of the block; the per-cell array has shape
        ``(ni - 1, nj - 1, nk - 1)``, with one cell along a dimension of one
        point (the k of a 2-D block: ``(ni - 1, nj - 1, 1)``).
    face : str or int
    rng : ((a0, a1), (b0, b1)), optional
        Point range of the running indices; default the whole face.  A
        running index with cells covers cells ``a0 .. a1 - 1``; one with a
        single point covers its one cell.
    depth : int
        Cell layer counted from the face (0: the cells touching it).

    Returns
    -------
    tuple of (int, slice, slice) in block axis order
        ``cells[face_cells(...)]`` is an ``(na - 1, nb - 1)`` view (a single
        point counting one cell).
    """
    (a0, a1), (b0, b1) = _check_range(dims, face, rng)
    d, a, b = face_axes(face)
    idx: list = [None, None, None]
    idx[d] = face_layer([max(n - 1, 1) for n in dims], face, depth)
    idx[a] = slice(a0, a1) if dims[a] > 1 else slice(0, 1)
    idx[b] = slice(b0, b1) if dims[b] > 1 else slice(0, 1)
    return tuple(idx)


def has_z(xyz: np.ndarray) -> bool:
    """Whether any z coordinate of ``xyz`` (..., 3) is not zero (NaN counts; no FPU warning)."""
    with np.errstate(invalid="ignore"):   # a signalling NaN raises "invalid" when tested
        return bool(np.any(xyz[..., 2]))


def _where(name: str | None) -> str:
    return f"block {name!r}" if name else "block"


class Block:
    """One structured block.

    Parameters
    ----------
    xyz : array_like, shape (ni, nj, nk, 3) or (ni, nj, 3)
        Coordinates.  A 3-D input ``(ni, nj, 3)`` is taken as a 2-D block
        (``nk = 1``); ``(ni, nj, 2)`` as a 2-D block with z = 0.  Stored as
        float64 in Fortran order (copied only when needed, or when
        ``copy=True``).
    iblank : array_like of int, shape (ni, nj, nk), optional
        Plot3D IBLANK values, stored as int32 in Fortran order.
    name : str, optional
        Block name (HDF5 group name, messages).
    copy : bool
        Always copy the input arrays.
    allow_nonfinite : bool
        Accept NaN or infinite coordinates (default: error).

    Raises
    ------
    GridValueError
        Wrong shape, a dimension < 1, or non-finite coordinates.
    """

    __slots__ = ("xyz", "iblank", "name")

    def __init__(self, xyz, iblank=None, name: str | None = None, *, copy: bool = False,
                 allow_nonfinite: bool = False):
        where = _where(name)
        arr = np.asarray(xyz)
        if arr.ndim == 3 and arr.shape[-1] in (2, 3):
            if arr.shape[-1] == 2:
                full = np.zeros(arr.shape[:2] + (3,), dtype=np.float64)
                full[..., :2] = arr
                arr = full
            arr = arr[:, :, np.newaxis, :]
        if arr.ndim != 4 or arr.shape[-1] != 3:
            raise GridValueError(f"{where}: xyz must have shape (ni, nj, nk, 3), got {arr.shape}")
        if min(arr.shape[:3]) < 1:
            raise GridValueError(f"{where}: dimensions must be >= 1, got {arr.shape[:3]}")
        if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
            raise GridValueError(f"{where}: xyz must be real numbers, got dtype {arr.dtype}")
        arr = np.array(arr, dtype=np.float64, order="F", copy=True) if copy else \
            np.asarray(arr, dtype=np.float64, order="F")
        if not allow_nonfinite:
            bad = ~np.isfinite(arr)
            if bad.any():
                i, j, k, c = np.argwhere(bad)[0]
                raise GridValueError(
                    f"{where}: {int(bad.sum())} non-finite coordinate value(s); first at "
                    f"(i, j, k) = ({i + 1}, {j + 1}, {k + 1}) (1-based), component {'xyz'[c]} "
                    "(pass allow_nonfinite=True to accept)")
        self.xyz = arr
        if iblank is not None:
            ib = np.asarray(iblank)
            if ib.shape != arr.shape[:3]:
                if ib.size == int(np.prod(arr.shape[:3])) and ib.ndim == 1:
                    ib = ib.reshape(arr.shape[:3], order="F")
                else:
                    raise GridValueError(f"{where}: iblank shape {ib.shape} does not match "
                                         f"block dimensions {arr.shape[:3]}")
            if not np.issubdtype(ib.dtype, np.integer):
                if not np.all(np.isfinite(ib)) or np.any(ib != np.round(ib)):
                    raise GridValueError(f"{where}: iblank must hold integers")
            ib = np.array(ib, dtype=np.int32, order="F", copy=True) if copy else \
                np.asarray(ib, dtype=np.int32, order="F")
        self.iblank = ib if iblank is not None else None
        self.name = None if name is None else str(name)

    # ------------------------------------------------------------------ shape
    @property
    def dims(self) -> tuple[int, int, int]:
        """``(ni, nj, nk)``."""
        return tuple(int(n) for n in self.xyz.shape[:3])  # type: ignore[return-value]

    @property
    def npoints(self) -> int:
        ni, nj, nk = self.dims
        return ni * nj * nk

    @property
    def x(self) -> np.ndarray:
        return self.xyz[..., 0]

    @property
    def y(self) -> np.ndarray:
        return self.xyz[..., 1]

    @property
    def z(self) -> np.ndarray:
        return self.xyz[..., 2]

    def face(self, face: str | int, depth: int = 0) -> np.ndarray:
        """View of one face's points, shape ``(na, nb, 3)``.

        The two running indices are the block's remaining indices in order:
        imin/imax -> (j, k), jmin/jmax -> (i, k), kmin/kmax -> (i, j).
        ``depth``: the layer that many steps in from the face (:func:`face_layer`).
        """
        d, _ = face_axis(face)
        idx = [slice(None)] * 3
        idx[d] = face_layer(self.dims, face, depth)
        return self.xyz[tuple(idx)]

    def copy(self) -> "Block":
        return Block(self.xyz, self.iblank, self.name, copy=True, allow_nonfinite=True)

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(lo, hi)`` corner coordinates, each shape (3,)."""
        flat = self.xyz.reshape(-1, 3, order="F")
        return flat.min(axis=0), flat.max(axis=0)

    def __repr__(self) -> str:
        ib = ", iblank" if self.iblank is not None else ""
        nm = f"{self.name!r}, " if self.name else ""
        return f"Block({nm}{self.dims[0]}x{self.dims[1]}x{self.dims[2]}{ib})"

    def __eq__(self, other) -> bool:  # value equality, for tests and round trips
        if not isinstance(other, Block):
            return NotImplemented
        if self.dims != other.dims or not np.array_equal(self.xyz, other.xyz):
            return False
        if (self.iblank is None) != (other.iblank is None):
            return False
        return self.iblank is None or np.array_equal(self.iblank, other.iblank)

    __hash__ = None  # type: ignore[assignment]


class Grid:
    """Ordered list of :class:`Block` with a dimension.

    Parameters
    ----------
    blocks : iterable of Block or array_like
        The blocks; arrays are wrapped in :class:`Block`.
    ndim : {2, 3}, optional
        Grid dimension.  Default: 2 when every block has ``nk == 1`` and
        z == 0 everywhere, else 3.  A 2-D grid must have ``nk == 1`` and
        z == 0 in every block.
    source_format : object, optional
        The file variant the grid was read from (e.g. a
        :class:`tfi_quat.io.plot3d.Plot3DFormat`); ``write(..., like=grid)``
        writes that variant again.
    source_path : str or path, optional
        The file the grid was read from; writing over it needs ``overwrite=True``.
    allow_nonfinite : bool
        Passed on to :class:`Block` for array inputs.
    connectivity : tfi_quat.topology.Connectivity, optional
        The grid's interfaces and boundary patches with their kinds, as a file
        that records them (CGNS) gives them; None (the default) for formats
        that do not.  Checked against the blocks (ndim, block count and
        dimensions).  :class:`tfi_quat.deform.Deformer` uses it when given no
        ``connectivity``; a CGNS writer writes it.  It is shared, not copied,
        by :meth:`copy` and :meth:`with_blocks` (a connectivity is not
        modified once made), and ``==`` ignores it: two grids are equal when
        their coordinates (and IBLANK) are.

    Raises
    ------
    GridValueError
        No blocks, a bad ``ndim``, a 3-D block or z != 0 in a 2-D grid.
    ConnectivityError
        ``connectivity`` is not made for these blocks.
    """

    #: the cell check of the :meth:`tfi_quat.deform.Deformer.deform` step that made or
    #: filled this grid (a :class:`tfi_quat.quality.CellCheck`), None otherwise
    quality = None

    #: the blocks' 0-based numbers in their file when the grid holds some of its blocks
    #: (``read(path, blocks=...)``), None for a whole grid; kept by :meth:`copy`
    block_ids = None

    def __init__(self, blocks: Iterable[Block | np.ndarray] | Block, ndim: int | None = None, *,
                 source_format=None, source_path=None, allow_nonfinite: bool = False,
                 connectivity=None):
        if isinstance(blocks, (Block, np.ndarray)):
            blocks = [blocks]
        blist: list[Block] = []
        for n, b in enumerate(blocks):
            if not isinstance(b, Block):
                b = Block(b, name=f"block{n + 1}", allow_nonfinite=allow_nonfinite)
            blist.append(b)
        if not blist:
            raise GridValueError("a grid needs at least one block")
        flat2d = all(b.dims[2] == 1 and not has_z(b.xyz) for b in blist)
        if ndim is None:
            ndim = 2 if flat2d else 3
        if ndim not in (2, 3):
            raise GridValueError(f"ndim must be 2 or 3, got {ndim!r}")
        if ndim == 2:
            for n, b in enumerate(blist):
                if b.dims[2] != 1:
                    raise GridValueError(f"block {n + 1}: a 2-D grid needs nk == 1, got nk = {b.dims[2]}")
                if has_z(b.xyz):
                    raise GridValueError(f"block {n + 1}: a 2-D grid needs z == 0")
        self.blocks = blist
        self.ndim = int(ndim)
        self.source_format = source_format
        self.source_path = None if source_path is None else os.fspath(source_path)
        if connectivity is not None:
            check = getattr(connectivity, "check", None)
            if not callable(check):
                raise GridValueError(f"connectivity must be a tfi_quat.topology.Connectivity, "
                                     f"got {type(connectivity).__name__}")
            check(self)
        #: interfaces and boundary patches (:class:`tfi_quat.topology.Connectivity`) or None
        self.connectivity = connectivity

    # ------------------------------------------------------------ container
    def __len__(self) -> int:
        return len(self.blocks)

    def __iter__(self) -> Iterator[Block]:
        return iter(self.blocks)

    def __getitem__(self, b: int) -> Block:
        return self.blocks[b]

    @property
    def nblocks(self) -> int:
        return len(self.blocks)

    @property
    def npoints(self) -> int:
        return sum(b.npoints for b in self.blocks)

    @property
    def dims(self) -> list[tuple[int, int, int]]:
        return [b.dims for b in self.blocks]

    @property
    def has_iblank(self) -> bool:
        return any(b.iblank is not None for b in self.blocks)

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(lo, hi)`` over all blocks, each shape (3,)."""
        lo, hi = zip(*(b.bbox() for b in self.blocks))
        return np.min(lo, axis=0), np.max(hi, axis=0)

    def copy(self) -> "Grid":
        """Deep copy (coordinates and iblank); keeps ``source_format`` and ``connectivity`` (shared),
        drops ``source_path``."""
        out = Grid([b.copy() for b in self.blocks], self.ndim, source_format=self.source_format,
                   connectivity=self.connectivity)
        out.block_ids = self.block_ids
        return out

    def with_blocks(self, blocks: Sequence[Block]) -> "Grid":
        """A new grid with other blocks and this grid's ndim and source format, and its
        ``connectivity`` when the new blocks have this grid's dimensions (else None)."""
        out = Grid(list(blocks), self.ndim, source_format=self.source_format)
        if out.dims == self.dims:
            out.connectivity = self.connectivity    # made for these dimensions: checked already
        return out

    def __eq__(self, other) -> bool:
        """Equal coordinates, IBLANK and ndim; ``source_format``, ``source_path`` and
        ``connectivity`` are not compared."""
        if not isinstance(other, Grid):
            return NotImplemented
        return self.ndim == other.ndim and len(self) == len(other) and \
            all(a == b for a, b in zip(self.blocks, other.blocks))

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        dims = ", ".join("x".join(map(str, d)) for d in self.dims[:4])
        more = ", ..." if len(self) > 4 else ""
        return f"Grid(ndim={self.ndim}, {len(self)} block(s): {dims}{more})"


def partition(dims, nparts: int) -> list[list[int]]:
    """Split blocks over ``nparts`` parts, balanced by point count.

    Greedy, largest block first onto the least-loaded part (ties: the block
    with the lower number first, the part with the lower number first): a
    pure function of ``dims`` and ``nparts``, so every rank of an MPI job
    computes the same partition without communicating.  The largest part
    holds at most the mean load plus the largest block.

    Parameters
    ----------
    dims : sequence of (ni, nj, nk), or a Grid / GridFaces (their ``dims``)
        The blocks' point dimensions, in file order.
    nparts : int
        Number of parts (ranks), 1 to the number of blocks.

    Returns
    -------
    list of list of int
        ``nparts`` lists of 0-based block numbers, each in increasing order;
        every block in exactly one, none empty.

    Raises
    ------
    GridValueError
        ``nparts`` not an integer, < 1, or more than the blocks (a part
        would be empty: split the blocks first); bad dims.

    >>> partition([(10, 10, 10), (10, 10, 5), (10, 10, 5), (4, 4, 4)], 2)
    [[0, 3], [1, 2]]
    """
    dims = getattr(dims, "dims", dims)
    sizes = []
    for n, d in enumerate(dims):
        try:
            ni, nj, nk = (int(v) for v in d)
        except (TypeError, ValueError):
            raise GridValueError(f"partition: block {n}: dims must be (ni, nj, nk), got {d!r}") from None
        if min(ni, nj, nk) < 1:
            raise GridValueError(f"partition: block {n}: dims {d!r} must all be >= 1")
        sizes.append(ni * nj * nk)
    if isinstance(nparts, bool) or not isinstance(nparts, (int, np.integer)):
        raise GridValueError(f"partition: nparts must be an integer, got {nparts!r}")
    nparts = int(nparts)
    if nparts < 1:
        raise GridValueError(f"partition: nparts must be >= 1, got {nparts}")
    if nparts > len(sizes):
        raise GridValueError(f"partition: {nparts} parts for {len(sizes)} block(s): a part would be "
                             "empty (use at most as many parts as blocks, or split the blocks)")
    load = [0] * nparts
    parts: list[list[int]] = [[] for _ in range(nparts)]
    for n in sorted(range(len(sizes)), key=lambda m: (-sizes[m], m)):
        p = min(range(nparts), key=lambda q: (load[q], q))
        load[p] += sizes[n]
        parts[p].append(n)
    return [sorted(p) for p in parts]
