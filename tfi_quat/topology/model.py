"""Connectivity data model: :class:`Interface`, :class:`Patch`, :class:`Connectivity`.

Index conventions
-----------------
Everything here is 0-based and inclusive.  A face's two *running* indices are
the block's other two indices in order (imin/imax -> (j, k), jmin/jmax -> (i, k),
kmin/kmax -> (i, j)), as in :meth:`tfi_quat.grid.Block.face` and
:class:`tfi_quat.spec.PatchSpec`.

An interface maps master block indices to slave block indices with a CGNS
``Transform`` ``(t1, t2, t3)``: master index direction ``m`` (1 = i, 2 = j,
3 = k) runs along slave direction ``|t_m|``, in the same sense when
``t_m > 0``.  With ``T`` the signed permutation matrix (``T[|t_m|-1, m-1] =
sign(t_m)``)::

    ijk_slave = T @ (ijk_master - master_begin) + slave_begin

``master_begin`` is the block index of the first corner of the master range
and ``slave_begin`` is its partner.  The face-normal entry follows CGNS: it
is +-(normal direction of the slave face), with the sign that continues the
master's index space through the interface (imax -> imin: +, imax -> imax: -).
In 2-D the third entry is always ``+3`` (k -> k; both blocks have nk = 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConnectivityError
from ..grid import face_axes, face_axis, face_cells, face_ijk, face_index, face_shape, faces_of
from ..spec import PatchSpec

__all__ = ["Interface", "Patch", "Connectivity", "FaceMap", "KINDS", "MAX_DIM", "check_dims"]

#: patch kinds: prescribed (wall, fixed), derived (symmetry, free)
KINDS = ("wall", "fixed", "symmetry", "free")
#: largest block dimension a connectivity may declare (a Plot3D int32 header's limit)
MAX_DIM = 2**31 - 1
#: priority where patches meet at a point (docs/method.md §3.3: wall beats fixed beats derived)
_PRIORITY = {"wall": 0, "fixed": 1, "symmetry": 2, "free": 3}


def _signed_perm(transform) -> np.ndarray:
    t = tuple(int(v) for v in transform)
    if len(t) != 3 or sorted(abs(v) for v in t) != [1, 2, 3]:
        raise ConnectivityError(f"Transform {list(transform)} is not a signed permutation of (1, 2, 3)")
    T = np.zeros((3, 3), dtype=np.int64)
    for m, v in enumerate(t):
        T[abs(v) - 1, m] = 1 if v > 0 else -1
    return T


def check_dims(ndim: int, dims, grid) -> None:
    """Raise :class:`ConnectivityError` unless ``grid`` is ``ndim``-D with block dimensions ``dims``.

    The file readers call it as soon as they have read the declared sizes,
    before they build (or allocate) anything from them.
    """
    if grid.ndim != ndim:
        raise ConnectivityError(f"connectivity is for a {ndim}-D grid, the grid is {grid.ndim}-D")
    if len(grid) != len(dims):
        raise ConnectivityError(f"connectivity is for {len(dims)} block(s), the grid has {len(grid)}")
    for n, (b, d) in enumerate(zip(grid, dims)):
        if tuple(b.dims) != tuple(d):
            raise ConnectivityError(f"block {n + 1}: connectivity is for {d[0]} x {d[1]} x {d[2]}, "
                                    f"the grid block is {b.dims[0]} x {b.dims[1]} x {b.dims[2]}")


@dataclass(frozen=True)
class Interface:
    """A point-matched interface: a rectangle of a master face coincides with one of a slave face.

    Attributes
    ----------
    master, slave : PatchSpec
        Explicit (0-based, inclusive) ranges over each face's running indices.
        The slave range is stored ascending; which corner matches which is
        given by the transform.
    transform : tuple of 3 int
        CGNS ``Transform`` (see the module docstring); in 2-D the third entry is +3.
    master_begin : tuple of 3 int
        Block indices ``(i, j, k)`` of the master range's first corner
        (``range[0][0], range[1][0]`` on the face).
    slave_begin : tuple of 3 int
        Block indices of the slave point that coincides with ``master_begin``.

    The master is the lower ``(block, face)``; for a self-matching face (a
    C-grid wake cut) the master is the part that starts first.  Derived data
    is computed on the master and copied to the slave (docs/method.md §3.7).
    """

    master: PatchSpec
    slave: PatchSpec
    transform: tuple[int, int, int]
    master_begin: tuple[int, int, int]
    slave_begin: tuple[int, int, int]

    def __post_init__(self):
        for name in ("master", "slave"):
            s = getattr(self, name)
            if not isinstance(s, PatchSpec) or s.range is None:
                raise ConnectivityError(f"interface {name} must be a PatchSpec with an explicit range, got {s!r}")
        object.__setattr__(self, "transform", tuple(int(v) for v in self.transform))
        object.__setattr__(self, "master_begin", tuple(int(v) for v in self.master_begin))
        object.__setattr__(self, "slave_begin", tuple(int(v) for v in self.slave_begin))
        _signed_perm(self.transform)
        (a0, a1), (b0, b1) = self.master.range
        d, a, b = face_axes(self.master.face)
        if self.master_begin[a] != a0 or self.master_begin[b] != b0:
            raise ConnectivityError(f"interface {self.master} -> {self.slave}: master_begin "
                                    f"{self.master_begin} is not the first corner of the master range")
        # the image of the master range must be the slave range, on the slave face
        img = self.slave_index(np.array(self.point_range))
        ds, sa, sb = face_axes(self.slave.face)
        (c0, c1), (e0, e1) = self.slave.range
        lo, hi = img.min(axis=0), img.max(axis=0)
        if (lo[ds] != hi[ds] or lo[sa] != c0 or hi[sa] != c1 or lo[sb] != e0 or hi[sb] != e1
                or int(np.abs(_signed_perm(self.transform)[:, d]).argmax()) != ds):
            raise ConnectivityError(
                f"interface {self.master} -> {self.slave}: Transform {list(self.transform)} maps the "
                f"master range onto block indices {lo.tolist()}..{hi.tolist()}, not onto the slave range")

    # --------------------------------------------------------------- ranges
    @property
    def point_range(self) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
        """Master range as block indices ``(begin, end)``, 0-based, ascending."""
        (a0, a1), (b0, b1) = self.master.range
        d, a, b = face_axes(self.master.face)
        end = list(self.master_begin)
        end[a], end[b] = a1, b1
        return self.master_begin, tuple(end)

    @property
    def point_range_donor(self) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
        """Slave block indices of the master ``begin`` and ``end`` (CGNS ``PointRangeDonor``, may descend)."""
        img = self.slave_index(np.array(self.point_range))
        return tuple(int(v) for v in img[0]), tuple(int(v) for v in img[1])

    @property
    def is_self(self) -> bool:
        """True for a block matching itself (wake cut, periodic seam)."""
        return self.master.block == self.slave.block

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 signed permutation matrix ``T`` of the transform."""
        return _signed_perm(self.transform)

    # -------------------------------------------------------------- mapping
    def slave_index(self, ijk_master) -> np.ndarray:
        """Slave block indices of master block indices.

        Parameters
        ----------
        ijk_master : array_like of int, shape (..., 3)
            0-based ``(i, j, k)`` on the master block.

        Returns
        -------
        ndarray of int64, shape (..., 3)
        """
        x = np.asarray(ijk_master, dtype=np.int64)
        T = self.matrix
        return (x - np.asarray(self.master_begin)) @ T.T + np.asarray(self.slave_begin)

    def master_index(self, ijk_slave) -> np.ndarray:
        """Master block indices of slave block indices (inverse of :meth:`slave_index`)."""
        x = np.asarray(ijk_slave, dtype=np.int64)
        T = self.matrix
        return (x - np.asarray(self.slave_begin)) @ T + np.asarray(self.master_begin)

    def inverse_transform(self) -> tuple[int, int, int]:
        """The Transform of the same interface seen from the slave side."""
        inv = [0, 0, 0]
        for m, v in enumerate(self.transform):
            inv[abs(v) - 1] = (m + 1) * (1 if v > 0 else -1)
        return tuple(inv)

    def reversed(self) -> "Interface":
        """The same interface with master and slave exchanged."""
        (c0, _), (e0, _) = self.slave.range
        ds, sa, sb = face_axes(self.slave.face)
        begin = list(self.slave_begin)
        begin[sa], begin[sb] = c0, e0
        begin = tuple(begin)
        return Interface(self.slave, self.master, self.inverse_transform(), begin,
                         tuple(int(v) for v in self.master_index(np.array(begin))))

    def __str__(self) -> str:
        t = ",".join(f"{v:+d}" for v in self.transform)
        return f"{self.master} -> {self.slave} [{t}]"

    @staticmethod
    def from_face_map(master: PatchSpec, slave_face: str, M, off, master_dims, slave_dims,
                      slave_block: int) -> "Interface":
        """Build an interface from an affine map of face running indices.

        ``q = M @ p + off`` maps master face indices ``p = (a, b)`` to slave
        face indices ``q``; ``M`` is a 2x2 signed permutation.
        """
        M = np.asarray(M, dtype=np.int64)
        off = np.asarray(off, dtype=np.int64)
        dm, am, bm = face_axes(master.face)
        ds, as_, bs = face_axes(slave_face)
        sax = (as_, bs)
        t = [0, 0, 0]
        for u, ax in enumerate((am, bm)):
            v = int(np.abs(M[:, u]).argmax())
            t[ax] = int(M[v, u]) * (sax[v] + 1)
        side_m = 1 if face_axis(master.face)[1] else -1
        side_s = 1 if face_axis(slave_face)[1] else -1
        t[dm] = -side_m * side_s * (ds + 1)
        (a0, a1), (b0, b1) = master.range
        p0 = np.array([a0, b0])
        p1 = np.array([a1, b1])
        q0, q1 = M @ p0 + off, M @ p1 + off
        srange = ((int(min(q0[0], q1[0])), int(max(q0[0], q1[0]))),
                  (int(min(q0[1], q1[1])), int(max(q0[1], q1[1]))))
        mb = tuple(int(v) for v in face_ijk(master_dims, master.face, ((a0, a0), (b0, b0)))[0, 0])
        c0, e0 = (int(v) for v in q0)
        sb = tuple(int(v) for v in face_ijk(slave_dims, slave_face, ((c0, c0), (e0, e0)))[0, 0])
        return Interface(master, PatchSpec(slave_block, slave_face, srange), tuple(t), mb, sb)

    def face_map_matrix(self) -> tuple[np.ndarray, np.ndarray]:
        """``(M, off)`` with ``q = M @ p + off`` from master to slave face running indices."""
        dm, am, bm = face_axes(self.master.face)
        ds, as_, bs = face_axes(self.slave.face)
        T = self.matrix
        M = np.array([[T[as_, am], T[as_, bm]], [T[bs, am], T[bs, bm]]], dtype=np.int64)
        p0 = np.array([self.master_begin[am], self.master_begin[bm]])
        q0 = np.array([self.slave_begin[as_], self.slave_begin[bs]])
        return M, q0 - M @ p0


