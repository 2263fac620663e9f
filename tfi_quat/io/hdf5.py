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

**Strings and checksums.**  Strings are written as fixed-length UTF-8 and
the file with HDF5 1.10 file-format objects (:data:`_LIBVER`), so every
piece of metadata is checksummed; readers accept any string form.

**Damaged and hostile files.**  Before this process opens a file, a forked
child walks all its metadata under CPU, time and memory limits
(:func:`guard`); gzip chunks are inflated here, never beyond their
declared size; the declared grid is checked against ``max_points`` or the
memory available before anything is allocated.  See docs/formats.md.

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

import contextlib
import datetime as _dt
import faulthandler
import functools
import gc
import json
import marshal
import math
import mmap
import os
import select
import signal
import time
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

try:
    import resource  # the guard's limits; POSIX only, as is the guard (os.fork)
except ImportError:  # pragma: no cover  (Windows)
    resource = None

from ..errors import GridFormatError, GridValueError, TfiQuatError
from ..grid import FACES, Block, Grid, face_axis, face_index, face_layer, face_shape
from ._atomic import atomic_output, check_target
from ._limits import check_points
from .partial import GridFaces, block_numbers, empty_faces, fill_faces

__all__ = ["HDF5Format", "HDF5Info", "read", "write", "read_block", "read_face", "read_faces", "info",
           "read_extra", "is_hdf5", "guard", "mapped_offset", "map_file", "close_map", "check_finite",
           "alloc", "damaged_file_errors",
           "FORMAT_NAME", "LAYOUT_VERSION", "write_options", "write_blocks"]

#: value of the root attribute ``format``
FORMAT_NAME = "tfi_quat-grid"
#: layout version written (and the newest one read)
LAYOUT_VERSION = 1
#: values per chunk of a compressed dataset (at most)
_CHUNK_VALUES = 1 << 16
_COMPRESSIONS = ("gzip",)
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
#: HDF5 file-format objects written: those of HDF5 1.10 (superblock 3, object header 2,
#: fixed-array chunk index), all checksummed; readable by HDF5 >= 1.10
_LIBVER = ("v110", "v110")


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


# ----------------------------------------------------------------------------- guard

#: CPU seconds that one step of the metadata walk (one attribute, one chunk index, ...) may
#: use: a damaged file can make libhdf5 loop
GUARD_CPU_SECONDS = 10
#: wall-clock seconds that one step of the metadata walk may take (a stalled file system)
GUARD_WALL_SECONDS = 120
#: bytes that the metadata walk may map beyond what the process maps already
GUARD_MEMORY = 1 << 30

#: files that passed the walk, by (device, inode, size, mtime, ctime): unchanged, they pass again
_PASSED: dict = {}
_PASSED_MAX = 256

_DEFLATE, _SHUFFLE, _FLETCHER32 = 1, 2, 3
_FILTER_NAMES = {_DEFLATE: "deflate (gzip)", _SHUFFLE: "shuffle", _FLETCHER32: "fletcher32",
                 4: "szip", 5: "nbit", 6: "scaleoffset", 32000: "lzf"}


def _filters(ds: h5py.Dataset) -> list[int]:
    """Filter codes of a dataset's pipeline, in the order they were applied on writing."""
    plist = ds.id.get_create_plist()
    return [plist.get_filter(i)[0] for i in range(plist.get_nfilters())]


def _chunk_bound(chunk_bytes: int, filters) -> int:
    """Most bytes a stored chunk of ``chunk_bytes`` can take after our filters.

    zlib's ``compressBound`` for deflate, plus four bytes for a fletcher32 checksum.
    """
    n = chunk_bytes
    if _DEFLATE in filters:
        n += (n >> 12) + (n >> 14) + (n >> 25) + 13
    return n + (4 if _FLETCHER32 in filters else 0)


def _chunk_infos(ds) -> list:
    """Offset, filter mask, file position and size of every stored chunk of ``ds``
    (an h5py Dataset or its DatasetID)."""
    dsid = ds.id if isinstance(ds, h5py.Dataset) else ds
    out = []
    if hasattr(dsid, "chunk_iter"):
        dsid.chunk_iter(out.append)
        return out
    return [dsid.get_chunk_info(i) for i in range(dsid.get_num_chunks())]


#: classes of attribute types whose values have a fixed size and refer to nothing else in the file
_PLAIN_CLASSES = frozenset((h5py.h5t.INTEGER, h5py.h5t.FLOAT, h5py.h5t.BITFIELD, h5py.h5t.OPAQUE,
                            h5py.h5t.ENUM, h5py.h5t.TIME))


#: values of at most this many bytes go into a catalogue (:func:`guard`)
CATALOGUE_VALUE_BYTES = 4096
#: fixed-length string attributes of at most this many bytes go into a catalogue
_CATALOGUE_TEXT_BYTES = 256


def _number_dtype(tid) -> str:
    """The native numpy type code of an HDF5 integer or float type (``'i4'``, ``'f8'``), else ``''``."""
    cls, size = tid.get_class(), tid.get_size()
    if cls == h5py.h5t.INTEGER and size in (1, 2, 4, 8):
        return f"{'u' if tid.get_sign() == h5py.h5t.SGN_NONE else 'i'}{size}"
    if cls == h5py.h5t.FLOAT and size in (2, 4, 8):
        return f"f{size}"
    return ""


_NATIVE: dict = {}


def _native_type(code: str):
    """The HDF5 memory type of a numpy type code from :func:`_number_dtype` (made once)."""
    tid = _NATIVE.get(code)
    if tid is None:
        tid = _NATIVE[code] = h5py.h5t.py_create(np.dtype(code))
    return tid


