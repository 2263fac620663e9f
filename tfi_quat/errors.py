"""Exception hierarchy.

Every error the library raises on bad input derives from :class:`TfiQuatError`,
so the CLI can turn it into one line on stderr.  Errors that describe bad
values also derive from :class:`ValueError`.
"""

from __future__ import annotations

__all__ = [
    "TfiQuatError",
    "GridFormatError",
    "GridValueError",
    "ConnectivityError",
    "CaseError",
    "DeformationError",
    "OverwriteError",
    "ParallelError",
]


class TfiQuatError(Exception):
    """Base class of every error raised by tfi_quat on bad input."""


class GridFormatError(TfiQuatError, ValueError):
    """A grid file cannot be read or written: names the file, block, offset or line."""


class GridValueError(TfiQuatError, ValueError):
    """A grid or block holds invalid values (shape, dtype, non-finite coordinates)."""


class ConnectivityError(TfiQuatError, ValueError):
    """Patches or interfaces are inconsistent (unknown face, overlap, mismatch)."""


class CaseError(TfiQuatError, ValueError):
    """A case file or a boundary specification is invalid."""


class DeformationError(TfiQuatError, RuntimeError):
    """A deformation could not be carried out or produced an invalid grid."""


class OverwriteError(TfiQuatError, FileExistsError):
    """A write would replace an input or an existing file without permission."""


class ParallelError(TfiQuatError, RuntimeError):
    """An MPI collective cannot run: mpi4py not installed, a bad communicator, ranks
    whose grids or file variants disagree."""
