"""CGNS files (CGNS/HDF5): structured zones, boundary conditions, 1-to-1 connectivity.

What is read
------------
A CGNS/HDF5 file is a tree of HDF5 groups, one per CGNS node, each with the
attributes ``name`` and ``label`` (33-byte strings), ``type`` (3 bytes:
``MT I4 I8 R4 R8 C1 LK``) and ``flags``, and its value, if any, in a dataset
named ``" data"`` (a leading space) stored in Fortran order, so that h5py
sees the dimensions reversed.  The reader takes one ``CGNSBase_t`` (``base=``
by name, default the first) of cell dimension 3 or 2, and from it:

* every ``Zone_t`` (``ZoneType`` ``Structured``; an unstructured zone is an
  error naming it), its name as the block name;
* ``GridCoordinates/CoordinateX, CoordinateY[, CoordinateZ]`` (``R4`` or
  ``R8``, converted to float64).  A component's ``" data"`` dataset is, in
  HDF5's C order, ``(nk, nj, ni)`` (2-D: ``(nj, ni)``): the transpose of the
  block's ``xyz[..., c]``, which HDF5 fills in place (no copy);
* ``ZoneBC/BC_t`` with ``PointRange`` (or a ``PointList`` covering a whole
  rectangle), the type given directly or ``FamilySpecified`` through the
  base's ``Family_t/FamilyBC_t``; kinds by :func:`bc_kind`;
* ``ZoneGridConnectivity/GridConnectivity1to1_t`` (``PointRange``,
  ``PointRangeDonor``, ``Transform``; ranges may run backwards, a zone may
  abut itself), the two records of an interface merged into one
  :class:`~tfi_quat.topology.Interface` whose points are checked to coincide.

The grid gets ``source_format`` a :class:`CGNSFormat` (the base, the
coordinate precision, the file) and ``connectivity`` a
:class:`~tfi_quat.topology.Connectivity` (None when the file has neither
boundary conditions nor 1-to-1 records).  Other ``GridConnectivity_t``
records (overset, mismatched abutting) are not used; :func:`info` lists them
and writing ``like`` the file keeps them.

What is written
---------------
:func:`write` writes a new tree (``CGNSLibraryVersion``, one base, its zones
with ``ZoneType``, coordinates, ``ZoneBC`` and both records of each 1-to-1
interface, families on request), or, ``like`` a grid read from a CGNS file,
a copy of that file's tree in which only the coordinates of the base read are
replaced: flow solutions, families, descriptors, reference states, other
bases and connectivity records are kept.

Robustness
----------
Before h5py opens a file, its metadata is walked in a guarded child process
(:func:`tfi_quat.io.hdf5.guard`); declared sizes are checked against
``max_points`` or the available memory before anything is allocated; every
error is a :class:`~tfi_quat.errors.GridFormatError` naming the file and the
node (e.g. ``/wing/inner/ZoneBC/wall1/PointRange``).  ADF-format CGNS files
(the pre-3.0 default) are refused with a message naming ``adf2hdf``.
"""

from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from ..errors import ConnectivityError, GridFormatError, GridValueError, TfiQuatError
from ..grid import Block, Grid, face_axes, face_axis, face_index, face_shape, faces_of
from ..spec import PatchSpec
from ..topology.model import MAX_DIM, Connectivity, Interface, Patch
from ._atomic import atomic_output, check_target
from ._limits import check_points
from .hdf5 import (alloc, check_finite, close_map, damaged_file_errors, guard, is_hdf5, map_file,
                   mapped_offset)
from .partial import GridFaces, block_numbers, empty_faces, fill_faces

__all__ = ["CGNSFormat", "CGNSInfo", "read", "read_faces", "write", "info", "bc_kind", "BC_TYPES", "is_adf"]

#: every BCType_t value of the CGNS standard (SIDS 9.3), as the files spell them
BC_TYPES = (
    "Null", "UserDefined", "BCAxisymmetricWedge", "BCDegenerateLine", "BCDegeneratePoint",
    "BCDirichlet", "BCExtrapolate", "BCFarfield", "BCGeneral", "BCInflow", "BCInflowSubsonic",
    "BCInflowSupersonic", "BCNeumann", "BCOutflow", "BCOutflowSubsonic", "BCOutflowSupersonic",
    "BCSymmetryPlane", "BCSymmetryPolar", "BCTunnelInflow", "BCTunnelOutflow", "BCWall",
    "BCWallInviscid", "BCWallViscous", "BCWallViscousHeatFlux", "BCWallViscousIsothermal",
    "FamilySpecified")

#: other spellings of BCType_t values met in files (the names of the C enumeration)
_BC_ALIASES = {"BCTypeNull": "Null", "BCTypeUserDefined": "UserDefined"}

#: CGNS library version written in ``CGNSLibraryVersion`` (the layout of CGNS 3.4)
LIBRARY_VERSION = 3.4
_NAME_LEN = 32
_LABEL_TRANSFORM = '"int[IndexDimension]"'
_ADF_MARK = b"ADF Database"


def bc_kind(bctype: str) -> str:
    """The patch kind of a CGNS ``BCType``.

    ``BCWall*`` -> ``"wall"``; ``BCSymmetryPlane`` -> ``"symmetry"``; every
    other type (``BCFarfield``, ``BCInflow*``, ``BCOutflow*``,
    ``BCExtrapolate``, ``BCDirichlet``, ``BCTunnel*``, user-defined, ...)
    -> ``"fixed"``.
    """
    if bctype.startswith("BCWall"):
        return "wall"
    if bctype == "BCSymmetryPlane":
        return "symmetry"
    return "fixed"


@dataclass(frozen=True)
class CGNSFormat:
    """The variant of a CGNS file (kept in ``Grid.source_format``).

    Attributes
    ----------
    base : str
        Name of the ``CGNSBase_t`` read (and written).
    single : bool
        Coordinates stored as ``R4`` (float32) rather than ``R8``.
    source : str or None
        The file read: writing ``like`` this variant copies that file's tree
        and replaces only the coordinates of ``base``.
    """

    base: str = "Base"
    single: bool = False
    source: str | None = None

    def replace(self, **changes) -> "CGNSFormat":
        from dataclasses import replace
        return replace(self, **changes)

    def describe(self) -> str:
        """One line for people, e.g. ``CGNS/HDF5, base 'wing', float64 coordinates``."""
        return f"CGNS/HDF5, base {self.base!r}, {'float32' if self.single else 'float64'} coordinates"


@dataclass(frozen=True)
class CGNSInfo:
    """What :func:`info` finds in a CGNS file without reading coordinates.

    Attributes
    ----------
    path : str
    bases : list of (name, cell_dim, phys_dim, zone names)
        Every ``CGNSBase_t`` in file order.
    base : str
        The base read (``base=`` or the first).
    zones : list of (name, (ni, nj, nk), datatype)
        Zones of that base; datatype ``"R4"``/``"R8"`` of CoordinateX.
    bcs : list of dict
        ``zone``, ``name``, ``type`` (BCType or ``FamilySpecified``),
        ``family`` (or None), ``resolved`` (the BCType after the family),
        ``kind``, ``face``, ``range`` (1-based ``[[i1,j1,k1],[i2,j2,k2]]``), ``node``.
    one_to_one : list of dict
        ``zone``, ``name``, ``donor``, ``range``, ``donor_range``, ``transform``, ``node``.
    other_connectivity : list of dict
        ``zone``, ``name``, ``type`` (``Overset``, ``Abutting``, ...), ``donor``,
        ``node``: kept on rewriting, not used.
    """

    path: str
    bases: list = field(default_factory=list)
    base: str = ""
    zones: list = field(default_factory=list)
    bcs: list = field(default_factory=list)
    one_to_one: list = field(default_factory=list)
    other_connectivity: list = field(default_factory=list)


# ----------------------------------------------------------------------------- file checks

def is_adf(path) -> bool:
    """Whether ``path`` starts like an ADF-format CGNS file."""
    try:
        with open(os.fspath(path), "rb") as fh:
            return _ADF_MARK in fh.read(32)
    except OSError:
        return False


def _stamp(p: Path) -> tuple:
    st = os.stat(p)
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns


def _open(path) -> tuple:
    """Check the file kind, walk its metadata in the guard, open it with h5py.

    Returns the open file and the guard's catalogue of its objects (None when
    the guard did not walk it: a file that passed before), which is dropped
    when the file changed between the walk and the opening.
    """
    p = Path(os.fspath(path))
    with open(p, "rb") as fh:  # the OS's own FileNotFoundError / IsADirectoryError / PermissionError
        size = os.fstat(fh.fileno()).st_size
        head = fh.read(32)
    if size == 0:
        raise GridFormatError(f"{p}: empty file, not a CGNS file")
    if _ADF_MARK in head:
        raise GridFormatError(f"{p}: an ADF-format CGNS file; tfi_quat reads CGNS/HDF5 files: convert it "
                              f"with 'adf2hdf {p.name} NEW.cgns' from the CGNS tools (cgns-convert)")
    if not is_hdf5(p):
        raise GridFormatError(f"{p}: not a CGNS/HDF5 file (no HDF5 signature)")
    before = _stamp(p)
    catalogue = guard(p, str(p), catalogue=True)
    try:
        f = h5py.File(p, "r")
    except OSError as exc:
        raise GridFormatError(f"{p}: cannot open as HDF5: {exc}") from None
    if catalogue is not None and _stamp(p) != before:
        catalogue = None
    return f, catalogue