def _walk_metadata(source, report, close: bool = True, catalogue: dict | None = None) -> None:
    """Read every piece of metadata the reader may use; what the guard's child runs.

    Opens the file; reads every attribute of every object (opening one decodes
    its type, shape and value; variable-length values are then read from the
    heap, compound, array and reference values read as stored), every group's
    links, every dataset's type, shape, layout and filters, the whole chunk
    index of a chunked dataset (each chunk must lie inside the file and not
    exceed what its filters can produce) and the value of string datasets.
    ``report(where)`` is called before each step, so that a crash can be
    placed.  Raises on the first problem.  ``close=False`` leaves the file
    open (the guard's child exits at once: closing would only free HDF5's
    metadata cache, entry by entry).

    h5py's low-level calls throughout, each object opened relative to its
    parent: a CGNS tree has hundreds of small groups with four attributes
    each, and the high-level objects cost several times more per item.

    ``catalogue``, a dict, is filled with what the walk saw, by object path
    (``""`` the root, ``"/a/b"``; an object reached by several hard links
    under one of its paths only): for a group ``(0, attrs, links)``, for a
    dataset ``(1, attrs, dtype, shape, chunked, nfilters, stored, value)``.
    ``attrs`` maps attribute names to the stored bytes of the fixed-length
    string attributes of one value (at most ``_CATALOGUE_TEXT_BYTES``);
    ``links`` maps child names (decoded with
    ``surrogateescape``) to their link types, in creation order where the
    group tracks it, else by name; ``dtype`` is the native numpy code of
    an integer or float type (``''`` for any other), ``shape`` None for an
    empty dataspace, ``stored`` the bytes stored, ``value`` the native bytes
    of a contiguous or compact dataset of numbers of at most
    :data:`CATALOGUE_VALUE_BYTES` (else None).  Only marshal-able types.
    """
    report("the superblock")
    f = h5py.File(source, "r")
    with f if close else contextlib.nullcontext(f):
        eof = f.id.get_filesize()

        def attrs(oid, where):
            report(f"the attribute list of {where}")
            names = []
            h5py.h5a.iterate(oid, lambda name, *_: names.append(name))
            texts = {}
            for name in names:
                report(f"attribute {name.decode('utf-8', 'replace')!r} of {where}")
                # opening decodes the attribute's message: its type, its shape and its value
                # (from the object header or the dense attribute storage)
                aid = h5py.h5a.open(oid, name)
                tid = aid.get_type()
                cls = tid.get_class()
                if cls == h5py.h5t.STRING and not tid.is_variable_str():
                    # a value of fixed size, in memory now: reading it reads no more of the file
                    if catalogue is not None:
                        size = tid.get_size()
                        # one value (whatever the rank): read as stored, in the attribute's own type
                        # (the reader's text is the same: cut at the first NUL, trailing spaces dropped)
                        if size <= _CATALOGUE_TEXT_BYTES and aid.get_storage_size() == size:
                            buf = np.zeros((), dtype=f"S{size}")
                            aid.read(buf, mtype=tid)
                            texts[name.decode("utf-8", "replace")] = buf.tobytes()
                    continue
                if cls in _PLAIN_CLASSES:
                    continue
                shape = aid.shape
                if shape is None:  # an empty (null) dataspace holds no value
                    continue
                if cls != h5py.h5t.VLEN and cls != h5py.h5t.STRING:
                    # compound, array, reference: the stored bytes in the stored type
                    aid.read(np.empty(shape, dtype=f"V{tid.get_size()}"), mtype=tid)
                    continue
                try:  # variable-length data: through h5py, which frees what HDF5 allocates
                    value = np.empty(shape, dtype=aid.dtype)
                except TypeError:  # a type numpy cannot hold: read it as h5py would
                    f[where].attrs[name.decode("utf-8", "replace")]
                    continue
                aid.read(value)
            return texts

        def dataset(dsid, where, key, texts):
            report(f"the header of dataset {where}")
            shape = dsid.get_space().shape  # the dataspace message
            tid = dsid.get_type()
            cls, itemsize = tid.get_class(), tid.get_size()
            plist = dsid.get_create_plist()
            layout = plist.get_layout()
            chunks = plist.get_chunk() if layout == h5py.h5d.CHUNKED else None
            filters = [plist.get_filter(i)[0] for i in range(plist.get_nfilters())]
            report(f"the storage of dataset {where}")
            stored = dsid.get_storage_size()
            if chunks is None:
                offset = dsid.get_offset()
                if offset is not None and offset + stored > eof:
                    raise ValueError(f"dataset {where}: its data (bytes {offset}..{offset + stored}) "
                                     f"lie beyond the end of the file ({eof} bytes)")
            if catalogue is not None:
                code, value = _number_dtype(tid), None
                if (code and shape is not None and stored and not filters
                        and layout in (h5py.h5d.CONTIGUOUS, h5py.h5d.COMPACT)
                        and not plist.get_external_count()
                        and math.prod(shape) * itemsize <= CATALOGUE_VALUE_BYTES):
                    report(f"the value of dataset {where}")
                    out = np.empty(shape, dtype=code)
                    dsid.read(h5py.h5s.ALL, h5py.h5s.ALL, out, mtype=_native_type(code))
                    value = out.tobytes()
                catalogue[key] = (1, texts, code, shape, chunks is not None, len(filters), stored, value)
            if chunks is None:
                if cls in (h5py.h5t.STRING, h5py.h5t.VLEN, h5py.h5t.REFERENCE):
                    report(f"the value of dataset {where}")
                    h5py.Dataset(dsid)[()]
                return
            report(f"the chunk index of dataset {where}")
            known = all(c in _FILTER_NAMES for c in filters)
            bound = _chunk_bound(int(np.prod(chunks)) * itemsize, filters)
            for c in _chunk_infos(dsid):
                if c.byte_offset + c.size > eof or (known and c.size > bound):
                    raise ValueError(f"dataset {where}: chunk {c.chunk_offset} of {c.size} bytes at "
                                     f"byte {c.byte_offset} does not fit (file of {eof} bytes, "
                                     f"chunk of at most {bound} bytes)")

        def links(gid, where, key, texts):
            """The links of a group, by name: ``[(name, link type, address of a hard link's object)]``."""
            report(f"the links of {where}")
            found = []
            gid.links.iterate(lambda name, info: found.append((name, info.type, info.u)), info=True)
            if catalogue is not None:
                # the CGNS reader lists them in creation order where the group tracks it
                # (a second index where the links are stored densely)
                ordered = {}

                def seen(name, info):
                    ordered[name.decode("utf-8", "surrogateescape")] = info.type
                try:
                    gid.links.iterate(seen, idx_type=h5py.h5.INDEX_CRT_ORDER, info=True)
                except RuntimeError:  # no creation-order index: by name, as the reader lists them
                    ordered = {n.decode("utf-8", "surrogateescape"): t for n, t, _ in found}
                except Exception:  # the reader reports it
                    ordered = None
                catalogue[key] = (0, texts, ordered)
            return found

        # every object reached through hard links, each once (by the address of its header; the
        # root's is not asked for, a link back to it walks it once more), depth first; no
        # recursion: a crafted file may nest groups deeply
        walked = set()
        todo = [(f.id, b"", attrs(f.id, "the root group"))]
        try:
            while todo:
                gid, path, texts = todo.pop()
                where = f"group /{path.decode('utf-8', 'replace')}" if path else "the root group"
                key = "/" + path.decode("utf-8", "surrogateescape") if path else ""
                for name, ltype, addr in links(gid, where, key, texts):
                    if ltype != h5py.h5l.TYPE_HARD or addr in walked:
                        continue  # soft and external links are not followed
                    walked.add(addr)
                    sub = path + b"/" + name if path else name
                    there = "/" + sub.decode("utf-8", "replace")
                    oid = h5py.h5o.open(gid, name)
                    got = attrs(oid, there)
                    if isinstance(oid, h5py.h5g.GroupID):
                        todo.append((oid, sub, got))
                    elif isinstance(oid, h5py.h5d.DatasetID):
                        dataset(oid, there, "/" + sub.decode("utf-8", "surrogateescape"), got)
        finally:
            todo.clear()  # before the file closes: h5py's close walks the objects left open


