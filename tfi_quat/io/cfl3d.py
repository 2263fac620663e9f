"""CFL3D grid files and input-deck sections.

NASA's CFL3D (v6) reads a grid as a *PLOT3D-type* file when the input
deck's ``ngrid`` is negative.  The facts this module relies on, from the
CFL3D Version 5.0 User's Manual (valid for v6; chapter 5 "File Formats",
5.1.1 and 5.1.2; chapter 3, line types LT8, LT13 to LT19 and LT24 to LT26;
chapter 6, boundary types) and the v6.7 source (``libs/rp3d.F``,
``dist/setup.F``, ``libs/global.F``):

- the file is Fortran unformatted sequential: one record with the block
  count, one record with ``idim jdim kdim`` of every block, then one record
  per block with all x, all y, all z, ``i`` fastest;
- coordinates are read as the reals CFL3D was compiled with (float64 in the
  default double-precision build: "grid not written in same precision" is
  its read error), with the compiler's record markers (4 bytes for
  gfortran and ifort) in the machine's byte order (little-endian on x86-64
  and aarch64);
- a 2-D case (``i2d = 1``) needs ``idim = 2``: the grid repeated on two
  planes, each planar; the manual recommends a plane distance of 1;
- with ``ialph = 0`` the angle of attack is measured in the x-z plane (z
  up), so a 2-D grid lies in the x-z plane;
- the indices ``(i, j, k)`` must form a right-handed system with
  ``(x, y, z)``, else CFL3D stops; ``k`` is best the body-normal direction,
  ``j`` the streamwise one, ``i`` the spanwise one.

Index mapping
-------------
A 2-D grid (``ndim`` 2, our ``(i, j)`` in the x-y plane) is written as
CFL3D ``(i, j, k) = (span, our i, our j)``, ``(X, Y, Z) = (x, -s, y)`` with
``s = 0`` on the plane ``i = 1`` and ``s = 1`` on ``i = 2``: the span
coordinate Y decreases with ``i``.  The map ``(x, y, z) -> (x, -z, y)`` is a
rotation, so a block whose cells turn counter-clockwise in x-y (positive
areas, as every shipped 2-D grid) becomes a right-handed CFL3D block; the
writer refuses a clockwise one, naming it.  A 3-D grid is written as it is:
CFL3D ``(i, j, k)`` = ours, ``(X, Y, Z)`` = ours (``ialph = 1`` in the deck
when y is up).

:func:`read` undoes the mapping: a file whose blocks all have ``idim = 2``
with equal x and z on both planes and one constant, decreasing Y per plane
is a 2-D grid (``ndim=3`` reads it as it is); the result is the original
2-D grid bit for bit (z = 0, ``nk = 1``).

:func:`input_deck` turns a :class:`~tfi_quat.topology.Connectivity` into
the deck's dimension, boundary-segment and 1-1 blocking sections with the
same mapping.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConnectivityError, GridFormatError, GridValueError
from ..grid import Block, Grid, face_axes
from . import register
from . import plot3d
from .plot3d import Plot3DFormat

__all__ = ["CFL3DFormat", "PLOT3D_VARIANT", "BCTYPES", "COLLAPSED_BCTYPE", "SPAN_BCTYPE", "to_cfl3d",
           "from_cfl3d", "read", "write", "input_deck", "bctype_table"]

#: the Plot3D variant CFL3D reads (PLOT3D-type grid, ``ngrid < 0``)
PLOT3D_VARIANT = Plot3DFormat(encoding="fortran", endian="<", precision=8, ndim=3, multiblock=True,
                              iblank=False, records="block", int_size=4, marker_size=4)

#: longest record 4-byte markers frame (bytes)
_MAX_RECORD = (1 << 31) - 1
#: CFL3D boundary types (``bctype``) written by :func:`input_deck` for each patch kind
BCTYPES = {"wall": 1005, "fixed": 1003, "symmetry": 1001, "free": 1002}
#: bctype of collapsed patches (singular axis, extrapolation; needs no metrics there)
COLLAPSED_BCTYPE = 1013
#: bctype of the two span faces of a 2-D grid (the manual's usual choice; any works with i2d = 1)
SPAN_BCTYPE = 1002
#: bctypes :func:`input_deck` writes: those without auxiliary data, and 2004 (no-slip wall,
#: written with its two data values Twtype = 0 (adiabatic) and Cq = 0 (no flow through))
_BCTYPE_NAMES = {1000: "free stream", 1001: "symmetry plane", 1002: "extrapolation",
                 1003: "inflow/outflow, far field", 1005: "inviscid surface",
                 1008: "constant enthalpy and entropy inflow", 1011: "singular axis, half plane",
                 1012: "singular axis, full plane", 1013: "singular axis, partial plane",
                 2004: "no-slip wall"}


@dataclass(frozen=True)
class CFL3DFormat:
    """A grid file written for CFL3D (``grid.source_format`` of a grid read with ``target="cfl3d"``).

    Attributes
    ----------
    ndim : {2, 3}
        The grid's dimension: 2 = stored as two ``i`` planes with the
        mapping of the module docstring; 3 = stored as it is.
    """

    ndim: int = 3

    def __post_init__(self):
        if self.ndim not in (2, 3):
            raise GridFormatError(f"CFL3D format: ndim={self.ndim!r} is not 2 or 3")

    def describe(self) -> str:
        """One line for people."""
        layout = ("2-D grid as two i planes (CFL3D X = x, Z = y, Y = 0 and -1)" if self.ndim == 2
                  else "3-D grid as it is")
        return f"CFL3D PLOT3D-type grid ({PLOT3D_VARIANT.describe()}); {layout}"


# ---------------------------------------------------------------- mapping

def _signed_area(xyz: np.ndarray) -> float:
    """Sum of the signed cell areas of a 2-D block (x-y), from its boundary loop alone.

    The shoelace sums of neighbouring cells cancel on their shared edges, so
    the total is the shoelace sum around the block's boundary (i along j = 0,
    j along i = ni - 1, back along j = nj - 1 and i = 0).
    """
    p = xyz[:, :, 0, :2]
    loop = np.concatenate([p[:, 0], p[-1, 1:], p[-2::-1, -1], p[0, -2:0:-1]])
    x, y = loop[:, 0], loop[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def to_cfl3d(grid: Grid) -> Grid:
    """The grid as CFL3D indexes it (3-D, the mapping of the module docstring).

    Parameters
    ----------
    grid : Grid

    Returns
    -------
    Grid
        3-D.  From a 2-D grid: new blocks of shape ``(2, ni, nj, 3)``
        (CFL3D ``idim, jdim, kdim = 2, ni, nj``) with X = x, Y = 0 and -1,
        Z = y; a 3-D grid is returned as it is (the same object).
        ``source_path`` is kept.

    Raises
    ------
    GridValueError
        Not a Grid, a 2-D block with one point in i or j, or a 2-D block
        whose cells turn clockwise in x-y (CFL3D would refuse it as
        left-handed; reverse its i or j index).
    """
    if not isinstance(grid, Grid):
        raise GridValueError(f"to_cfl3d needs a Grid, got {type(grid).__name__}")
    if grid.ndim == 3:
        return grid
    blocks = []
    for n, b in enumerate(grid):
        ni, nj, _ = b.dims
        if ni < 2 or nj < 2:
            raise GridValueError(f"block {n + 1}: {ni} x {nj} points; CFL3D needs at least 2 in each "
                                 "index direction")
        area = _signed_area(b.xyz)
        if not area > 0:
            raise GridValueError(
                f"block {n + 1}: its cells turn clockwise in x-y (net signed area {area:.6g}); mapped "
                "to CFL3D's x-z plane it would be left-handed, which CFL3D refuses (manual 5.1.2): "
                "reverse its i or j index")
        out = np.empty((2, ni, nj, 3), dtype=np.float64, order="F")
        for s, span in enumerate((0.0, -1.0)):
            out[s, :, :, 0] = b.xyz[:, :, 0, 0]
            out[s, :, :, 1] = span
            out[s, :, :, 2] = b.xyz[:, :, 0, 1]
        blocks.append(Block(out, name=b.name))
    return Grid(blocks, 3, source_path=grid.source_path)


def _mapped_2d(block: Block) -> bool:
    """Whether a block holds a 2-D grid mapped by :func:`to_cfl3d` (two equal planes, Y falling)."""
    if block.dims[0] != 2:
        return False
    a, b = block.xyz[0], block.xyz[1]
    if not (np.array_equal(a[..., 0], b[..., 0]) and np.array_equal(a[..., 2], b[..., 2])):
        return False
    y0, y1 = a[0, 0, 1], b[0, 0, 1]
    return bool(y1 < y0 and np.all(a[..., 1] == y0) and np.all(b[..., 1] == y1))


def from_cfl3d(grid: Grid, ndim: int | None = None, where: str = "grid") -> Grid:
    """Undo :func:`to_cfl3d`.

    Parameters
    ----------
    grid : Grid
        3-D, as CFL3D indexes it.
    ndim : {2, 3}, optional
        2: every block must be a mapped 2-D block (error otherwise); 3: the
        grid as it is.  Default: 2 when every block is one, else 3.
    where : str
        Name for messages (the file).

    Returns
    -------
    Grid
        ``ndim`` 2: blocks ``(ni, nj, 1, 3)`` with x = X, y = Z of the plane
        ``i = 1`` and z = 0; ``ndim`` 3: ``grid`` itself.

    Raises
    ------
    GridValueError
        Not a 3-D Grid, or a bad ``ndim``.
    GridFormatError
        ``ndim=2`` and a block is not two equal planes of constant,
        decreasing span coordinate (the block is named).
    """
    if ndim not in (None, 2, 3):
        raise GridValueError(f"ndim must be 2, 3 or None, got {ndim!r}")
    if not isinstance(grid, Grid):
        raise GridValueError(f"from_cfl3d needs a Grid, got {type(grid).__name__}")
    if grid.ndim != 3:
        raise GridValueError(f"from_cfl3d needs the 3-D grid CFL3D indexes, got a {grid.ndim}-D grid")
    mapped = [_mapped_2d(b) for b in grid]
    if ndim == 3 or (ndim is None and not all(mapped)):
        return grid
    if not all(mapped):
        n = mapped.index(False)
        d = grid[n].dims
        raise GridFormatError(
            f"{where}: block {n + 1} ({d[0]} x {d[1]} x {d[2]}) is not a 2-D grid written for CFL3D "
            "(two i planes with equal x and z, y constant on each and decreasing with i); "
            "read it with ndim=3")
    blocks = []
    for b in grid:
        _, nj, nk = b.dims
        xyz = np.zeros((nj, nk, 1, 3), dtype=np.float64, order="F")
        xyz[:, :, 0, 0] = b.xyz[0, :, :, 0]
        xyz[:, :, 0, 1] = b.xyz[0, :, :, 2]
        blocks.append(Block(xyz, name=b.name))
    return Grid(blocks, 2, source_format=CFL3DFormat(2), source_path=grid.source_path)


# ---------------------------------------------------------------- files

def write(path, grid: Grid, *, like=None, overwrite: bool = False, **options) -> None:
    """Write the grid file CFL3D reads, atomically (see the module docstring).

    Parameters
    ----------
    path : str or path-like
    grid : Grid
        2-D grids are mapped (two ``i`` planes, x-z plane); 3-D grids are
        written as they are.  IBLANK is not written (CFL3D takes blanking
        from its overlap file).
    like : CFL3DFormat, optional
        Accepted for :func:`tfi_quat.io.write`'s ``like=``; the file is the
        same either way.
    overwrite : bool
        Allow writing over ``grid.source_path``.
    **options
        None are accepted: CFL3D reads one variant (any option is an error).

    Raises
    ------
    GridValueError
        See :func:`to_cfl3d`.
    GridFormatError
        An option given, ``like`` not a CFL3D format, a block too large for
        one record framed by 4-byte markers (2**31 - 1 bytes: 89 M points).
    OverwriteError
        ``path`` is the grid's own input file and ``overwrite`` is False.
    """
    if like is not None and not isinstance(like, CFL3DFormat):
        raise GridFormatError(f"{path}: like= must be a CFL3DFormat for a CFL3D file, "
                              f"got {type(like).__name__}")
    if options:
        raise GridFormatError(f"{path}: a CFL3D grid file has one variant ({PLOT3D_VARIANT.describe()}); "
                              f"the option(s) {', '.join(sorted(options))} do not apply")
    mapped = to_cfl3d(grid)
    for n, b in enumerate(mapped):
        length = 3 * 8 * b.npoints
        if length > _MAX_RECORD:
            raise GridFormatError(f"{path}: block {n + 1} ({b.npoints:,} points) needs a record of "
                                  f"{length:,} bytes, more than 4-byte record markers frame "
                                  f"({_MAX_RECORD:,}); split the block")
    plot3d.write(path, mapped, like=PLOT3D_VARIANT, overwrite=overwrite, iblank=False)


def read(path, *, ndim: int | None = None, allow_nonfinite: bool = False,
         max_points: int | None = None) -> Grid:
    """Read a grid file written for CFL3D, undoing the 2-D mapping.

    Parameters
    ----------
    path : str or path-like
    ndim : {2, 3}, optional
        See :func:`from_cfl3d` (default: 2 when every block is a mapped 2-D
        block, else 3).
    allow_nonfinite, max_points
        As for :func:`tfi_quat.io.plot3d.read`.

    Returns
    -------
    Grid
        ``source_format`` a :class:`CFL3DFormat`, ``source_path`` the path.

    Raises
    ------
    GridFormatError
        The file is not exactly the Plot3D variant CFL3D reads (Fortran
        unformatted, little-endian, 4-byte markers, int32, float64,
        multi-block, 3-D, one record per block), or ``ndim=2`` and a block
        is not a mapped 2-D block; the message names the file.
    GridValueError
        ``ndim`` is not 2, 3 or None.
    """
    if ndim not in (None, 2, 3):
        raise GridValueError(f"ndim must be 2, 3 or None, got {ndim!r}")
    try:
        raw = plot3d.read(path, format=PLOT3D_VARIANT, allow_nonfinite=allow_nonfinite,
                          max_points=max_points)
    except GridFormatError as exc:
        raise GridFormatError(f"{path}: not a CFL3D grid file (CFL3D reads a PLOT3D-type grid: "
                              f"{PLOT3D_VARIANT.describe()}): {_reason(str(exc), path)}; "
                              "'tfi-quat convert IN OUT --for cfl3d' writes one") from None
    out = from_cfl3d(raw, ndim, where=str(path))
    out.source_format = CFL3DFormat(out.ndim)
    out.source_path = raw.source_path
    return out


def _reason(msg: str, path) -> str:
    """The reader's reason without the path and the variant the message above already names."""
    for prefix in (f"{path}: ", f"not a {PLOT3D_VARIANT.describe()} Plot3D file: "):
        if msg.startswith(prefix):
            msg = msg[len(prefix):]
    return msg