@contextlib.contextmanager
def _tree(path):
    """The checked :class:`_Tree` of a CGNS file (guarded, opened, closed on leaving)."""
    f, catalogue = _open(path)
    t = _Tree(Path(os.fspath(path)), f, catalogue)
    try:
        yield t
    finally:
        t.release()
        f.close()


def _text(value) -> str:
    if isinstance(value, np.ndarray):
        value = value.tobytes() if value.dtype.kind in "iuS" else value[()]
    if isinstance(value, (bytes, np.bytes_)):
        return bytes(value).split(b"\0", 1)[0].decode("utf-8", "replace").rstrip()
    return str(value)


class _Tree:
    """Checked access to the CGNS nodes of an open file; errors name the file and node.

    Nodes are named by their paths (``/Base/zone/ZoneBC``; the root is ``""``).
    On a first read, the guard's child has walked every node already and
    handed back its catalogue (:func:`tfi_quat.io.hdf5.guard`): links, labels,
    the headers of the datasets and the values of the small ones come from
    it, and only the datasets read in full (the coordinates) are opened here.
    Otherwise (a file the guard passed before, or what the catalogue lacks)
    the links of a whole base are listed by one ``H5Lvisit`` (:meth:`prefetch`),
    every node is opened once and its label read once (cached): a CGNS tree has
    hundreds of small nodes, and per-node lookups through h5py's high-level
    objects cost ten times more.
    """

    def __init__(self, path, f: h5py.File, catalogue: dict | None = None):
        self.path = path
        self.f = f
        self.cat = catalogue or {}
        self._links: dict = {}    # node -> {child key: link type}, in the file's order
        self._objs: dict = {}     # node -> its GroupID or DatasetID
        self._labels: dict = {}
        self._buf = np.zeros((), dtype=f"S{_ATTR_LEN}")

    def fail(self, node: str, msg: str):
        raise GridFormatError(f"{self.path}: {node}: {msg}")

    # ------------------------------------------------------------------ links and objects
    def prefetch(self, node: str) -> None:
        """List the links of ``node`` and of every group below it in one pass."""
        if node in self.cat:
            return  # the catalogue has them
        gid = self._group_id(node)
        found: dict = {}

        def seen(name, info):
            parent, _, key = name.decode("utf-8", "surrogateescape").rpartition("/")
            found.setdefault(f"{node}/{parent}" if parent else node, {})[key] = info.type
        try:
            # groups that do not track the creation order are listed by name (as h5py lists them)
            gid.links.visit(seen, idx_type=h5py.h5.INDEX_CRT_ORDER, info=True)
        except (RuntimeError, OSError, ValueError, KeyError):
            return  # listed group by group instead (:meth:`links`), with their own errors
        for key, links in found.items():
            self._links.setdefault(key, links)

    def links(self, node: str) -> dict:
        """``{key: link type}`` of the children of group ``node``, in the file's order."""
        links = self._links.get(node)
        if links is None:
            entry = self.cat.get(node)
            if entry is not None and entry[0] == 0 and entry[2] is not None:
                self._links[node] = entry[2]
                return entry[2]
            gid = self._group_id(node)
            links = {}

            def seen(name, info):
                links[name.decode("utf-8", "surrogateescape")] = info.type
            try:
                try:
                    gid.links.iterate(seen, idx_type=h5py.h5.INDEX_CRT_ORDER, info=True)
                except RuntimeError:  # no creation order index: by name, as h5py lists them
                    links.clear()
                    gid.links.iterate(seen, idx_type=h5py.h5.INDEX_NAME, info=True)
            except (RuntimeError, OSError, ValueError) as exc:
                self.fail(node or "/", f"cannot list its children: {exc}")
            self._links[node] = links
        return links

    def _group_id(self, node: str):
        if node == "":
            return self.f.id
        oid = self.obj(node)
        if not isinstance(oid, h5py.h5g.GroupID):
            self.fail(node, "is not a CGNS node (not an HDF5 group)")
        return oid

    def is_group(self, node: str) -> bool:
        """Whether the object at ``node`` is an HDF5 group."""
        entry = self.cat.get(node)
        if entry is not None:
            return entry[0] == 0
        return isinstance(self.obj(node), h5py.h5g.GroupID)

    def obj(self, node: str):
        """The GroupID or DatasetID at ``node`` (reached through hard links only)."""
        oid = self._objs.get(node)
        if oid is None:
            parent, _, key = node.rpartition("/")
            # relative to the parent (open already): one link lookup, not one per level
            loc = self.f.id if parent == "" else self._objs.get(parent)
            if loc is None:
                loc, key = self.f.id, node
            try:
                oid = h5py.h5o.open(loc, key.encode("utf-8", "surrogateescape"))
            except (OSError, KeyError, ValueError, RuntimeError) as exc:
                self.fail(node, f"cannot open: {exc}")
            self._objs[node] = oid
        return oid

    def release(self) -> None:
        """Drop the objects held open (before the file closes: h5py's close walks those left)."""
        self._objs.clear()

    def _hard(self, g: str, key: str, sub: str) -> bool:
        """Whether ``key`` is a child of ``g``; a soft or external link is an error."""
        ltype = self.links(g).get(key)
        if ltype is None:
            return False
        if ltype != h5py.h5l.TYPE_HARD:
            self.fail(sub, "is a link; tfi_quat does not follow CGNS links")
        return True

    # ------------------------------------------------------------------ attributes
    def attr(self, g: str, key: str, node: str) -> str:
        """A string attribute of any form (the general, slower way)."""
        entry = self.cat.get(g)
        if entry is not None and key in entry[1]:
            return _text(entry[1][key])
        kb = key.encode("ascii")
        oid = self._group_id(g)
        try:
            exists = h5py.h5a.exists(oid, kb)
        except (OSError, TypeError, ValueError, KeyError, RuntimeError) as exc:
            self.fail(node, f"cannot read attribute {key!r}: {exc}")
        if not exists:
            self.fail(node, f"has no attribute {key!r} (not a CGNS node)")
        try:
            aid = h5py.h5a.open(oid, kb)
            tid = aid.get_type()
            if tid.get_class() != h5py.h5t.STRING or tid.is_variable_str() or aid.shape not in ((), (1,)):
                return _text(h5py.AttributeManager(h5py.Group(oid))[key])
            buf = np.zeros(aid.shape, dtype=f"S{tid.get_size()}")
            aid.read(buf)
            return _text(buf.reshape(-1)[0])
        except (OSError, TypeError, ValueError, KeyError, RuntimeError) as exc:
            self.fail(node, f"cannot read attribute {key!r}: {exc}")

    def label(self, g: str, node: str) -> str:
        """The node's ``label`` attribute (read once)."""
        have = self._labels.get(g)
        if have is not None:
            return have
        entry = self.cat.get(g)
        if entry is not None and "label" in entry[1]:
            have = self._labels[g] = _text(entry[1]["label"])
            return have
        oid = self._group_id(g)
        try:
            # the common form (a scalar fixed-length string) in one read; anything else the general way
            aid = h5py.h5a.open(oid, b"label")
            if aid.shape != ():  # h5py does not check the buffer's size against the attribute's
                raise TypeError("not a scalar")
            aid.read(self._buf, mtype=_S_ATTR)
            have = _text(self._buf[()])
        except (OSError, TypeError, ValueError, KeyError, RuntimeError):
            have = self.attr(g, "label", node)
        self._labels[g] = have
        return have

    # ------------------------------------------------------------------ children
    def children(self, g: str, node: str, label: str | None = None):
        """``(name, path, path)`` of the child nodes (hard-linked groups) with ``label``.

        Links (CGNS ``LK`` nodes, soft or external HDF5 links) are not followed: the
        guard vouches for this file only; with a ``label`` they are an error.
        """
        out = []
        for key, ltype in self.links(g).items():
            if key.startswith(" "):
                continue
            sub = f"{node.rstrip('/')}/{key}"
            if ltype != h5py.h5l.TYPE_HARD:
                if label is None:
                    continue
                self.fail(sub, "is a link; tfi_quat does not follow CGNS links")
            if not self.is_group(sub):
                continue
            if label is None or self.label(sub, sub) == label:
                out.append((key, sub, sub))
        return out

    def child(self, g: str, key: str, node: str, label: str | None = None, required: bool = True):
        """``(path, path)`` of child ``key`` (``(None, path)`` when absent and not ``required``)."""
        sub = f"{node.rstrip('/')}/{key}"
        if not self._hard(g, key, sub):
            if required:
                self.fail(sub, "is missing")
            return None, sub
        if not self.is_group(sub):
            self.fail(sub, "is not a CGNS node (not an HDF5 group)")
        if label is not None:
            have = self.label(sub, sub)
            if have != label:
                self.fail(sub, f"has label {have!r}, expected {label!r}")
        return sub, sub

    def has(self, g: str, key: str) -> bool:
        return key in self.links(g)

    # ------------------------------------------------------------------ values
    def dataset(self, g: str, node: str):
        """``(DatasetID, numpy dtype)`` of the node's ``" data"``."""
        sub = f"{node}/ data"
        if not self._hard(g, " data", sub):
            self.fail(node, "has no data")
        entry = self.cat.get(sub)
        if entry is not None and entry[0] == 1 and entry[2]:
            return self.obj(sub), np.dtype(entry[2])
        dsid = self.obj(sub)
        if not isinstance(dsid, h5py.h5d.DatasetID):
            self.fail(node, "its ' data' is not a dataset")
        return dsid, self._dtype(dsid, node)

    def _dtype(self, dsid, node: str) -> np.dtype:
        """The native numpy type of a dataset of numbers (fails on anything else)."""
        try:
            tid = dsid.get_type()
            cls, size = tid.get_class(), tid.get_size()
            if cls == h5py.h5t.INTEGER and size in (1, 2, 4, 8):
                return np.dtype(f"{'u' if tid.get_sign() == h5py.h5t.SGN_NONE else 'i'}{size}")
            if cls == h5py.h5t.FLOAT and size in (2, 4, 8):
                return np.dtype(f"f{size}")
            try:
                what = str(dsid.dtype)
            except (TypeError, ValueError):
                what = f"HDF5 class {cls}"
        except (OSError, TypeError, ValueError, RuntimeError) as exc:
            self.fail(node, f"cannot read the type of its data: {exc}")
        self.fail(node, f"data of type {what} is not numbers or characters")

    def storage(self, g: str, node: str, dsid) -> tuple:
        """``(shape, chunked, filtered, stored bytes)`` of the node's data ``dsid``."""
        entry = self.cat.get(f"{node}/ data")
        if entry is not None and entry[0] == 1:
            return entry[3], entry[4], entry[5], entry[6]
        try:
            plist = dsid.get_create_plist()
            return (dsid.shape, plist.get_layout() == h5py.h5d.CHUNKED, plist.get_nfilters(),
                    dsid.get_storage_size())
        except (OSError, TypeError, ValueError, RuntimeError) as exc:
            self.fail(node, f"cannot read the header of its data: {exc}")

    def data(self, g: str, node: str, max_values: int = 1 << 16) -> np.ndarray:
        """The node's value, at most ``max_values`` values (metadata, not coordinates)."""
        sub = f"{node}/ data"
        entry = self.cat.get(sub)
        if entry is not None and entry[0] == 1 and entry[7] is not None and self._hard(g, " data", sub):
            shape = entry[3]
            if math.prod(shape) > max_values:
                self.fail(node, f"holds {math.prod(shape):,} values, more than the {max_values:,} expected")
            return np.frombuffer(entry[7], dtype=entry[2]).reshape(shape).copy()
        dsid, dtype = self.dataset(g, node)
        try:
            shape = dsid.shape
        except (OSError, TypeError, ValueError, RuntimeError) as exc:
            self.fail(node, f"cannot read the shape of its data: {exc}")
        if shape is None:
            self.fail(node, "its data has an empty (null) dataspace")
        size = math.prod(shape)
        if size > max_values:
            self.fail(node, f"holds {size:,} values, more than the {max_values:,} expected")
        try:
            out = np.empty(shape, dtype=dtype)
            if size:
                dsid.read(h5py.h5s.ALL, h5py.h5s.ALL, out, mtype=_mem_type(dtype))
            return out
        except (OSError, TypeError, ValueError, RuntimeError) as exc:
            self.fail(node, f"cannot read its data: {exc}")

    def string(self, g: str, node: str) -> str:
        arr = self.data(g, node, 4096)
        if arr.dtype.kind not in "iu" or arr.dtype.itemsize != 1:
            self.fail(node, f"expected a character (C1) value, got {arr.dtype}")
        return _text(np.ascontiguousarray(arr).reshape(-1))

    def ints(self, g: str, node: str, shape: tuple, max_values: int = 1 << 16) -> np.ndarray:
        arr = self.data(g, node, max_values)
        if arr.dtype.kind not in "iu" or arr.dtype.itemsize < 4:
            self.fail(node, f"expected integers (I4 or I8), got {arr.dtype}")
        if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
            want = " x ".join("n" if s is None else str(s) for s in reversed(shape))
            got = " x ".join(map(str, arr.shape[::-1])) or "a scalar"
            self.fail(node, f"has shape {got} (Fortran order), expected {want}")
        return arr.astype(np.int64)


