"""Block connectivity: point-matched interfaces and boundary patches.

:func:`connect` finds the interfaces of a grid (coincident boundary points
grown into maximal rectangles with a CGNS ``Transform``) and classifies the
rest of the boundary into patches (wall, fixed, symmetry, free);
:func:`classify` re-applies user kinds.  A :class:`Connectivity` is saved and
read as JSON (:meth:`Connectivity.to_json`) or as a Neutral Map File
(:meth:`Connectivity.to_nmf`).  See ``docs/connectivity.md``.
"""

from __future__ import annotations

from ..grid import face_axes
from .model import KINDS, Connectivity, FaceMap, Interface, Patch
from .search import (DEFAULT_RTOL, PLANE_RTOL, check_interfaces, classify, connect, interface_mismatches,
                     node_labels)

__all__ = ["connect", "classify", "node_labels", "interface_mismatches", "check_interfaces", "Connectivity",
           "Interface", "Patch", "FaceMap", "KINDS", "DEFAULT_RTOL", "PLANE_RTOL", "face_axes"]
