"""The multiblock Deformer (docs/method.md §3.3, docs/deformer.md).

:class:`Deformer` is the front: built once per grid, it deforms the grid for
each new wall position (:meth:`Deformer.deform`).  The package, one module per
concern:

``skeleton``
    the frozen skeleton: global boundary points and their kinds, wall halos,
    vertices, segments, patches, symmetry points, blocks, with their weights
    and blending parameters.
``twolevel``
    the two-level formulation's parts: wall layer, bodies and their rigid
    fits and weights, the centre field and its arms; its step's fields.
``stages``
    the compiled stages (numba kernels on the global boundary arrays) and the
    thin driver of each hierarchy level.
``walls``
    the wall in the solver's terms (every wall point copy as block, i, j, k)
    and a step's wall targets from any input form, checked.
``buffers``
    the caller's coordinate buffers (``out=``): their checks, layouts and
    the kept scratch.
``modal``
    modal wall motion from mode shapes on the wall.
``deformer``
    the front: options, each formulation's step, the result grid.
"""

from __future__ import annotations

from .deformer import METHODS, Deformer, StepTimings, deformer_from_case, rigid_motion
from .skeleton import DERIVED, FIXED, SYMMETRY, WALL

__all__ = ["Deformer", "rigid_motion", "StepTimings", "deformer_from_case", "METHODS",
           "WALL", "FIXED", "SYMMETRY", "DERIVED"]