#: the memory type of the ``label`` read (longer labels are cut: no CGNS label is that long)
_ATTR_LEN = 64
_S_ATTR = h5py.h5t.C_S1.copy()
_S_ATTR.set_size(_ATTR_LEN)
_S_ATTR.set_strpad(h5py.h5t.STR_NULLTERM)
_MEM_TYPES: dict = {}


def _mem_type(dtype: np.dtype):
    """The HDF5 type of a numpy number type (made once: h5py's conversion is slow)."""
    tid = _MEM_TYPES.get(dtype)
    if tid is None:
        tid = _MEM_TYPES[dtype] = h5py.h5t.py_create(dtype)
    return tid


# ----------------------------------------------------------------------------- the base

@dataclass
class _Zone:
    name: str
    node: str
    group: str          # its path in the file (as node)
    dims: tuple
    coords: list        # (name, DatasetID, node, dtype) for X, Y[, Z]


class _Base:
    """One base of an open CGNS file: zones, families, BC and connectivity records."""

    def __init__(self, tree: _Tree, base: str | None):
        self.tree = tree
        t = tree
        bases = []
        for name, g, node in t.children("", "", "CGNSBase_t"):
            dims = t.ints(g, node, (2,))
            bases.append((name, g, node, int(dims[0]), int(dims[1])))
        if not bases:
            raise GridFormatError(f"{t.path}: no CGNSBase_t node: not a CGNS file")
        self.all = bases
        if base is None:
            chosen = bases[0]
        else:
            named = [b for b in bases if b[0] == base]
            if not named:
                raise GridFormatError(f"{t.path}: no base named {base!r}; the file holds "
                                      f"{', '.join(repr(b[0]) for b in bases)}")
            chosen = named[0]
        self.name, self.group, self.node, self.cell_dim, self.phys_dim = chosen
        if self.cell_dim not in (2, 3):
            t.fail(self.node, f"cell dimension {self.cell_dim}: tfi_quat reads bases of cell dimension 2 or 3")
        if not self.cell_dim <= self.phys_dim <= 3:
            t.fail(self.node, f"physical dimension {self.phys_dim} with cell dimension {self.cell_dim}")
        self.idim = self.cell_dim
        t.prefetch(self.node)
        self.zones = [self._zone(name, g, node) for name, g, node in t.children(self.group, self.node, "Zone_t")]
        if not self.zones:
            t.fail(self.node, "has no Zone_t node")
        self.index = {z.name: n for n, z in enumerate(self.zones)}
        self.families = {}
        for name, g, node in t.children(self.group, self.node, "Family_t"):
            fbc = t.children(g, node, "FamilyBC_t")
            self.families[name] = t.string(fbc[0][1], fbc[0][2]) if fbc else None

    @property
    def ndim(self) -> int:
        return self.cell_dim

    def _zone(self, name, g, node) -> _Zone:
        t = self.tree
        zt, ztnode = t.child(g, "ZoneType", node, "ZoneType_t", required=False)
        if zt is not None:
            kind = t.string(zt, ztnode)
            if kind != "Structured":
                t.fail(node, f"zone {name!r} is {kind}: tfi_quat reads structured zones only")
        size = t.ints(g, node, (3, self.idim))
        vert = [int(v) for v in size[0]]
        if min(vert) < 1 or max(vert) > MAX_DIM:
            t.fail(node, f"zone {name!r}: vertex sizes {vert} must be from 1 to {MAX_DIM}")
        dims = tuple(vert + [1] * (3 - self.idim))
        gc, gcnode = t.child(g, "GridCoordinates", node, "GridCoordinates_t")
        comps = ("CoordinateX", "CoordinateY", "CoordinateZ")[:self.phys_dim]
        coords = []
        shape = tuple(reversed(vert))
        for c in comps:
            cg, cnode = t.child(gc, c, gcnode, "DataArray_t")
            ds, dtype = t.dataset(cg, cnode)
            have, chunked, filtered, stored = t.storage(cg, cnode, ds)
            if have is None:
                t.fail(cnode, "its data has an empty (null) dataspace")
            if have != shape:
                t.fail(cnode, f"data of shape {' x '.join(map(str, have[::-1]))} (Fortran order) "
                              f"does not match the zone size {' x '.join(map(str, vert))}")
            if dtype.kind != "f" or dtype.itemsize not in (4, 8):
                t.fail(cnode, f"coordinates of type {dtype}: expected R4 or R8")
            if filtered:
                t.fail(cnode, "compressed or filtered coordinates are not supported")
            if not chunked:
                need = math.prod(shape) * dtype.itemsize
                if stored < need:
                    t.fail(cnode, f"only {stored} of {need} bytes are stored (incomplete data)")
            coords.append((c, ds, cnode, dtype))
        return _Zone(name, node, g, dims, coords)

    # ------------------------------------------------------------------ records
    def _range(self, g, node, zone: _Zone, what: str = "PointRange"):
        """0-based begin and end (3-vectors) of an IndexRange_t child ``what``."""
        t = self.tree
        pr, prnode = t.child(g, what, node, "IndexRange_t")
        r = t.ints(pr, prnode, (2, self.idim))
        lo = [int(v) - 1 for v in r[0]] + [0] * (3 - self.idim)
        hi = [int(v) - 1 for v in r[1]] + [0] * (3 - self.idim)
        return lo, hi, prnode, r

    def _check_in(self, lo, hi, zone: _Zone, node, r):
        for a in range(3):
            for v in (lo[a], hi[a]):
                if not 0 <= v < zone.dims[a]:
                    self.tree.fail(node, f"{_show(r)} lies outside zone {zone.name!r} "
                                         f"({' x '.join(map(str, zone.dims[:self.idim]))})")

    def _face(self, lo, hi, zone: _Zone, node, r) -> str:
        """The face of ``zone`` holding the range (first matching axis)."""
        for a in range(self.idim):
            if lo[a] == hi[a] and lo[a] in (0, zone.dims[a] - 1):
                if zone.dims[a] == 1:
                    continue
                return "ijk"[a] + ("min" if lo[a] == 0 else "max")
        self.tree.fail(node, f"{_show(r)} does not lie on a face of zone {zone.name!r} "
                             f"({' x '.join(map(str, zone.dims[:self.idim]))})")

    def _point_list(self, g, node, zone: _Zone):
        """A PointList covering a full rectangle, as the 0-based corners of that rectangle."""
        t = self.tree
        pl, plnode = t.child(g, "PointList", node, "IndexArray_t")
        limit = int(np.prod(zone.dims))
        arr = t.ints(pl, plnode, (None, self.idim), max_values=self.idim * limit)
        if arr.shape[0] == 0:
            t.fail(plnode, "is empty")
        lo, hi = arr.min(axis=0), arr.max(axis=0)
        count = int(np.prod(hi - lo + 1))
        if count != arr.shape[0] or len(np.unique(arr, axis=0)) != count:
            t.fail(plnode, f"its {arr.shape[0]} points do not cover the rectangle "
                           f"{lo.tolist()}..{hi.tolist()} exactly once; tfi_quat reads point lists of "
                           "whole rectangles only")
        pad = [1] * (3 - self.idim)
        return [int(v) - 1 for v in lo] + [0] * len(pad), [int(v) - 1 for v in hi] + [0] * len(pad), plnode, \
            np.stack([lo, hi])

    def bcs(self):
        """Every BC_t of the base: dicts as :attr:`CGNSInfo.bcs` plus ``block`` and ``spec``."""
        t = self.tree
        out = []
        for zn, zone in enumerate(self.zones):
            zbc, zbcnode = t.child(zone.group, "ZoneBC", zone.node, "ZoneBC_t", required=False)
            if zbc is None:
                continue
            for name, g, node in t.children(zbc, zbcnode, "BC_t"):
                bctype = t.string(g, node)
                bctype = _BC_ALIASES.get(bctype, bctype)
                if bctype not in BC_TYPES:
                    t.fail(node, f"unknown BCType {bctype!r}")
                loc, locnode = t.child(g, "GridLocation", node, "GridLocation_t", required=False)
                if loc is not None and t.string(loc, locnode) != "Vertex":
                    t.fail(locnode, f"BC location {t.string(loc, locnode)!r}: tfi_quat reads vertex "
                                    "ranges (GridLocation Vertex) only")
                family = None
                resolved = bctype
                if bctype == "FamilySpecified":
                    fam, famnode = t.child(g, "FamilyName", node, "FamilyName_t", required=False)
                    if fam is None:
                        t.fail(node, "BCType FamilySpecified without a FamilyName")
                    family = t.string(fam, famnode)
                    if family not in self.families:
                        t.fail(famnode, f"family {family!r} is not a Family_t of base {self.name!r}")
                    resolved = _BC_ALIASES.get(self.families[family], self.families[family]) or "Null"
                    if resolved not in BC_TYPES:
                        t.fail(f"{self.node}/{family}", f"unknown BCType {resolved!r} in its FamilyBC")
                if t.has(g, "PointRange"):
                    lo, hi, rnode, r = self._range(g, node, zone)
                elif t.has(g, "PointList"):
                    lo, hi, rnode, r = self._point_list(g, node, zone)
                else:
                    t.fail(node, "has neither PointRange nor PointList (element ranges are not "
                                 "structured-grid boundary conditions)")
                self._check_in(lo, hi, zone, rnode, r)
                face = self._face(lo, hi, zone, rnode, r)
                d, a, b = face_axes(face)
                rng = ((min(lo[a], hi[a]), max(lo[a], hi[a])), (min(lo[b], hi[b]), max(lo[b], hi[b])))
                out.append(dict(zone=zone.name, name=name, type=bctype, family=family, resolved=resolved,
                                kind=bc_kind(resolved), face=face, range=_one_based(lo, hi, self.idim),
                                node=node, block=zn, spec=PatchSpec(zn, face, rng)))
        return out

    def connectivity_records(self):
        """``(one_to_one, other)``: dicts as :attr:`CGNSInfo.one_to_one` / ``other_connectivity``."""
        t = self.tree
        ones, other = [], []
        for zn, zone in enumerate(self.zones):
            zgc, zgcnode = t.child(zone.group, "ZoneGridConnectivity", zone.node,
                                   "ZoneGridConnectivity_t", required=False)
            if zgc is None:
                continue
            for name, g, node in t.children(zgc, zgcnode):
                label = t.label(g, node)
                if label == "GridConnectivity_t":
                    gtype = "Overset"
                    ct, ctnode = t.child(g, "GridConnectivityType", node, required=False)
                    if ct is not None:
                        gtype = t.string(ct, ctnode)
                    other.append(dict(zone=zone.name, name=name, type=gtype, donor=t.string(g, node),
                                      node=node))
                    continue
                if label != "GridConnectivity1to1_t":
                    continue
                donor = t.string(g, node)
                if "/" in donor:
                    dbase, _, dzone = donor.partition("/")
                    if dbase != self.name:
                        t.fail(node, f"donor zone {donor!r} is in another base; tfi_quat reads one base")
                    donor = dzone
                if donor not in self.index:
                    t.fail(node, f"donor zone {donor!r} is not a zone of base {self.name!r}")
                lo, hi, rnode, r = self._range(g, node, zone)
                dzone_ = self.zones[self.index[donor]]
                dlo, dhi, dnode, dr = self._range(g, node, dzone_, "PointRangeDonor")
                tr, trnode = t.child(g, "Transform", node, required=False)
                if tr is None:
                    transform = list(range(1, self.idim + 1))
                else:
                    transform = [int(v) for v in t.ints(tr, trnode, (self.idim,))]
                    if sorted(abs(v) for v in transform) != list(range(1, self.idim + 1)):
                        t.fail(trnode, f"{transform} is not a signed permutation of "
                                       f"{list(range(1, self.idim + 1))}")
                ones.append(dict(zone=zone.name, name=name, donor=donor, range=_one_based(lo, hi, self.idim),
                                 donor_range=_one_based(dlo, dhi, self.idim), transform=transform,
                                 node=node, block=zn, donor_block=self.index[donor],
                                 lo=lo, hi=hi, dlo=dlo, dhi=dhi, rnode=rnode, dnode=dnode))
        return ones, other

    def interface(self, rec) -> Interface:
        """The canonical :class:`Interface` of one 1-to-1 record."""
        t = self.tree
        zone, dzone = self.zones[rec["block"]], self.zones[rec["donor_block"]]
        lo, hi, dlo, dhi = rec["lo"], rec["hi"], rec["dlo"], rec["dhi"]
        self._check_in(lo, hi, zone, rec["rnode"], rec["range"])
        self._check_in(dlo, dhi, dzone, rec["dnode"], rec["donor_range"])
        face = self._face(lo, hi, zone, rec["rnode"], rec["range"])
        dface = self._face(dlo, dhi, dzone, rec["dnode"], rec["donor_range"])
        tr = list(rec["transform"]) + [3] * (3 - self.idim)
        T = np.zeros((3, 3), dtype=np.int64)
        for m, v in enumerate(tr):
            T[abs(v) - 1, m] = 1 if v > 0 else -1
        d, a, b = face_axes(face)
        ds = face_axes(dface)[0]
        where = (f"{rec['node']}: zone {zone.name!r} {_show(rec['range'])} -> zone {dzone.name!r} "
                 f"{_show(rec['donor_range'])}, Transform {rec['transform']}")
        if abs(tr[d]) != ds + 1:
            t.fail(where, f"the Transform does not map the normal of face {face} onto the normal "
                          f"of donor face {dface}")
        # the normal entry continues the index space through the interface (see topology.model)
        side_m = 1 if face.endswith("max") else -1
        side_s = 1 if dface.endswith("max") else -1
        tr[d] = -side_m * side_s * (ds + 1)
        T[:, d] = 0
        T[ds, d] = 1 if tr[d] > 0 else -1
        img = T @ (np.array(hi) - np.array(lo))
        if not np.array_equal(img, np.array(dhi) - np.array(dlo)):
            t.fail(where, "PointRangeDonor is not the image of PointRange under the Transform")
        mb = list(lo)
        mb[a], mb[b] = min(lo[a], hi[a]), min(lo[b], hi[b])
        sb = T @ (np.array(mb) - np.array(lo)) + np.array(dlo)
        rng = ((min(lo[a], hi[a]), max(lo[a], hi[a])), (min(lo[b], hi[b]), max(lo[b], hi[b])))
        _, da, db = face_axes(dface)
        srng = ((min(dlo[da], dhi[da]), max(dlo[da], dhi[da])), (min(dlo[db], dhi[db]), max(dlo[db], dhi[db])))
        try:
            it = Interface(PatchSpec(rec["block"], face, rng), PatchSpec(rec["donor_block"], dface, srng),
                           tuple(tr), tuple(mb), tuple(int(v) for v in sb))
        except ConnectivityError as exc:
            t.fail(where, str(exc))
        key1 = (it.master.block, face_index(it.master.face))
        key2 = (it.slave.block, face_index(it.slave.face))
        if key2 < key1 or (key1 == key2 and (it.slave.range[0][0], it.slave.range[1][0]) <
                           (it.master.range[0][0], it.master.range[1][0])):
            it = it.reversed()
        return it

    def connectivity(self, grid=None) -> Connectivity | None:
        """The :class:`Connectivity` of the base (None when it has no BC and no 1-to-1 record).

        With ``grid``, the points of every interface are checked to coincide.
        """
        t = self.tree
        bcs = self.bcs()
        ones, _ = self.connectivity_records()
        if not bcs and not ones:
            return None
        interfaces, nodes = [], []
        for rec in ones:
            it = self.interface(rec)
            if it in interfaces:
                nodes[interfaces.index(it)].append(rec)
                continue
            interfaces.append(it)
            nodes.append([rec])
        patches = [Patch(b["spec"], b["kind"], b["family"] or b["resolved"], origin="file") for b in bcs]
        dims = [z.dims for z in self.zones]
        try:
            conn = Connectivity(interfaces, patches, self.ndim, dims)
        except ConnectivityError as exc:
            raise GridFormatError(f"{t.path}: {self.node}: {exc}") from None

        def name(item):
            role, n = item
            if role == "patch":
                return bcs[n]["node"]
            return " and ".join(r["node"] for r in nodes[n])
        overlaps = conn.overlaps()
        if overlaps:
            first, second = overlaps[0]
            spec = conn.item_spec(second)
            raise GridFormatError(f"{t.path}: {name(second)} overlaps {name(first)} (zone "
                                  f"{self.zones[spec.block].name!r} face {spec.face})")
        if grid is not None:
            from ..topology.search import check_interfaces

            def where(n):
                recs = nodes[n]
                r = recs[0]
                return (f"{t.path}: {' and '.join(x['node'] for x in recs)} (zone {r['zone']!r} "
                        f"{_show(r['range'])}, donor zone {r['donor']!r} {_show(r['donor_range'])})")
            try:
                check_interfaces(conn, grid, where)
            except ConnectivityError as exc:
                raise GridFormatError(str(exc)) from None
        return conn

    # ------------------------------------------------------------------ coordinates
    def blocks(self, allow_nonfinite: bool, max_points, ids=None):
        """The zones' blocks (those numbered ``ids``, 0-based, when given) and whether any is R4."""
        t = self.tree
        zones = self.zones if ids is None else [self.zones[n] for n in ids]
        what = f"{len(self.zones)} zone(s)" if ids is None else f"{len(zones)} of {len(self.zones)} zone(s)"
        check_points(f"{t.path}: base {self.name!r}, {what}",
                     sum(int(np.prod(z.dims)) for z in zones), max_points=max_points)
        blocks, single = [], False
        for z in zones:
            xyz = alloc(z.dims + (3,), np.float64, t.path, f"zone {z.name!r}")
            if len(z.coords) < 3:
                xyz[..., 2] = 0.0
            for c, (cname, ds, cnode, dtype) in enumerate(z.coords):
                single = single or dtype.itemsize == 4
                view = xyz[..., c].T if self.idim == 3 else xyz[:, :, 0, c].T
                try:
                    ds.read(h5py.h5s.ALL, h5py.h5s.ALL, view, mtype=_mem_type(view.dtype))
                except (OSError, TypeError, ValueError) as exc:
                    t.fail(cnode, f"cannot read: {exc}")
            if not allow_nonfinite:
                check_finite(xyz, t.path, f"zone {z.name!r}", f"{z.node}/GridCoordinates")
            blocks.append(Block(xyz, None, z.name, allow_nonfinite=True))
        return blocks, single


    def faces(self, allow_nonfinite: bool, ids=None) -> list:
        """Every zone's faces (:func:`tfi_quat.grid.faces_of`): through a memory map of the file
        where a coordinate array is stored contiguously, else one hyperslab per face and coordinate."""
        t = self.tree
        mm = map_file(t.path)
        try:
            return [self._zone_faces(z, mm, allow_nonfinite) if ids is None or n in ids else None
                    for n, z in enumerate(self.zones)]
        finally:
            close_map(mm)

    def _zone_faces(self, z: _Zone, mm, allow_nonfinite: bool) -> tuple:
        t = self.tree
        mapped = []
        for cname, ds, cnode, dtype in z.coords:
            try:
                fdt = ds.dtype
            except (OSError, TypeError, ValueError):
                fdt = None
            off = None
            if mm is not None and fdt is not None and fdt.kind == "f" and fdt.itemsize == dtype.itemsize:
                off = mapped_offset(ds, int(np.prod(z.dims)) * fdt.itemsize, len(mm))
            mapped.append((off, fdt))
        if all(off is not None for off, _ in mapped):
            faces = empty_faces(z.dims, self.ndim)      # z = 0 in a base of physical dimension 2
            for c, (off, fdt) in enumerate(mapped):
                coord = np.ndarray(z.dims, dtype=fdt, buffer=mm, offset=off, order="F")
                fill_faces(faces, c, coord, self.ndim)
                del coord
            if not allow_nonfinite:
                for f, arr in zip(faces_of(self.ndim), faces):
                    d, side = face_axis(f)
                    check_finite(arr, t.path, f"zone {z.name!r} face {f}", f"{z.node}/GridCoordinates",
                                 face=(d, z.dims[d] - 1 if side else 0))
            return tuple(faces)
        return self._zone_face_slabs(z, allow_nonfinite)

    def _zone_face_slabs(self, z: _Zone, allow_nonfinite: bool) -> tuple:
        """A zone's faces, one hyperslab per face and coordinate (any storage libhdf5 reads)."""
        t = self.tree
        faces = []
        for f in faces_of(self.ndim):
            d, side = face_axis(f)
            arr = np.zeros(face_shape(z.dims, f) + (3,), dtype=np.float64, order="F")
            # the data's axes are the zone's index axes reversed: (k, j, i) or (j, i)
            shape = tuple(reversed(z.dims[:self.idim]))
            ax = self.idim - 1 - d
            start = [0] * self.idim
            start[ax] = z.dims[d] - 1 if side else 0
            count = list(shape)
            count[ax] = 1
            tmp = np.empty(count, dtype=np.float64)
            plane = [1 if m == d else z.dims[m] for m in range(3)]
            idx = [slice(None)] * 3
            idx[d] = 0
            for c, (cname, ds, cnode, dtype) in enumerate(z.coords):
                try:
                    fspace = ds.get_space()
                    fspace.select_hyperslab(tuple(start), tuple(count))
                    mspace = h5py.h5s.create_simple(tuple(count))
                    ds.read(mspace, fspace, tmp, mtype=_mem_type(tmp.dtype))
                except (OSError, TypeError, ValueError) as exc:
                    t.fail(cnode, f"cannot read face {f}: {exc}")
                arr[..., c] = tmp.T.reshape(plane, order="C")[tuple(idx)]
            if not allow_nonfinite:
                check_finite(arr, t.path, f"zone {z.name!r} face {f}", f"{z.node}/GridCoordinates",
                             face=(d, start[ax]))
            faces.append(arr)
        return tuple(faces)