@dataclass(frozen=True)
class Patch:
    """A rectangular part of a block face that is not an interface, with its kind.

    Attributes
    ----------
    spec : PatchSpec
        Explicit range (0-based, inclusive).
    kind : str
        ``"wall"`` (moving, prescribed), ``"fixed"`` (does not move),
        ``"symmetry"`` (moves in its plane) or ``"free"`` (derived).
    name : str or None
        A label, e.g. the boundary type read from a Neutral Map File (``"VISCOUS"``).
    collapsed : bool
        The patch is degenerate: its points coincide among themselves so it
        has no area (a pole, a face collapsed to a line, a wing-tip cap).
        Unclassified collapsed patches get the kind ``"free"``.
    origin : str
        Where the kind came from: ``"user"`` (walls/symmetry/fixed given by
        the user), ``"file"`` (read from a file), ``"default"`` (the default
        kind), ``"auto"`` (planar patch next to a wall made ``symmetry``),
        ``"collapsed"`` (degenerate, made ``free``).
    plane : tuple or None
        For planar ``symmetry`` patches: ``(origin, unit_normal)``, two
        3-tuples of float.  In 2-D the plane contains the (straight) patch and
        the z axis.
    """

    spec: PatchSpec
    kind: str
    name: str | None = None
    collapsed: bool = False
    origin: str = "user"
    plane: tuple | None = None

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ConnectivityError(f"patch {self.spec}: unknown kind {self.kind!r}, "
                                    f"expected one of {', '.join(KINDS)}")
        if not isinstance(self.spec, PatchSpec) or self.spec.range is None:
            raise ConnectivityError(f"patch {self.spec!r}: needs a PatchSpec with an explicit range")

    def __str__(self) -> str:
        extra = " (collapsed)" if self.collapsed else ""
        return f"{self.kind} {self.spec}{extra}"