def _limit_child() -> None:
    """Limits of the guard's child: address space, no core file, SIGXCPU ends it.

    The child imports nothing (``resource`` and ``faulthandler`` are imported
    with this module): a thread of the parent, such as the CLI's numba
    warm-up, may hold a module's import lock at the fork.
    """
    if faulthandler.is_enabled():
        faulthandler.disable()  # a crash is the expected way for the child to fail
    signal.signal(signal.SIGXCPU, signal.SIG_DFL)
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    mapped = None
    with open("/proc/self/status", "rb") as fh:
        for line in fh:
            if line.startswith(b"VmSize:"):
                mapped = int(line.split()[1]) * 1024
    if mapped is not None:
        soft, hard = resource.getrlimit(resource.RLIMIT_AS)
        cap = mapped + int(GUARD_MEMORY)
        if soft == resource.RLIM_INFINITY or soft > cap:
            resource.setrlimit(resource.RLIMIT_AS, (cap, hard))


#: bytes of the shared page in which the guard's child records its step count and current step
_PROGRESS_BYTES = 4096
_WHERE_MAX = _PROGRESS_BYTES - 16
#: wall-clock seconds between two settings of the guard child's CPU limit
_REARM_SECONDS = 0.1


def _guard_child(source, size: int, wfd, progress, want: bool = False) -> None:
    """Body of the guard's child: walk, write the outcome to ``wfd``, ``os._exit``.

    Before each step the child writes the step count and what it is about to
    read into ``progress`` (a page shared with the parent): no system call and
    no wake-up of the parent per step, and the parent still knows where a
    crash or an overrun happened.  With ``want``, a file that passed is
    followed by its catalogue (:func:`_walk_metadata`) in :mod:`marshal` form.
    """
    status = 3
    try:
        # no cyclic garbage collection here: a full collection writes to every object of the
        # parent's heap, and each page it writes to is copied (the walk makes little garbage,
        # and the child ends soon)
        gc.disable()
        steps = 0
        # every step of the walk reads at least a few bytes of metadata
        max_steps = 100 + size // 4
        cpu_hard = resource.getrlimit(resource.RLIMIT_CPU)[1]
        rearm = -1.0

        def report(where):
            nonlocal steps, rearm
            steps += 1
            if steps > max_steps:
                raise ValueError(f"more than {max_steps} metadata items, more than the file can hold")
            # each step gets its own CPU allowance: the limit follows the progress.  It is set
            # again once per _REARM_SECONDS of wall-clock time (two system calls; a CGNS tree has
            # thousands of small steps), with that much more allowance: the child has one
            # thread and cannot use more CPU time than wall-clock time meanwhile, so every step
            # still gets at least GUARD_CPU_SECONDS
            now = time.monotonic()
            if now >= rearm:
                use = resource.getrusage(resource.RUSAGE_SELF)
                soft = int(use.ru_utime + use.ru_stime + GUARD_CPU_SECONDS + _REARM_SECONDS) + 1
                if cpu_hard != resource.RLIM_INFINITY:
                    soft = min(soft, cpu_hard)
                resource.setrlimit(resource.RLIMIT_CPU, (soft, cpu_hard))
                rearm = now + _REARM_SECONDS
            text = where.encode("utf-8", "replace")[:_WHERE_MAX]
            progress[0:16 + len(text)] = steps.to_bytes(8, "little") + len(text).to_bytes(8, "little") + text

        catalogue = {} if want else None
        try:
            _limit_child()
            _walk_metadata(source, report, close=False, catalogue=catalogue)
            outcome = "="
        except MemoryError:
            outcome = f"!needs more than {GUARD_MEMORY / 2**20:.0f} MiB of memory"
        except BaseException as exc:  # everything ends up in the parent's message
            outcome = f"!{type(exc).__name__}: {exc}"[:2000]
        message = memoryview(outcome.replace("\n", " ").encode("utf-8", "replace") + b"\n"
                             + (marshal.dumps(catalogue) if outcome == "=" and want else b""))
        while message:
            message = message[os.write(wfd, message):]
        status = 0
    finally:
        os._exit(status)