def _one_based(lo, hi, idim) -> list:
    return [[v + 1 for v in lo[:idim]], [v + 1 for v in hi[:idim]]]


def _show(r) -> str:
    r = np.asarray(r).tolist()
    return f"[{', '.join('[' + ', '.join(map(str, c)) + ']' for c in r)}]"


# ----------------------------------------------------------------------------- reading

@damaged_file_errors
def read(path, *, base: str | None = None, allow_nonfinite: bool = False,
         max_points: int | None = None, blocks=None) -> Grid:
    """Read a CGNS/HDF5 file: the structured zones of one base with their connectivity.

    Parameters
    ----------
    path : str or path-like
    blocks : list of int, optional
        Read only these zones (0-based, in the base's order, which a full
        read keeps), in this order; the grid's ``block_ids`` records them
        and it carries no ``connectivity`` (:func:`read_faces` has it).
    base : str, optional
        Name of the ``CGNSBase_t`` to read (default: the first).
    allow_nonfinite : bool
        Accept NaN or infinite coordinates (default: GridFormatError).
    max_points : int, optional
        Refuse a base declaring more points (default: what fits in memory),
        before anything is allocated.

    Returns
    -------
    Grid
        One block per zone (named after it), ``xyz`` float64 ``(ni, nj, nk, 3)``
        Fortran order (nk = 1 for a base of cell dimension 2);
        ``source_format`` a :class:`CGNSFormat`, ``source_path`` the path,
        ``connectivity`` a :class:`~tfi_quat.topology.Connectivity` (patches
        from ``ZoneBC`` with ``name`` the BC type or family and
        ``origin="file"``, interfaces from ``GridConnectivity1to1_t``) or None.

    Raises
    ------
    GridFormatError
        An ADF file (convert it with ``adf2hdf``), not HDF5, damaged metadata,
        no base (or no base named ``base``), an unstructured zone, missing or
        malformed nodes, a BC or 1-to-1 range off the zone's faces, a
        ``PointList`` that is not a whole rectangle, 1-to-1 records whose points
        do not coincide or that overlap, more points than ``max_points``;
        each naming the file and the node.
    FileNotFoundError, IsADirectoryError, PermissionError
        From the operating system, naming the path.
    """
    p = Path(os.fspath(path))
    with _tree(p) as t:
        b = _Base(t, base)
        ids = None if blocks is None else block_numbers(p, blocks, len(b.zones))
        got, single = b.blocks(allow_nonfinite, max_points, ids)
        try:
            grid = Grid(got, b.ndim, source_format=CGNSFormat(b.name, single, os.path.abspath(p)), source_path=p)
        except GridValueError as exc:
            raise GridFormatError(f"{p}: base {b.name!r}: {exc}") from None
        if ids is None:
            grid.connectivity = b.connectivity(grid)
        else:
            grid.block_ids = tuple(ids)
    return grid


