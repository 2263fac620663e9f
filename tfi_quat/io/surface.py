"""Surface files (``MODES.h5``): the wall point copies of a Deformer with mode shapes.

A structural code describes the motion of a wall by mode shapes, one
displacement vector per wall point and unit amplitude.  The surface file
carries them with the wall points they belong to, identified as
:meth:`tfi_quat.Deformer.surface_ids` identifies them, so that the file can
be checked against the grid it is applied to.
:meth:`~tfi_quat.Deformer.write_surface` writes the template (the ids and
the undeformed points, with or without modes); a user fills in the modes
from the structural model; :meth:`~tfi_quat.Deformer.modal` and
``tfi-quat deform --modes`` read it back.

Layout, version 1
-----------------
::

    /                        root group
      @format    "tfi_quat-surface"       string, identifies the layout
      @version   1                        int, layout version
      @ndim      2 | 3                    int, of the grid
      @creator   "tfi_quat 0.1.0"         string, provenance
      @created   "2026-01-31T12:00:00Z"   string, UTC time of writing (ISO 8601)
      @source    "wing.x"                 string, the grid's file ("" if none)
    ids          int64,   shape (n, 4)            block (0-based), i, j, k (0-based) per row
    points       float64, shape (n, 3)            undeformed x, y, z of each row
    modes        float64, shape (n_modes, n, 3)   mode shapes: displacement per unit amplitude
    names        UTF-8 strings, shape (n_modes,)  optional: a name per mode

``n`` is the number of wall point copies: a point on a wall edge or on an
interface crossing a wall is listed once per patch or block holding it
(:meth:`~tfi_quat.Deformer.surface_ids`).  The rows may come in any order,
but each copy must be listed exactly once, and the mode vectors of the
copies of one point must agree (within the Deformer's ``dup_tol``).  A
template without modes has ``modes`` of shape ``(0, n, 3)``.

**Reading.**  :func:`read_surface` walks the file's metadata in a guarded
child process first (:func:`tfi_quat.io.hdf5.guard`), checks every dataset's
shape and dtype before reading it (and the row count against ``n_points``
when given, before anything is allocated), and refuses non-finite values;
every error names the file and the dataset.  Matching the ids to a
Deformer's wall is the Deformer's job (:meth:`~tfi_quat.Deformer.modal`).
"""

from __future__ import annotations

import datetime as _dt
import os
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from ..errors import GridFormatError, GridValueError
from ._atomic import atomic_output, check_target
from ._limits import check_points
from .hdf5 import alloc, damaged_file_errors, guard, is_hdf5

__all__ = ["SurfaceFile", "read_surface", "write_surface", "check_names", "FORMAT_NAME", "LAYOUT_VERSION"]

#: value of the root attribute ``format``
FORMAT_NAME = "tfi_quat-surface"
#: layout version written (and the newest one read)
LAYOUT_VERSION = 1
#: HDF5 file-format objects of HDF5 1.10: every piece of metadata is checksummed
_LIBVER = ("v110", "v110")


@dataclass(frozen=True)
class SurfaceFile:
    """The contents of a surface file (:func:`read_surface`).

    Attributes
    ----------
    path : str
        The file read.
    ids : ndarray, int64, shape (n, 4)
        ``(block, i, j, k)``, 0-based, in the file's row order.
    points : ndarray, float64, shape (n, 3)
        Undeformed coordinates of the rows.
    modes : ndarray, float64, shape (n_modes, n, 3)
        Mode shapes (displacement per unit amplitude), rows as ``ids``.
    names : tuple of str
        One name per mode (``"mode 1"``, ... when the file has none).
    ndim : int
        The grid's dimension (2 or 3), as written.
    """

    path: str
    ids: np.ndarray
    points: np.ndarray
    modes: np.ndarray
    names: tuple
    ndim: int

    @property
    def n_modes(self) -> int:
        """The number of mode shapes."""
        return int(self.modes.shape[0])


