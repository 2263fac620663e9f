"""Neutral Map Files (``.nmf``): the GEOLAB / NASA Langley multiblock boundary map.

Layout (``#`` starts a comment; blank lines are ignored)::

    # header comments
    NBLOCKS
    1  IDIM  JDIM  KDIM            (one line per block; KDIM may be left out in 2-D)
    ...
    TYPE        B1 F1 S1 E1 S2 E2                              (a boundary patch)
    ONE_TO_ONE  B1 F1 S1 E1 S2 E2  B2 F2 S1 E1 S2 E2  SWAP     (a point-matched interface)

Faces (3-D numbering, GEOLAB) and their (primary, secondary) index directions:

====  ==========  =========  ===========
face  definition  primary    secondary
====  ==========  =========  ===========
1     K = 1       I          J
2     K = KDIM    I          J
3     I = 1       J          K
4     I = IDIM    J          K
5     J = 1       K          I
6     J = JDIM    K          I
====  ==========  =========  ===========

``S1 E1`` is the primary range and ``S2 E2`` the secondary range, 1-based and
inclusive.  On a ONE_TO_ONE line the first side is written ascending; the
second side's ``S`` values are the indices of the point that matches the
first side's start corner and its ``E`` values those matching the end corner,
so a reversed direction shows as ``S > E``.  ``SWAP`` is TRUE when the first
side's primary direction runs along the second side's secondary direction.

2-D grids (Construct2D style, ``convention="2d"``) number the sides
1..4 = I = 1, I = IDIM, J = 1, J = JDIM, with ``S1 E1`` along the side and
``S2 E2 = 1 1``.  The reader picks it automatically when every block has
KDIM = 1 and no face number exceeds 4.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import ConnectivityError
from ..grid import face_axes, face_axis, face_index, face_layer
from ..io._atomic import atomic_output, check_target, read_text
from ..spec import PatchSpec
from .model import KINDS, MAX_DIM, Connectivity, Interface, Patch, check_dims

__all__ = ["read_nmf", "write_nmf", "nmf_kind", "NMF_FACES_3D", "NMF_FACES_2D"]

#: NMF face number -> face name (3-D numbering)
NMF_FACES_3D = {1: "kmin", 2: "kmax", 3: "imin", 4: "imax", 5: "jmin", 6: "jmax"}
#: NMF face number -> face name (2-D numbering)
NMF_FACES_2D = {1: "imin", 2: "imax", 3: "jmin", 4: "jmax"}

#: (primary, secondary) block axes of each face in the 3-D numbering
_PRIMARY = {"kmin": (0, 1), "kmax": (0, 1), "imin": (1, 2), "imax": (1, 2), "jmin": (2, 0), "jmax": (2, 0)}

_EXACT = {
    "ONE_TO_ONE": "interface",
    "WALL": "wall", "VISCOUS": "wall", "INVISCID": "wall", "SOLID": "wall", "NO_SLIP": "wall",
    "NOSLIP": "wall", "SLIP": "wall", "TANGENCY": "wall", "ADIABATIC": "wall", "ISOTHERMAL": "wall",
    "FIXED": "fixed", "FARFIELD": "fixed", "FAR_FIELD": "fixed", "FAR": "fixed", "FREESTREAM": "fixed",
    "INFLOW": "fixed", "OUTFLOW": "fixed", "INLET": "fixed", "OUTLET": "fixed", "EXTRAPOLATE": "fixed",
    "EXTRAPOLATION": "fixed", "CHARACTERISTIC": "fixed", "RIEMANN": "fixed", "DIRICHLET": "fixed",
    "UNPROCESSED": "free", "UNSPECIFIED": "free", "FREE": "free",
    "COLLAPSED": "collapsed", "POLE": "collapsed", "POLE_DIR1": "collapsed", "POLE_DIR2": "collapsed",
    "SINGULAR": "collapsed", "DEGENERATE": "collapsed",
}


def _norm(name: str) -> str:
    return str(name).strip().strip("'\"").upper().replace("-", "_").replace(" ", "_")


def nmf_kind(name: str, types=None) -> str | None:
    """Kind of an NMF boundary type: wall, fixed, symmetry, free, collapsed, interface (None: unknown).

    Exact names first (``types`` overrides, then the built-in table), then
    families: ``SYM*`` -> symmetry; ``*WALL*``, ``VISCOUS*``, ``INVISCID*``
    -> wall; ``*INFLOW*``, ``*OUTFLOW*``, ``*INLET*``, ``*OUTLET*``,
    ``FAR*``, ``*EXTRAP*``, ``*PRESSURE*`` -> fixed.
    """
    key = _norm(name)
    if types:
        for k, v in types.items():
            if _norm(k) == key:
                return v
    if key in _EXACT:
        return _EXACT[key]
    if key.startswith("SYM"):
        return "symmetry"
    if "WALL" in key or key.startswith(("VISCOUS", "INVISCID")):
        return "wall"
    if any(s in key for s in ("INFLOW", "OUTFLOW", "INLET", "OUTLET", "EXTRAP", "PRESSURE")) or \
            key.startswith("FAR"):
        return "fixed"
    return None


# ------------------------------------------------------------------ write
def _type_name(p: Patch) -> str:
    want = "collapsed" if (p.kind == "free" and p.collapsed) else p.kind
    if p.name and nmf_kind(p.name) == want and not any(c.isspace() for c in p.name):
        return p.name
    if want == "wall":
        return "WALL"
    if want == "fixed":
        return "FARFIELD"
    if want == "collapsed":
        return "COLLAPSED"
    if want == "free":
        return "UNPROCESSED"
    if p.plane is not None:
        n = np.abs(np.asarray(p.plane[1], dtype=float))
        if n.max() > 1 - 1e-9:
            return "SYMMETRY-" + "XYZ"[int(n.argmax())]
    return "SYMMETRY"


def _nmf_corners(spec: PatchSpec, dims, convention: str) -> tuple[list[int], list[int], list[int], list[int]]:
    """Block ijk (0-based) of the (start, end) corners, and the primary/secondary 1-based ranges."""
    d, a, b = face_axes(spec.face)
    pa, sa = (a, b) if convention == "2d" else _PRIMARY[spec.face]
    fix = face_layer(dims, spec.face)
    (a0, a1), (b0, b1) = spec.range
    lo = [0, 0, 0]
    hi = [0, 0, 0]
    lo[d] = hi[d] = fix
    lo[a], hi[a], lo[b], hi[b] = a0, a1, b0, b1
    return lo, hi, [lo[pa] + 1, hi[pa] + 1], [lo[sa] + 1, hi[sa] + 1]


def write_nmf(conn: Connectivity, path, *, overwrite: bool = False, convention: str = "3d") -> None:
    """Write a connectivity as a Neutral Map File (see the module docstring)."""
    if convention not in ("3d", "2d"):
        raise ConnectivityError(f"convention must be '3d' or '2d', got {convention!r}")
    if convention == "2d" and conn.ndim != 2:
        raise ConnectivityError("the 2-D face numbering needs a 2-D grid")
    target = check_target(path, overwrite=overwrite, replace_existing=False)
    number = {v: k for k, v in (NMF_FACES_2D if convention == "2d" else NMF_FACES_3D).items()}
    bar = "# " + "=" * 92
    rows = [f"# ===== Neutral Map File written by tfi_quat {__version__} "
            f"({'2-D' if convention == '2d' else '3-D'} face numbering) =====", bar,
            "# Block#    IDIM    JDIM    KDIM", "# " + "-" * 92, f"{len(conn.dims):8d}"]
    for n, d in enumerate(conn.dims):
        rows.append(f"{n + 1:8d}{d[0]:8d}{d[1]:8d}{d[2]:8d}")
    rows += [bar, "# Type              B1  F1     S1    E1     S2    E2     B2  F2     S1    E1     S2    E2  Swap",
             "# " + "-" * 92]
    for it in conn.interfaces:
        lo, hi, p1, s1 = _nmf_corners(it.master, conn.dims[it.master.block], convention)
        img = it.slave_index(np.array([lo, hi]))
        d2, a2, b2 = face_axes(it.slave.face)
        pa2, sa2 = (a2, b2) if convention == "2d" else _PRIMARY[it.slave.face]
        pa1 = face_axes(it.master.face)[1] if convention == "2d" else _PRIMARY[it.master.face][0]
        swap = abs(it.transform[pa1]) - 1 == sa2
        rows.append(f"{'ONE_TO_ONE':<18}{it.master.block + 1:5d}{number[it.master.face]:4d}"
                    f"{p1[0]:7d}{p1[1]:6d}{s1[0]:7d}{s1[1]:6d}"
                    f"{it.slave.block + 1:7d}{number[it.slave.face]:4d}"
                    f"{img[0][pa2] + 1:7d}{img[1][pa2] + 1:6d}{img[0][sa2] + 1:7d}{img[1][sa2] + 1:6d}"
                    f"  {'TRUE' if swap else 'FALSE'}")
    for p in conn.patches:
        _, _, pr, sr = _nmf_corners(p.spec, conn.dims[p.spec.block], convention)
        rows.append(f"{_type_name(p):<18}{p.spec.block + 1:5d}{number[p.spec.face]:4d}"
                    f"{pr[0]:7d}{pr[1]:6d}{sr[0]:7d}{sr[1]:6d}")
    with atomic_output(target, "w") as fh:
        fh.write("\n".join(rows) + "\n")


# ------------------------------------------------------------------- read
_INT = re.compile(r"[+-]?[0-9]+")


def _ints(tokens) -> list[int]:
    """Plain decimal integers (``int()`` alone would take ``1_000`` or non-ASCII digits)."""
    if not all(_INT.fullmatch(t) for t in tokens):
        raise ValueError("not an integer")
    return [int(t) for t in tokens]


def _lines(path: Path):
    text = read_text(path, ConnectivityError)
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].replace("\\", " ").strip()
        if line:
            yield n, line


def read_nmf(path, *, types=None, convention: str = "auto", grid=None) -> Connectivity:
    """Read a Neutral Map File (see the module docstring).

    Parameters
    ----------
    path : str or path-like
    types : dict, optional
        Extra boundary type names -> kind (wall, fixed, symmetry, free,
        collapsed, interface); they take precedence over the built-in table.
    convention : {"auto", "3d", "2d"}
        Face numbering.
    grid : Grid, optional
        Check the file's dimensions against the grid, and that the points of
        every ``ONE_TO_ONE`` coincide.

    Returns
    -------
    Connectivity
        Patches carry the file's type in ``name`` and ``origin="file"``;
        interfaces are put in canonical master/slave order.

    Raises
    ------
    ConnectivityError
        Naming the file and line: bad counts or dimensions, unknown face
        numbers or boundary types (``PATCHED`` non-matching interfaces are
        not supported), ranges out of bounds, ONE_TO_ONE sides that do not
        have the same size.
    """
    p = Path(os.fspath(path))
    if types:
        for k, v in types.items():
            if v not in KINDS + ("collapsed", "interface"):
                raise ConnectivityError(f"types: kind {v!r} for {k!r} is not one of "
                                        f"{', '.join(KINDS + ('collapsed', 'interface'))}")
    if convention not in ("auto", "3d", "2d"):
        raise ConnectivityError(f"convention must be 'auto', '3d' or '2d', got {convention!r}")
    lines = list(_lines(p))
    if not lines:
        raise ConnectivityError(f"{p}: empty Neutral Map File")
    ln, first = lines[0]
    try:
        (nblk,) = _ints(first.split())
        if nblk < 1:
            raise ValueError
    except ValueError:
        raise ConnectivityError(f"{p}:{ln}: expected the number of blocks, got {first!r}") from None
    if len(lines) < 1 + nblk:
        raise ConnectivityError(f"{p}: {nblk} block(s) announced, only {len(lines) - 1} line(s) follow")
    dims: list = [None] * nblk
    for ln, line in lines[1:1 + nblk]:
        try:
            v = _ints(line.split())
            if len(v) == 3:
                v.append(1)
            if len(v) != 4 or not 1 <= v[0] <= nblk or dims[v[0] - 1] is not None:
                raise ValueError
        except ValueError:
            raise ConnectivityError(f"{p}:{ln}: expected 'BLOCK IDIM JDIM [KDIM]' for a new block "
                                    f"1..{nblk}, got {line!r}") from None
        if not all(1 <= n <= MAX_DIM for n in v[1:]):
            raise ConnectivityError(f"{p}:{ln}: block {v[0]}: sizes must be from 1 to {MAX_DIM}, "
                                    f"got {' x '.join(map(str, v[1:]))}")
        dims[v[0] - 1] = tuple(v[1:])
    if grid is not None:    # the declared sizes against the grid, before anything is built from them
        try:
            check_dims(2 if all(d[2] == 1 for d in dims) else 3, dims, grid)
        except ConnectivityError as exc:
            raise ConnectivityError(f"{p}: {exc}") from None
    entries = []
    for ln, line in lines[1 + nblk:]:
        tok = line.split()
        kind = nmf_kind(tok[0], types)
        if kind is None:
            raise ConnectivityError(
                f"{p}:{ln}: unknown boundary type {tok[0]!r} (PATCHED/non-matching interfaces are not "
                "supported; map other names with types={'NAME': 'wall'|'fixed'|'symmetry'|'free'})")
        need = 13 if kind == "interface" else 7
        try:
            nums = _ints(tok[1:need])
            if len(nums) != need - 1:
                raise ValueError
        except ValueError:
            raise ConnectivityError(f"{p}:{ln}: {tok[0]} needs {need - 1} integers, got {line!r}") from None
        swap = False
        if kind == "interface" and len(tok) > 13:
            s = tok[13].strip("'\"").upper()
            if s not in ("TRUE", "FALSE", "T", "F", "1", "0", ".TRUE.", ".FALSE.", "YES", "NO"):
                raise ConnectivityError(f"{p}:{ln}: swap flag must be TRUE or FALSE, got {tok[13]!r}")
            swap = s in ("TRUE", "T", "1", ".TRUE.", "YES")
        entries.append((ln, tok[0].strip("'\""), kind, nums, swap))
    flat = all(d[2] == 1 for d in dims)
    if convention == "auto":
        used = [e[3][1] for e in entries] + [e[3][7] for e in entries if e[2] == "interface"]
        convention = "2d" if flat and used and max(used) <= 4 else "3d"
    ndim = 2 if flat else 3
    table = NMF_FACES_2D if convention == "2d" else NMF_FACES_3D
    table_inv = {v: f"face {k}" for k, v in table.items()}
    interfaces, patches, notes = [], [], []
    lines_of = {"interface": [], "patch": []}

    def side(ln, b, f, s1, e1, s2, e2):
        where = f"{p}:{ln}"
        if not 1 <= b <= nblk:
            raise ConnectivityError(f"{where}: block {b} does not exist ({nblk} block(s))")
        if f not in table:
            raise ConnectivityError(f"{where}: face {f} is not one of {sorted(table)} ({convention} numbering)")
        face = table[f]
        dm = dims[b - 1]
        d, a, bb = face_axes(face)
        pa, sa = (a, bb) if convention == "2d" else _PRIMARY[face]
        fix = face_layer(dm, face)
        start = [0, 0, 0]
        end = [0, 0, 0]
        start[d] = end[d] = fix
        start[pa], end[pa], start[sa], end[sa] = s1 - 1, e1 - 1, s2 - 1, e2 - 1
        for ax in (pa, sa):
            for v in (start[ax], end[ax]):
                if not 0 <= v < dm[ax]:
                    raise ConnectivityError(f"{where}: range {s1}-{e1},{s2}-{e2} on face {f} ({face}) of block "
                                            f"{b} exceeds its size {dm[0]} x {dm[1]} x {dm[2]}")
        rng = ((min(start[a], end[a]), max(start[a], end[a])), (min(start[bb], end[bb]), max(start[bb], end[bb])))
        return PatchSpec(b - 1, face, rng), face, start, end, pa, sa

    for ln, name, kind, nums, swap in entries:
        if kind != "interface":
            spec, face, *_ = side(ln, *nums[:6])
            if ndim == 2 and face in ("kmin", "kmax"):
                notes.append(f"{p}:{ln}: {name} on a k face of a 2-D grid ignored")
                continue
            k = "free" if kind == "collapsed" else kind
            patches.append(Patch(spec, k, name, kind == "collapsed", "file"))
            lines_of["patch"].append(ln)
            continue
        s_1, face1, st1, en1, pa1, sa1 = side(ln, *nums[:6])
        s_2, face2, st2, en2, pa2, sa2 = side(ln, *nums[6:12])
        pair = {pa1: sa2, sa1: pa2} if swap else {pa1: pa2, sa1: sa2}
        d1, d2 = face_axes(face1)[0], face_axes(face2)[0]
        t = [0, 0, 0]
        for ax1, ax2 in pair.items():
            n1, n2 = en1[ax1] - st1[ax1], en2[ax2] - st2[ax2]
            if abs(n1) != abs(n2):
                raise ConnectivityError(f"{p}:{ln}: ONE_TO_ONE sides differ in size along "
                                        f"{'IJK'[ax1]} of block {nums[0]} ({abs(n1) + 1} points) and "
                                        f"{'IJK'[ax2]} of block {nums[6]} ({abs(n2) + 1} points)")
            t[ax1] = (ax2 + 1) * (1 if (n1 >= 0) == (n2 >= 0) or n1 == 0 else -1)
        side1 = 1 if face_axis(face1)[1] else -1
        side2 = 1 if face_axis(face2)[1] else -1
        t[d1] = -side1 * side2 * (d2 + 1)
        T = np.zeros((3, 3), dtype=np.int64)
        for m, v in enumerate(t):
            T[abs(v) - 1, m] = 1 if v > 0 else -1
        d_, a_, b_ = face_axes(face1)
        mb = list(st1)
        mb[a_], mb[b_] = s_1.range[0][0], s_1.range[1][0]
        sb = T @ (np.array(mb) - np.array(st1)) + np.array(st2)
        try:
            it = Interface(s_1, s_2, tuple(t), tuple(mb), tuple(int(v) for v in sb))
        except ConnectivityError as exc:
            raise ConnectivityError(f"{p}:{ln}: {exc}") from None
        key1 = (it.master.block, face_index(it.master.face))
        key2 = (it.slave.block, face_index(it.slave.face))
        if key2 < key1 or (key1 == key2 and (it.slave.range[0][0], it.slave.range[1][0]) <
                           (it.master.range[0][0], it.master.range[1][0])):
            it = it.reversed()
        if ndim == 2 and it.master.face in ("kmin", "kmax"):
            notes.append(f"{p}:{ln}: ONE_TO_ONE on k faces of a 2-D grid ignored")
            continue
        interfaces.append(it)
        lines_of["interface"].append(ln)
    try:
        conn = Connectivity(interfaces, patches, ndim, dims, notes)
    except ConnectivityError as exc:
        raise ConnectivityError(f"{p}: {exc}") from None
    overlaps = conn.overlaps()
    if overlaps:
        first, second = overlaps[0]

        def line(item):
            return lines_of["patch" if item[0] == "patch" else "interface"][item[1]]
        spec = conn.item_spec(second)
        raise ConnectivityError(f"{p}:{line(second)}: overlaps the entry on line {line(first)} "
                                f"(block {spec.block + 1} face {spec.face}, {table_inv[spec.face]} in the file)")
    if grid is not None:
        from .search import check_interfaces
        check_interfaces(conn, grid, lambda n: f"{p}:{lines_of['interface'][n]}: ONE_TO_ONE")
    return conn.sorted()