@damaged_file_errors
def read_faces(path, *, base: str | None = None, allow_nonfinite: bool = False, blocks=None) -> GridFaces:
    """Read the faces of every zone of a CGNS base (hyperslabs), their dims and connectivity.

    Parameters
    ----------
    path : str or path-like
    base : str, optional
        Name of the ``CGNSBase_t`` (default: the first).
    allow_nonfinite : bool
        Accept NaN or infinite coordinates on the faces.
    blocks : list of int, optional
        Read the faces of these zones only (0-based); the dims of all.

    Returns
    -------
    GridFaces
        With ``connectivity`` as :func:`read` gives it, except that the
        points of the 1-to-1 interfaces are not checked to coincide (that
        needs the volumes); ``source_format`` says R4 when any zone is.

    Raises
    ------
    GridFormatError
        As :func:`read`.
    """
    p = Path(os.fspath(path))
    with _tree(p) as t:
        b = _Base(t, base)
        ids = None if blocks is None else block_numbers(p, blocks, len(b.zones))
        faces = b.faces(allow_nonfinite, ids)
        single = any(dtype.itemsize == 4 for z in b.zones for *_, dtype in z.coords)
        return GridFaces(b.ndim, [z.dims for z in b.zones], faces, [z.name for z in b.zones], os.fspath(p),
                         CGNSFormat(b.name, single, os.path.abspath(p)), b.connectivity(),
                         None if ids is None else tuple(ids))


