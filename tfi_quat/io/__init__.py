"""Grid file I/O: a small registry of formats.

Each format module registers a reader and a writer with :func:`register`;
:func:`read` and :func:`write` pick the format from the ``format`` argument,
from ``like`` (a grid read earlier, or a format description), or from the
file extension.

===========  ===============================================
format       extensions
===========  ===============================================
``plot3d``   ``.x .xyz .g .grd .p3d .p2dfmt .p3dfmt .fmt .bin .xyzb``
``hdf5``     ``.h5 .hdf5 .hdf``
``cgns``     ``.cgns`` (CGNS/HDF5)
===========  ===============================================

A *target* names a solver whose grid files are one fixed variant of a
format plus an index mapping: ``target="cfl3d"`` (:mod:`tfi_quat.io.cfl3d`)
writes the Fortran Plot3D file NASA's CFL3D reads, 2-D grids mapped to two
planes in its x-z plane, and reads such a file back with the mapping
undone.  A target is never chosen by extension; a grid read with one is
written for it again by ``like=grid``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..errors import GridFormatError, ParallelError

__all__ = ["read", "read_faces", "write", "register", "format_for", "check_readable", "FORMATS", "TARGETS"]


@dataclass(frozen=True)
class _Format:
    name: str
    extensions: tuple[str, ...]
    reader: Callable
    writer: Callable
    #: class of the variant object a reader stores in ``grid.source_format``
    variant_type: type | None = None
    #: a solver target (``target=``): a fixed variant of another format with an index mapping
    target: bool = False
    #: ``faces_reader(path, **kw) -> GridFaces``: the faces of every block (:func:`read_faces`)
    faces_reader: Callable | None = None


#: the registered formats: name -> (name, extensions, reader, writer, variant type), filled by
#: :func:`register` as each format module is imported
FORMATS: dict[str, _Format] = {}


#: names of the registered solver targets (``read(..., target=)``, ``write(..., target=)``)
TARGETS: tuple[str, ...] = ("cfl3d",)


def register(name, extensions, reader, writer, variant_type=None, faces_reader=None) -> None:
    """Register a format: ``reader(path, **kw) -> Grid``, ``writer(path, grid, **kw)``.

    A name in :data:`TARGETS` registers a solver target (no extensions).  A
    format whose reader takes ``blocks=`` (a partial read) also gives
    ``faces_reader(path, **kw) -> GridFaces`` (:func:`read_faces`).
    """
    FORMATS[name] = _Format(name, tuple(e.lower() for e in extensions), reader, writer, variant_type,
                            name in TARGETS, faces_reader)


def _ensure_loaded() -> None:
    # every format module registers itself on import; importing is idempotent, and a
    # module imported directly (e.g. tfi_quat.io.hdf5) must not hide the others
    from . import cfl3d, cgns, hdf5, plot3d  # noqa: F401


_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _has_hdf5_signature(path) -> bool:
    try:
        with open(os.fspath(path), "rb") as fh:
            return fh.read(8) == _HDF5_SIGNATURE
    except OSError:
        return False


def format_for(path=None, format: str | None = None, like=None) -> _Format:
    """Choose the format: explicit name, then ``like``, then the file extension."""
    _ensure_loaded()
    if format is not None:
        key = str(format).lower()
        names = sorted(n for n, f in FORMATS.items() if not f.target)
        if key not in names:
            hint = f" (a grid file for a solver: target={key!r})" if key in TARGETS else ""
            raise GridFormatError(f"unknown format {format!r}: expected one of {', '.join(names)}{hint}")
        return FORMATS[key]
    if like is not None:
        variant = getattr(like, "source_format", like)
        for f in FORMATS.values():
            if f.variant_type is not None and isinstance(variant, f.variant_type):
                return f
    if path is not None:
        name = Path(os.fspath(path)).name.lower()
        for f in FORMATS.values():
            if any(name.endswith(ext) for ext in f.extensions):  # targets have none
                return f
        if _has_hdf5_signature(path):
            return FORMATS["hdf5"]
        raise GridFormatError(
            f"{path}: unknown file extension; give format= ('plot3d', 'hdf5' or 'cgns'), "
            f"known extensions: {', '.join(e for f in FORMATS.values() for e in f.extensions)}")
    raise GridFormatError("no format given and no path or reference grid to infer it from")


def check_readable(path) -> None:
    """Raise the standard OSError for a path that cannot be read as a file.

    FileNotFoundError, IsADirectoryError or PermissionError, exactly as
    ``open`` raises them (errno, message, the path in ``filename`` and in the
    text), so that every reader reports a missing file, a folder or a file
    without read permission the same way, before any format looks at it.
    """
    with open(os.fspath(path), "rb"):
        pass


def _target(target, format) -> _Format:
    """The registry entry of a solver target; ``format`` may only name the format it writes."""
    _ensure_loaded()
    key = str(target).lower()
    if key not in TARGETS:
        raise GridFormatError(f"unknown target {target!r}: expected one of {', '.join(TARGETS)}")
    if format is not None and str(format).lower() not in ("plot3d", key):
        raise GridFormatError(f"target={target!r} is a Plot3D file; format={format!r} contradicts it")
    return FORMATS[key]


def read(path, format: str | None = None, *, target: str | None = None, blocks=None, **kw):
    """Read a grid file, or some of its blocks.

    Parameters
    ----------
    path : str or path-like
    format : {"plot3d", "hdf5", "cgns"}, optional
        Default: from the extension.
    blocks : list of int, optional
        Read only these blocks (0-based numbers in the file, no repeats), in
        this order, and allocate only them: binary Plot3D reads their bytes
        at offsets computed from the header, HDF5 their datasets, CGNS those
        zones (a text Plot3D file is parsed whole, then the blocks kept).
        The grid's ``block_ids`` gives their numbers; its blocks keep the
        names a full read gives them; a CGNS grid read so carries no
        ``connectivity`` (it is made for all blocks: :func:`read_faces` has
        it).  Not with ``target``.
    target : {"cfl3d"}, optional
        The file was written for this solver: read exactly its variant and
        undo its index mapping (:func:`tfi_quat.io.cfl3d.read`; ``ndim=``
        forces 2 or 3).
    **kw
        Passed on to the format's reader (e.g. Plot3D variant overrides,
        the CGNS ``base``, ``allow_nonfinite``, ``max_points``: refuse a file
        declaring more points, before allocating; default what fits in the
        memory available).

    Returns
    -------
    Grid
        With ``source_format`` (the detected variant) and ``source_path`` set
        (CGNS: also ``connectivity``, from the file's BCs and 1-to-1 records).

    Raises
    ------
    FileNotFoundError, IsADirectoryError, PermissionError
        The path is missing, a folder, or not readable (the path in the
        message), whatever the format.
    GridFormatError
        The file is not a grid of the format (or of the target's variant),
        or declares one too large.
    GridValueError
        ``blocks`` empty, repeated, or a number outside the file's blocks
        (naming the file and the block).
    """
    p = Path(os.fspath(path))
    check_readable(p)
    if blocks is None:
        fmt = _target(target, format) if target is not None else format_for(p, format)
        return fmt.reader(p, **kw)
    if target is not None:
        raise GridFormatError(f"{p}: blocks= reads a file as it is stored; it does not combine with "
                              f"target={target!r} (read the file with format='plot3d')")
    return format_for(p, format).reader(p, blocks=blocks, **kw)


def read_faces(path, format: str | None = None, **kw):
    """Read the boundary faces of every block of a grid file, and every block's dims.

    What each rank of a distributed deformation needs besides its own
    blocks: the O(surface) data to build the skeleton and the partition,
    without the volume.  Binary Plot3D touches only the file pages holding
    face values (a memory map: runs for the k and j faces, strided values for
    the i faces), HDF5 and CGNS read one hyperslab per face and coordinate; a
    text Plot3D file is parsed whole.

    Parameters
    ----------
    path : str or path-like
    format : {"plot3d", "hdf5", "cgns"}, optional
        Default: from the extension.
    **kw
        Passed on to the format's faces reader: ``blocks`` (read the faces
        of these 0-based blocks only, the others None: ranks can split the
        face reads and exchange them), ``allow_nonfinite``, Plot3D variant
        overrides, the CGNS ``base``.

    Returns
    -------
    tfi_quat.io.partial.GridFaces
        ``faces[b][f]`` float64 ``(na, nb, 3)``, bit-identical to
        ``read(path)[b].face(f)``; ``dims``, ``names``, ``ndim``.

    Raises
    ------
    FileNotFoundError, IsADirectoryError, PermissionError
    GridFormatError
        As :func:`read`.
    """
    p = Path(os.fspath(path))
    check_readable(p)
    fmt = format_for(p, format)
    if fmt.faces_reader is None:
        raise GridFormatError(f"{p}: the {fmt.name} format has no faces reader")
    return fmt.faces_reader(p, **kw)


def write(path, grid, format: str | None = None, *, like=None, target: str | None = None,
          overwrite: bool = False, comm=None, blocks=None, **kw) -> None:
    """Write a grid file atomically (under MPI: collectively, from each rank's blocks).

    Parameters
    ----------
    path : str or path-like
        Target file; written to a temporary file in the same folder and
        renamed into place.
    grid : Grid
    format : {"plot3d", "hdf5", "cgns"}, optional
        Default: the format of ``like``, else the extension.
    like : Grid or variant, optional
        Write the same variant as this grid was read in (its
        ``source_format``), or as this variant object (a grid read with a
        ``target`` is written for that target again).
    target : {"cfl3d"}, optional
        Write the file this solver reads (:func:`tfi_quat.io.cfl3d.write`:
        Fortran unformatted float64 multi-block Plot3D, 2-D grids as two
        planes in CFL3D's x-z plane); takes no variant options, no ``like``.
    overwrite : bool
        Allow writing over the grid's own input file (``grid.source_path``).
    comm : mpi4py.MPI.Intracomm, optional
        Write one file collectively (:func:`tfi_quat.io.mpi.write`): every
        rank calls ``write`` with its own blocks as ``grid`` (None: none) and
        the same other arguments; the file is byte for byte that of a serial
        write of the whole grid.  Plot3D (binary, Fortran) and HDF5.  Needs
        the ``mpi`` extra: ``pip install "tfi_quat[mpi]"``.
    blocks : sequence of int, optional
        With ``comm``: the 0-based global numbers of this rank's blocks
        (default: the ranks' blocks in rank order).
    **kw
        Variant options of the format's writer (override ``like``).

    Raises
    ------
    ParallelError
        ``comm`` given without mpi4py installed (the message names the
        extra), or not a communicator; ``blocks`` given without ``comm``.
    """
    if comm is not None:
        if target is not None:
            raise GridFormatError(f"{path}: a collective write (comm=) does not write solver "
                                  f"targets (target={target!r})")
        from . import mpi      # imports mpi4py: only under MPI
        return mpi.write(path, grid, comm, blocks=blocks, format=format, like=like,
                         overwrite=overwrite, **kw)
    if blocks is not None:
        raise ParallelError("blocks= numbers a rank's blocks in a collective write; give comm= too")
    if target is not None:
        fmt = _target(target, format)
        if like is not None:
            raise GridFormatError(f"{path}: target={target!r} fixes the file variant; do not give like= too")
        return fmt.writer(path, grid, overwrite=overwrite, **kw)
    fmt = format_for(path, format, like)
    variant = getattr(like, "source_format", like) if like is not None else None
    if variant is not None and fmt.variant_type is not None and not isinstance(variant, fmt.variant_type):
        variant = None
    return fmt.writer(path, grid, like=variant, overwrite=overwrite, **kw)