def guard(source, name: str, *, catalogue: bool = False) -> dict | None:
    """Walk the HDF5 metadata of ``source`` in a forked child before this process touches it.

    libhdf5 can crash, loop forever or allocate gigabytes on damaged metadata
    (a few flipped bytes suffice), and a crash would take the caller's process
    down.  The child (``os.fork``; it calls only h5py, whose lock is released
    at fork, and ends with ``os._exit``) reads everything the reader will read
    (:func:`_walk_metadata`) under a CPU limit (:data:`GUARD_CPU_SECONDS` per
    step of the walk), a wall-clock limit (:data:`GUARD_WALL_SECONDS` without
    progress), an address-space limit (:data:`GUARD_MEMORY` beyond the
    current mappings) and at most one step per 4 bytes of file.  If it reports an
    error, dies, or overruns, the file is refused with a GridFormatError that
    names what the child was reading.  A file (by path) that passed is
    remembered by device, inode, size, modification and change time, and not
    walked again while these stay the same.  Without ``os.fork`` (Windows)
    there is no guard.

    With ``catalogue=True`` a walk that passes also hands back what it saw:
    every object's links, its fixed-length string attributes, every
    dataset's type, shape and storage and the values of small datasets of
    numbers (the layout is described in ``_walk_metadata``), so that a
    reader of a file of many small objects (CGNS) need not open them a
    second time.  Returns that dict, or None when nothing was walked (a file
    that passed before, no ``os.fork``) or without ``catalogue``.
    """
    if not hasattr(os, "fork"):
        return None
    key = None
    if hasattr(source, "seek"):
        pos = source.tell()
        size = source.seek(0, os.SEEK_END)
        source.seek(pos)
    else:
        st = os.stat(source)
        key, size = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns), st.st_size
        if key in _PASSED:
            return None
    progress = mmap.mmap(-1, _PROGRESS_BYTES)  # anonymous and shared with the child
    rfd, wfd = os.pipe()
    try:
        with warnings.catch_warnings():
            # Python >= 3.12 warns about fork() in a process with other threads
            # (numba's pool): the child runs no code that needs them
            warnings.simplefilter("ignore", DeprecationWarning)
            pid = os.fork()
    except BaseException:
        os.close(rfd)
        os.close(wfd)
        progress.close()
        raise
    if pid == 0:  # pragma: no cover  (the child; coverage cannot follow it)
        os.close(rfd)
        _guard_child(source, size, wfd, progress, catalogue)
    os.close(wfd)
    outcome, overrun, pending, payload, seen = None, False, bytearray(), b"", 0
    deadline = time.monotonic() + GUARD_WALL_SECONDS
    try:
        while True:
            # the child writes to the pipe only at the end; meanwhile look at its
            # step count a few times a second to tell a slow walk from a stuck one
            now = time.monotonic()
            steps = int.from_bytes(progress[0:8], "little")
            if steps != seen:
                seen, deadline = steps, now + GUARD_WALL_SECONDS
            left = deadline - now
            if left <= 0:
                overrun = True
                break
            if not select.select([rfd], [], [], min(left, 0.25))[0]:
                continue
            chunk = os.read(rfd, 1 << 16)
            if not chunk:
                break
            pending += chunk
        if pending:
            outcome, _, payload = bytes(pending).partition(b"\n")
    finally:
        os.close(rfd)
        if outcome is None:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:  # pragma: no cover
                pass
        try:
            status = os.waitpid(pid, 0)[1]
        except ChildProcessError:  # SIGCHLD ignored by the application: reaped already
            status = None
        n = int.from_bytes(progress[8:16], "little")
        where = bytes(progress[16:16 + min(n, _WHERE_MAX)]) if progress[0:8] != bytes(8) \
            else b"opening the file"
        progress.close()
    where = where.decode("utf-8", "replace")
    if outcome == b"=":
        if key is not None:
            if len(_PASSED) >= _PASSED_MAX:
                _PASSED.pop(next(iter(_PASSED)))
            _PASSED[key] = None
        if not catalogue:
            return None
        try:
            found = marshal.loads(payload)
        except (EOFError, ValueError, TypeError):  # pragma: no cover  (our own child wrote it)
            return None
        return found if isinstance(found, dict) else None
    if outcome is not None:
        raise GridFormatError(f"{name}: damaged HDF5 file: reading {where}: "
                              f"{outcome[1:].decode('utf-8', 'replace')}")
    if overrun:
        raise GridFormatError(f"{name}: damaged HDF5 file: reading {where} did not end within "
                              f"{GUARD_WALL_SECONDS} s (tfi_quat.io.hdf5.GUARD_WALL_SECONDS)")
    if status is not None and os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        if sig in (signal.SIGXCPU, signal.SIGKILL):
            raise GridFormatError(
                f"{name}: damaged HDF5 file: libhdf5 used more than {GUARD_CPU_SECONDS} s of CPU "
                f"reading {where} (tfi_quat.io.hdf5.GUARD_CPU_SECONDS)")
        raise GridFormatError(f"{name}: damaged HDF5 file: libhdf5 crashed "
                              f"({signal.Signals(sig).name}) reading {where}")
    code = "unknown" if status is None else os.WEXITSTATUS(status)
    raise GridFormatError(f"{name}: damaged HDF5 file: the metadata check stopped reading {where} "
                          f"(exit status {code})")


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


def alloc(shape, dtype, path, where, order="F") -> np.ndarray:
    """``np.empty(shape, dtype, order)``; a refused allocation is a GridFormatError."""
    try:
        return np.empty(shape, dtype=dtype, order=order)
    except MemoryError:
        nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
        raise GridFormatError(f"{path}: {where}: cannot allocate {nbytes:,} bytes for the "
                              f"declared shape {tuple(shape)}: out of memory") from None


_INT32 = np.iinfo(np.int32)