@dataclass(frozen=True)
class FaceMap:
    """Which interface and patch cover each point of one face (see :meth:`Connectivity.face_map`).

    Attributes
    ----------
    interface : ndarray of int, shape (na, nb)
        Index into ``Connectivity.interfaces`` of an interface containing the
        point (the lowest index where several do), -1 where none.
    role : ndarray of int8, shape (na, nb)
        1 where that interface has the point on its master side, 2 on its
        slave side, 0 where no interface covers the point.
    patch : ndarray of int, shape (na, nb)
        Index into ``Connectivity.patches`` of the patch containing the point
        with the highest priority (wall > fixed > symmetry > free), -1 where none.
    """

    interface: np.ndarray
    role: np.ndarray
    patch: np.ndarray


def _sort_key_spec(s: PatchSpec):
    return (s.block, face_index(s.face), s.range)


class Connectivity:
    """Interfaces and boundary patches of a multiblock grid.

    Parameters
    ----------
    interfaces : list of Interface
    patches : list of Patch
        Every boundary face part that is not an interface, with its kind.
    ndim : {2, 3}
    dims : list of (ni, nj, nk)
        Block dimensions the connectivity was made for (checked by :meth:`check`).
    notes : list of str
        Human-readable remarks: automatic symmetry planes, collapsed faces,
        user patches lying on interfaces.
    """

    def __init__(self, interfaces, patches, ndim: int, dims, notes=()):
        self.interfaces: list[Interface] = list(interfaces)
        self.patches: list[Patch] = list(patches)
        self.ndim = int(ndim)
        self.dims = [tuple(int(n) for n in d) for d in dims]
        self.notes: list[str] = list(notes)
        for n, d in enumerate(self.dims):
            if len(d) != 3 or min(d) < 1 or max(d) > MAX_DIM:
                raise ConnectivityError(f"block {n + 1}: dimensions {list(d)} are not three sizes "
                                        f"from 1 to {MAX_DIM}")
        for s in [i.master for i in self.interfaces] + [i.slave for i in self.interfaces] + \
                [p.spec for p in self.patches]:
            self._check_spec(s)

    def _check_spec(self, s: PatchSpec) -> None:
        if s.block >= len(self.dims):
            raise ConnectivityError(f"{s}: the grid has {len(self.dims)} block(s)")
        if self.ndim == 2 and s.face in ("kmin", "kmax"):
            raise ConnectivityError(f"{s}: a 2-D grid has no k faces")
        na, nb = face_shape(self.dims[s.block], s.face)
        (a0, a1), (b0, b1) = s.range
        if a1 >= na or b1 >= nb:
            d = self.dims[s.block]
            raise ConnectivityError(f"{s}: range exceeds the face size {na} x {nb} of block "
                                    f"{s.block + 1} ({d[0]} x {d[1]} x {d[2]})")

    # ----------------------------------------------------------- queries
    def check(self, grid) -> None:
        """Raise :class:`ConnectivityError` unless ``grid`` has the block dimensions of this map."""
        check_dims(self.ndim, self.dims, grid)

    def faces(self):
        """The boundary faces ``(block, face)`` of the grid (4 per block in 2-D, 6 in 3-D)."""
        return [(b, f) for b in range(len(self.dims)) for f in faces_of(self.ndim)]

    def interfaces_on(self, block: int, face: str) -> list[tuple[int, Interface, str]]:
        """``(index, interface, side)`` for the interfaces touching a face; side is "master"/"slave"."""
        out = []
        for n, itf in enumerate(self.interfaces):
            if itf.master.block == block and itf.master.face == face:
                out.append((n, itf, "master"))
            if itf.slave.block == block and itf.slave.face == face:
                out.append((n, itf, "slave"))
        return out

    def patches_on(self, block: int, face: str) -> list[tuple[int, Patch]]:
        """``(index, patch)`` for the patches of a face."""
        return [(n, p) for n, p in enumerate(self.patches) if p.spec.block == block and p.spec.face == face]

    def face_map(self, block: int, face: str) -> FaceMap:
        """Which interface and patch cover each point of a face.

        Returns
        -------
        FaceMap
            Arrays of the face's shape ``(na, nb)``.
        """
        na, nb = face_shape(self.dims[block], face)
        itf = np.full((na, nb), -1, dtype=np.int64)
        role = np.zeros((na, nb), dtype=np.int8)
        pat = np.full((na, nb), -1, dtype=np.int64)
        prio = np.full((na, nb), 99, dtype=np.int64)
        for n, it, side in reversed(self.interfaces_on(block, face)):
            s = it.master if side == "master" else it.slave
            (a0, a1), (b0, b1) = s.range
            itf[a0:a1 + 1, b0:b1 + 1] = n
            role[a0:a1 + 1, b0:b1 + 1] = 1 if side == "master" else 2
        for n, p in self.patches_on(block, face):
            (a0, a1), (b0, b1) = p.spec.range
            sl = (slice(a0, a1 + 1), slice(b0, b1 + 1))
            better = prio[sl] > _PRIORITY[p.kind]
            pat[sl][better] = n
            prio[sl][better] = _PRIORITY[p.kind]
        return FaceMap(itf, role, pat)

    def overlaps(self) -> list[tuple[tuple[str, int], tuple[str, int]]]:
        """Pairs of items that cover a common boundary cell (an area, not only edge points).

        Items are ``("patch", n)`` for ``patches[n]`` and ``("master", n)`` /
        ``("slave", n)`` for the sides of ``interfaces[n]``; in each pair the
        first item comes earlier in the order interfaces (master, slave), then
        patches, and is the earliest item the second one overlaps.  A
        connectivity made by :func:`~tfi_quat.topology.connect` has none; the
        file readers refuse files that have some.

        Works on the ranges alone (interval arithmetic), so it allocates
        nothing proportional to the declared block sizes.
        """
        items = [(("master", n), it.master) for n, it in enumerate(self.interfaces)]
        items += [(("slave", n), it.slave) for n, it in enumerate(self.interfaces)]
        items.sort(key=lambda x: (x[0][1], x[0][0] != "master"))
        items += [(("patch", n), p.spec) for n, p in enumerate(self.patches)]
        # half-open cell rectangles [a0, a1) x [b0, b1) per face, in item order
        by_face: dict = {}
        for k, (item, s) in enumerate(items):
            _, a, b = face_axes(s.face)
            idx = face_cells(self.dims[s.block], s.face, s.range)
            sa, sb = idx[a], idx[b]
            if sa.stop > sa.start and sb.stop > sb.start:
                by_face.setdefault((s.block, s.face), []).append((k, sa.start, sa.stop, sb.start, sb.stop))
        found = []
        for rects in by_face.values():
            r = np.array(rects, dtype=np.int64).reshape(-1, 5)
            k, a0, a1, b0, b1 = r.T
            for m in range(1, len(r)):
                hit = (a0[:m] < a1[m]) & (a0[m] < a1[:m]) & (b0[:m] < b1[m]) & (b0[m] < b1[:m])
                if hit.any():
                    found.append((int(k[int(np.argmax(hit))]), int(k[m])))
        found.sort(key=lambda pair: pair[1])
        return [(items[j][0], items[m][0]) for j, m in found]

    def item_spec(self, item: tuple[str, int]) -> PatchSpec:
        """The range of an item ``("patch", n)``, ``("master", n)`` or ``("slave", n)``."""
        role, n = item
        return self.patches[n].spec if role == "patch" else getattr(self.interfaces[n], role)

    def kinds(self) -> dict[str, list[Patch]]:
        """Patches grouped by kind."""
        out: dict[str, list[Patch]] = {k: [] for k in KINDS}
        for p in self.patches:
            out[p.kind].append(p)
        return out

    def sorted(self) -> "Connectivity":
        """A copy with interfaces and patches in a canonical order."""
        return Connectivity(sorted(self.interfaces, key=lambda i: (_sort_key_spec(i.master), _sort_key_spec(i.slave))),
                            sorted(self.patches, key=lambda p: _sort_key_spec(p.spec)),
                            self.ndim, self.dims, self.notes)

    def with_patches(self, patches, notes=None) -> "Connectivity":
        """A copy with other patches (and notes)."""
        return Connectivity(self.interfaces, patches, self.ndim, self.dims,
                            self.notes if notes is None else notes)

    # ------------------------------------------------------------- files
    def to_json(self, path, *, overwrite: bool = False) -> None:
        """Write the JSON connectivity file (see ``docs/formats.md``)."""
        from .files import write_json
        write_json(self, path, overwrite=overwrite)

    @classmethod
    def from_json(cls, path, grid=None) -> "Connectivity":
        """Read a JSON connectivity file; with ``grid``, check it against the grid.

        The check: the block dimensions, and that the points of every interface
        coincide (within a quarter of the local spacing; errors name the file and
        line of the interface).
        """
        from .files import read_json
        return read_json(path, grid)

    def to_nmf(self, path, *, overwrite: bool = False, convention: str = "3d") -> None:
        """Write a Neutral Map File (see ``docs/formats.md``).

        ``convention="2d"`` writes a 2-D grid with the 2-D face numbers
        1..4 = imin, imax, jmin, jmax (Construct2D style) instead of the
        GEOLAB 3-D numbers.
        """
        from .nmf import write_nmf
        write_nmf(self, path, overwrite=overwrite, convention=convention)

    @classmethod
    def from_nmf(cls, path, grid=None, *, types=None, convention: str = "auto") -> "Connectivity":
        """Read a Neutral Map File.

        Parameters
        ----------
        path : str or path-like
        grid : Grid, optional
            Check the file against the grid (dimensions; the points of every
            ``ONE_TO_ONE`` coincide), and derive what the file does not
            hold (collapsed patches, symmetry planes, parts of faces the file
            leaves out, which get the kind ``fixed``).
        types : dict, optional
            Extra boundary type names -> kind (``"wall"``, ``"fixed"``,
            ``"symmetry"``, ``"free"``, ``"interface"``).
        convention : {"auto", "3d", "2d"}
            Face numbering (see ``docs/formats.md``).
        """
        from .nmf import read_nmf
        conn = read_nmf(path, types=types, convention=convention, grid=grid)
        if grid is not None:
            from .search import classify
            conn = classify(conn, grid)
        return conn

    # ----------------------------------------------------------- display
    def table(self) -> str:
        """A text table of interfaces (1-based ranges, Transform), patches and notes."""
        from .files import format_table
        return format_table(self)

    def __eq__(self, other) -> bool:
        if not isinstance(other, Connectivity):
            return NotImplemented
        a, b = self.sorted(), other.sorted()

        def pkey(p):
            return (p.spec, p.kind, p.collapsed)
        return (a.ndim == b.ndim and a.dims == b.dims and a.interfaces == b.interfaces
                and [pkey(p) for p in a.patches] == [pkey(p) for p in b.patches])

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        k = self.kinds()
        kinds = ", ".join(f"{len(v)} {n}" for n, v in k.items() if v)
        return (f"Connectivity(ndim={self.ndim}, {len(self.dims)} block(s), "
                f"{len(self.interfaces)} interface(s), patches: {kinds or 'none'})")

