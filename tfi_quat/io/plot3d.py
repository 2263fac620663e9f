"""Plot3D grid files: every common variant, detected automatically.

(Skeleton: the variant description below is the contract; reader and writer
are being written.)
"""

from __future__ import annotations

from dataclasses import dataclass, replace

__all__ = ["Plot3DFormat", "read", "write", "detect"]


@dataclass(frozen=True)
class Plot3DFormat:
    """One Plot3D file variant.

    Attributes
    ----------
    encoding : {"binary", "fortran", "ascii"}
        ``binary``: C stream, no record markers.  ``fortran``: Fortran
        unformatted sequential, each record framed by length markers.
        ``ascii``: formatted text.
    endian : {"<", ">"}
        Byte order of binary and Fortran files (ignored for ASCII).
    precision : {4, 8}
        Bytes per coordinate value (float32 / float64).
    ndim : {2, 3}
        2: ``ni nj`` headers and x, y only; 3: ``ni nj nk`` and x, y, z.
    multiblock : bool
        The file starts with the block count.  Single-block files have no
        block-count line.
    iblank : bool
        Each block's coordinates are followed by an int IBLANK array.
    records : {"block", "coordinate"}
        Fortran only: one record per block (x, y, z[, iblank]) or the older
        layout with one record per coordinate array.
    int_size : {4, 8}
        Bytes per header integer (block count, dimensions) and IBLANK value;
        8 for codes that write 64-bit default integers.
    marker_size : {4, 8}
        Fortran only: bytes per record-length marker.
    """

    encoding: str = "binary"
    endian: str = "<"
    precision: int = 8
    ndim: int = 3
    multiblock: bool = True
    iblank: bool = False
    records: str = "block"
    int_size: int = 4
    marker_size: int = 4

    def replace(self, **changes) -> "Plot3DFormat":
        return replace(self, **changes)