class _Reader:
    """An open HDF5 grid file, checked at the root; checks blocks on demand.

    The file's metadata is walked in a guarded child process (:func:`guard`)
    before this process opens it.
    """

    def __init__(self, path):
        self.path = path
        if not hasattr(path, "read"):
            p = Path(os.fspath(path))
            # the OS's own FileNotFoundError / IsADirectoryError / PermissionError, naming the path
            with open(p, "rb") as fh:
                size = os.fstat(fh.fileno()).st_size
            if size == 0:
                raise GridFormatError(f"{p}: empty file, not an HDF5 grid")
            if not is_hdf5(p):
                raise GridFormatError(f"{p}: not an HDF5 file (no HDF5 signature)")
        guard(path, str(path))
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

    def _member(self, group: h5py.Group, key: str, kind: type, where: str):
        """Member ``key`` of ``group`` if it is a hard link to a ``kind``; None when absent.

        Soft and external links are not followed: the guard vouches for this file only.
        """
        link = group.get(key, getlink=True)
        if link is None:
            return None
        what = "group" if kind is h5py.Group else "dataset"
        full = f"{group.name.rstrip('/')}/{key}"
        if not isinstance(link, h5py.HardLink):
            kind_of = {h5py.SoftLink: "a soft", h5py.ExternalLink: "an external"}.get(type(link), "a")
            raise GridFormatError(f"{self.path}: {where}: {full} is {kind_of} link, not a {what} "
                                  "(links are not followed)")
        obj = group[key]
        if not isinstance(obj, kind):
            raise GridFormatError(f"{self.path}: {where}: {full} is not a {what}")
        return obj

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
        blocks = self._member(f, "blocks", h5py.Group, "root group")
        if blocks is None:
            raise GridFormatError(f"{path}: group /blocks is missing")
        self.blocks = blocks
        expected = {_block_group_name(n) for n in range(self.nblocks)}
        extra = sorted(k for k in blocks if k not in expected)
        if extra:
            more = f" (and {len(extra) - 3} more)" if len(extra) > 3 else ""
            raise GridFormatError(
                f"{path}: /blocks holds {', '.join('/blocks/' + k for k in extra[:3])}{more}, "
                f"beyond the root attribute nblocks = {self.nblocks}")

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
        g = self._member(self.blocks, name, h5py.Group, f"block {n + 1}")
        if g is None:
            raise GridFormatError(f"{self.path}: block {n + 1}: group /blocks/{name} is missing "
                                  f"(root attribute nblocks = {self.nblocks})")
        return g

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
        ds = self._member(g, key, h5py.Dataset, where)
        if ds is None:
            raise GridFormatError(f"{self.path}: {where}: dataset {key!r} is missing")
        dsname = f"{where}, dataset {ds.name}"
        if ds.shape != shape:
            raise GridFormatError(f"{self.path}: {dsname}: shape {ds.shape} does not match the "
                                  f"block dims (expected {shape})")
        if ds.dtype.kind not in kinds:
            raise GridFormatError(f"{self.path}: {dsname}: dtype {ds.dtype} is not "
                                  f"{'a float' if kinds == 'f' else 'an integer'} type")
        filters = _filters(ds)
        for code in filters:
            if code not in (_DEFLATE, _SHUFFLE, _FLETCHER32):
                raise GridFormatError(f"{self.path}: {dsname}: filter {_FILTER_NAMES.get(code, code)!r} "
                                      "is not part of the layout (gzip, shuffle, fletcher32)")
        if _DEFLATE in filters and _FLETCHER32 in filters:
            raise GridFormatError(f"{self.path}: {dsname}: gzip together with fletcher32 "
                                  "is not supported")
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
        """Fill ``out`` (C-contiguous, the dataset's selection shape) from ``ds``.

        ``sel``: a tuple of unit-step slices, one per dataset axis (None: all).
        gzip-compressed datasets are decompressed here (:meth:`_read_deflated`),
        never into more than the chunk's declared size.
        """
        try:
            filters = _filters(ds)
            if _DEFLATE in filters:
                self._read_deflated(ds, out, where, sel, filters)
            elif sel is None:
                ds.read_direct(out)
            else:
                ds.read_direct(out, source_sel=sel)
        except (OSError, TypeError, ValueError) as exc:
            if isinstance(exc, TfiQuatError):
                raise
            raise GridFormatError(f"{self.path}: {where}, dataset {ds.name}: cannot read: {exc}") from None

    def _read_deflated(self, ds, out, where, sel, filters) -> None:
        """Read a (shuffle +) deflate chunked dataset chunk by chunk, each inflated with a cap.

        libhdf5's own deflate filter grows its buffer for as long as the stream
        goes on (a 400 KB chunk can inflate to 400 MB); here no chunk may
        inflate to more than its ``prod(chunks) * itemsize`` bytes.
        """
        shape, chunks, dt = ds.shape, ds.chunks, ds.dtype
        cbytes = int(np.prod(chunks)) * dt.itemsize
        bound = _chunk_bound(cbytes, filters)
        box = [(0, s) for s in shape] if sel is None else [s.indices(n)[:2] for s, n in zip(sel, shape)]
        name = f"{self.path}: {where}, dataset {ds.name}"
        seen, filled = set(), 0
        for c in _chunk_infos(ds):
            off = tuple(int(o) for o in c.chunk_offset)
            if (len(off) != len(shape) or off in seen
                    or any(o % k or not 0 <= o < s for o, k, s in zip(off, chunks, shape))):
                raise GridFormatError(f"{name}: the chunk index lists a chunk at {off}, "
                                      f"which is not a chunk of shape {shape} in chunks of {chunks}")
            seen.add(off)
            lo = [max(o, a) for o, (a, _) in zip(off, box)]
            hi = [min(o + k, b) for o, k, (_, b) in zip(off, chunks, box)]
            if any(a >= b for a, b in zip(lo, hi)):
                continue
            if c.size > bound:
                raise GridFormatError(f"{name}: chunk {off} stores {c.size} bytes, more than a "
                                      f"compressed chunk of {cbytes} bytes can take ({bound})")
            mask, raw = ds.id.read_direct_chunk(off)
            data, shuffled = _inflate(raw, mask, filters, cbytes, f"{name}: chunk {off}")
            dst = out[tuple(slice(a - b0, b - b0) for a, b, (b0, _) in zip(lo, hi, box))]
            src_sel = tuple(slice(a - o, b - o) for a, b, o in zip(lo, hi, off))
            _place(data, shuffled, dt, chunks, src_sel, dst)
            filled += dst.size
        if filled != out.size:
            raise GridFormatError(f"{name}: the stored chunks hold {filled} of the {out.size} "
                                  "values read (incomplete dataset)")

    def variant(self) -> HDF5Format:
        for n in range(self.nblocks):
            ds = self.group(n).get("xyz")
            if isinstance(ds, h5py.Dataset) and ds.compression:
                level = ds.compression_opts if isinstance(ds.compression_opts, int) else None
                return HDF5Format(str(ds.compression), level, bool(ds.shuffle), self.version)
        return HDF5Format(version=self.version)

    def block(self, n: int, allow_nonfinite: bool, meta=None) -> Block:
        name, dims, xyz_ds, ib_ds = self.meta(n) if meta is None else meta
        where = f"block {n + 1}"
        xyz = alloc(dims + (3,), np.float64, self.path, where)
        self.read_into(xyz_ds, xyz.T, where)
        if not allow_nonfinite:
            check_finite(xyz, self.path, where, xyz_ds.name)
        ib = None
        if ib_ds is not None:
            ib = alloc(dims, np.int32, self.path, where)
            if np.can_cast(ib_ds.dtype, np.int32):
                self.read_into(ib_ds, ib.T, where)
            else:
                # read as stored: HDF5 would clamp values beyond int32 without a word
                wide = alloc(ib_ds.shape, ib_ds.dtype.newbyteorder("="), self.path, where, "C")
                self.read_into(ib_ds, wide, where)
                _check_int32(wide, self.path, where, ib_ds.name)
                ib.T[...] = wide
        return Block(xyz, ib, name, allow_nonfinite=True)

    def face(self, n: int, f: int, allow_nonfinite: bool, max_points=None, meta=None) -> np.ndarray:
        """Face ``f`` (0..5) of block ``n``: one hyperslab of its xyz dataset."""
        path = self.path
        _, dims, xyz_ds, _ = self.meta(n) if meta is None else meta
        d = face_axis(f)[0]
        pos = face_layer(dims, f)
        run = face_shape(dims, f)
        where = f"block {n + 1} face {FACES[f]}"
        check_points(f"{path}: {where}", run[0] * run[1], max_points=max_points,
                     bytes_per_point=3 * 8)
        out = alloc((run[0], run[1], 3), np.float64, path, where)
        # dataset axes are (c, k, j, i): block axis a is dataset axis 3 - a
        sel = [slice(None)] * 4
        sel[3 - d] = slice(pos, pos + 1)
        view = out.T.reshape(tuple(1 if a == 3 - d else s for a, s in
                                   enumerate((3, dims[2], dims[1], dims[0]))))
        self.read_into(xyz_ds, view, where, np.s_[tuple(sel)])
        if not allow_nonfinite:
            check_finite(out, path, where, xyz_ds.name, face=(d, pos))
        return out