def _set_text(obj, name: str, text: str) -> None:
    data = text.encode("utf-8")
    obj.attrs.create(name, np.bytes_(data), dtype=h5py.string_dtype("utf-8", max(1, len(data))))


def check_names(names, n_modes: int) -> tuple:
    """``names`` as a tuple of ``n_modes`` strings (None: ``"mode 1"``, ...)."""
    if names is None:
        return tuple(f"mode {m + 1}" for m in range(n_modes))
    if isinstance(names, str):
        names = names.split(",")
    names = tuple(names)
    if len(names) != n_modes or not all(isinstance(s, str) for s in names):
        raise GridValueError(f"names must be {n_modes} strings, one per mode, got {names!r}")
    return names


def write_surface(path, ids, points, modes=None, names=None, *, ndim: int = 3, source: str = "",
                  overwrite: bool = False, protect=()) -> None:
    """Write a surface file (layout :data:`LAYOUT_VERSION`), atomically.

    :meth:`tfi_quat.Deformer.write_surface` is the usual way in: it passes the
    Deformer's wall.

    Parameters
    ----------
    path : str or path-like
        Target; written to a temporary file in the same folder, renamed into
        place when complete.
    ids : array_like, int, shape (n, 4)
        ``(block, i, j, k)``, 0-based.
    points : array_like, float, shape (n, 3)
        Undeformed coordinates of the rows.
    modes : array_like, float, shape (n_modes, n, 3), optional
        Mode shapes in the rows' order; None writes a template with no modes.
    names : sequence of str, optional
        One name per mode (stored only when given).
    ndim : {2, 3}
        The grid's dimension.
    source : str
        The grid's file, for provenance.
    overwrite : bool
        Allow replacing a file in ``protect`` (the inputs of the operation).

    Raises
    ------
    GridValueError
        Shapes that do not fit together, non-finite values, names not one per mode.
    OverwriteError
        ``path`` is one of ``protect`` and ``overwrite`` is false.
    """
    ids = np.asarray(ids)
    if ids.ndim != 2 or ids.shape[1] != 4 or not np.issubdtype(ids.dtype, np.integer):
        raise GridValueError(f"ids must be integers of shape (n, 4), got {ids.dtype} {ids.shape}")
    n = ids.shape[0]
    points = np.asarray(points, dtype=np.float64)
    if points.shape != (n, 3):
        raise GridValueError(f"points must have shape ({n}, 3), got {points.shape}")
    if modes is None:
        modes = np.zeros((0, n, 3))
    modes = np.asarray(modes, dtype=np.float64)
    if modes.ndim != 3 or modes.shape[1:] != (n, 3):
        raise GridValueError(f"modes must have shape (n_modes, {n}, 3), got {modes.shape}")
    for what, arr in (("points", points), ("modes", modes)):
        if not np.all(np.isfinite(arr)):
            raise GridValueError(f"{what} holds {int((~np.isfinite(arr)).sum())} non-finite value(s)")
    if names is not None:
        names = check_names(names, modes.shape[0])
    target = check_target(path, overwrite=overwrite, protect=protect)
    from .. import __version__
    with atomic_output(target, mode="path") as tmp:
        os.unlink(tmp)      # HDF5 creates the file itself
        with h5py.File(tmp, "x", libver=_LIBVER) as f:
            _set_text(f, "format", FORMAT_NAME)
            f.attrs["version"] = np.int64(LAYOUT_VERSION)
            f.attrs["ndim"] = np.int64(ndim)
            _set_text(f, "creator", f"tfi_quat {__version__}")
            _set_text(f, "created", _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"))
            _set_text(f, "source", str(source))
            f.create_dataset("ids", data=ids.astype(np.int64), track_times=False)
            f.create_dataset("points", data=points, track_times=False)
            f.create_dataset("modes", data=modes, track_times=False)
            if names is not None:
                data = [s.encode("utf-8") for s in names]
                width = max([1] + [len(s) for s in data])
                f.create_dataset("names", data=np.array(data, dtype=h5py.string_dtype("utf-8", width)),
                                 track_times=False)


def _as_str(value) -> str:
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value[()]
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    return str(value)


class _Reader:
    """The open file's checks, each error naming the file and the dataset."""

    def __init__(self, f: h5py.File, path: str):
        self.f, self.path = f, path

    def fail(self, what: str):
        return GridFormatError(f"{self.path}: {what}")

    def attr(self, name: str):
        if name not in self.f.attrs:
            raise self.fail(f"root attribute {name!r} is missing; not a {FORMAT_NAME} file")
        return self.f.attrs[name]

    def int_attr(self, name: str) -> int:
        v = np.asarray(self.attr(name))
        if v.shape not in ((), (1,)) or not np.issubdtype(v.dtype, np.integer):
            raise self.fail(f"root attribute {name!r} must be one integer, got {v!r}")
        return int(v.reshape(()))

    def dataset(self, key: str, required: bool = True) -> h5py.Dataset | None:
        link = self.f.get(key, getlink=True)
        if link is None:
            if required:
                raise self.fail(f"dataset /{key} is missing")
            return None
        if not isinstance(link, h5py.HardLink):
            raise self.fail(f"/{key} is a link, not a dataset (links are not followed)")
        ds = self.f[key]
        if not isinstance(ds, h5py.Dataset):
            raise self.fail(f"/{key} is not a dataset")
        return ds

    def array(self, key: str, shape: tuple, kinds: str, what: str) -> np.ndarray:
        """Dataset ``key`` checked for ``shape`` (None entries: any) and dtype kind, read."""
        ds = self.dataset(key)
        if len(ds.shape) != len(shape) or any(s is not None and a != s for a, s in zip(ds.shape, shape)):
            want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
            raise self.fail(f"dataset /{key}: shape {ds.shape}, expected {want} ({what})")
        if ds.dtype.kind not in kinds:
            raise self.fail(f"dataset /{key}: dtype {ds.dtype}, expected "
                            f"{'integers' if 'i' in kinds else 'floating-point numbers'}")
        # a declared size that cannot be held is refused before anything is allocated
        check_points(f"{self.path}: dataset /{key}", ds.size, bytes_per_point=8)
        stored, need = ds.id.get_storage_size(), ds.size * ds.dtype.itemsize
        if ds.chunks is None and stored < need:
            raise self.fail(f"dataset /{key}: only {stored} of {need} bytes are stored "
                            "(incomplete dataset)")
        if ds.chunks is not None and ds.size:
            # HDF5 gives fill values for chunks that were never written
            nchunks = int(np.prod([-(-s // c) for s, c in zip(ds.shape, ds.chunks)]))
            if ds.id.get_num_chunks() < nchunks:
                raise self.fail(f"dataset /{key}: only {ds.id.get_num_chunks()} of {nchunks} "
                                "chunks are stored (incomplete dataset)")
        out = alloc(ds.shape, np.int64 if "i" in kinds else np.float64, self.path,
                    f"dataset /{key}", order="C")
        if out.size:
            try:
                ds.read_direct(out)
            except (OSError, TypeError, ValueError) as exc:
                raise self.fail(f"dataset /{key}: cannot read: {exc}") from None
        return out

    def finite(self, key: str, arr: np.ndarray, ids: np.ndarray) -> None:
        bad = ~np.isfinite(arr)
        if bad.any():
            at = np.argwhere(bad)[0]
            row = int(at[-2])
            where = f"mode {int(at[0]) + 1}, " if arr.ndim == 3 else ""
            raise self.fail(f"dataset /{key}: {int(bad.sum())} non-finite value(s); first at "
                            f"{where}row {row} (block, i, j, k) = {tuple(int(v) for v in ids[row])} "
                            f"(0-based), component {'xyz'[int(at[-1])]}")


@damaged_file_errors
def read_surface(path, *, n_points: int | None = None) -> SurfaceFile:
    """Read and check a surface file (layout :data:`LAYOUT_VERSION` or older).

    Parameters
    ----------
    path : str or path-like
    n_points : int, optional
        The number of rows expected (the Deformer's wall point copies),
        checked before anything is allocated.

    Returns
    -------
    SurfaceFile
        Its arrays, in the file's row order.

    Raises
    ------
    GridFormatError
        Not an HDF5 file, damaged metadata (see :func:`tfi_quat.io.hdf5.guard`),
        not a surface file or a newer layout, a dataset missing or of the wrong
        shape or dtype (named), ids with negative values, non-finite points or
        modes (the first row named), names not one per mode.
    FileNotFoundError, IsADirectoryError, PermissionError
        From the operating system, naming the path.
    """
    p = Path(os.fspath(path))
    with open(p, "rb") as fh:      # the OS's own errors, naming the path
        size = os.fstat(fh.fileno()).st_size
    if size == 0 or not is_hdf5(p):
        raise GridFormatError(f"{p}: not an HDF5 file (no HDF5 signature); a surface file is "
                              "written by Deformer.write_surface or tfi-quat deform --write-surface")
    guard(str(p), str(p))
    try:
        f = h5py.File(p, "r")
    except OSError as exc:
        raise GridFormatError(f"{p}: cannot open as HDF5: {exc}") from None
    with f:
        r = _Reader(f, str(p))
        fmt = _as_str(r.attr("format"))
        if fmt != FORMAT_NAME:
            raise r.fail(f"root attribute format = {fmt!r}, expected {FORMAT_NAME!r}")
        version = r.int_attr("version")
        if not 1 <= version <= LAYOUT_VERSION:
            raise r.fail(f"layout version {version} is not supported (this tfi_quat reads "
                         f"versions 1..{LAYOUT_VERSION})")
        ndim = r.int_attr("ndim")
        if ndim not in (2, 3):
            raise r.fail(f"root attribute ndim = {ndim}, expected 2 or 3")
        ids_ds = r.dataset("ids")
        n = ids_ds.shape[0] if len(ids_ds.shape) == 2 else None
        if n_points is not None and n is not None and n != n_points:
            raise r.fail(f"dataset /ids: {n} rows, expected {n_points} (one per wall point copy "
                         "of the grid's surface_ids())")
        ids = r.array("ids", (n_points, 4), "iu", "block, i, j, k per row")
        n = ids.shape[0]
        if ids.size and ids.min() < 0:
            row = int(np.argwhere(ids < 0)[0][0])
            raise r.fail(f"dataset /ids: row {row} holds a negative index "
                         f"{tuple(int(v) for v in ids[row])}")
        points = r.array("points", (n, 3), "f", "x, y, z per row of /ids")
        r.finite("points", points, ids)
        mds = r.dataset("modes")
        if len(mds.shape) != 3:
            raise r.fail(f"dataset /modes: shape {mds.shape}, expected (n_modes, {n}, 3)")
        modes = r.array("modes", (None, n, 3), "f", "a displacement per row of /ids and mode")
        r.finite("modes", modes, ids)
        names = None
        nds = r.dataset("names", required=False)
        if nds is not None:
            if nds.shape != (modes.shape[0],) or nds.dtype.kind not in "SOU":
                raise r.fail(f"dataset /names: {nds.dtype} of shape {nds.shape}, expected "
                             f"{modes.shape[0]} strings (one per mode)")
            names = tuple(_as_str(v) for v in nds[()])
        names = check_names(names, modes.shape[0])
    for a in (ids, points, modes):
        a.flags.writeable = False
    return SurfaceFile(str(p), ids, points, modes, names, ndim)
