"""HDF5 grid files: a documented, versioned layout (h5py).

Layout, version 1
-----------------
::

    /                        root group
      @format    "tfi_quat-grid"          string, identifies the layout
      @version   1                        int, layout version
      @ndim      2 | 3                    int
      @nblocks   N                        int
      @creator   "tfi_quat 0.1.0"         string, provenance
      @created   "2026-01-31T12:00:00Z"   string, UTC time of writing (ISO 8601)
      @source    "wing.x"                 string, file the grid was read from ("" if none)
      @source_format  "Plot3DFormat(...)" string, variant of that file ("" if none)
    /blocks                  group, one member per block
      /blocks/000001         group of block 1 (1-based, zero-padded to 6 digits)
        @name    "wing"                   string ("" when the block has no name)
        @dims    [ni, nj, nk]             int64[3]
        xyz      float64, shape (3, nk, nj, ni)
        iblank   int32,   shape (nk, nj, ni)      optional
      /blocks/000002 ...
    /extra                   optional scalar UTF-8 string: a JSON object

**Coordinates.**  A block's ``xyz`` in memory is ``(ni, nj, nk, 3)`` float64 in
Fortran order: all x with i fastest, then all y, then all z (the Plot3D
whole-block order).  HDF5 and h5py describe arrays in C order, and the C-order
description of exactly those bytes is ``(3, nk, nj, ni)``: that is the shape
of the ``xyz`` dataset, so ``dataset[c, k, j, i]`` is component ``c`` of point
``(i, j, k)``.  Writing stores ``Block.xyz.T`` (a view, no copy); reading
allocates the Fortran array and has HDF5 fill its transpose view in place
(no copy either).  ``iblank`` is stored the same way, ``(nk, nj, ni)``.
Uncompressed datasets use HDF5's contiguous layout, so a block's coordinates
are one run of bytes in the file, exactly as in a Plot3D binary file.
Compressed datasets (gzip with the shuffle filter) are chunked in near-cubic
chunks of at most 64 Ki values (one coordinate component per chunk, e.g.
``(1, 40, 40, 40)``), so a face read touches only the chunks along that face.

**Extra data.**  ``/extra`` holds arbitrary JSON text attached by the writer
(``write(..., extra_json=...)``, read back with :func:`read_extra`).  Its
top-level keys ``"connectivity"`` and ``"patches"`` are reserved for the
connectivity and boundary-patch descriptions of later tfi_quat versions.

**Versions.**  Readers accept layouts up to :data:`LAYOUT_VERSION` and reject
newer ones.  Additions that a version-1 reader can safely ignore (new
attributes, new root members) do not change the version.

Reading one block (:func:`read_block`) or one face (:func:`read_face`) uses
hyperslab selections and never loads the rest of the file.
"""

from __future__ import annotations

import datetime as _dt
import functools
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from ..errors import GridFormatError, GridValueError, TfiQuatError
from ..grid import FACES, Block, Grid, face_index
from ._atomic import atomic_output, check_target

__all__ = ["HDF5Format", "HDF5Info", "read", "write", "read_block", "read_face", "info",
           "read_extra", "is_hdf5", "FORMAT_NAME", "LAYOUT_VERSION"]

#: value of the root attribute ``format``
FORMAT_NAME = "tfi_quat-grid"
#: layout version written (and the newest one read)
LAYOUT_VERSION = 1
#: values per chunk of a compressed dataset (at most)
_CHUNK_VALUES = 1 << 16
_COMPRESSIONS = ("gzip",)
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


@dataclass(frozen=True)
class HDF5Format:
    """The variant of an HDF5 grid file (kept in ``Grid.source_format``).

    Attributes
    ----------
    compression : {None, "gzip"}
        Compression filter of the coordinate datasets.
    compression_level : int or None
        gzip level 0..9 (None when uncompressed).
    shuffle : bool
        Byte-shuffle filter before compression (written with gzip).
    version : int
        Layout version of the file.
    """

    compression: str | None = None
    compression_level: int | None = None
    shuffle: bool = False
    version: int = LAYOUT_VERSION

    def replace(self, **changes) -> "HDF5Format":
        from dataclasses import replace
        return replace(self, **changes)

    def describe(self) -> str:
        """One line for people, e.g. ``layout v1, gzip level 4 + shuffle``."""
        if not self.compression:
            return f"layout v{self.version}, uncompressed"
        shuffle = " + shuffle" if self.shuffle else ""
        return f"layout v{self.version}, {self.compression} level {self.compression_level}{shuffle}"


