"""Collective grid writes under MPI: one file from blocks spread over the ranks.

Every rank of a communicator holds some blocks of a grid (a :class:`Grid` of
its own blocks, or None for none) and knows their global 0-based block
numbers; :func:`write`, called by every rank with the same arguments but its
own blocks, writes the file a serial :func:`tfi_quat.write` of the whole grid
writes, byte for byte.  It is reached through ``tfi_quat.write(path,
local_grid, comm=comm, blocks=[...])`` and imports ``mpi4py`` only then: the
package imports and runs serially without it (``pip install
"tfi_quat[mpi]"`` brings ``mpi4py`` and the MPICH library).

How each format is written:

- **Plot3D** (C binary and Fortran unformatted, every precision, endianness
  and record layout of the serial writer; ASCII has no fixed offsets and is
  refused): rank 0 creates the temporary file and writes the header, every
  rank then writes its blocks at their offsets, computed from all blocks'
  dimensions (gathered from every rank), through its own descriptor, and
  syncs them.  A rank holds only its blocks.
- **HDF5** (the project's layout): the h5py here is not built for parallel
  HDF5, and the bytes of a serial write come only from the same sequence of
  library calls, so rank 0 writes the file and asks each block's owner for
  it when its turn comes (point to point, coordinates as raw buffers): rank
  0 holds its own blocks plus one other at a time, the other ranks their own
  (tests/test_mpi.py measures both).

Atomic as the serial writers (:mod:`tfi_quat.io._atomic`): a temporary file
in the target's folder (which every rank must see: a shared file system),
renamed into place by rank 0 once every rank has written and synced its part.
An error on any rank reaches every rank: each stage ends with an exchange of
the ranks' errors, and every rank then raises the same exception (that of
the lowest failing rank), with the temporary file removed and the target
untouched.  No rank is left waiting.
"""

from __future__ import annotations

import contextlib
import os
import pickle
from pathlib import Path

import numpy as np

from ..errors import GridFormatError, GridValueError, ParallelError
from ..grid import Block, Grid
from ._atomic import check_target, install, new_temp

__all__ = ["write", "require_mpi", "check_comm", "INSTALL_HINT", "portable", "raise_first", "agree",
           "from_root"]

#: how to install what ``comm=`` needs
INSTALL_HINT = 'pip install "tfi_quat[mpi]"'

# message tags of the HDF5 block exchange
_TAG_ASK, _TAG_META, _TAG_DATA = 71, 72, 73


def require_mpi():
    """The ``mpi4py.MPI`` module; ParallelError naming the extra when it is not installed."""
    try:
        from mpi4py import MPI
    except ImportError as exc:
        raise ParallelError(f"comm= needs mpi4py and an MPI library, which are not installed: "
                            f"{INSTALL_HINT}") from exc
    return MPI


def check_comm(comm):
    """The ``mpi4py.MPI`` module; ParallelError unless ``comm`` is an intracommunicator."""
    MPI = require_mpi()
    if not isinstance(comm, MPI.Intracomm):
        raise ParallelError(f"comm= must be an mpi4py intracommunicator (e.g. MPI.COMM_WORLD), "
                            f"got {type(comm).__name__}")
    return MPI


def portable(exc: BaseException | None):
    """``exc`` if it survives pickling (to be raised on another rank), else a ParallelError."""
    if exc is None:
        return None
    try:
        back = pickle.loads(pickle.dumps(exc))
        if type(back) is type(exc) and str(back) == str(exc):
            return exc
    except Exception:
        pass
    return ParallelError(f"{type(exc).__name__}: {exc}")


def raise_first(comm, errors, exc) -> None:
    """Raise the error of the lowest failing rank, on every rank (the original where it arose)."""
    for rank, err in enumerate(errors):
        if err is not None:
            if rank == comm.rank and exc is not None:
                raise exc
            raise err


def agree(comm, exc: BaseException | None) -> None:
    """Collective: every rank raises the first rank's error, or all go on."""
    raise_first(comm, comm.allgather(portable(exc)), exc)


def from_root(comm, exc: BaseException | None, value=None):
    """Collective: rank 0's error raised on every rank, else rank 0's ``value`` on every rank."""
    err, value = comm.bcast((portable(exc), value) if comm.rank == 0 else None, root=0)
    if err is not None:
        raise (exc if comm.rank == 0 and exc is not None else err)
    return value


