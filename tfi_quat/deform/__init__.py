"""The multiblock Deformer (docs/method.md §3.3, docs/deformer.md).

:class:`Deformer` is the front: built once per grid, it deforms the grid for
each new wall position (:meth:`Deformer.deform`).  The package's modules:

``deformer``
    the front: options, the step of each formulation, the result grid.
``stages``
    the compiled stages (numba kernels on the global boundary arrays).
"""

from __future__ import annotations

from .deformer import (DERIVED, FIXED, FORMULATIONS, SYMMETRY, WALL, Deformer, StepTimings,
                       _face_ijk, _faces_of, deformer_from_case, rigid_motion)

__all__ = ["Deformer", "rigid_motion", "StepTimings", "deformer_from_case", "FORMULATIONS",
           "WALL", "FIXED", "SYMMETRY", "DERIVED"]