# ---------------------------------------------------------------- input deck

#: our face -> CFL3D face name of a 2-D grid (CFL3D j = our i, k = our j)
_FACE_2D = {"imin": "j0", "imax": "jdim", "jmin": "k0", "jmax": "kdim"}
_FACE_3D = {"imin": "i0", "imax": "idim", "jmin": "j0", "jmax": "jdim", "kmin": "k0", "kmax": "kdim"}
_CFL3D_FACES = ("i0", "idim", "j0", "jdim", "k0", "kdim")
#: running indices of each CFL3D face, in the deck's column order
_RUNNING = {"i": ("j", "k"), "j": ("i", "k"), "k": ("i", "j")}


def _axis_map(ndim: int) -> tuple[int, ...]:
    """CFL3D index number (0 = i, 1 = j, 2 = k) of our axis 0, 1 (and 2)."""
    return (1, 2) if ndim == 2 else (0, 1, 2)


def _cfl3d_point(ijk, ndim: int, span: int) -> list[int]:
    """1-based CFL3D (i, j, k) of our 0-based (i, j, k); ``span`` is the i of a 2-D grid (1 or 2)."""
    if ndim == 2:
        return [span, int(ijk[0]) + 1, int(ijk[1]) + 1]
    return [int(v) + 1 for v in ijk]