@damaged_file_errors
def info(path, *, base: str | None = None) -> CGNSInfo:
    """Describe a CGNS file from its metadata (no coordinates are read).

    Parameters
    ----------
    path : str or path-like
    base : str, optional
        The base to describe in detail (default: the first).

    Returns
    -------
    CGNSInfo
    """
    p = Path(os.fspath(path))
    with _tree(p) as t:
        b = _Base(t, base)
        bases = []
        for name, g, node, cd, pd in b.all:
            bases.append((name, cd, pd, [z for z, *_ in t.children(g, node, "Zone_t")]))
        zones = [(z.name, z.dims, "R4" if z.coords[0][3].itemsize == 4 else "R8") for z in b.zones]
        keep = ("zone", "name", "type", "family", "resolved", "kind", "face", "range", "node")
        bcs = [{k: r[k] for k in keep} for r in b.bcs()]
        ones, other = b.connectivity_records()
        keep1 = ("zone", "name", "donor", "range", "donor_range", "transform", "node")
        return CGNSInfo(os.fspath(p), bases, b.name, zones, bcs, [{k: r[k] for k in keep1} for r in ones], other)


# ----------------------------------------------------------------------------- writing

def _tid(size: int):
    tid = h5py.h5t.C_S1.copy()
    tid.set_size(size)
    tid.set_strpad(h5py.h5t.STR_NULLTERM)
    return tid


class _Writer:
    """Creates CGNS nodes with the attributes of the CGNS/HDF5 mapping.

    Works on h5py's low-level identifiers (FileID, GroupID): a CGNS tree has
    hundreds of small nodes, and the high-level objects cost more per node.
    """

    def __init__(self):
        self.s33, self.s3 = _tid(33), _tid(3)
        self.scalar = h5py.h5s.create(h5py.h5s.SCALAR)
        self.one = h5py.h5s.create_simple((1,))
        self.flag = np.array([1], dtype=np.int32)
        # children listed in creation order, as the CGNS library lists them
        self.gcpl = h5py.h5p.create(h5py.h5p.GROUP_CREATE)
        self.gcpl.set_link_creation_order(h5py.h5p.CRT_ORDER_TRACKED | h5py.h5p.CRT_ORDER_INDEXED)
        self.dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        self.dcpl.set_obj_track_times(False)

    def group(self, parent, name: str):
        """A new child group of ``parent`` (a FileID or GroupID): its GroupID."""
        return h5py.h5g.create(parent, name.encode("ascii"), gcpl=self.gcpl)

    def data(self, g, arr: np.ndarray, key: bytes = b" data") -> None:
        """Dataset ``key`` of ``g`` holding the C-contiguous ``arr`` (contiguous layout)."""
        arr = np.ascontiguousarray(arr)
        space = h5py.h5s.create_simple(arr.shape) if arr.shape else self.scalar
        tid = _mem_type(arr.dtype)  # the native type, stored as it is
        ds = h5py.h5d.create(g, key, tid, space, dcpl=self.dcpl)
        ds.write(h5py.h5s.ALL, h5py.h5s.ALL, arr, mtype=tid)

    def _str_attr(self, gid, key: bytes, text: str, tid, size: int):
        aid = h5py.h5a.create(gid, key, tid, self.scalar)
        aid.write(np.array(text.encode("ascii")[:size - 1].ljust(size, b"\0"), dtype=f"S{size}"), mtype=tid)

    def attrs(self, gid, name: str, label: str, dtype: str, flags: bool = True):
        self._str_attr(gid, b"name", name, self.s33, 33)
        self._str_attr(gid, b"label", label, self.s33, 33)
        self._str_attr(gid, b"type", dtype, self.s3, 3)
        if flags:
            aid = h5py.h5a.create(gid, b"flags", h5py.h5t.NATIVE_INT32, self.one)
            aid.write(self.flag, mtype=h5py.h5t.NATIVE_INT32)

    def node(self, parent, name: str, label: str, data=None, dtype: str | None = None):
        """Create a node; ``data`` a str (C1), an int array (I4/I8) or float array (R4/R8)."""
        g = self.group(parent, name)
        if data is None:
            self.attrs(g, name, label, "MT")
            return g
        if isinstance(data, str):
            arr, dtype = np.frombuffer(data.encode("ascii"), dtype=np.int8), "C1"
        else:
            arr = np.asarray(data)
            if dtype is None:
                dtype = {("i", 4): "I4", ("i", 8): "I8", ("f", 4): "R4", ("f", 8): "R8"}[
                    (arr.dtype.kind, arr.dtype.itemsize)]
        self.attrs(g, name, label, dtype)
        self.data(g, arr)
        return g


def _valid_name(name: str) -> bool:
    return 0 < len(name) <= _NAME_LEN and "/" not in name and name not in (".", "..") and \
        not name.startswith(" ") and name.isascii()