@dataclass(frozen=True)
class HDF5Info:
    """What :func:`info` finds in an HDF5 grid file without reading coordinates.

    Attributes
    ----------
    path : str
    ndim : int
    dims : list of tuple of int
        ``(ni, nj, nk)`` of each block, in file order.
    names : list of str or None
    iblank : list of bool
        Whether each block has an iblank dataset.
    format : HDF5Format
    creator, created, source : str
        Provenance attributes ("" when absent).
    has_extra : bool
        The file holds an ``/extra`` JSON dataset.
    """

    path: str
    ndim: int
    dims: list = field(default_factory=list)
    names: list = field(default_factory=list)
    iblank: list = field(default_factory=list)
    format: HDF5Format = HDF5Format()
    creator: str = ""
    created: str = ""
    source: str = ""
    has_extra: bool = False

    @property
    def nblocks(self) -> int:
        return len(self.dims)

    @property
    def npoints(self) -> int:
        return sum(int(np.prod(d)) for d in self.dims)


# ----------------------------------------------------------------------------- helpers

def _block_group_name(n: int) -> str:
    """Group name of block ``n`` (0-based), e.g. ``'000001'`` for n = 0."""
    return f"{n + 1:06d}"


def is_hdf5(path) -> bool:
    """Whether ``path`` is a file with an HDF5 signature (at offset 0, 512, 1024, ...)."""
    p = Path(os.fspath(path))
    try:
        size = p.stat().st_size
        with open(p, "rb") as fh:
            off = 0
            while off + 8 <= size:
                fh.seek(off)
                if fh.read(8) == _HDF5_SIGNATURE:
                    return True
                off = 512 if off == 0 else off * 2
    except OSError:
        return False
    return False


def _as_str(value) -> str:
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.ndarray) and value.shape == ():
        return _as_str(value[()])
    return str(value)


def _as_int(value, what: str, path) -> int:
    arr = np.asarray(value)
    if arr.shape not in ((), (1,)) or not np.issubdtype(arr.dtype, np.integer):
        raise GridFormatError(f"{path}: {what} must be one integer, got {value!r}")
    return int(arr.reshape(()))