def _inflate(raw, mask: int, filters, cbytes: int, name: str):
    """Undo the deflate filter of one stored chunk, never inflating beyond ``cbytes``.

    ``mask`` bit i set: filter i was skipped for this chunk.  Returns the bytes and
    whether they are still byte-shuffled (the shuffle filter is undone by :func:`_place`).
    """
    data = raw
    for i in reversed(range(len(filters))):
        if mask >> i & 1 or filters[i] != _DEFLATE:
            continue
        z = zlib.decompressobj()
        try:
            data = z.decompress(data, cbytes)
            if not z.eof and len(data) == cbytes and z.decompress(z.unconsumed_tail, 1):
                raise GridFormatError(f"{name}: inflates to more than the chunk's "
                                      f"{cbytes} bytes (a decompression bomb)")
        except zlib.error as exc:
            raise GridFormatError(f"{name}: corrupt gzip data: {exc}") from None
        if not z.eof:
            raise GridFormatError(f"{name}: the gzip stream is cut short")
    if len(data) != cbytes:
        raise GridFormatError(f"{name}: holds {len(data)} bytes after decompression, "
                              f"expected {cbytes}")
    shuffled = any(c == _SHUFFLE and not mask >> i & 1 for i, c in enumerate(filters))
    return data, shuffled


def _place(data, shuffled: bool, dt: np.dtype, chunks, src_sel, dst: np.ndarray) -> None:
    """Copy the part ``src_sel`` of one inflated chunk into ``dst``, undoing the shuffle.

    A shuffled chunk holds byte 0 of every value, then byte 1, ...: each byte plane
    goes into its byte of a flat temporary of one chunk, which is then copied
    (and cast, if the stored type is not the destination's) into place.
    """
    size = dt.itemsize
    if not shuffled or size == 1:
        dst[...] = np.frombuffer(data, dtype=dt).reshape(chunks)[src_sel]
        return
    planes = np.frombuffer(data, np.uint8).reshape(size, -1)
    values = np.empty((planes.shape[1], size), np.uint8)
    for b in range(size):  # flat, one byte plane at a time: faster than a transposing copy
        values[:, b] = planes[b]
    dst[...] = values.view(dt).reshape(chunks)[src_sel]


def _check_int32(arr: np.ndarray, path, where: str, dataset: str) -> None:
    """Raise GridFormatError when an IBLANK array ``(nk, nj, ni)`` has values beyond int32."""
    if arr.size == 0 or (int(arr.min()) >= _INT32.min and int(arr.max()) <= _INT32.max):
        return
    bad = (arr < _INT32.min) | (arr > _INT32.max)
    k, j, i = (int(x) for x in np.argwhere(bad)[0])
    raise GridFormatError(
        f"{path}: {where}, dataset {dataset}: {int(bad.sum())} IBLANK value(s) beyond int32, "
        f"first {int(arr[k, j, i])} at point ({i + 1}, {j + 1}, {k + 1}) (1-based)")


def check_finite(arr: np.ndarray, path, where: str, dataset: str, face=None) -> None:
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

def damaged_file_errors(fn):
    """Turn h5py's errors on a damaged file (KeyError, RuntimeError, ...) into GridFormatError."""
    @functools.wraps(fn)
    def wrapper(path, *args, **kwargs):
        try:
            return fn(path, *args, **kwargs)
        except (TfiQuatError, FileNotFoundError, IsADirectoryError, PermissionError):
            raise
        except (OSError, KeyError, RuntimeError, TypeError) as exc:
            raise GridFormatError(f"{path}: damaged or unreadable HDF5 grid file "
                                  f"({type(exc).__name__}: {exc})") from exc
    return wrapper


