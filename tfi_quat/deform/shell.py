"""The boundary shell of a multiblock grid: what a distributed set-up knows of every block.

A rank of a distributed deformation (:mod:`.distributed`) holds the volume of
its own blocks only.  Of every other block it holds a :class:`ShellBlock`:
the dims, the name, the bounding box, the boundary faces and the layer of
points next to each face (the connectivity search measures the spacing
there), all O(surface) and bit-identical to what the owner's
:class:`~tfi_quat.grid.Block` gives.  A :class:`ShellGrid` puts the rank's
own blocks and the others' shells in global block order; it answers what the
Deformer's set-up asks of a grid (``len``, iteration, ``dims``, ``bbox``,
``face(f, depth)``, ``ndim``, ``connectivity``, ``source_format``), so the
skeleton is built from it exactly as from the whole grid.
"""

from __future__ import annotations

import numpy as np

from ..errors import GridValueError
from ..grid import face_axis, faces_of

__all__ = ["ShellBlock", "ShellGrid", "shell_of", "boundary_values"]


class ShellBlock:
    """The boundary of a block another rank owns: ``dims``, ``name``, ``lo``/``hi`` (its
    bounding box), ``faces`` (the ``2 ndim`` boundary faces, ``(na, nb, 3)``) and ``layers``
    (the point layer next to each face; None where the block is one point thick, or once
    dropped).  ``xyz`` is None: the volume lives on its owner."""

    __slots__ = ("dims", "name", "lo", "hi", "faces", "layers")
    xyz = None
    iblank = None

    def __init__(self, dims, name, lo, hi, faces, layers):
        self.dims = tuple(int(v) for v in dims)
        self.name = name
        self.lo, self.hi = lo, hi
        self.faces = tuple(faces)
        self.layers = None if layers is None else tuple(layers)

    @property
    def npoints(self) -> int:
        ni, nj, nk = self.dims
        return ni * nj * nk

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lo, hi)``, as the owner's ``Block.bbox()`` gives them."""
        return self.lo, self.hi

    def face(self, face, depth: int = 0) -> np.ndarray:
        """Face ``face`` (``depth`` 0) or the layer next to it (``depth`` 1)."""
        d, side = face_axis(face)
        f = 2 * d + side
        if depth == 0:
            return self.faces[f]
        if depth == 1 and self.layers is not None and self.layers[f] is not None:
            return self.layers[f]
        raise GridValueError(f"block {self.name!r}: layer {depth} of face {f} is not held on this "
                             "rank (the volume lives on its owner)")


def shell_of(blk, ndim: int) -> ShellBlock:
    """The :class:`ShellBlock` of a block (copies of its faces and of the layers next to them)."""
    faces, layers = [], []
    for f in faces_of(ndim):
        d, _ = face_axis(f)
        faces.append(np.array(blk.face(f), order="F"))
        layers.append(np.array(blk.face(f, 1), order="F") if blk.dims[d] >= 2 else None)
    lo, hi = blk.bbox()
    return ShellBlock(blk.dims, blk.name, lo, hi, faces, layers)


class ShellGrid:
    """Every block of a grid in global order: the rank's own :class:`~tfi_quat.grid.Block`\\ s
    and the others' :class:`ShellBlock`\\ s.

    ``local``: the Grid of the own blocks (in the order of ``own``); ``own``: their global
    0-based numbers; ``exchange_plans``: the collective that gives every rank the other
    blocks' face parameters (:func:`tfi_quat.deform.skeleton.build_skeleton`).
    """

    def __init__(self, blocks, ndim: int, local, own, *, connectivity=None, source_format=None,
                 source_path=None, exchange_plans=None):
        self.blocks = list(blocks)
        self.ndim = int(ndim)
        self.local = local
        self.own = tuple(int(b) for b in own)
        self.connectivity = connectivity
        self.source_format = source_format
        self.source_path = source_path
        self.exchange_plans = exchange_plans

    def __len__(self) -> int:
        return len(self.blocks)

    def __iter__(self):
        return iter(self.blocks)

    def __getitem__(self, b: int):
        return self.blocks[b]

    @property
    def dims(self) -> list:
        return [b.dims for b in self.blocks]

    @property
    def npoints(self) -> int:
        return sum(b.npoints for b in self.blocks)

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lo, hi)`` over all blocks: the values ``Grid.bbox()`` of the whole grid gives."""
        lo, hi = zip(*(b.bbox() for b in self.blocks))
        return np.min(lo, axis=0), np.max(hi, axis=0)

    def drop_layers(self) -> None:
        """Forget the layers next to the faces (only the set-up's connectivity search reads them)."""
        for blk in self.blocks:
            if isinstance(blk, ShellBlock):
                blk.layers = None


def boundary_values(grid, ids: np.ndarray) -> np.ndarray:
    """Coordinates ``(n, 3)`` of the boundary points ``ids`` (rows ``(block, i, j, k)``), read from
    the blocks' faces: the same values from a Grid or a :class:`ShellGrid`."""
    out = np.empty((ids.shape[0], 3))
    done = np.zeros(ids.shape[0], dtype=bool)
    for b, blk in enumerate(grid):
        sel = ids[:, 0] == b
        if not sel.any():
            continue
        for f in faces_of(grid.ndim):
            d, side = face_axis(f)
            run = [a for a in range(3) if a != d]
            on = sel & ~done & (ids[:, 1 + d] == (blk.dims[d] - 1 if side else 0))
            if on.any():
                face = blk.face(f)
                out[on] = face[ids[on, 1 + run[0]], ids[on, 1 + run[1]]]
                done |= on
    if not done.all():
        r = int(np.flatnonzero(~done)[0])
        raise GridValueError(f"point {tuple(int(v) for v in ids[r])} (block, i, j, k; 0-based) is "
                             "not on a block boundary")
    return out