def _zone_names(grid: Grid) -> list[str]:
    names, seen = [], set()
    for n, b in enumerate(grid.blocks):
        name = b.name if b.name and _valid_name(b.name) else f"block{n + 1}"
        base, k = name, 1
        while name in seen:
            k += 1
            suffix = f"_{k}"
            name = base[:_NAME_LEN - len(suffix)] + suffix
        seen.add(name)
        names.append(name)
    return names


#: the type written for a kind when no more specific one is known
_PLAIN = {"wall": "BCWall", "symmetry": "BCSymmetryPlane", "fixed": "BCFarfield"}


def _bc_type(p: Patch) -> str | None:
    """The BCType written for a patch (None: not written, see :func:`write`)."""
    name = p.name or ""
    if p.kind == "wall":
        return name if name in BC_TYPES and bc_kind(name) == "wall" else "BCWall"
    if p.kind == "symmetry":
        return "BCSymmetryPlane"
    if p.kind == "fixed":
        ok = name in BC_TYPES and bc_kind(name) == "fixed" and name not in ("FamilySpecified", "Null")
        return name if ok else "BCFarfield"
    return None


def _family_of(p: Patch, families) -> str | None:
    if not families:
        return None
    for key in (p, p.name, p.kind):
        if key is not None and key in families:
            fam = families[key]
            if not isinstance(fam, str) or not _valid_name(fam):
                raise GridValueError(f"families: {fam!r} for {key!r} is not a valid CGNS name "
                                     f"(1 to {_NAME_LEN} ASCII characters, no '/')")
            return fam
    return None


def _range_array(lo, hi, idim):
    return np.array([list(lo)[:idim], list(hi)[:idim]], dtype=np.int32) + 1


def _write_records(w: _Writer, base_g, zone_groups, names, conn: Connectivity, families, idim: int,
                   zbc_keep=None):
    """ZoneBC, families and both 1-to-1 records of every interface of ``conn``."""
    fam_types: dict = {}
    bc_rows = [[] for _ in zone_groups]
    for p in conn.patches:
        bctype = _bc_type(p)
        if bctype is None:
            continue
        fam = _family_of(p, families)
        if fam is not None:
            if fam in names:
                raise GridValueError(f"families: family {fam!r} has the name of a zone")
            have = fam_types.setdefault(fam, bctype)
            if have != bctype:
                if bc_kind(have) != bc_kind(bctype):
                    raise GridValueError(f"families: family {fam!r} holds patches of kinds "
                                         f"{bc_kind(have)} ({have}) and {bc_kind(bctype)} ({bctype})")
                # one type per family: the plain type of the kind
                fam_types[fam] = _PLAIN[bc_kind(bctype)]
        bc_rows[p.spec.block].append((p, bctype, fam))
    for fam, bctype in fam_types.items():
        if base_g.links.exists(fam.encode("ascii")):  # a family of the copied file: kept as it is
            continue
        fg = w.node(base_g, fam, "Family_t")
        w.node(fg, "FamilyBC", "FamilyBC_t", bctype)
    for zn, rows in enumerate(bc_rows):
        if not rows:
            continue
        zbc = w.node(zone_groups[zn], "ZoneBC", "ZoneBC_t")
        used = set()
        for p, bctype, fam in rows:
            s = p.spec
            stem = f"{fam or bctype}_{s.face}"[:_NAME_LEN - 4]
            name, k = stem, 1
            while name in used:
                k += 1
                name = f"{stem}_{k}"
            used.add(name)
            g = w.node(zbc, name, "BC_t", "FamilySpecified" if fam else bctype)
            lo, hi = _spec_corners(s, conn.dims[s.block])
            w.node(g, "PointRange", "IndexRange_t", _range_array(lo, hi, idim))
            if fam:
                w.node(g, "FamilyName", "FamilyName_t", fam)
    zgc = {}

    def conn_group(zn):
        if zn not in zgc:
            zg = zone_groups[zn]
            zgc[zn] = h5py.h5o.open(zg, b"ZoneGridConnectivity") if zg.links.exists(b"ZoneGridConnectivity") \
                else w.node(zg, "ZoneGridConnectivity", "ZoneGridConnectivity_t")
        return zgc[zn]

    for n, it in enumerate(conn.interfaces):
        for side, rec in (("", it), ("_donor", it.reversed())):
            zn, dn = rec.master.block, rec.slave.block
            g = w.node(conn_group(zn), f"interface{n + 1}{side}", "GridConnectivity1to1_t", names[dn])
            w.node(g, "PointRange", "IndexRange_t", _range_array(*rec.point_range, idim))
            w.node(g, "PointRangeDonor", "IndexRange_t", _range_array(*rec.point_range_donor, idim))
            w.node(g, "Transform", _LABEL_TRANSFORM, np.array(rec.transform[:idim], dtype=np.int32))


def _spec_corners(s: PatchSpec, dims):
    d, a, b = face_axes(s.face)
    lo, hi = [0, 0, 0], [0, 0, 0]
    lo[d] = hi[d] = 0 if s.face.endswith("min") else dims[d] - 1
    (lo[a], hi[a]), (lo[b], hi[b]) = s.range
    return lo, hi


def _root(w: _Writer, f: h5py.File):
    w.attrs(f, "HDF5 MotherNode", "Root Node of HDF5 File", "MT", flags=False)
    fmt = b"IEEE_LITTLE_32\0" if np.little_endian else b"IEEE_BIG_32\0"
    w.data(f, np.frombuffer(fmt, dtype=np.int8), b" format")
    ver = f"HDF5 Version {h5py.version.hdf5_version}".encode("ascii")[:32].ljust(33, b"\0")
    w.data(f, np.frombuffer(ver, dtype=np.int8), b" hdf5version")


def _coords(w: _Writer, zg, block: Block, ndim: int, single: bool):
    gc = w.node(zg, "GridCoordinates", "GridCoordinates_t")
    xyz = block.xyz
    for c, cname in enumerate(("CoordinateX", "CoordinateY", "CoordinateZ")[:ndim]):
        view = xyz[..., c].T if ndim == 3 else xyz[:, :, 0, c].T
        g = w.group(gc, cname)
        w.attrs(g, cname, "DataArray_t", "R4" if single else "R8")
        w.data(g, view.astype(np.float32) if single else view)


def _write_new(path, grid: Grid, base: str, single: bool, conn, families):
    w = _Writer()
    ndim = grid.ndim
    names = _zone_names(grid)
    with h5py.File(path, "x", libver=("v108", "v108"), track_order=True) as fh:
        f = fh.id
        _root(w, f)
        w.node(f, "CGNSLibraryVersion", "CGNSLibraryVersion_t", np.array([LIBRARY_VERSION], dtype=np.float32))
        bg = w.node(f, base, "CGNSBase_t", np.array([ndim, ndim], dtype=np.int32))
        zgs = []
        for b, name in zip(grid.blocks, names):
            dims = list(b.dims[:ndim])
            size = np.array([dims, [max(1, d - 1) for d in dims], [0] * ndim], dtype=np.int64)
            zg = w.node(bg, name, "Zone_t", size.astype(np.int32) if size.max() <= 2**31 - 1 else size)
            w.node(zg, "ZoneType", "ZoneType_t", "Structured")
            _coords(w, zg, b, ndim, single)
            zgs.append(zg)
        if conn is not None:
            _write_records(w, bg, zgs, names, conn, families, ndim)


def _copy_attrs_node(w: _Writer, t: _Tree, src: str, dst_parent, key: str):
    """A new group ``key`` of ``dst_parent`` with the name, label, type (and flags) of node ``src``."""
    g = w.group(dst_parent, key)
    sid = t.obj(src)
    for a in ("name", "label", "type"):
        size = 3 if a == "type" else 33
        text = t.attr(src, a, src) if h5py.h5a.exists(sid, a.encode()) else ""
        w._str_attr(g, a.encode(), text, w.s3 if size == 3 else w.s33, size)
    if h5py.h5a.exists(sid, b"flags"):
        h5py.h5a.create(g, b"flags", h5py.h5t.NATIVE_INT32, w.one).write(w.flag, mtype=h5py.h5t.NATIVE_INT32)
    return g


def _copy(t: _Tree, src: str, key: str, dst) -> None:
    """Copy child ``key`` of node ``src`` (and everything below it) into ``dst`` (``H5Ocopy``),
    or the link itself when it is a soft or external one."""
    loc = t.f.id if src == "" else t.obj(src)
    kb = key.encode("utf-8", "surrogateescape")
    ltype = t.links(src)[key]
    if ltype == h5py.h5l.TYPE_HARD:
        h5py.h5o.copy(loc, kb, dst, kb)
    elif ltype == h5py.h5l.TYPE_SOFT:
        dst.links.create_soft(kb, loc.links.get_val(kb))
    elif ltype == h5py.h5l.TYPE_EXTERNAL:
        filename, obj = loc.links.get_val(kb)
        dst.links.create_external(kb, filename, obj)