@damaged_file_errors
def read(path, *, allow_nonfinite: bool = False, max_points: int | None = None, blocks=None) -> Grid:
    """Read an HDF5 grid file (layout :data:`LAYOUT_VERSION` or older).

    Parameters
    ----------
    path : str or path-like
    blocks : list of int, optional
        Read only these blocks (0-based numbers, in this order; their
        datasets only); the grid's ``block_ids`` records them.
    allow_nonfinite : bool
        Accept NaN or infinite coordinates (default: GridFormatError).
    max_points : int, optional
        Refuse a file declaring more grid points than this (default: what
        fits in the memory available), before anything is allocated.

    Returns
    -------
    Grid
        Blocks with ``xyz`` float64 ``(ni, nj, nk, 3)`` Fortran order (filled by
        HDF5 in place) and ``iblank`` int32 ``(ni, nj, nk)`` where stored;
        ``source_format`` an :class:`HDF5Format`, ``source_path`` the path.

    Raises
    ------
    GridFormatError
        Not an HDF5 file, damaged metadata (libhdf5 crashing, looping or
        allocating while reading it, see :func:`guard`), missing or extra
        groups/attributes/datasets (named), an unsupported layout version, a
        dataset whose shape or dtype does not match its block's dims, an
        incomplete dataset, a gzip chunk inflating beyond its size, IBLANK
        values beyond int32, non-finite coordinates, more points than
        ``max_points`` or the available memory.
    FileNotFoundError, IsADirectoryError, PermissionError
        From the operating system, naming the path.
    """
    with _Reader(path) as r:
        ids = list(range(r.nblocks)) if blocks is None else block_numbers(path, blocks, r.nblocks)
        metas = [r.meta(n) for n in ids]
        what = f"{r.nblocks} block(s)" if blocks is None else f"{len(ids)} of {r.nblocks} block(s)"
        check_points(f"{path}: {what}", sum(int(np.prod(m[1])) for m in metas), max_points=max_points)
        got = [r.block(n, allow_nonfinite, m) for n, m in zip(ids, metas)]
        variant = r.variant()
        try:
            grid = Grid(got, r.ndim, source_format=variant, source_path=path)
        except GridValueError as exc:
            raise GridFormatError(f"{path}: {exc}") from None
        if blocks is not None:
            grid.block_ids = tuple(ids)
        return grid


def _block_faces(r: _Reader, n: int, meta, mm, allow_nonfinite: bool) -> tuple:
    """The faces of block ``n``: from the memory map ``mm`` where its dataset is contiguous
    (the pages holding face values only), else one hyperslab each."""
    _, dims, xyz_ds, _ = meta
    off = None if mm is None else mapped_offset(xyz_ds.id, xyz_ds.size * xyz_ds.dtype.itemsize, len(mm))
    if off is None:
        return tuple(r.face(n, f, allow_nonfinite, meta=meta) for f in range(2 * r.ndim))
    faces = empty_faces(dims, r.ndim)
    data = np.ndarray(xyz_ds.shape, dtype=xyz_ds.dtype, buffer=mm, offset=off)
    try:
        for c in range(3):
            fill_faces(faces, c, data[c].T, r.ndim)
    finally:
        del data
    if not allow_nonfinite:
        for f, arr in enumerate(faces):
            d = face_axis(f)[0]
            check_finite(arr, r.path, f"block {n + 1} face {FACES[f]}", xyz_ds.name,
                         face=(d, face_layer(dims, f)))
    return tuple(faces)


def mapped_offset(dsid, nbytes: int, size: int) -> int | None:
    """File offset of a dataset's values when they can be read through a memory map, else None.

    They can when the dataset is stored contiguously in the file itself
    (no chunks, filters or external storage) and its ``nbytes`` lie within
    the file's ``size`` bytes; the caller then reads them in the dataset's
    own dtype (byte order included).
    """
    try:
        plist = dsid.get_create_plist()
        if (plist.get_layout() != h5py.h5d.CONTIGUOUS or plist.get_nfilters()
                or plist.get_external_count()):
            return None
        off = dsid.get_offset()
    except (OSError, TypeError, ValueError, RuntimeError):
        return None
    if off is None or off < 0 or off + nbytes > size:
        return None
    return int(off)


def map_file(path):
    """A read-only memory map of a grid file (None for an empty file or where mapping fails)."""
    try:
        with open(os.fspath(path), "rb") as fh:
            return mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
    except (OSError, ValueError):
        return None


def close_map(mm) -> None:
    """Close a map from :func:`map_file` (None: nothing); one an error left a view of closes when it goes."""
    if mm is not None:
        try:
            mm.close()
        except BufferError:
            pass


@damaged_file_errors
def read_faces(path, *, allow_nonfinite: bool = False, blocks=None) -> GridFaces:
    """Read the faces of every block of an HDF5 grid file (one hyperslab each), and their dims.

    Parameters
    ----------
    path : str or path-like
    allow_nonfinite : bool
        Accept NaN or infinite coordinates on the faces.
    blocks : list of int, optional
        Read the faces of these blocks only (0-based); the dims of all.

    Returns
    -------
    GridFaces
        As :func:`read_face` for every face of every block, from one open file
        (a contiguous dataset through a memory map, touching the pages that
        hold face values only).

    Raises
    ------
    GridFormatError
        As :func:`read`.
    """
    with _Reader(path) as r:
        metas = [r.meta(n) for n in range(r.nblocks)]
        mm = map_file(path)
        try:
            ids = None if blocks is None else block_numbers(path, blocks, r.nblocks)
            faces = [_block_faces(r, n, m, mm, allow_nonfinite) if ids is None or n in ids else None
                     for n, m in enumerate(metas)]
        finally:
            close_map(mm)
        return GridFaces(r.ndim, [m[1] for m in metas], faces, [m[0] for m in metas], os.fspath(path),
                         r.variant(), block_ids=None if ids is None else tuple(ids))


@damaged_file_errors
def read_block(path, b, *, allow_nonfinite: bool = False, max_points: int | None = None) -> Block:
    """Read one block, and nothing else, from an HDF5 grid file.

    Parameters
    ----------
    path : str, path-like, or binary file object
    b : int or str
        0-based block number (negative counts from the end) or block name.
    allow_nonfinite : bool
        Accept NaN or infinite coordinates.
    max_points : int, optional
        Refuse a block of more points (default: what fits in memory).

    Returns
    -------
    Block
        ``xyz`` float64 ``(ni, nj, nk, 3)`` Fortran order, ``iblank`` int32 or None.
    """
    with _Reader(path) as r:
        n = r.index(b)
        meta = r.meta(n)
        check_points(f"{path}: block {n + 1}", int(np.prod(meta[1])), max_points=max_points)
        return r.block(n, allow_nonfinite, meta)