class _Reader:
    """An open HDF5 grid file, checked at the root; checks blocks on demand."""

    def __init__(self, path):
        self.path = path
        p = Path(os.fspath(path)) if not hasattr(path, "read") else None
        if p is not None:
            if not p.exists():
                raise FileNotFoundError(f"{p}: no such file")
            if p.is_dir():
                raise GridFormatError(f"{p}: is a directory, not a grid file")
            if p.stat().st_size == 0:
                raise GridFormatError(f"{p}: empty file, not an HDF5 grid")
            if not is_hdf5(p):
                raise GridFormatError(f"{p}: not an HDF5 file (no HDF5 signature)")
        try:
            self.f = h5py.File(path, "r")
        except OSError as exc:
            raise GridFormatError(f"{path}: cannot open as HDF5: {exc}") from None
        try:
            self._check_root()
        except BaseException:
            self.f.close()
            raise

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()

    def _attr(self, obj, name: str, where: str):
        if name not in obj.attrs:
            raise GridFormatError(f"{self.path}: {where} has no attribute {name!r}; "
                                  f"not a {FORMAT_NAME} file (layout v{LAYOUT_VERSION})")
        try:
            return obj.attrs[name]
        except OSError as exc:
            raise GridFormatError(f"{self.path}: {where}: cannot read attribute {name!r}: {exc}") from None

    def _check_root(self) -> None:
        f, path = self.f, self.path
        fmt = _as_str(self._attr(f, "format", "root group"))
        if fmt != FORMAT_NAME:
            raise GridFormatError(f"{path}: root attribute format = {fmt!r}, expected {FORMAT_NAME!r}")
        self.version = _as_int(self._attr(f, "version", "root group"), "root attribute 'version'", path)
        if self.version < 1 or self.version > LAYOUT_VERSION:
            raise GridFormatError(f"{path}: layout version {self.version} is not supported "
                                  f"(this tfi_quat reads versions 1..{LAYOUT_VERSION})")
        self.ndim = _as_int(self._attr(f, "ndim", "root group"), "root attribute 'ndim'", path)
        if self.ndim not in (2, 3):
            raise GridFormatError(f"{path}: root attribute ndim = {self.ndim}, expected 2 or 3")
        self.nblocks = _as_int(self._attr(f, "nblocks", "root group"), "root attribute 'nblocks'", path)
        if self.nblocks < 1:
            raise GridFormatError(f"{path}: root attribute nblocks = {self.nblocks}, expected >= 1")
        if "blocks" not in f or not isinstance(f["blocks"], h5py.Group):
            raise GridFormatError(f"{path}: group /blocks is missing")
        self.blocks = f["blocks"]

    def index(self, b) -> int:
        """0-based block number of ``b`` (an int, negative from the end, or a block name)."""
        if isinstance(b, str):
            for n in range(self.nblocks):
                g = self.group(n)
                if _as_str(g.attrs.get("name", "")) == b:
                    return n
            raise GridValueError(f"{self.path}: no block named {b!r}")
        if isinstance(b, bool) or not isinstance(b, (int, np.integer)):
            raise GridValueError(f"block must be an int (0-based) or a block name, got {b!r}")
        n = int(b) + (self.nblocks if b < 0 else 0)
        if not 0 <= n < self.nblocks:
            raise GridValueError(f"{self.path}: block {b} out of range: the file holds "
                                 f"{self.nblocks} block(s) (0-based 0..{self.nblocks - 1})")
        return n

    def group(self, n: int) -> h5py.Group:
        name = _block_group_name(n)
        if name not in self.blocks or not isinstance(self.blocks[name], h5py.Group):
            raise GridFormatError(f"{self.path}: block {n + 1}: group /blocks/{name} is missing "
                                  f"(root attribute nblocks = {self.nblocks})")
        return self.blocks[name]

    def meta(self, n: int):
        """Checked metadata of block ``n``: (name, dims, xyz dataset, iblank dataset or None)."""
        g = self.group(n)
        where = f"block {n + 1} (/blocks/{_block_group_name(n)})"
        name = _as_str(self._attr(g, "name", where)) or None
        dims = np.asarray(self._attr(g, "dims", where))
        if dims.shape != (3,) or not np.issubdtype(dims.dtype, np.integer):
            raise GridFormatError(f"{self.path}: {where}: attribute dims must be 3 integers "
                                  f"(ni, nj, nk), got {dims!r}")
        dims = tuple(int(d) for d in dims)
        if min(dims) < 1:
            raise GridFormatError(f"{self.path}: {where}: dims {dims} must all be >= 1")
        if self.ndim == 2 and dims[2] != 1:
            raise GridFormatError(f"{self.path}: {where}: a 2-D grid needs nk = 1, got dims {dims}")
        ni, nj, nk = dims
        xyz = self._dataset(g, "xyz", where, (3, nk, nj, ni), "f")
        ib = None
        if "iblank" in g:
            ib = self._dataset(g, "iblank", where, (nk, nj, ni), "iu")
        return name, dims, xyz, ib

    def _dataset(self, g, key, where, shape, kinds) -> h5py.Dataset:
        if key not in g:
            raise GridFormatError(f"{self.path}: {where}: dataset {key!r} is missing")
        ds = g[key]
        dsname = f"{where}, dataset {ds.name}"
        if not isinstance(ds, h5py.Dataset):
            raise GridFormatError(f"{self.path}: {dsname} is not a dataset")
        if ds.shape != shape:
            raise GridFormatError(f"{self.path}: {dsname}: shape {ds.shape} does not match the "
                                  f"block dims (expected {shape})")
        if ds.dtype.kind not in kinds:
            raise GridFormatError(f"{self.path}: {dsname}: dtype {ds.dtype} is not "
                                  f"{'a float' if kinds == 'f' else 'an integer'} type")
        # every value must be stored: HDF5 would return fill values for missing data
        if ds.chunks is None:
            stored, need = ds.id.get_storage_size(), ds.size * ds.dtype.itemsize
            if stored < need:
                raise GridFormatError(f"{self.path}: {dsname}: only {stored} of {need} bytes "
                                      "are stored (incomplete dataset)")
        else:
            nchunks = int(np.prod([-(-s // c) for s, c in zip(ds.shape, ds.chunks)]))
            have = ds.id.get_num_chunks()
            if have < nchunks:
                raise GridFormatError(f"{self.path}: {dsname}: only {have} of {nchunks} chunks "
                                      "are stored (incomplete dataset)")
        return ds

    def read_into(self, ds, out: np.ndarray, where: str, sel=None) -> None:
        """Fill ``out`` (C-contiguous, the dataset's selection shape) from ``ds``."""
        try:
            if sel is None:
                ds.read_direct(out)
            else:
                ds.read_direct(out, source_sel=sel)
        except (OSError, TypeError, ValueError) as exc:
            raise GridFormatError(f"{self.path}: {where}, dataset {ds.name}: cannot read: {exc}") from None

    def variant(self) -> HDF5Format:
        for n in range(self.nblocks):
            ds = self.group(n).get("xyz")
            if isinstance(ds, h5py.Dataset) and ds.compression:
                level = ds.compression_opts if isinstance(ds.compression_opts, int) else None
                return HDF5Format(str(ds.compression), level, bool(ds.shuffle), self.version)
        return HDF5Format(version=self.version)

    def block(self, n: int, allow_nonfinite: bool) -> Block:
        name, dims, xyz_ds, ib_ds = self.meta(n)
        where = f"block {n + 1}"
        xyz = np.empty(dims + (3,), dtype=np.float64, order="F")
        self.read_into(xyz_ds, xyz.T, where)
        if not allow_nonfinite:
            _check_finite(xyz, self.path, where, xyz_ds.name)
        ib = None
        if ib_ds is not None:
            ib = np.empty(dims, dtype=np.int32, order="F")
            self.read_into(ib_ds, ib.T, where)
        return Block(xyz, ib, name, allow_nonfinite=True)


def _check_finite(arr: np.ndarray, path, where: str, dataset: str, face=None) -> None:
    """Raise GridFormatError at the first NaN/inf of ``arr``, shape (ni, nj, nk, 3).

    For a face array ``(na, nb, 3)``, ``face = (d, pos)`` puts back the fixed
    index ``pos`` of block axis ``d`` so the message names the block point.

    One reduction pass (no temporaries) when every value is finite; the exact
    scan runs only to locate a bad value (or after a sum that overflowed).
    """
    flat = arr.ravel(order="K")
    with np.errstate(over="ignore", invalid="ignore"):
        if np.isfinite(np.add.reduce(flat)):
            return
    bad = ~np.isfinite(arr)
    if not bad.any():
        return
    idx = np.argwhere(bad)[0]
    pt = [int(i) for i in idx[:-1]]
    if face is not None:
        pt.insert(face[0], face[1])
    pt = tuple(i + 1 for i in pt)
    raise GridFormatError(
        f"{path}: {where}, dataset {dataset}: {int(bad.sum())} non-finite coordinate value(s); "
        f"first at point {pt} (1-based), component {'xyz'[int(idx[-1])]} "
        "(pass allow_nonfinite=True to accept)")


# ----------------------------------------------------------------------------- reading

def _damaged_file_errors(fn):
    """Turn h5py's errors on a damaged file (KeyError, RuntimeError, ...) into GridFormatError."""
    @functools.wraps(fn)
    def wrapper(path, *args, **kwargs):
        try:
            return fn(path, *args, **kwargs)
        except (TfiQuatError, FileNotFoundError):
            raise
        except (OSError, KeyError, RuntimeError, TypeError) as exc:
            raise GridFormatError(f"{path}: damaged or unreadable HDF5 grid file "
                                  f"({type(exc).__name__}: {exc})") from exc
    return wrapper


@_damaged_file_errors
def read(path, *, allow_nonfinite: bool = False) -> Grid:
    """Read an HDF5 grid file (layout :data:`LAYOUT_VERSION` or older).

    Parameters
    ----------
    path : str or path-like
    allow_nonfinite : bool
        Accept NaN or infinite coordinates (default: GridFormatError).

    Returns
    -------
    Grid
        Blocks with ``xyz`` float64 ``(ni, nj, nk, 3)`` Fortran order (filled by
        HDF5 in place) and ``iblank`` int32 ``(ni, nj, nk)`` where stored;
        ``source_format`` an :class:`HDF5Format`, ``source_path`` the path.

    Raises
    ------
    GridFormatError
        Not an HDF5 file, missing groups/attributes/datasets (named), an
        unsupported layout version, a dataset whose shape or dtype does not
        match its block's dims, an incomplete dataset, non-finite coordinates.
    """
    with _Reader(path) as r:
        blocks = [r.block(n, allow_nonfinite) for n in range(r.nblocks)]
        variant = r.variant()
        try:
            return Grid(blocks, r.ndim, source_format=variant, source_path=path)
        except GridValueError as exc:
            raise GridFormatError(f"{path}: {exc}") from None


@_damaged_file_errors
def read_block(path, b, *, allow_nonfinite: bool = False) -> Block:
    """Read one block, and nothing else, from an HDF5 grid file.

    Parameters
    ----------
    path : str, path-like, or binary file object
    b : int or str
        0-based block number (negative counts from the end) or block name.
    allow_nonfinite : bool
        Accept NaN or infinite coordinates.

    Returns
    -------
    Block
        ``xyz`` float64 ``(ni, nj, nk, 3)`` Fortran order, ``iblank`` int32 or None.
    """
    with _Reader(path) as r:
        return r.block(r.index(b), allow_nonfinite)


@_damaged_file_errors
def read_face(path, b, face, *, allow_nonfinite: bool = False) -> np.ndarray:
    """Read the points of one face of one block (a hyperslab), and nothing else.

    Parameters
    ----------
    path : str, path-like, or binary file object
    b : int or str
        0-based block number or block name.
    face : str or int
        ``"imin" "imax" "jmin" "jmax" "kmin" "kmax"`` or 0..5.
    allow_nonfinite : bool
        Accept NaN or infinite coordinates.

    Returns
    -------
    ndarray, float64, shape (na, nb, 3), Fortran order
        Equal to ``Block.face(face)`` of the block: imin/imax -> ``(nj, nk, 3)``,
        jmin/jmax -> ``(ni, nk, 3)``, kmin/kmax -> ``(ni, nj, 3)``.
    """
    f = face_index(face)
    with _Reader(path) as r:
        n = r.index(b)
        _, dims, xyz_ds, _ = r.meta(n)
        d, side = divmod(f, 2)
        pos = dims[d] - 1 if side else 0
        run = [dims[a] for a in range(3) if a != d]
        out = np.empty((run[0], run[1], 3), dtype=np.float64, order="F")
        # dataset axes are (c, k, j, i): block axis a is dataset axis 3 - a
        sel = [slice(None)] * 4
        sel[3 - d] = slice(pos, pos + 1)
        view = out.T.reshape(tuple(1 if a == 3 - d else s for a, s in
                                   enumerate((3, dims[2], dims[1], dims[0]))))
        where = f"block {n + 1} face {FACES[f]}"
        r.read_into(xyz_ds, view, where, np.s_[tuple(sel)])
        if not allow_nonfinite:
            _check_finite(out, path, where, xyz_ds.name, face=(d, pos))
        return out


@_damaged_file_errors
def info(path) -> HDF5Info:
    """Describe an HDF5 grid file from its metadata only (no coordinates are read).

    Parameters
    ----------
    path : str, path-like, or binary file object

    Returns
    -------
    HDF5Info
        ndim, per-block dims, names and iblank presence, variant, provenance.
    """
    with _Reader(path) as r:
        metas = [r.meta(n) for n in range(r.nblocks)]
        return HDF5Info(
            path=os.fspath(path) if not hasattr(path, "read") else str(path),
            ndim=r.ndim,
            dims=[m[1] for m in metas],
            names=[m[0] for m in metas],
            iblank=[m[3] is not None for m in metas],
            format=r.variant(),
            creator=_as_str(r.f.attrs.get("creator", "")),
            created=_as_str(r.f.attrs.get("created", "")),
            source=_as_str(r.f.attrs.get("source", "")),
            has_extra="extra" in r.f,
        )


@_damaged_file_errors
def read_extra(path) -> dict | None:
    """Return the JSON object stored in ``/extra``, or None when the file has none.

    Raises
    ------
    GridFormatError
        ``/extra`` is not a string dataset holding a JSON object.
    """
    with _Reader(path) as r:
        if "extra" not in r.f:
            return None
        ds = r.f["extra"]
        if not isinstance(ds, h5py.Dataset) or ds.shape != () or ds.dtype.kind not in "OSU":
            raise GridFormatError(f"{path}: /extra must be a scalar string dataset")
        text = _as_str(ds[()])
        try:
            obj = json.loads(text)
        except ValueError as exc:
            raise GridFormatError(f"{path}: dataset /extra is not valid JSON: {exc}") from None
        if not isinstance(obj, dict):
            raise GridFormatError(f"{path}: dataset /extra must hold a JSON object, "
                                  f"got {type(obj).__name__}")
        return obj


# ----------------------------------------------------------------------------- writing

def _chunks(shape: tuple[int, ...]) -> tuple[int, ...]:
    """Near-cubic chunk shape of at most ``_CHUNK_VALUES`` values.

    ``shape`` is ``(3, nk, nj, ni)`` (one component per chunk) or
    ``(nk, nj, ni)``.  Axes are filled smallest first, each with the side that
    a cube of the remaining budget would have, so a short axis (nk = 1 in 2-D)
    leaves its share to the others.
    """
    dims = list(shape[-3:])
    c = [1, 1, 1]
    budget = _CHUNK_VALUES
    for r, a in enumerate(sorted(range(3), key=lambda a: dims[a])):
        side = int(np.floor(budget ** (1.0 / (3 - r)) + 1e-9))
        c[a] = max(1, min(dims[a], side))
        budget = max(1, budget // c[a])
    return (1, *c) if len(shape) == 4 else tuple(c)


def _resolve_compression(compression, compression_level, like):
    base = like if isinstance(like, HDF5Format) else None
    if compression is None:
        compression = base.compression if base is not None else None
        if compression_level is None and base is not None:
            compression_level = base.compression_level
    elif compression is False or (isinstance(compression, str) and compression.lower() == "none"):
        compression = None
    elif compression is True:
        compression = "gzip"
    if compression is not None:
        compression = str(compression).lower()
        if compression not in _COMPRESSIONS:
            raise GridValueError(f"compression {compression!r} is not supported: "
                                 f"use None or {', '.join(map(repr, _COMPRESSIONS))}")
        level = 4 if compression_level is None else compression_level
        if isinstance(level, bool) or not isinstance(level, (int, np.integer)) or not 0 <= level <= 9:
            raise GridValueError(f"compression_level must be an int 0..9, got {compression_level!r}")
        return compression, int(level)
    return None, None


def write(path, grid: Grid, *, like=None, overwrite: bool = False, compression=None,
          compression_level: int | None = None, extra_json: dict | None = None) -> None:
    """Write a grid as an HDF5 file (layout :data:`LAYOUT_VERSION`), atomically.

    Parameters
    ----------
    path : str or path-like
        Target; written to a temporary file in the same folder, renamed into
        place when complete.
    grid : Grid
        Blocks ``xyz`` float64 ``(ni, nj, nk, 3)`` Fortran order, stored as the
        ``(3, nk, nj, ni)`` C-order view of the same bytes (no copy).
    like : HDF5Format or Grid, optional
        Take the compression settings of this variant (or of a grid read from
        HDF5) where ``compression`` / ``compression_level`` are not given.
    overwrite : bool
        Allow replacing the grid's own input file (``grid.source_path``).
    compression : {None, False, "none", "gzip", True}
        None: as ``like``, else uncompressed.  False or "none": uncompressed
        (contiguous datasets).  "gzip" or True: gzip with the shuffle filter,
        chunked datasets.
    compression_level : int, optional
        gzip level 0..9 (default: ``like``'s, else 4).
    extra_json : dict, optional
        A JSON-serialisable object stored as text in ``/extra``
        (see :func:`read_extra`).

    Raises
    ------
    OverwriteError
        ``path`` is the grid's input file and ``overwrite`` is false.
    GridValueError
        Not a Grid, an unknown compression, ``extra_json`` not a JSON object.
    """
    if not isinstance(grid, Grid):
        raise GridValueError(f"write needs a Grid, got {type(grid).__name__}")
    like = getattr(like, "source_format", like)
    comp, level = _resolve_compression(compression, compression_level, like)
    extra_text = None
    if extra_json is not None:
        if not isinstance(extra_json, dict):
            raise GridValueError(f"extra_json must be a dict, got {type(extra_json).__name__}")
        try:
            extra_text = json.dumps(extra_json, allow_nan=False, sort_keys=True)
        except (TypeError, ValueError) as exc:
            raise GridValueError(f"extra_json is not JSON-serialisable: {exc}") from None
    target = check_target(path, overwrite=overwrite, protect=[grid.source_path])
    with atomic_output(target, mode="path") as tmp:
        # Let HDF5 create the file rather than truncate the empty temporary
        # one: on ext4, closing a file that was opened with O_TRUNC forces a
        # flush of all its data (auto_da_alloc), 0.15 s per 0.5 GB.
        os.unlink(tmp)
        _write_file(tmp, grid, comp, level, extra_text)


def _write_file(path, grid: Grid, comp, level, extra_text) -> None:
    """Create the HDF5 file ``path`` (it must not exist) holding ``grid``: the bytes of a write."""
    from .. import __version__
    src_fmt = "" if grid.source_format is None else repr(grid.source_format)
    with h5py.File(path, "x") as f:
        f.attrs["format"] = FORMAT_NAME
        f.attrs["version"] = np.int64(LAYOUT_VERSION)
        f.attrs["ndim"] = np.int64(grid.ndim)
        f.attrs["nblocks"] = np.int64(grid.nblocks)
        f.attrs["creator"] = f"tfi_quat {__version__}"
        f.attrs["created"] = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
        f.attrs["source"] = "" if grid.source_path is None else str(grid.source_path)
        f.attrs["source_format"] = src_fmt
        blocks = f.create_group("blocks")
        for n, b in enumerate(grid.blocks):
            g = blocks.create_group(_block_group_name(n))
            g.attrs["name"] = b.name or ""
            g.attrs["dims"] = np.asarray(b.dims, dtype=np.int64)
            _write_array(g, "xyz", b.xyz.T, comp, level)
            if b.iblank is not None:
                _write_array(g, "iblank", np.asarray(b.iblank, dtype=np.int32, order="F").T,
                             comp, level)
        if extra_text is not None:
            f.create_dataset("extra", data=extra_text, dtype=h5py.string_dtype("utf-8"),
                             track_times=False)


def _write_array(g: h5py.Group, key: str, data: np.ndarray, comp, level) -> None:
    """Store a C-contiguous array as dataset ``key`` (contiguous, or chunked + gzip)."""
    if comp is None:
        g.create_dataset(key, data=data, track_times=False)
    else:
        g.create_dataset(key, data=data, chunks=_chunks(data.shape), compression=comp,
                         compression_opts=level, shuffle=True, track_times=False)


from . import register  # noqa: E402  (registers the format on import)

register("hdf5", (".h5", ".hdf5", ".hdf"), read, write, HDF5Format)