def _segment(spec, ndim: int):
    """(CFL3D face, (sta1, end1, sta2, end2)) of a patch or interface side, 1-based."""
    (a0, a1), (b0, b1) = spec.range
    face = (_FACE_2D if ndim == 2 else _FACE_3D)[spec.face]
    if ndim == 2:
        # our face runs over one index (a); CFL3D's adds the span i (1..2), listed first
        return face, (1, 2, a0 + 1, a1 + 1)
    return face, (a0 + 1, a1 + 1, b0 + 1, b1 + 1)


def _has_cells(spec, ndim: int) -> bool:
    (a0, a1), (b0, b1) = spec.range
    return a1 > a0 and (ndim == 2 or b1 > b0)


def bctype_table(bctypes: dict | None = None) -> dict:
    """The bctype of every patch kind: :data:`BCTYPES` and ``"collapsed"``, with overrides.

    Parameters
    ----------
    bctypes : dict, optional
        Kind -> bctype; kinds ``"wall"``, ``"fixed"``, ``"symmetry"``,
        ``"free"``, ``"collapsed"``; bctypes 1000, 1001, 1002, 1003, 1005,
        1008, 1011, 1012, 1013 (no auxiliary data) and 2004 (no-slip wall).

    Raises
    ------
    ConnectivityError
        An unknown kind or a bctype outside that list.
    """
    table = dict(BCTYPES)
    for kind, value in (bctypes or {}).items():
        if kind not in BCTYPES and kind != "collapsed":
            raise ConnectivityError(f"bctypes: unknown patch kind {kind!r}: expected one of "
                                    f"{', '.join(list(BCTYPES) + ['collapsed'])}")
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) not in _BCTYPE_NAMES:
            raise ConnectivityError(f"bctypes: {kind}={value!r} is not a bctype this writer supports: "
                                    + ", ".join(f"{k} ({v})" for k, v in _BCTYPE_NAMES.items()))
        table[kind] = int(value)
    table.setdefault("collapsed", COLLAPSED_BCTYPE)
    return table