def _write_like(path, grid: Grid, fmt: CGNSFormat, single: bool, conn, families):
    """Copy the tree of ``fmt.source``, replacing the coordinates of ``fmt.base`` (and the records
    when ``conn`` is given).

    Every subtree that stays as it is (other bases, families, flow solutions,
    ``ZoneBC`` without ``conn``, ...) is copied whole by HDF5 (``H5Ocopy``);
    only the base, its zones and their ``GridCoordinates`` are made anew.
    """
    src_path = Path(fmt.source)
    w = _Writer()
    with _tree(src_path) as t:
        b = _Base(t, fmt.base)
        if len(b.zones) != grid.nblocks or any(z.dims != blk.dims for z, blk in zip(b.zones, grid.blocks)):
            raise GridValueError(
                f"like={src_path}: base {fmt.base!r} holds zones of sizes "
                f"{[z.dims for z in b.zones]}, the grid blocks {[blk.dims for blk in grid.blocks]}; "
                "write without like (keep=False) to make a new file")
        if b.ndim != grid.ndim:
            raise GridValueError(f"like={src_path}: base {fmt.base!r} is {b.ndim}-D, the grid {grid.ndim}-D")
        zone_keys = {z.group: n for n, z in enumerate(b.zones)}
        with h5py.File(path, "x", libver=("v108", "v108"), track_order=True) as fh:
            f = fh.id
            names = []
            h5py.h5a.iterate(t.f.id, lambda name, *_: names.append(name))
            for a in names:
                key = a.decode("utf-8", "replace")
                w._str_attr(f, a, t.attr("", key, "/"), w.s3 if key == "type" else w.s33,
                            3 if key == "type" else 33)
            for key, ltype in t.links("").items():
                if ltype != h5py.h5l.TYPE_HARD or key != fmt.base:
                    _copy(t, "", key, f)
                    continue
                bsrc = b.node
                bdst = _copy_attrs_node(w, t, bsrc, f, key)
                zgs = []
                for ck, cltype in t.links(bsrc).items():
                    zsrc = f"{bsrc}/{ck}"
                    if cltype != h5py.h5l.TYPE_HARD or zsrc not in zone_keys:
                        _copy(t, bsrc, ck, bdst)
                        continue
                    n = zone_keys[zsrc]
                    zdst = _copy_attrs_node(w, t, zsrc, bdst, ck)
                    for zk, zltype in t.links(zsrc).items():
                        if zltype != h5py.h5l.TYPE_HARD:
                            _copy(t, zsrc, zk, zdst)
                        elif zk == "GridCoordinates":
                            _replace_coords(w, t, f"{zsrc}/{zk}", zdst, grid.blocks[n], grid.ndim, single)
                        elif conn is not None and zk == "ZoneBC":
                            continue
                        elif conn is not None and zk == "ZoneGridConnectivity":
                            gsrc = f"{zsrc}/{zk}"
                            zg = _copy_attrs_node(w, t, gsrc, zdst, zk)
                            for ck2, ltype2 in t.links(gsrc).items():
                                node = f"{gsrc}/{ck2}"
                                if ltype2 == h5py.h5l.TYPE_HARD and t.is_group(node) \
                                        and t.label(node, node) == "GridConnectivity1to1_t":
                                    continue
                                _copy(t, gsrc, ck2, zg)
                        else:
                            _copy(t, zsrc, zk, zdst)
                    zgs.append(zdst)
                if conn is not None:
                    _write_records(w, bdst, zgs, [z.name for z in b.zones], conn, families, grid.ndim)


def _replace_coords(w: _Writer, t: _Tree, gsrc: str, zdst, block: Block, ndim: int, single: bool):
    gdst = _copy_attrs_node(w, t, gsrc, zdst, "GridCoordinates")
    names = ("CoordinateX", "CoordinateY", "CoordinateZ")[:ndim]
    links = t.links(gsrc)
    for key in links:
        if key not in names:
            _copy(t, gsrc, key, gdst)
    xyz = block.xyz
    for c, cname in enumerate(names):
        view = xyz[..., c].T if ndim == 3 else xyz[:, :, 0, c].T
        g = w.group(gdst, cname)
        w.attrs(g, cname, "DataArray_t", "R4" if single else "R8")
        w.data(g, view.astype(np.float32) if single else view)
        csrc = f"{gsrc}/{cname}"
        if links.get(cname) == h5py.h5l.TYPE_HARD and t.is_group(csrc):
            for extra in t.links(csrc):  # DataClass, DimensionalUnits, ... of the coordinate
                if extra != " data":
                    _copy(t, csrc, extra, g)


def write(path, grid: Grid, *, like=None, overwrite: bool = False, connectivity=None, families=None,
          single: bool | None = None, base: str | None = None, keep: bool = True) -> None:
    """Write a grid as a CGNS/HDF5 file, atomically.

    Parameters
    ----------
    path : str or path-like
        Target; written to a temporary file in the same folder, renamed into
        place when complete.
    grid : Grid
        One zone per block (named after the block, made unique; ``blockN``
        when unnamed); coordinates ``R8`` from the ``(ni, nj, nk, 3)`` arrays'
        transposed views (no copy), or ``R4`` with ``single``.  A 2-D grid
        gets a base of cell and physical dimension 2 (``CoordinateX/Y``).
    like : CGNSFormat or Grid, optional
        A grid read from a CGNS file (or its ``source_format``): the new file
        is a copy of that file's tree in which only the coordinates of the
        base read are replaced (flow solutions, families, descriptors,
        reference state, other bases and connectivity kept).  Its precision
        is kept unless ``single`` says otherwise.  By default (``keep``) a
        grid read from a CGNS file is written like that file.
    overwrite : bool
        Allow replacing the grid's own input file (``grid.source_path``).
    connectivity : Connectivity, optional
        Boundary patches and interfaces to write (default: ``grid.connectivity``
        for a new file).  Written as ``ZoneBC`` (BCType from the kind: wall ->
        the patch name when it is a ``BCWall*`` type, else ``BCWall``;
        symmetry -> ``BCSymmetryPlane``; fixed -> the name when it is a CGNS
        BCType of that kind, else ``BCFarfield``) and both
        ``GridConnectivity1to1_t`` records of every interface.  Patches of
        kind ``free`` are not written: they are derived from the grid by the
        deformer (collapsed faces), and every CGNS type would read back as
        another kind.  Given together with ``like``, it replaces the copied
        file's ``ZoneBC`` and 1-to-1 records (other connectivity kept).
    families : dict, optional
        Family names for patches, keyed by :class:`~tfi_quat.topology.Patch`,
        patch name or kind: the BCs get ``FamilySpecified`` and a
        ``FamilyName``, the base a ``Family_t`` with its ``FamilyBC``.
    single : bool, optional
        Coordinates as float32 (``R4``); default: as ``like``, else float64.
    base : str, optional
        Base name of a new file (default ``like``'s, else ``"Base"``).
    keep : bool
        Write a grid read from a CGNS file like that file (see ``like``);
        False makes a new file.

    Raises
    ------
    OverwriteError
        ``path`` is the grid's input file and ``overwrite`` is false.
    GridValueError
        Not a Grid; ``like``'s file no longer matches the grid; bad family names.
    """
    if not isinstance(grid, Grid):
        raise GridValueError(f"write needs a Grid, got {type(grid).__name__}")
    like = getattr(like, "source_format", like)
    if like is None and keep and isinstance(grid.source_format, CGNSFormat):
        like = grid.source_format
    fmt = like if isinstance(like, CGNSFormat) else None
    if single is None:
        single = bool(fmt.single) if fmt is not None else False
    copy = fmt is not None and fmt.source is not None
    if copy and not Path(fmt.source).is_file():
        raise GridValueError(f"like: the file {fmt.source} that the grid was read from is gone; "
                             "pass keep=False to write a new file")
    conn_default = getattr(grid, "connectivity", None)
    conn = connectivity if connectivity is not None else (None if copy else conn_default)
    if conn is not None:
        if not isinstance(conn, Connectivity):
            raise GridValueError(f"connectivity must be a Connectivity, got {type(conn).__name__}")
        try:
            conn.check(grid)
        except ConnectivityError as exc:
            raise GridValueError(f"connectivity: {exc}") from None
    name = base or (fmt.base if fmt is not None else "Base")
    if not _valid_name(name):
        raise GridValueError(f"base name {name!r} is not a valid CGNS name")
    target = check_target(path, overwrite=overwrite, protect=[grid.source_path])
    with atomic_output(target, mode="path") as tmp:
        os.unlink(tmp)
        try:
            if copy:
                _write_like(tmp, grid, fmt, single, conn, families)
            else:
                _write_new(tmp, grid, name, single, conn, families)
        except TfiQuatError:
            raise
        except (OSError, KeyError, RuntimeError) as exc:
            raise GridFormatError(f"{target}: cannot write CGNS file: {exc}") from None


from . import register  # noqa: E402  (registers the format on import)

register("cgns", (".cgns",), read, write, CGNSFormat, read_faces)