def _local_part(grid, blocks):
    """This rank's blocks and their 0-based numbers (``blocks=None``: filled in later)."""
    if grid is None:
        if blocks is not None and len(list(blocks)) > 0:
            raise GridValueError(f"blocks={list(blocks)!r} given with no grid (None) on this rank")
        return [], None if blocks is None else []
    if not isinstance(grid, Grid):
        raise GridValueError(f"write needs a Grid (or None on a rank without blocks), "
                             f"got {type(grid).__name__}")
    if blocks is None:
        return list(grid.blocks), None
    numbers = []
    for b in blocks:
        if isinstance(b, (bool, np.bool_)) or not isinstance(b, (int, np.integer)) or b < 0:
            raise GridValueError(f"blocks= must list 0-based global block numbers, got {b!r}")
        numbers.append(int(b))
    if len(numbers) != len(grid):
        raise GridValueError(f"blocks= lists {len(numbers)} block number(s) for a grid of "
                             f"{len(grid)} block(s)")
    return list(grid.blocks), numbers


def _global_layout(path, parts):
    """Owner and dims of every global block from the ranks' ``(numbers, dims)``.

    ``numbers`` None on every rank: the blocks in rank order.  Identical on
    every rank (computed from the same gathered values).
    """
    given = [nums is not None for nums, _ in parts]
    if any(given) and not all(given):
        ranks = [r for r, g in enumerate(given) if not g]
        raise GridValueError(f"{path}: blocks= given on some ranks but not on rank(s) "
                             f"{', '.join(map(str, ranks))}; give it on every rank or on none")
    owner, dims = {}, {}
    start = 0
    for rank, (nums, ds) in enumerate(parts):
        if nums is None:
            nums = list(range(start, start + len(ds)))
            start += len(ds)
        for n, d in zip(nums, ds):
            if n in owner:
                raise GridValueError(f"{path}: block {n} (0-based) is given by rank {owner[n]} "
                                     f"and rank {rank}")
            owner[n], dims[n] = rank, d
    total = len(owner)
    if total == 0:
        raise GridValueError(f"{path}: no rank holds a block")
    missing = [n for n in range(total) if n not in owner]
    if missing:
        raise GridValueError(f"{path}: block numbers must be 0..{total - 1} over all ranks; "
                             f"block {missing[0]} (0-based) is held by no rank "
                             f"(the largest given is {max(owner)})")
    return [owner[n] for n in range(total)], [dims[n] for n in range(total)]


def write(path, grid, comm, *, blocks=None, format: str | None = None, like=None,
          overwrite: bool = False, **kw) -> None:
    """Write one grid file collectively from the blocks each rank holds.

    Every rank of ``comm`` calls it with the same ``path`` and options.

    Parameters
    ----------
    path : str or path-like
        Target file, in a folder every rank can write to.
    grid : Grid or None
        This rank's blocks (None: none).  All grids must have the same
        ``ndim`` (``Grid(blocks, ndim=...)`` or ``whole.with_blocks(...)``).
    comm : mpi4py.MPI.Intracomm
    blocks : sequence of int, optional
        The 0-based global numbers of this rank's blocks, in the order of
        ``grid``; over all ranks they must be 0 .. N-1, each once.  Default
        (None on every rank): rank 0's blocks first, then rank 1's, ...
    format, like, overwrite, **kw
        As :func:`tfi_quat.io.write`: ``"plot3d"`` (binary or Fortran, not
        ASCII) or ``"hdf5"``, with their variant options.  ``like`` and the
        grids' ``source_format`` must give the same variant on every rank;
        HDF5 ``source``/``source_format`` attributes come from rank 0.

    Raises
    ------
    ParallelError
        mpi4py is not installed, ``comm`` is no intracommunicator, the ranks'
        grids or variants disagree.
    GridFormatError, GridValueError, OverwriteError, OSError
        As a serial write, from whichever rank met it first (the lowest),
        raised on every rank.
    """
    MPI = check_comm(comm)
    from . import format_for, hdf5, plot3d

    # 1. local checks, then every rank learns every block's owner and dims
    exc = local = numbers = None
    try:
        local, numbers = _local_part(grid, blocks)
        fmt = format_for(path, format, like)
        if fmt.name not in ("plot3d", "hdf5"):
            raise GridFormatError(f"{path}: a collective write (comm=) writes Plot3D or HDF5 files, "
                                  f"not {fmt.name}")
    except Exception as e:      # noqa: BLE001  (raised on every rank below)
        exc = e
    info = None if exc is not None else (
        numbers, [b.dims for b in local], None if grid is None else grid.ndim,
        grid is not None and grid.has_iblank,
        None if grid is None else grid.source_path)
    gathered = comm.allgather((portable(exc), info))
    raise_first(comm, [e for e, _ in gathered], exc)
    infos = [i for _, i in gathered]
    owner, dims = _global_layout(path, [(i[0], i[1]) for i in infos])
    if numbers is None:
        numbers = [n for n, r in enumerate(owner) if r == comm.rank]
    ndims = {i[2] for i in infos if i[2] is not None}
    if len(ndims) > 1:
        per_rank = ", ".join(f"rank {r}: {i[2]}-D" for r, i in enumerate(infos) if i[2] is not None)
        raise ParallelError(f"{path}: the ranks' grids disagree on ndim ({per_rank}); "
                            "build each with Grid(blocks, ndim=...) or whole.with_blocks(...)")
    ndim = ndims.pop()
    has_iblank = any(i[3] for i in infos)
    protect = [i[4] for i in infos]
    if fmt.name == "plot3d":
        _write_plot3d(path, grid, local, numbers, owner, dims, ndim, has_iblank, protect,
                      comm, plot3d, like, overwrite, kw)
    else:
        _write_hdf5(path, grid, local, numbers, owner, dims, ndim, protect,
                    comm, MPI, hdf5, like, overwrite, kw)