@damaged_file_errors
def read_face(path, b, face, *, allow_nonfinite: bool = False,
              max_points: int | None = None) -> np.ndarray:
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
    max_points : int, optional
        Refuse a face of more points (default: what fits in memory).

    Returns
    -------
    ndarray, float64, shape (na, nb, 3), Fortran order
        Equal to ``Block.face(face)`` of the block: imin/imax -> ``(nj, nk, 3)``,
        jmin/jmax -> ``(ni, nk, 3)``, kmin/kmax -> ``(ni, nj, 3)``.
    """
    f = face_index(face)
    with _Reader(path) as r:
        n = r.index(b)
        return r.face(n, f, allow_nonfinite, max_points)


@damaged_file_errors
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


@damaged_file_errors
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

    The root attribute ``created`` is the time of the write, or the time the
    environment variable ``SOURCE_DATE_EPOCH`` (seconds since 1970, UTC)
    gives, for reproducible files.

    Raises
    ------
    OverwriteError
        ``path`` is the grid's input file and ``overwrite`` is false.
    GridValueError
        Not a Grid, an unknown compression, ``extra_json`` not a JSON object.
    """
    if not isinstance(grid, Grid):
        raise GridValueError(f"write needs a Grid, got {type(grid).__name__}")
    options = write_options(like, compression, compression_level, extra_json)
    target = check_target(path, overwrite=overwrite, protect=[grid.source_path])
    with atomic_output(target, mode="path") as tmp:
        # Let HDF5 create the file rather than truncate the empty temporary
        # one: on ext4, closing a file that was opened with O_TRUNC forces a
        # flush of all its data (auto_da_alloc), 0.15 s per 0.5 GB.
        os.unlink(tmp)
        write_blocks(tmp, grid.blocks, ndim=grid.ndim, nblocks=grid.nblocks,
                     source_path=grid.source_path, source_format=grid.source_format, **options)


def write_options(like=None, compression=None, compression_level=None, extra_json=None) -> dict:
    """The checked options of :func:`write_blocks` from those of :func:`write`.

    Raises
    ------
    GridValueError
        An unknown compression, ``extra_json`` not a JSON object.
    """
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
    return {"compression": comp, "compression_level": level, "extra_text": extra_text}


def _created() -> str:
    """The ``created`` stamp: now, or ``SOURCE_DATE_EPOCH`` when set (reproducible files)."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    if epoch:
        try:
            when = _dt.datetime.fromtimestamp(int(epoch), _dt.timezone.utc)
        except (ValueError, OverflowError, OSError):
            raise GridValueError(f"SOURCE_DATE_EPOCH={epoch!r} is not a time in seconds since 1970") from None
    else:
        when = _dt.datetime.now(_dt.timezone.utc)
    return when.strftime("%Y-%m-%dT%H:%M:%SZ")


def write_blocks(path, blocks, *, ndim: int, nblocks: int, source_path=None, source_format=None,
                 compression=None, compression_level=None, extra_text=None) -> None:
    """Create the HDF5 file ``path`` (it must not exist) from blocks given one at a time.

    The bytes of :func:`write` (which calls it on a temporary file), for
    writers that hold one block at a time: ``blocks`` is an iterable of the
    ``nblocks`` blocks in order (a generator may fetch each when asked).
    ``compression``, ``compression_level`` and ``extra_text`` are the
    checked options of :func:`write_options`; not atomic by itself.
    """
    from .. import __version__
    src_fmt = "" if source_format is None else repr(source_format)
    comp, level = compression, compression_level
    created = _created()
    # file-format objects of HDF5 1.10: every piece of metadata carries a checksum
    with h5py.File(path, "x", libver=_LIBVER) as f:
        _set_text(f, "format", FORMAT_NAME)
        f.attrs["version"] = np.int64(LAYOUT_VERSION)
        f.attrs["ndim"] = np.int64(ndim)
        f.attrs["nblocks"] = np.int64(nblocks)
        _set_text(f, "creator", f"tfi_quat {__version__}")
        _set_text(f, "created", created)
        _set_text(f, "source", "" if source_path is None else str(source_path))
        _set_text(f, "source_format", src_fmt)
        group = f.create_group("blocks")
        count = 0
        for b in blocks:        # not enumerate(): its cached tuple would keep the last block
            g = group.create_group(_block_group_name(count))
            _set_text(g, "name", b.name or "")
            g.attrs["dims"] = np.asarray(b.dims, dtype=np.int64)
            _write_array(g, "xyz", b.xyz.T, comp, level)
            if b.iblank is not None:
                _write_array(g, "iblank", np.asarray(b.iblank, dtype=np.int32, order="F").T,
                             comp, level)
            count += 1
            del b           # a generator's next block may come from elsewhere: hold one at a time
        if count != nblocks:
            raise GridValueError(f"{path}: {count} blocks given for a file of {nblocks}")
        if extra_text is not None:
            data = extra_text.encode("utf-8")
            f.create_dataset("extra", data=np.bytes_(data),
                             dtype=h5py.string_dtype("utf-8", max(1, len(data))), track_times=False)


def _set_text(obj, name: str, text: str) -> None:
    """A fixed-length UTF-8 string attribute: kept in the (checksummed) object header.

    h5py's default, a variable-length string, lives in the global heap, which
    has no checksum.
    """
    data = text.encode("utf-8")
    obj.attrs.create(name, np.bytes_(data), dtype=h5py.string_dtype("utf-8", max(1, len(data))))


def _write_array(g: h5py.Group, key: str, data: np.ndarray, comp, level) -> None:
    """Store a C-contiguous array as dataset ``key`` (contiguous, or chunked + gzip)."""
    if comp is None:
        g.create_dataset(key, data=data, track_times=False)
    else:
        g.create_dataset(key, data=data, chunks=_chunks(data.shape), compression=comp,
                         compression_opts=level, shuffle=True, track_times=False)


from . import register  # noqa: E402  (registers the format on import)

register("hdf5", (".h5", ".hdf5", ".hdf"), read, write, HDF5Format, read_faces)
