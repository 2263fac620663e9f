"""tfi_quat: multiblock structured grids and quaternion TFI mesh deformation.

Reads and writes Plot3D (every common variant) and HDF5 grids, finds how
blocks connect, and deforms a volume grid when its walls move with
transfinite interpolation of translations *and* rotations (quaternions),
after Samareh, NASA/TM-2002-211646.
"""

from __future__ import annotations

__version__ = "0.1.0"

from .errors import (CaseError, ConnectivityError, DeformationError, GridFormatError,
                     GridValueError, OverwriteError, ParallelError, TfiQuatError)
from .grid import FACES, Block, Grid, partition
from .io import read, read_faces, write

__all__ = [
    "__version__",
    "Block", "Grid", "FACES",
    "read", "read_faces", "write", "partition",
    "TfiQuatError", "GridFormatError", "GridValueError", "ConnectivityError",
    "CaseError", "DeformationError", "OverwriteError", "ParallelError",
    "Deformer", "StepTimings", "rigid_motion", "deformer_from_case", "connect", "Connectivity",
]

# The numba-backed parts load on first use, so ``import tfi_quat`` (and the
# CLI's start-up) stays fast.
_LAZY = {
    "Deformer": (".deform", "Deformer"),
    "StepTimings": (".deform", "StepTimings"),
    "rigid_motion": (".deform", "rigid_motion"),
    "deformer_from_case": (".deform", "deformer_from_case"),
    "connect": (".topology", "connect"),
    "Connectivity": (".topology", "Connectivity"),
}


def __getattr__(name):
    try:
        modname, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module 'tfi_quat' has no attribute {name!r}") from None
    import importlib
    value = getattr(importlib.import_module(modname, __name__), attr)
    globals()[name] = value
    return value