def _variant(path, comm, grid, make):
    """The file variant ``make(grid)`` on every rank holding blocks; they must agree."""
    exc = variant = None
    try:
        variant = None if grid is None else make(grid)
    except Exception as e:      # noqa: BLE001
        exc = e
    gathered = comm.allgather((portable(exc), variant))
    raise_first(comm, [e for e, _ in gathered], exc)
    variants = [(r, v) for r, (_, v) in enumerate(gathered) if v is not None]
    r0, v0 = variants[0]
    for r, v in variants[1:]:
        if v != v0:
            raise ParallelError(f"{path}: the ranks would write different variants "
                                f"(rank {r0}: {v0.describe()}; rank {r}: {v.describe()}); "
                                "give like= or the variant options explicitly")
    return v0


def _create_temp(target: Path) -> str:
    """A new temporary file next to ``target`` (rank 0), closed."""
    fd, tmp = new_temp(target)
    os.close(fd)
    return tmp


def _finish(comm, target: Path, tmp: str | None, exc) -> None:
    """Collective end: gather errors; rank 0 renames the temporary file or removes it."""
    errors = comm.allgather(portable(exc))
    failed = any(e is not None for e in errors)
    rename_exc = None
    if comm.rank == 0 and tmp is not None:
        if failed:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        else:
            try:
                install(tmp, target)
            except Exception as e:      # noqa: BLE001
                rename_exc = e
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
    raise_first(comm, errors, exc)
    from_root(comm, rename_exc)


def _write_plot3d(path, grid, local, numbers, owner, dims, ndim, has_iblank, protect,
                  comm, plot3d, like, overwrite, kw):
    options = dict(kw)
    options.setdefault("ndim", ndim)
    options.setdefault("iblank", has_iblank)
    fmt = _variant(path, comm, grid, lambda g: plot3d.write_format(g, like, **options))
    if fmt.encoding == "ascii":
        raise GridFormatError(f"{path}: an ASCII Plot3D file has no fixed block offsets; a "
                              "collective write (comm=) writes binary or Fortran Plot3D")
    # 2. checks of the own blocks; rank 0 creates the file and writes the header
    exc = tmp = target = None
    try:
        plot3d.check_write(path, fmt, dims, local, numbers)
        offsets, size = plot3d.block_offsets(fmt, dims)
    except Exception as e:      # noqa: BLE001
        exc = e
    agree(comm, exc)
    if comm.rank == 0:
        try:
            target = check_target(path, overwrite=overwrite, protect=protect)
            tmp = _create_temp(target)
            with open(tmp, "r+b") as fh:
                plot3d.write_header(fh, fmt, dims)
                fh.truncate(size)
        except Exception as e:      # noqa: BLE001
            exc = e
            if tmp is not None:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
    target, tmp = from_root(comm, exc, (target, tmp))
    # 3. every rank writes its blocks at their offsets and syncs them
    try:
        if local:
            with open(tmp, "r+b") as fh:
                for n, b in zip(numbers, local):
                    fh.seek(offsets[n])
                    plot3d.write_block(fh, b, fmt, f"{path}: block {n + 1} of {len(dims)}")
                fh.flush()
                os.fsync(fh.fileno())
        elif comm.rank == 0:
            with open(tmp, "rb") as fh:
                os.fsync(fh.fileno())
    except Exception as e:      # noqa: BLE001
        exc = e
    _finish(comm, target, tmp, exc)


