"""Size limits checked before a reader allocates a declared grid.

A damaged or hostile file can declare a grid far larger than itself (a
60-byte header declaring 800^3 points, a gzip-compressed dataset, a sparse
file).  Every reader checks the declared size with :func:`check_points`
*before* it allocates anything, so such a file ends in a
:class:`~tfi_quat.errors.GridFormatError` that names the size, never in an
unbounded allocation or a raw ``MemoryError``.

The limit is the caller's ``max_points`` when given, else what fits in the
memory available now (``MemAvailable`` of ``/proc/meminfo`` where there is
one, else the physical memory).
"""

from __future__ import annotations

import os

from ..errors import GridFormatError

__all__ = ["available_memory", "check_points", "BYTES_PER_POINT"]

#: bytes a reader keeps per grid point: three float64 coordinates and an int32 IBLANK
BYTES_PER_POINT = 3 * 8 + 4


def available_memory() -> int:
    """Bytes of memory available to a new allocation now (best effort)."""
    try:
        with open("/proc/meminfo", "rb") as fh:
            for line in fh:
                if line.startswith(b"MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return 1 << 34


def _human(nbytes: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if nbytes < 1024 or unit == "PiB":
            return f"{nbytes:.1f} {unit}" if unit != "B" else f"{int(nbytes)} B"
        nbytes /= 1024
    return f"{nbytes:.1f} PiB"  # pragma: no cover


def check_points(where: str, npoints: int, *, max_points: int | None = None,
                 bytes_per_point: int = BYTES_PER_POINT) -> None:
    """Refuse a declared grid of ``npoints`` points that cannot be held.

    Parameters
    ----------
    where : str
        What declared the size, for the message (``"grid.x: block 3"``).
    npoints : int
        Points declared (all blocks so far, or one block).
    max_points : int, optional
        The caller's cap; default: what fits in the available memory.
    bytes_per_point : int
        Bytes the reader will allocate per point.

    Raises
    ------
    GridFormatError
        Naming the declared size and the limit.
    """
    npoints = int(npoints)
    if max_points is not None:
        if npoints > int(max_points):
            raise GridFormatError(
                f"{where}: declares {npoints:,} points, more than max_points={int(max_points):,}")
        return
    need = npoints * int(bytes_per_point)
    have = available_memory()
    if need > have:
        raise GridFormatError(
            f"{where}: declares {npoints:,} points ({_human(need)}), more than the "
            f"{_human(have)} of memory available; pass max_points= to set the limit")