def input_deck(conn, bctypes: dict | None = None) -> str:
    """The CFL3D input-deck sections for a grid's connectivity, as text.

    Prints, with the mapping of :func:`to_cfl3d` (stated in ``#`` comment
    lines, which are not part of the deck): the grid dimensions (LT8), the
    boundary-condition segments (LT13 to LT19: the interfaces as
    ``bctype 0`` segments, each patch with the bctype of its kind) and the
    1-1 blocking data (LT24 to LT26: one line per interface side, ranges
    from the first corner to the last, ``isva1``/``isva2`` the varying
    indices, 1 = i, 2 = j, 3 = k).  Header lines are written as CFL3D
    reads them (it skips them), so the sections can be pasted into a deck.

    Parameters
    ----------
    conn : tfi_quat.topology.Connectivity
    bctypes : dict, optional
        Kind -> bctype overrides of :data:`BCTYPES` (``"wall"``,
        ``"fixed"``, ``"symmetry"``, ``"free"``, and ``"collapsed"`` for
        collapsed patches, default 1013), e.g. ``{"wall": 2004}`` for a
        viscous run.

    Returns
    -------
    str

    Raises
    ------
    ConnectivityError
        An unknown kind or an unsupported bctype.
    """
    table = bctype_table(bctypes)
    nd = conn.ndim
    ngrid = len(conn.dims)
    segs: dict[tuple[int, str], list] = {(n, f): [] for n in range(ngrid) for f in _CFL3D_FACES}
    for it in conn.interfaces:
        for side in (it.master, it.slave):
            face, rng = _segment(side, nd)
            segs[(side.block, face)].append((rng, 0, "1-1 interface"))
    for p in conn.patches:
        if not _has_cells(p.spec, nd):
            continue
        face, rng = _segment(p.spec, nd)
        key = "collapsed" if p.collapsed and p.kind == "free" else p.kind
        segs[(p.spec.block, face)].append((rng, table[key], key))
    for n, (ni, nj, nk) in enumerate(conn.dims):
        if nd == 2:
            for face in ("i0", "idim"):
                segs[(n, face)].append(((1, ni, 1, nj), SPAN_BCTYPE, "span"))
    for key in segs:
        segs[key].sort(key=lambda s: (s[0][2], s[0][0], s[0][3], s[0][1]))

    lines = [f"# CFL3D input-deck sections written by tfi_quat: {ngrid} grid(s), "
             f"{len(conn.interfaces)} 1-1 interface(s); '#' lines are not part of the deck"]
    if nd == 2:
        lines.append("# index mapping (2-D): CFL3D (i, j, k) = (span, our i, our j); X = x, Z = y, "
                     "Y = 0 on i = 1 and -1 on i = 2; deck: ngrid < 0 (PLOT3D-type grid), i2d = 1, "
                     "ialph = 0")
    else:
        lines.append("# index mapping (3-D): CFL3D (i, j, k) = our (i, j, k), (X, Y, Z) = (x, y, z); "
                     "deck: ngrid < 0 (PLOT3D-type grid); ialph = 1 if y is up")
    used = sorted({(s[2], s[1]) for v in segs.values() for s in v})
    lines.append("# bctypes: " + "; ".join(f"{what} {bc}" + (f" ({_BCTYPE_NAMES[bc]})" if bc else "")
                                          for what, bc in used))
    if any(s[1] == 2004 for v in segs.values() for s in v):
        lines.append("# 2004 needs ivisc > 0 in the wall-normal direction (LT7); Twtype 0 = adiabatic, "
                     "Cq 0 = no flow through the wall")

    def row(values, width=10):
        return "".join(f"{v:>{width}}" for v in values)

    lines.append("# LT8 grid dimensions")
    lines.append(row(("idim", "jdim", "kdim"), 8))
    for ni, nj, nk in conn.dims:
        lines.append(row((2, ni, nj) if nd == 2 else (ni, nj, nk), 8))
    lines.append("# LT13-LT19 boundary condition segments")
    lines.append(row(("grid", "nbci0", "nbcidim", "nbcj0", "nbcjdim", "nbck0", "nbckdim", "iovrlp")))
    for n in range(ngrid):
        lines.append(row([n + 1] + [len(segs[(n, f)]) for f in _CFL3D_FACES] + [0]))
    for face in _CFL3D_FACES:
        r1, r2 = _RUNNING[face[0]]
        lines.append(f"{face + ':':<6}" + row(("grid", "segment", "bctype", f"{r1}sta", f"{r1}end",
                                                 f"{r2}sta", f"{r2}end", "ndata"))[6:])
        for n in range(ngrid):
            for m, (rng, bc, _) in enumerate(segs[(n, face)]):
                ndata = 2 if bc == 2004 else 0
                lines.append(row((n + 1, m + 1, bc) + tuple(rng) + (ndata,)))
                if ndata:
                    lines.append(row(("twtype", "cq"), 20))
                    lines.append(row(("0.", "0."), 20))
    lines.append("# LT24-LT26 1-1 blocking data (first side: the interface's master, ascending)")
    lines.append("   1-1 blocking data:")
    lines.append("      nbli")
    lines.append(row((len(conn.interfaces),)))
    head = " number   grid     :    ista   jsta   ksta   iend   jend   kend  isva1  isva2"
    sides = ([], [])
    amap = _axis_map(nd)
    for m, it in enumerate(conn.interfaces):
        d, a, b = face_axes(it.master.face)
        running = (a,) if nd == 2 else (a, b)
        begin, end = it.point_range
        dbegin, dend = it.point_range_donor
        T = it.matrix
        # side 1: the master's running indices; side 2: the slave index each one runs along
        isva_m = [amap[ax] + 1 for ax in running]
        isva_s = [amap[int(np.abs(T[:, ax]).argmax())] + 1 for ax in running]
        if nd == 2:
            isva_m, isva_s = [1] + isva_m, [1] + isva_s
        for out, blk, p0, p1, isva in ((sides[0], it.master.block, begin, end, isva_m),
                                       (sides[1], it.slave.block, dbegin, dend, isva_s)):
            c0, c1 = _cfl3d_point(p0, nd, 1), _cfl3d_point(p1, nd, 2)
            out.append(f"{m + 1:>7}{blk + 1:>7}" + " " * 6 + "".join(f"{v:>7}" for v in c0 + c1 + isva))
    for side in sides:
        lines.append(head)
        lines.extend(side)
    return "\n".join(lines) + "\n"


register("cfl3d", (), read, write, CFL3DFormat)