def _write_hdf5(path, grid, local, numbers, owner, dims, ndim, protect,
                comm, MPI, hdf5, like, overwrite, kw):
    exc = options = None
    try:
        options = hdf5.write_options(like, **kw)
    except Exception as e:      # noqa: BLE001
        exc = e
    agree(comm, exc)
    mine = dict(zip(numbers, local))
    if comm.rank != 0:
        _serve_blocks(comm, MPI, mine)
        _finish(comm, None, None, None)
        return
    # rank 0: the serial writer's calls, each block fetched from its owner in turn
    tmp = target = None
    try:
        try:
            target = check_target(path, overwrite=overwrite, protect=protect)
            tmp = _create_temp(target)
            os.unlink(tmp)          # HDF5 creates it (see tfi_quat.io.hdf5.write)
            hdf5.write_blocks(tmp, _fetch_blocks(comm, MPI, owner, mine), ndim=ndim,
                              nblocks=len(dims),
                              source_path=None if grid is None else grid.source_path,
                              source_format=None if grid is None else grid.source_format, **options)
            with open(tmp, "rb") as fh:
                os.fsync(fh.fileno())
        finally:
            for r in range(1, comm.size):       # the owners stop serving, whatever happened
                comm.send(None, dest=r, tag=_TAG_ASK)
    except Exception as e:      # noqa: BLE001
        exc = e
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
    _finish(comm, target, tmp, exc)


def _fetch_blocks(comm, MPI, owner, mine):
    """Rank 0: every block in order, its own or received from its owner when asked for.

    No reference to a received block stays here once the next is asked for:
    rank 0 holds one other rank's block at a time.
    """
    for n, r in enumerate(owner):
        yield mine[n] if r == 0 else _receive(comm, MPI, n, r)


def _receive(comm, MPI, n: int, r: int) -> Block:
    """Rank 0: ask rank ``r`` for block ``n`` and receive it (its error raised here)."""
    comm.send(n, dest=r, tag=_TAG_ASK)
    meta = comm.recv(source=r, tag=_TAG_META)
    if isinstance(meta, BaseException):
        raise meta
    name, dims, has_iblank = meta
    xyz = np.empty((*dims, 3), dtype=np.float64, order="F")
    comm.Recv([xyz, MPI.DOUBLE], source=r, tag=_TAG_DATA)
    iblank = None
    if has_iblank:
        iblank = np.empty(dims, dtype=np.int32, order="F")
        comm.Recv([iblank, MPI.INT32_T], source=r, tag=_TAG_DATA)
    return Block(xyz, iblank, name=name, allow_nonfinite=True)    # checked on its rank


def _serve_blocks(comm, MPI, mine) -> None:
    """Other ranks: send rank 0 each block it asks for, until it says stop (None)."""
    while True:
        n = comm.recv(source=0, tag=_TAG_ASK)
        if n is None:
            return
        try:
            b = mine[n]
            xyz = np.asfortranarray(b.xyz, dtype=np.float64)
            iblank = None if b.iblank is None else np.asfortranarray(b.iblank, dtype=np.int32)
            meta = (b.name, tuple(b.dims), iblank is not None)
        except Exception as e:      # noqa: BLE001
            comm.send(portable(e), dest=0, tag=_TAG_META)
            continue
        comm.send(meta, dest=0, tag=_TAG_META)
        comm.Send([xyz, MPI.DOUBLE], dest=0, tag=_TAG_DATA)
        if iblank is not None:
            comm.Send([iblank, MPI.INT32_T], dest=0, tag=_TAG_DATA)
