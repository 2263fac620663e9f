"""Patch specifications: which part of which block face.

Text form (files and CLI, 1-based inclusive, as Plot3D and CGNS users expect)::

    BLOCK:FACE                    the whole face, e.g. "1:jmin"
    BLOCK:FACE:A1-A2,B1-B2        a sub-range of the face's two running indices

The running indices of a face are the block's other two indices in order:
imin/imax -> (j, k), jmin/jmax -> (i, k), kmin/kmax -> (i, j) -- the axes of
:meth:`tfi_quat.grid.Block.face`.  In the Python API everything is 0-based:
``PatchSpec(block=0, face="jmin", range=((0, 128), (0, 0)))``.
"""

from __future__ import annotations

import numbers
import re
from dataclasses import dataclass

import numpy as np

from .errors import CaseError
from .grid import FACES, Grid, face_shape

__all__ = ["PatchSpec", "parse_patch_spec", "as_patch_specs", "resolve_patch_specs"]

_RANGE = re.compile(r"^\s*([0-9]+)\s*-\s*([0-9]+)\s*$")
_BLOCK = re.compile(r"^\s*[0-9]+\s*$")


def _is_int(v) -> bool:
    """An integer (Python or NumPy), not a bool and not a float such as 3.7."""
    return isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_))


@dataclass(frozen=True)
class PatchSpec:
    """A block face, or a rectangular part of one (0-based, inclusive).

    Attributes
    ----------
    block : int
        Block number, 0-based.
    face : str
        ``"imin"`` ... ``"kmax"``.
    range : ((a0, a1), (b0, b1)) or None
        Inclusive ranges of the face's two running indices; None = whole face.
    """

    block: int
    face: str
    range: tuple[tuple[int, int], tuple[int, int]] | None = None

    def __post_init__(self):
        face = str(self.face).strip().lower()
        if face not in FACES:
            raise CaseError(f"unknown face {self.face!r}: expected one of {', '.join(FACES)}")
        object.__setattr__(self, "face", face)
        if not _is_int(self.block):
            raise CaseError(f"block: expected an integer, got {self.block!r}")
        if int(self.block) < 0:
            raise CaseError(f"block number must be >= 1 (1-based), got {int(self.block) + 1}")
        object.__setattr__(self, "block", int(self.block))
        if self.range is not None:
            try:
                (a0, a1), (b0, b1) = self.range
            except (TypeError, ValueError):
                raise CaseError(f"range: expected ((a0, a1), (b0, b1)), got {self.range!r}") from None
            if not all(_is_int(v) for v in (a0, a1, b0, b1)):
                raise CaseError(f"range: expected integers ((a0, a1), (b0, b1)), got {self.range!r}")
            r = ((int(a0), int(a1)), (int(b0), int(b1)))
            if min(a0, b0) < 0 or a1 < a0 or b1 < b0:
                raise CaseError(f"{self}: a range must be increasing and >= 1 (1-based)")
            object.__setattr__(self, "range", r)

    def resolve(self, grid: Grid) -> "PatchSpec":
        """Check against ``grid`` and return the spec with an explicit range."""
        if self.block >= len(grid):
            raise CaseError(f"{self}: the grid has {len(grid)} block(s)")
        dims = grid[self.block].dims
        if grid.ndim == 2 and self.face in ("kmin", "kmax"):
            raise CaseError(f"{self}: a 2-D grid has no k faces")
        na, nb = face_shape(dims, self.face)
        if self.range is None:
            return PatchSpec(self.block, self.face, ((0, na - 1), (0, nb - 1)))
        (a0, a1), (b0, b1) = self.range
        if a1 >= na or b1 >= nb:
            raise CaseError(f"{self}: range exceeds the face size {na} x {nb} of block "
                            f"{self.block + 1} ({dims[0]} x {dims[1]} x {dims[2]})")
        return self

    def __str__(self) -> str:
        s = f"{self.block + 1}:{self.face}"
        if self.range is not None:
            (a0, a1), (b0, b1) = self.range
            s += f":{a0 + 1}-{a1 + 1},{b0 + 1}-{b1 + 1}"
        return s


def parse_patch_spec(text: str) -> PatchSpec:
    """Parse ``"BLOCK:FACE[:A1-A2,B1-B2]"`` (1-based, inclusive) into a :class:`PatchSpec`.

    A 2-D grid's face has one running index; ``"1:jmin:1-129"`` is accepted and
    means ``1-129,1-1``.
    """
    parts = str(text).strip().split(":")
    if len(parts) not in (2, 3) or not _BLOCK.match(parts[0]):
        raise CaseError(f"patch {text!r}: expected BLOCK:FACE or BLOCK:FACE:A1-A2,B1-B2 (1-based)")
    block = int(parts[0]) - 1
    if block < 0:
        raise CaseError(f"patch {text!r}: block numbers start at 1")
    rng = None
    if len(parts) == 3:
        pieces = parts[2].split(",")
        if len(pieces) == 1:
            pieces.append("1-1")
        if len(pieces) != 2:
            raise CaseError(f"patch {text!r}: a range is A1-A2,B1-B2")
        pairs = []
        for p in pieces:
            m = _RANGE.match(p)
            if not m:
                raise CaseError(f"patch {text!r}: bad range {p!r}, expected N1-N2")
            lo, hi = int(m.group(1)), int(m.group(2))
            if lo < 1 or hi < lo:
                raise CaseError(f"patch {text!r}: range {p!r} must satisfy 1 <= N1 <= N2")
            pairs.append((lo - 1, hi - 1))
        rng = (pairs[0], pairs[1])
    try:
        return PatchSpec(block, parts[1], rng)
    except CaseError as exc:
        raise CaseError(f"patch {text!r}: {exc}") from None


def as_patch_specs(items, what: str) -> list[PatchSpec]:
    """A list of :class:`PatchSpec` from PatchSpecs, ``"B:FACE[:range]"`` strings or
    ``(block, face[, range])`` tuples (0-based); one item may be given bare.
    ``what`` names the argument in the error message."""
    if items is None:
        return []
    if isinstance(items, (str, PatchSpec)):
        items = [items]
    out = []
    for it in items:
        if isinstance(it, PatchSpec):
            out.append(it)
        elif isinstance(it, str):
            out.append(parse_patch_spec(it))
        elif isinstance(it, (tuple, list)) and len(it) in (2, 3):
            out.append(PatchSpec(*it))
        else:
            raise CaseError(f"{what}: cannot read {it!r} as a patch (BLOCK:FACE[:range] or PatchSpec)")
    return out


def resolve_patch_specs(grid: Grid, items, what: str) -> list[PatchSpec]:
    """:func:`as_patch_specs` resolved against ``grid`` (:meth:`PatchSpec.resolve`):
    every spec checked and given its explicit range."""
    return [spec.resolve(grid) for spec in as_patch_specs(items, what)]
