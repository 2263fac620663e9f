"""Plot3D grid files: every common variant, detected automatically.

A Plot3D grid file is a header (the block count, then the dimensions of every
block) followed by each block's coordinates as whole arrays: all x with i
fastest, then all y, then (3-D) all z, then optionally an integer IBLANK
array.  The variants differ in framing and number types; one
:class:`Plot3DFormat` describes one variant:

=============  =====================================================  ==============
field          values (detection prefers the first)                   where it counts
=============  =====================================================  ==============
encoding       ``binary`` (C stream), ``fortran`` (unformatted,        all
               sequential, records framed by length markers),
               ``ascii``
endian         ``<``, ``>``                                           binary, fortran
int_size       4, 8 (header integers and IBLANK values)               binary, fortran
marker_size    4, 8 (Fortran record-length markers)                   fortran
multiblock     True (block count first), False (no block count)       all
ndim           3 (``ni nj nk``; x y z), 2 (``ni nj``; x y)             all
precision      8 (float64), 4 (float32)                               all
iblank         False, True                                            all
records        ``block`` (one record per block: x y z [iblank]),      fortran
               ``coordinate`` (one record per array: x, y, z,
               [iblank])
=============  =====================================================  ==============

Fortran files hold the block count in one record and all block dimensions
in the next (single-block files: one record with the dimensions).

Detection (:func:`detect`) tries every variant left open by the caller's
overrides: for binary files it parses the header (in chunks, stopping at the
first impossible dimension, so a wrong framing costs kilobytes), computes the
exact file size each variant implies and, for Fortran files, checks every
record marker; for text files it counts the values.  A variant fits only
when the sizes add up exactly and, when detection chooses among several,
when the ends of its arrays hold coordinates and IBLANK codes
(:func:`_check_content`; text: integer header lines).  When several fit (tiny grids; 2-D files with 8-byte
integers), the preferred values above decide, deterministically, and
:func:`detect_all` lists them all; when none fits, the error lists what was
tried and the closest misses (truncation, a bad record marker, a bad
dimension), with the block and byte offset.  A mostly-text file with a few
bytes that are not printable ASCII that fits no binary variant gets the
text reader's error, naming the line of the offending token.

Binary reads move the file bytes straight into each block's final
Fortran-order float64 array (``os.preadv`` in chunks, two threads for large
files); float32 values and the other byte order are converted chunk by
chunk, so the peak memory stays at the grid's own size plus a few
megabytes.  ASCII files are written with 17 significant digits and read by
one compiled pass over the text that converts every plain decimal exactly
(correctly rounded, Clinger's fast path and the Eisel-Lemire algorithm, also
for tokens of more than 19 digits when the first 19 decide the rounding), so
float64 values round-trip bit for bit; the rare other tokens (halfway cases
past 19 digits, subnormals, ``nan``) go through Python's ``float``, which
also reports a non-numeric token with its line.
"""

from __future__ import annotations

import functools
import math
import mmap
import os
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from ..errors import GridFormatError, GridValueError
from ..grid import Block, Grid, faces_of, has_z
from .._jit import jit
from . import register
from ._atomic import atomic_output, check_target
from ._limits import BYTES_PER_POINT, available_memory, check_points
from .partial import GridFaces, block_numbers, empty_faces, fill_faces

__all__ = ["Plot3DFormat", "read", "read_faces", "write", "detect", "detect_all", "write_format",
           "check_write", "block_offsets", "write_header", "write_block"]

#: allowed values of each field, the preferred (most common) value first
_CHOICES = {
    "encoding": ("binary", "fortran", "ascii"),
    "endian": ("<", ">"),
    "precision": (8, 4),
    "ndim": (3, 2),
    "multiblock": (True, False),
    "iblank": (False, True),
    "records": ("block", "coordinate"),
    "int_size": (4, 8),
    "marker_size": (4, 8),
}
#: field order of the detection preference (earlier fields weigh more)
_PRIORITY = ("encoding", "endian", "int_size", "marker_size", "multiblock", "ndim",
             "precision", "iblank", "records")
_ENDIAN_ALIASES = {"<": "<", ">": ">", "little": "<", "big": ">", "l": "<", "b": ">"}
#: fields that mean nothing for an encoding (kept at their default there)
_IGNORED = {
    "binary": ("records", "marker_size"),
    "ascii": ("endian", "records", "int_size", "marker_size"),
    "fortran": (),
}


@dataclass(frozen=True)
class Plot3DFormat:
    """One Plot3D file variant.

    Attributes
    ----------
    encoding : {"binary", "fortran", "ascii"}
        ``binary``: C stream, no record markers.  ``fortran``: Fortran
        unformatted sequential, each record framed by length markers.
        ``ascii``: formatted text.
    endian : {"<", ">"}
        Byte order of binary and Fortran files (ignored for ASCII).
        ``"little"`` and ``"big"`` are accepted.
    precision : {4, 8}
        Bytes per coordinate value (float32 / float64).  ASCII: 8 writes 17
        significant digits, 4 writes 9 and a reader given ``precision=4``
        rounds the values to float32.
    ndim : {2, 3}
        2: ``ni nj`` headers and x, y only; 3: ``ni nj nk`` and x, y, z.
    multiblock : bool
        The file starts with the block count.  Single-block files have no
        block-count line.
    iblank : bool
        Each block's coordinates are followed by an int IBLANK array.
    records : {"block", "coordinate"}
        Fortran only: one record per block (x, y, z[, iblank]) or the older
        layout with one record per coordinate array.
    int_size : {4, 8}
        Bytes per header integer (block count, dimensions) and IBLANK value;
        8 for codes that write 64-bit default integers.
    marker_size : {4, 8}
        Fortran only: bytes per record-length marker.

    Raises
    ------
    GridFormatError
        A field holds a value outside the lists above.
    """

    encoding: str = "binary"
    endian: str = "<"
    precision: int = 8
    ndim: int = 3
    multiblock: bool = True
    iblank: bool = False
    records: str = "block"
    int_size: int = 4
    marker_size: int = 4

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            choices = _CHOICES[f.name]
            if isinstance(choices[0], str):
                ok = isinstance(value, str)
                if ok:
                    value = value.strip().lower()
                    if f.name == "endian":
                        value = _ENDIAN_ALIASES.get(value, value)
                    ok = value in choices
            elif isinstance(choices[0], bool):
                ok = isinstance(value, (bool, np.bool_))
                value = bool(value) if ok else value
            else:
                ok = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)) \
                    and int(value) in choices
                value = int(value) if ok else value
            if not ok:
                raise GridFormatError(f"Plot3D format: {f.name}={value!r} is not one of "
                                      f"{', '.join(repr(c) for c in choices)}")
            object.__setattr__(self, f.name, value)

    def replace(self, **changes) -> "Plot3DFormat":
        """A copy with some fields changed (unknown field names raise GridFormatError)."""
        _check_names(changes, "Plot3D format")
        return replace(self, **changes)

    def canonical(self) -> "Plot3DFormat":
        """The same variant with the fields its encoding ignores set to their defaults."""
        return replace(self, **{n: _DEFAULT_VALUES[n] for n in _IGNORED[self.encoding]})

    def describe(self) -> str:
        """One line for people, e.g. ``Fortran unformatted, big-endian, float64, 3-D, ...``."""
        enc = {"binary": "C binary", "fortran": "Fortran unformatted", "ascii": "ASCII"}[self.encoding]
        parts = [enc]
        if self.encoding != "ascii":
            parts.append("little-endian" if self.endian == "<" else "big-endian")
        parts += [f"float{8 * self.precision}", f"{self.ndim}-D",
                  "multi-block" if self.multiblock else "single-block",
                  "iblank" if self.iblank else "no iblank"]
        if self.encoding != "ascii":
            parts.append(f"int{8 * self.int_size}")
        if self.encoding == "fortran":
            parts += [f"{self.marker_size}-byte markers",
                      "one record per block" if self.records == "block" else
                      "one record per coordinate"]
        return ", ".join(parts)

    def _key(self) -> tuple:
        return _preference_key(self)


_DEFAULT_VALUES = {f.name: f.default for f in fields(Plot3DFormat)}


@functools.lru_cache(maxsize=1024)
def _preference_key(fmt: Plot3DFormat) -> tuple:
    c = fmt.canonical()
    return tuple(_CHOICES[n].index(getattr(c, n)) for n in _PRIORITY)


_FIELD_NAMES = tuple(_DEFAULT_VALUES)


def _check_names(kw, what) -> None:
    bad = [k for k in kw if k not in _FIELD_NAMES]
    if bad:
        raise GridFormatError(f"{what}: unknown option(s) {', '.join(map(repr, bad))}; "
                              f"expected Plot3D format fields: {', '.join(_FIELD_NAMES)}")


# ---------------------------------------------------------------- layout

class _Miss(Exception):
    """One variant does not fit the file: ``rank`` (lower = more plausible) and why."""

    def __init__(self, rank: int, msg: str, distance: float = 0.0, limit: bool = False):
        super().__init__(msg)
        self.rank = rank
        self.msg = msg
        self.distance = distance
        #: the header declares more points than the size limit allows
        self.limit = limit


@dataclass
class _BlockLayout:
    dims: tuple            # (ni, nj, nk)
    npoints: int
    runs: list             # [(file offset, first value index in xyz flat, count)]
    iblank: int | None     # file offset of the IBLANK array
    markers: list          # [(file offset, expected record length)]
    start: int
    end: int


def _layout(fmt: Plot3DFormat, dims) -> tuple[int, list[_BlockLayout], int, list]:
    """File offsets of every array and record marker of ``fmt`` with these block dims.

    Returns ``(header_end, blocks, total_size, header_markers)``.
    """
    ms = fmt.marker_size if fmt.encoding == "fortran" else 0
    isz, prec, nd = fmt.int_size, fmt.precision, fmt.ndim
    off = 0
    markers: list = []

    def record(length):
        nonlocal off
        if ms:
            markers.append((off, length))
            markers.append((off + ms + length, length))
        start = off + ms
        off = start + length + ms
        return start

    if fmt.multiblock:
        record(isz)
    record(isz * nd * len(dims))
    header_end, header_markers = off, markers
    blocks = []
    for d in dims:
        d = tuple(int(v) for v in d)
        markers = []
        n = d[0] * d[1] * d[2]
        start = off
        if fmt.encoding == "fortran" and fmt.records == "coordinate":
            runs = [(record(n * prec), c * n, n) for c in range(nd)]
            ib = record(n * isz) if fmt.iblank else None
        else:
            s = record(n * (nd * prec + (isz if fmt.iblank else 0)))
            runs = [(s, 0, nd * n)]
            ib = s + nd * n * prec if fmt.iblank else None
        blocks.append(_BlockLayout(tuple(d), n, runs, ib, markers, start, off))
    return header_end, blocks, off, header_markers


def _int_dtype(fmt) -> np.dtype:
    return np.dtype(f"{fmt.endian}i{fmt.int_size}")


def _float_dtype(fmt) -> np.dtype:
    return np.dtype(f"{fmt.endian}f{fmt.precision}")


#: positioned reads without a shared file offset (POSIX); elsewhere seek + read, one thread
_HAVE_PREAD = hasattr(os, "pread") and hasattr(os, "preadv")


def _pread(fd, nbytes: int, offset: int) -> bytes:
    if _HAVE_PREAD:
        return os.pread(fd, nbytes, offset)
    os.lseek(fd, offset, os.SEEK_SET)
    return os.read(fd, nbytes)


def _read_ints(fd, size, offset, count, dtype) -> np.ndarray:
    raw = _pread(fd, count * dtype.itemsize, offset)
    if len(raw) != count * dtype.itemsize:
        raise _Miss(3, f"header at byte offset {offset} runs past the end of the file ({size} bytes)")
    return np.frombuffer(raw, dtype=dtype).astype(np.int64)


def _check_marker(fd, size, offset, expected, ms, endian, where, rank):
    raw = _pread(fd, ms, offset)
    if len(raw) != ms:
        raise _Miss(rank, f"{where}: record marker at byte offset {offset} is past the end of the "
                          f"file ({size} bytes): the file is truncated")
    got = int(np.frombuffer(raw, dtype=f"{endian}i{ms}")[0])
    if got != expected:
        raise _Miss(rank, f"{where}: inconsistent Fortran record marker at byte offset {offset}: "
                          f"reads {got}, the record holds {expected} bytes")


#: header integers read per positioned read: a wrong framing (the other byte order reads a
#: block count 1 as 16,777,216) is refused within the first chunk, not after reading its "header"
_HEADER_CHUNK = 1 << 13


def _parse_header(fd, size: int, fmt: Plot3DFormat, max_points=None) -> np.ndarray:
    """Block dims ``(nblocks, 3)`` int64 of a binary/Fortran file read as ``fmt``.

    Only the framing fields of ``fmt`` count.  The dimensions are read in
    chunks and checked as they come (each >= 1, and all blocks so far small
    enough to fit the file even as float32), so a wrong framing costs a few
    kilobytes of reading, whatever block count it reads.
    """
    it = _int_dtype(fmt)
    isz, nd = fmt.int_size, fmt.ndim
    ms = fmt.marker_size if fmt.encoding == "fortran" else 0
    off = 0
    if fmt.multiblock:
        if ms:
            # the first marker decides whether this framing is plausible at all
            first = _pread(fd, ms, 0)
            got = int(np.frombuffer(first, f"{fmt.endian}i{ms}")[0]) if len(first) == ms else None
            if got != isz:
                raise _Miss(4, f"header: the first record marker at byte offset 0 reads {got}, "
                               f"expected {isz} (a record holding the block count)")
            _check_marker(fd, size, ms + isz, isz, ms, fmt.endian, "header", 1)
        nb = int(_read_ints(fd, size, off + ms, 1, it)[0])
        off += isz + 2 * ms
        # the header, then at least one float32 point a block
        need = off + 2 * ms + nb * nd * isz + (nb * nd * 4 if nb > 0 else 0)
        if nb < 1 or need > size:
            rank = 1 if ms else (2 if -(1 << 20) < nb < 1 else 3)
            raise _Miss(rank, f"header: block count {nb} at byte offset {ms} "
                              + ("must be >= 1" if nb < 1 else
                                 f"needs at least {need} bytes (header and one float32 point a "
                                 f"block), the file has {size} bytes"))
    else:
        nb = 1
    if ms:
        raw = _pread(fd, ms, off)
        lead = int(np.frombuffer(raw, f"{fmt.endian}i{ms}")[0]) if len(raw) == ms else None
        if lead != nb * nd * isz:
            rank = 1 if fmt.multiblock else 4
            raise _Miss(rank, f"header: the dimensions record marker at byte offset {off} reads "
                              f"{lead}, expected {nb * nd * isz} ({nb} block(s) x {nd} x {isz} bytes)")
        _check_marker(fd, size, off + ms + nb * nd * isz, nb * nd * isz, ms, fmt.endian,
                      "header", 1)
    doff = off + ms
    data_start = doff + nb * nd * isz + ms
    chunks = []
    points = 0
    for b0 in range(0, nb, _HEADER_CHUNK):
        b1 = min(nb, b0 + _HEADER_CHUNK)
        vals = _read_ints(fd, size, doff + b0 * nd * isz, (b1 - b0) * nd, it).reshape(-1, nd)
        bad = np.argwhere((vals < 1) | (vals >= (1 << 31)))
        if bad.size:
            b, c = (int(v) for v in bad[0])
            v = int(vals[b, c])
            plausible = bool(np.all((vals > -(1 << 20)) & (vals <= size)))
            rank = 1 if ms else (2 if plausible else 3)
            raise _Miss(rank, f"header: block {b0 + b + 1} dimension {'ijk'[c]} = {v} at byte offset "
                              f"{doff + ((b0 + b) * nd + c) * isz} "
                              + ("must be >= 1" if v < 1 else "is too large"))
        chunks.append(vals)
        # in float64: a product of three dimensions below 2**31 can overflow int64
        points += int(np.prod(vals.astype(np.float64), axis=1).sum())
        least = data_start + points * nd * 4
        if least > size:
            if b1 == nb:
                break   # the layout check says which block the file ends in
            raise _Miss(1 if ms else 2,
                        f"header: blocks 1..{b1} of {nb} declare {points:,} points, at least "
                        f"{least} bytes even as float32, the file has {size} bytes: the file is "
                        "truncated or this is not its header")
        # a file (sparse, say) that holds what its header declares: refuse a grid too
        # large to hold before going on (its dimensions alone can be gigabytes)
        try:
            check_points(f"header: blocks 1..{b1} of {nb}", points, max_points=max_points)
        except GridFormatError as exc:
            raise _Miss(0, str(exc), limit=True) from None
    dims = np.ones((nb, 3), dtype=np.int64)
    dims[:, :nd] = np.concatenate(chunks)
    return dims


def _check_layout(fd, size: int, fmt: Plot3DFormat, dims, header_rank: int):
    """Check that ``fmt`` with these dims accounts for every byte (and marker) of the file."""
    header_end, blocks, total, _ = _layout(fmt, dims)
    if total != size:
        if total > size:
            cut = next(n for n, b in enumerate(blocks) if b.end > size)
            b = blocks[cut]
            msg = (f"the file is truncated: block {cut + 1} of {len(blocks)} "
                   f"({'x'.join(map(str, b.dims[:fmt.ndim]))}) occupies byte offsets "
                   f"{b.start}..{b.end}, but the file ends at byte offset {size} "
                   f"(the header claims {sum(x.npoints for x in blocks)} points, {total} bytes)")
        else:
            msg = (f"{size - total} unexpected bytes after the last block "
                   f"(block {len(blocks)} ends at byte offset {total}, the file has {size} bytes)")
        raise _Miss(header_rank + 1, msg, abs(math.log(max(total, 1) / size)))
    if fmt.encoding == "fortran":
        ms = fmt.marker_size
        for n, b in enumerate(blocks):
            for off, length in b.markers:
                _check_marker(fd, size, off, length, ms, fmt.endian, f"block {n + 1}", 0)
    return blocks


#: values read at each end of every coordinate and IBLANK array when detection checks
#: that a variant's arrays hold what they should
_SAMPLE = 512
#: a coordinate read from the right bytes is zero or between these magnitudes (the smallest
#: normal float32, and 2**120 for float32); the bits of integers or of floats of the other
#: precision almost never are: small integers read as floats are subnormal, float32 pairs
#: read as float64 are below 2**-126 (unless the float32 values exceed 2**97), the low
#: halves of float64 values read as float32 have random exponents
COORD_RANGE = {4: (2.0 ** -126, 2.0 ** 120), 8: (2.0 ** -126, math.inf)}
#: the nonzero float32 coordinates of one block are within this factor of each other in
#: size (round-off next to zero is 1e-8 of the block's size); the low halves of float64
#: values read as float32 have exponents spread over the whole float32 range
COORD_SPREAD = 2.0 ** 128
#: an IBLANK value read from the right bytes is at most this in size (1 field, 0 hole,
#: 2 or -n fringe with donor block n); the bits of a float beyond 2**-1000 never are
IBLANK_LIMIT = 1 << 20


def _sample_spans(count: int):
    """``(first, n)`` spans of at most ``_SAMPLE`` values at the start and end of ``count``."""
    if count <= 2 * _SAMPLE:
        return [(0, count)]
    return [(0, _SAMPLE), (count - _SAMPLE, _SAMPLE)]


def _check_content(fd, fmt: Plot3DFormat, blocks) -> None:
    """Check that ``fmt``'s arrays hold coordinates and IBLANK codes (their ends, O(1) a block).

    A damaged file can fit a wrong variant byte for byte (a truncated
    two-block float32 file is exactly one float64 block whose first values
    are the old header's integers); what its arrays would hold gives it away.
    """
    fdt, idt = _float_dtype(fmt), _int_dtype(fmt)
    lo, hi = COORD_RANGE[fmt.precision]
    expect = f"{lo:.3g} to {hi:.3g}" if hi < math.inf else f"at least {lo:.3g}"
    for n, b in enumerate(blocks):
        smallest, largest = (math.inf, 0), (0.0, 0)
        for c in range(fmt.ndim):
            first = c * b.npoints
            off, v0, _ = next(r for r in b.runs if r[1] <= first < r[1] + r[2])
            base = off + (first - v0) * fmt.precision
            for s, k in _sample_spans(b.npoints):
                at = base + s * fmt.precision
                with np.errstate(invalid="ignore", over="ignore"):   # signalling NaNs
                    vals = np.frombuffer(_pread(fd, k * fmt.precision, at), dtype=fdt).astype(np.float64)
                    mag = np.abs(vals)
                    bad = (mag > 0) & ((mag < lo) | (mag > hi)) & np.isfinite(vals)
                ok = (mag > 0) & np.isfinite(vals)
                if ok.any():
                    j, k = int(np.argmin(np.where(ok, mag, np.inf))), int(np.argmax(np.where(ok, mag, 0)))
                    smallest = min(smallest, (float(mag[j]), at + j * fmt.precision))
                    largest = max(largest, (float(mag[k]), at + k * fmt.precision))
                if bad.any():
                    j = int(np.argmax(bad))
                    raise _Miss(0, f"block {n + 1}: {'xyz'[c]} value {vals[j]:.6g} at byte offset "
                                   f"{at + j * fmt.precision} is no coordinate (neither 0 nor "
                                   f"{expect} in size): these are not the bytes of "
                                   f"float{8 * fmt.precision} coordinates")
        if fmt.precision == 4 and largest[0] > smallest[0] * COORD_SPREAD:
            raise _Miss(0, f"block {n + 1}: coordinates from {smallest[0]:.3g} (byte offset "
                           f"{smallest[1]}) to {largest[0]:.3g} (byte offset {largest[1]}) in size, "
                           f"more than a factor {COORD_SPREAD:.3g} apart: these are not the bytes "
                           f"of float{8 * fmt.precision} coordinates")
        if b.iblank is None:
            continue
        for s, k in _sample_spans(b.npoints):
            at = b.iblank + s * fmt.int_size
            vals = np.frombuffer(_pread(fd, k * fmt.int_size, at), dtype=idt).astype(np.int64)
            bad = np.abs(vals) > IBLANK_LIMIT
            if bad.any():
                j = int(np.argmax(bad))
                raise _Miss(0, f"block {n + 1}: IBLANK value {int(vals[j])} at byte offset "
                               f"{at + j * fmt.int_size} is no blanking code (at most "
                               f"{IBLANK_LIMIT:,} in size): these are not the bytes of IBLANK values")


def _all_binary_variants() -> list[tuple[Plot3DFormat, list[Plot3DFormat]]]:
    """Every binary/Fortran framing with its completions, in preference order (built once)."""
    if not _BINARY_VARIANTS:
        for enc in ("binary", "fortran"):
            for endian in _CHOICES["endian"]:
                for isz in _CHOICES["int_size"]:
                    for ms in (_CHOICES["marker_size"] if enc == "fortran" else (4,)):
                        for mb in _CHOICES["multiblock"]:
                            for nd in _CHOICES["ndim"]:
                                fr = Plot3DFormat(encoding=enc, endian=endian, int_size=isz,
                                                  marker_size=ms, multiblock=mb, ndim=nd)
                                recs = _CHOICES["records"] if enc == "fortran" else ("block",)
                                comps = [fr.replace(precision=p, iblank=ib, records=r)
                                         for p in _CHOICES["precision"] for ib in _CHOICES["iblank"]
                                         for r in recs]
                                _BINARY_VARIANTS.append((fr, comps))
    return _BINARY_VARIANTS


_BINARY_VARIANTS: list = []
_FRAMING_FIELDS = ("encoding", "endian", "int_size", "marker_size", "multiblock", "ndim")


def _framings(fixed: dict) -> list[tuple[Plot3DFormat, list[Plot3DFormat]]]:
    """Binary/Fortran framings compatible with ``fixed``, each with its compatible completions."""
    out = []
    for fr, comps in _all_binary_variants():
        if _compatible(fr, fixed, _FRAMING_FIELDS):
            out.append((fr, [f for f in comps if _compatible(f, fixed, ("precision", "iblank", "records"))]))
    return out


def _compatible(f: Plot3DFormat, fixed: dict, names) -> bool:
    ignored = _IGNORED[f.encoding]
    return all(getattr(f, n) == fixed[n] for n in names if n in fixed and n not in ignored)


def _summary(tried: list[Plot3DFormat]) -> str:
    parts = []
    for n in _PRIORITY:
        vals = sorted({getattr(t, n) for t in tried if n not in _IGNORED[t.encoding]},
                      key=lambda v: _CHOICES[n].index(v))
        if vals:
            parts.append(f"{n} in {{{', '.join(map(str, vals))}}}")
    return f"{len(tried)} variant(s): " + "; ".join(parts)


def _no_fit(path, size, tried, misses, what="") -> GridFormatError:
    """The error for a file no variant fits; ``misses``: (rank, framing key, distance, key, msg, fmt)."""
    misses = sorted(misses, key=lambda m: m[:4])
    if len(tried) == 1 and misses:
        return GridFormatError(f"{path}: not a {tried[0].describe()} Plot3D file: {misses[0][4]}")
    # the plausible misses; when there are none (e.g. every framing fails at its first
    # record marker), the first ones in preference order, so the message still says why
    close = [m for m in misses if m[0] <= 2] or misses
    shown = [f"  as {m[5].describe()}: {m[4]}" for m in close][:3]
    text = f"{path}: no Plot3D variant fits this {size}-byte file{what}; tried {_summary(tried)}"
    if shown:
        text += ". Closest:\n" + "\n".join(shown)
    return GridFormatError(text)


def _looks_like_text(fd, size) -> bool:
    head = _pread(fd, min(size, 4096), 0)
    return not head.translate(None, _TEXT_BYTES)


_TEXT_BYTES = bytes(range(0x20, 0x7F)) + b"\t\n\r\f\v"


def _detect_binary(fd, size, path, fixed, max_points=None):
    framings = _framings(fixed)
    # a caller who names the variant completely is taken at its word: sizes and record
    # markers must fit, but the arrays' contents are not second-guessed
    judge = sum(len(comps) for _, comps in framings) > 1
    tried, misses, fits, limits = [], [], [], []
    for fr, comps in framings:
        tried += comps
        if not comps:
            continue
        try:
            dims = _parse_header(fd, size, fr, max_points)
        except _Miss as m:
            (limits if m.limit else misses).append((m.rank, fr._key(), 0.0, fr._key(), m.msg, fr))
            continue
        header_rank = 0 if fr.encoding == "fortran" else 1
        for f in comps:
            try:
                blocks = _check_layout(fd, size, f, dims, header_rank)
                if judge:
                    _check_content(fd, f, blocks)
            except _Miss as m:
                misses.append((m.rank, fr._key(), m.distance, f._key(), m.msg, f))
                continue
            fits.append((f._key(), f, dims, blocks))
    if not fits:
        if limits:
            raise GridFormatError(f"{path}: {limits[0][4]}")
        raise _no_fit(path, size, tried, misses)
    fits.sort(key=lambda t: t[0])
    return fits


# ---------------------------------------------------------------- binary read

_CHUNK = 1 << 18            # values per read/convert/check chunk (2 MiB of float64)
_PARALLEL_BYTES = 32 << 20  # files larger than this are read with two threads


def _pread_into(fd, buf: memoryview, offset: int) -> int:
    """Fill ``buf`` from byte ``offset``; returns the bytes read (fewer at end of file)."""
    done = 0
    while done < len(buf):
        if _HAVE_PREAD:
            k = os.preadv(fd, [buf[done:]], offset + done)
        else:
            chunk = _pread(fd, len(buf) - done, offset + done)
            k = len(chunk)
            buf[done:done + k] = chunk
        if k <= 0:
            break
        done += k
    return done


def _read_task(fd, task):
    """Read one chunk into its destination; return a problem tuple or None."""
    offset, dest, fdtype, check, first = task
    need = dest.shape[0] * fdtype.itemsize
    if fdtype == dest.dtype or fdtype.newbyteorder("=") == dest.dtype:
        got = _pread_into(fd, memoryview(dest).cast("B"), offset)
        if got != need:
            return ("short", offset + got, None)
        if fdtype != dest.dtype:
            dest.byteswap(inplace=True)
    else:
        tmp = np.empty(dest.shape[0], dtype=fdtype)
        got = _pread_into(fd, memoryview(tmp).cast("B"), offset)
        if got != need:
            return ("short", offset + got, None)
        if dest.dtype.kind == "i" and (tmp.min() < -(1 << 31) or tmp.max() >= (1 << 31)):
            bad = int(np.argmax((tmp < -(1 << 31)) | (tmp >= (1 << 31))))
            return ("range", first + bad, int(tmp[bad]))
        # a signalling NaN raises the "invalid" flag when widened; NaNs are reported below
        with np.errstate(invalid="ignore"):
            dest[...] = tmp
    if check:
        bad = _first_nonfinite(dest)
        if bad is not None:
            return ("nonfinite", first + bad, None)
    return None


def _first_nonfinite(a: np.ndarray) -> int | None:
    """Index of the first NaN/inf of a 1-D float array, or None (one fast reduction if all finite)."""
    with np.errstate(over="ignore", invalid="ignore"):
        if np.isfinite(np.add.reduce(a)):
            return None
    bad = ~np.isfinite(a)
    return int(np.argmax(bad)) if bad.any() else None


def _read_blocks(fd, path, fmt, blocks, allow_nonfinite, ids=None, nblocks=None) -> list[Block]:
    """Read the blocks of these layouts; ``ids`` their 0-based numbers in the file (default
    0, 1, ...) out of ``nblocks`` (default ``len(blocks)``), for names and messages."""
    ids = list(range(len(blocks))) if ids is None else ids
    nblocks = len(blocks) if nblocks is None else nblocks
    fdt, idt = _float_dtype(fmt), _int_dtype(fmt)
    out, tasks = [], []
    for n, b in enumerate(blocks):
        ni, nj, nk = b.dims
        xyz = np.empty((ni, nj, nk, 3), dtype=np.float64, order="F")
        flat = xyz.reshape(-1, order="F")
        if fmt.ndim == 2:
            flat[2 * b.npoints:] = 0.0
        ib = np.empty((ni, nj, nk), dtype=np.int32, order="F") if fmt.iblank else None
        out.append((xyz, ib))
        for off, v0, count in b.runs:
            for s in range(0, count, _CHUNK):
                e = min(count, s + _CHUNK)
                tasks.append((n, "xyz", off + s * fmt.precision, v0 + s,
                              (off + s * fmt.precision, flat[v0 + s:v0 + e], fdt,
                               not allow_nonfinite, v0 + s)))
        if ib is not None:
            ibf = ib.reshape(-1, order="F")
            for s in range(0, b.npoints, _CHUNK):
                e = min(b.npoints, s + _CHUNK)
                tasks.append((n, "iblank", b.iblank + s * fmt.int_size, s,
                              (b.iblank + s * fmt.int_size, ibf[s:e], idt, False, s)))
    total = sum(t[4][1].nbytes for t in tasks)
    nthreads = min(2, os.cpu_count() or 1) if total > _PARALLEL_BYTES and _HAVE_PREAD else 1
    if nthreads > 1:
        with ThreadPoolExecutor(nthreads) as pool:
            results = list(pool.map(lambda t: _read_task(fd, t[4]), tasks))
    else:
        results = [_read_task(fd, t[4]) for t in tasks]
    for t, r in zip(tasks, results):
        if r is None:
            continue
        n, kind = t[0], t[1]
        b = blocks[n]
        where = f"{path}: block {ids[n] + 1} of {nblocks}"
        if r[0] == "short":
            raise GridFormatError(f"{where}: the file ended at byte offset {r[1]} while reading "
                                  f"its {kind} values (truncated while being read?)")
        if r[0] == "range":
            raise GridFormatError(f"{where}: IBLANK value {r[2]} at byte offset "
                                  f"{b.iblank + r[1] * fmt.int_size} does not fit a 32-bit integer")
        idx = r[1]
        c, rem = divmod(idx, b.npoints)
        ni, nj, _ = b.dims
        i, j, k = rem % ni, (rem // ni) % nj, rem // (ni * nj)
        off = next(o + (idx - v0) * fmt.precision for o, v0, cnt in b.runs if v0 <= idx < v0 + cnt)
        raise GridFormatError(f"{where}: non-finite coordinate {'xyz'[c]} = {out[n][0][i, j, k, c]} "
                              f"at (i, j, k) = ({i + 1}, {j + 1}, {k + 1}) (1-based), byte offset "
                              f"{off} (pass allow_nonfinite=True to accept)")
    return [Block(xyz, ib, name=f"block{ids[n] + 1}", allow_nonfinite=True)
            for n, (xyz, ib) in enumerate(out)]


def _read_faces(fd, path, fmt, layout, allow_nonfinite, ids=None) -> GridFaces:
    """The faces of every block of a binary file, read through a memory map of it.

    Only the pages holding face values are touched: the k faces are
    contiguous runs, the j faces ``nk`` runs of ``ni`` values, the i faces one
    value per row of ``ni`` (every page of a block whose rows are shorter
    than a page, but no copy of the volume is made).  ``ids``: the blocks
    whose faces are read (default all).
    """
    fdt = _float_dtype(fmt)
    names = faces_of(fmt.ndim)
    mm = mmap.mmap(fd, 0, access=mmap.ACCESS_READ)
    try:
        out = [None] * len(layout)
        for n in (range(len(layout)) if ids is None else ids):
            b = layout[n]
            ni, nj, nk = b.dims
            faces = empty_faces(b.dims, fmt.ndim)
            for c in range(fmt.ndim):
                v = c * b.npoints
                off = next(o + (v - v0) * fmt.precision for o, v0, cnt in b.runs if v0 <= v < v0 + cnt)
                coord = np.ndarray((ni, nj, nk), dtype=fdt, buffer=mm, offset=off, order="F")
                fill_faces(faces, c, coord, fmt.ndim)
                del coord
            if not allow_nonfinite:
                for f, arr in zip(names, faces):
                    if _first_nonfinite(arr.reshape(-1, order="F")) is not None:
                        raise GridFormatError(f"{path}: block {n + 1} of {len(layout)}, face {f}: "
                                              "non-finite coordinate (pass allow_nonfinite=True to accept)")
            out[n] = tuple(faces)
    finally:
        try:
            mm.close()      # every view of it (coord) is gone by now
        except BufferError:  # an error left one alive: the map closes when it goes
            pass
    return GridFaces(fmt.ndim, [b.dims for b in layout], out,
                     [f"block{n + 1}" for n in range(len(layout))], os.fspath(path), fmt,
                     block_ids=None if ids is None else tuple(ids))


# ---------------------------------------------------------------- ASCII read

_TOKEN = re.compile(rb"\S+")


def _token_position(data: bytes, index: int):
    """Line (1-based), column (1-based) and text of token number ``index`` (error paths only)."""
    for n, m in enumerate(_TOKEN.finditer(data)):
        if n == index:
            line = data.count(b"\n", 0, m.start()) + 1
            col = m.start() - (data.rfind(b"\n", 0, m.start()) + 1) + 1
            return line, col, m.group().decode("ascii", "replace")
    return None


def _parse_text(data: bytes, path) -> np.ndarray:
    """All whitespace-separated numbers of the file as float64, correctly rounded.

    The compiled scanner converts every plain decimal token exactly (more
    than 19 significant digits too, unless the digits past the 19th decide
    the rounding); the rare others (those, subnormal or overflowing values,
    ``nan``, ``inf``, Fortran's ``1.0-100``) go through Python's ``float``,
    which also finds the first non-numeric token.
    """
    buf = np.frombuffer(data, dtype=np.uint8)
    ntok = _count_tokens(buf)
    out = np.empty(ntok, dtype=np.float64)
    hi, lo, exact10 = _decimal_tables()
    cap = 1 << 12
    while True:
        fb = np.empty((3, min(cap, ntok)), dtype=np.int64)
        k, nfb = _parse_decimals(buf, out, out.view(np.uint64), hi, lo, exact10, fb)
        if nfb <= fb.shape[1]:
            break
        cap = nfb
    for t in range(nfb):
        idx, start, end = (int(v) for v in fb[:, t])
        tok = data[start:end]
        try:
            out[idx] = float(_FORTRAN_EXP.sub(rb"\1e\2", tok.translate(_D_TO_E)))
        except ValueError:
            line = data.count(b"\n", 0, start) + 1
            col = start - (data.rfind(b"\n", 0, start) + 1) + 1
            raise GridFormatError(
                f"{path}: line {line}, column {col}: non-numeric token "
                f"{tok[:40].decode('ascii', 'replace')!r} (value number {idx + 1}"
                f"{_ascii_block_hint(data, idx)})") from None
    return out


#: Fortran E format drops the E of three-digit exponents: 1.234567-100
_FORTRAN_EXP = re.compile(rb"^([-+]?(?:\d+\.?\d*|\.\d+))([-+]\d+)$")


@functools.lru_cache(maxsize=None)
def _decimal_tables():
    """128-bit truncated powers of five for q in -342..308 (Eisel-Lemire), and exact 10**0..22."""
    hi = np.zeros(651, dtype=np.uint64)
    lo = np.zeros(651, dtype=np.uint64)
    for q in range(-342, 309):
        if q >= 0:
            p = 5 ** q
            p = p << max(0, 128 - p.bit_length()) >> max(0, p.bit_length() - 128)
        else:
            p5 = 5 ** -q
            z = p5.bit_length()
            c = (1 << (z + 127 if q >= -27 else 2 * z + 128)) // p5 + 1
            p = c >> max(0, c.bit_length() - 128)
        hi[q + 342] = p >> 64
        lo[q + 342] = p & ((1 << 64) - 1)
    return hi, lo, np.array([10.0 ** k for k in range(23)])


_U = np.uint64
_M32 = np.uint64(0xFFFFFFFF)
_S32 = np.uint64(32)


@jit(inline="always")
def _mul128(a, b):
    """Full 64 x 64 -> 128-bit product ``(low, high)`` of two uint64."""
    alo = a & _M32
    ahi = a >> _S32
    blo = b & _M32
    bhi = b >> _S32
    p0 = alo * blo
    p1 = alo * bhi
    p2 = ahi * blo
    p3 = ahi * bhi
    mid = (p0 >> _S32) + (p1 & _M32) + (p2 & _M32)
    return (p0 & _M32) | (mid << _S32), p3 + (p1 >> _S32) + (p2 >> _S32) + (mid >> _S32)


@jit(inline="always")
def _clz64(w):
    n = 0
    for bits in (32, 16, 8, 4, 2, 1):
        if w < (_U(1) << _U(64 - bits)):
            w <<= _U(bits)
            n += bits
    return n


@jit
def _eisel_lemire(w, q, p5hi, p5lo):
    """Bits of the correctly rounded float64 of ``w * 10**q`` (w > 0), or -1 when undecided.

    Lemire, "Number parsing at a gigabyte per second" (2021); subnormal and
    overflowing results are left to the caller (-1).
    """
    if q < -342 or q > 308:
        return -1
    lz = _clz64(w)
    w = w << _U(lz)
    plo, phi = _mul128(w, p5hi[q + 342])
    if (phi & _U(0x1FF)) == _U(0x1FF):
        slo, shi = _mul128(w, p5lo[q + 342])
        plo = plo + shi
        if shi > plo:
            phi += _U(1)
        if plo == _U(0xFFFFFFFFFFFFFFFF) and (q < -27 or q > 55):
            return -1
    upperbit = phi >> _U(63)
    shift = upperbit + _U(9)
    mant = phi >> shift
    power2 = (((152170 + 65536) * q) >> 16) + 63 + np.int64(upperbit) - lz + 1023
    if power2 <= 0:
        return -1
    if plo <= _U(1) and -4 <= q <= 23 and (mant & _U(3)) == _U(1) and (mant << shift) == phi:
        mant &= ~_U(1)
    mant += mant & _U(1)
    mant >>= _U(1)
    if mant >= (_U(2) << _U(52)):
        mant = _U(1) << _U(52)
        power2 += 1
    mant &= ~(_U(1) << _U(52))
    if power2 >= 0x7FF:
        return -1
    return np.int64(mant | (_U(power2) << _U(52)))


@jit
def _count_tokens(buf):
    n = 0
    inside = False
    for c in buf:
        ws = c == 32 or (c >= 9 and c <= 13)
        if not ws and not inside:
            n += 1
        inside = not ws
    return n


@jit
def _parse_decimals(buf, out, bits, p5hi, p5lo, exact10, fallback):
    """Convert the whitespace-separated decimal tokens of ``buf`` (uint8) into ``out`` (float64).

    ``bits`` is ``out`` viewed as uint64.  Tokens this kernel does not
    convert exactly are recorded in ``fallback`` (3, cap) int64 as (token
    index, start, end) and get NaN.  Returns ``(tokens, fallbacks)``.
    """
    n = buf.shape[0]
    i = 0
    k = 0
    nfb = 0
    while True:
        while i < n and (buf[i] == 32 or (buf[i] >= 9 and buf[i] <= 13)):
            i += 1
        if i >= n:
            break
        start = i
        end = i
        while end < n and not (buf[end] == 32 or (buf[end] >= 9 and buf[end] <= 13)):
            end += 1
        neg = buf[i] == 45
        if neg or buf[i] == 43:
            i += 1
        w = _U(0)
        nd = 0          # significant digits in w (at most 19)
        adj = 0         # decimal exponent of w's last digit
        digits = 0
        exact = True
        while i < end and buf[i] >= 48 and buf[i] <= 57:
            d = _U(buf[i] - 48)
            digits += 1
            if nd < 19:
                if w != _U(0) or d != _U(0):
                    w = w * _U(10) + d
                    nd += 1
            else:
                adj += 1
                exact = exact and d == _U(0)
            i += 1
        if i < end and buf[i] == 46:
            i += 1
            while i < end and buf[i] >= 48 and buf[i] <= 57:
                d = _U(buf[i] - 48)
                digits += 1
                if nd < 19:
                    if w != _U(0) or d != _U(0):
                        w = w * _U(10) + d
                        nd += 1
                    adj -= 1
                else:
                    exact = exact and d == _U(0)
                i += 1
        e = 0
        ok = digits > 0
        if ok and i < end and (buf[i] == 101 or buf[i] == 69 or buf[i] == 100 or buf[i] == 68):
            i += 1
            eneg = False
            if i < end and (buf[i] == 45 or buf[i] == 43):
                eneg = buf[i] == 45
                i += 1
            ed = 0
            while i < end and buf[i] >= 48 and buf[i] <= 57:
                if e < 100000:
                    e = e * 10 + (buf[i] - 48)
                ed += 1
                i += 1
            ok = ed > 0
            if eneg:
                e = -e
        done = False
        if ok and i == end and exact:
            q = adj + e
            if w == _U(0):
                out[k] = -0.0 if neg else 0.0
                done = True
            elif w <= (_U(1) << _U(53)) and -22 <= q <= 22:
                v = np.float64(w)
                v = v * exact10[q] if q >= 0 else v / exact10[-q]
                out[k] = -v if neg else v
                done = True
            else:
                b = _eisel_lemire(w, q, p5hi, p5lo)
                if b >= 0:
                    ub = _U(b)
                    if neg:
                        ub |= _U(1) << _U(63)
                    bits[k] = ub
                    done = True
        elif ok and i == end:
            # more than 19 significant digits: the value lies in [w, w + 1) * 10**q, so
            # when both ends round to the same float64, so does the value
            q = adj + e
            b = _eisel_lemire(w, q, p5hi, p5lo)
            if b >= 0 and b == _eisel_lemire(w + _U(1), q, p5hi, p5lo):
                ub = _U(b)
                if neg:
                    ub |= _U(1) << _U(63)
                bits[k] = ub
                done = True
        if not done:
            out[k] = np.nan
            if nfb < fallback.shape[1]:
                fallback[0, nfb] = k
                fallback[1, nfb] = start
                fallback[2, nfb] = end
            nfb += 1
        k += 1
        i = end
    return k, nfb


_D_TO_E = bytes.maketrans(b"dD", b"eE")


def _ascii_block_hint(data: bytes, index: int) -> str:
    """Best effort: which block token number ``index`` falls in, from the header (error path only)."""
    toks = _TOKEN.findall(data)
    head = []
    for t in toks[:index]:
        try:
            head.append(float(t.translate(_D_TO_E)))
        except ValueError:
            return ""
    vals = np.array(head, dtype=np.float64)
    for mb in _CHOICES["multiblock"]:
        for nd in _CHOICES["ndim"]:
            for ib in _CHOICES["iblank"]:
                layout = _ascii_layout(vals, mb, nd, ib, len(toks))
                if layout is None:
                    continue
                hend, blocks = layout
                if index < hend:
                    return ", in the header"
                for n, (start, dims, npts) in enumerate(blocks):
                    if start <= index < start + npts * (nd + ib):
                        return f", in block {n + 1} of {len(blocks)}"
    return ""


def _ascii_layout(vals: np.ndarray, mb: bool, nd: int, ib: bool, total: int):
    """Header of a text file read as (multiblock, ndim, iblank): None if the counts do not add up.

    Returns ``(header_end, [(first value index, dims, npoints), ...])``.
    """
    if mb:
        if len(vals) < 1 or not 1 <= vals[0] <= total or vals[0] != int(vals[0]):
            return None
        nb, h = int(vals[0]), 1
    else:
        nb, h = 1, 0
    if len(vals) < h + nb * nd or h + nb * nd > total:
        return None
    d = vals[h:h + nb * nd]
    if np.any(d != np.round(d)) or np.any(d < 1) or np.any(d >= 2 ** 31):
        return None
    d = d.astype(np.int64).reshape(nb, nd)
    pos = h + nb * nd
    blocks = []
    for row in d:
        dims = (int(row[0]), int(row[1]), int(row[2]) if nd == 3 else 1)
        npts = dims[0] * dims[1] * dims[2]
        blocks.append((pos, dims, npts))
        pos += npts * (nd + ib)
        if pos > total:
            return None
    return (h + nb * nd, blocks) if pos == total else None


def _ascii_iblank_error(data, vals, fmt, layout) -> str | None:
    """Why the IBLANK values of a text file read as ``fmt`` are not integers, or None."""
    for n, (start, dims, npts) in enumerate(layout):
        s = start + fmt.ndim * npts
        raw = vals[s:s + npts]
        with np.errstate(invalid="ignore"):
            badi = ~np.isfinite(raw) | (raw != np.round(raw)) | (np.abs(raw) >= 2 ** 31)
        if badi.any():
            line, col, tok = _token_position(data, s + int(np.argmax(badi)))
            return (f"block {n + 1} of {len(layout)}: line {line}, column {col}: IBLANK value {tok} "
                    "is not a 32-bit integer")
    return None


def _ascii_candidates(vals, fixed):
    out = []
    for mb in _CHOICES["multiblock"]:
        for nd in _CHOICES["ndim"]:
            for ib in _CHOICES["iblank"]:
                f = Plot3DFormat(encoding="ascii", multiblock=mb, ndim=nd, iblank=ib,
                                 precision=fixed.get("precision", 8))
                if _compatible(f, fixed, ("multiblock", "ndim", "iblank")):
                    out.append(f)
    return out


def _last_line(data: bytes) -> int:
    """Line number (1-based) of the last line with text."""
    return data.rstrip().count(b"\n") + 1


def _is_count(v) -> bool:
    """Whether a header value read as a float is a block count or dimension: 1 <= v < 2**31, whole."""
    return bool(math.isfinite(v) and 1 <= v < 2 ** 31 and v == math.floor(v))


def _ascii_header_error(data, vals, fmt) -> str:
    """Explain why the text does not fit ``fmt`` (error path only)."""
    total = len(vals)
    h = 1 if fmt.multiblock else 0
    if fmt.multiblock:
        if total < 1 or not _is_count(vals[0]):
            pos = _token_position(data, 0)
            return (f"line {pos[0] if pos else 1}: block count {vals[0] if total else None} "
                    "must be an integer >= 1")
        nb = int(vals[0])
        if h + nb * fmt.ndim > total:
            return (f"the header claims {nb} blocks ({h + nb * fmt.ndim} header values), "
                    f"the file holds {total} values, up to line {_last_line(data)}")
    else:
        nb = 1
    if h + nb * fmt.ndim > total:
        return (f"the file holds only {total} values, up to line {_last_line(data)}, fewer than "
                "the header needs")
    for n in range(nb * fmt.ndim):
        v = vals[h + n]
        if not _is_count(v):
            line, col, tok = _token_position(data, h + n)
            return (f"line {line}: block {n // fmt.ndim + 1} dimension {'ijk'[n % fmt.ndim]} = {tok} "
                    "must be an integer >= 1")
    pos = h + nb * fmt.ndim
    for b in range(nb):
        d = vals[h + b * fmt.ndim:h + (b + 1) * fmt.ndim].astype(np.int64)
        npts = int(np.prod(d))
        end = pos + npts * (fmt.ndim + fmt.iblank)
        if end > total:
            last = _token_position(data, total - 1)
            return (f"the file is truncated: block {b + 1} of {nb} ({'x'.join(map(str, d))}) needs "
                    f"values {pos + 1}..{end}, the file ends after value {total}"
                    + (f" (line {last[0]})" if last else ""))
        pos = end
    line = _token_position(data, pos)
    return (f"{total - pos} unexpected values after the last block"
            + (f", from line {line[0]}" if line else ""))


_INTEGER_TOKEN = re.compile(rb"[-+]?[0-9]+")


def _ascii_header_shape_error(data: bytes, header_end: int) -> str | None:
    """Why the first ``header_end`` tokens are no header line(s), or None.

    Writers put the block count and the dimensions as integers on lines of
    their own, then start the coordinates on a new line; a variant that
    would read a coordinate as a dimension, or whose header stops in the
    middle of a line, is not the file's (a truncated multi-block file read
    as one block).  Reads the header tokens only.
    """
    tokens = _TOKEN.finditer(data)
    m = None
    for n in range(header_end):
        m = next(tokens)
        if not _INTEGER_TOKEN.fullmatch(m.group()):
            line = data.count(b"\n", 0, m.start()) + 1
            return (f"line {line}: header value number {n + 1} "
                    f"{m.group()[:40].decode('ascii', 'replace')!r} is not an integer")
    after = next(tokens, None)
    if m is not None and after is not None and b"\n" not in data[m.end():after.start()]:
        line = data.count(b"\n", 0, m.start()) + 1
        return (f"line {line}: the header ends after {header_end} value(s) in the middle of the "
                "line; the coordinates would start on the same line")
    return None


def _detect_ascii(path, data: bytes, fixed):
    """All numbers of a text file and the variants that fit them, preferred first.

    Returns ``(values, [(key, fmt, (header_end, layout)), ...])``.
    """
    vals = _parse_text(data, path)
    if vals.size == 0:
        raise GridFormatError(f"{path}: no numbers in the file")
    cands = _ascii_candidates(vals, fixed)
    fits, misses = [], []
    for f in cands:
        lay = _ascii_layout(vals, f.multiblock, f.ndim, f.iblank, len(vals))
        if lay is None:
            misses.append((1, f._key(), 0.0, f._key(), None, f))
            continue
        bad = _ascii_iblank_error(data, vals, f, lay[1]) if f.iblank else None
        if bad is None and len(cands) > 1:
            bad = _ascii_header_shape_error(data, lay[0])
        if bad is not None:
            misses.append((0, f._key(), 0.0, f._key(), bad, f))
            continue
        fits.append((f._key(), f, lay))
    if not fits:
        misses = [m if m[4] is not None else m[:4] + (_ascii_header_error(data, vals, m[5]), m[5])
                  for m in misses]
        raise _no_fit(path, len(data), cands, misses, f" ({len(vals)} values of text)")
    fits.sort(key=lambda t: t[0])
    return vals, fits


def _read_ascii(path, data: bytes, vals: np.ndarray, fmt, layout, allow_nonfinite) -> list[Block]:
    """The blocks of a text file whose numbers ``vals`` fit ``fmt`` with this layout."""
    if fmt.precision == 4:
        # out-of-range values become inf: reported below (as NaN payloads are)
        with np.errstate(over="ignore", invalid="ignore"):
            vals = vals.astype(np.float32).astype(np.float64)
    nd = fmt.ndim
    blocks = []
    for n, (start, dims, npts) in enumerate(layout):
        xyz = np.zeros(dims + (3,), dtype=np.float64, order="F")
        flat = xyz.reshape(-1, order="F")
        flat[:nd * npts] = vals[start:start + nd * npts]
        where = f"{path}: block {n + 1} of {len(layout)}"
        idx = None if allow_nonfinite else _first_nonfinite(flat)
        if idx is not None:
            line, col, tok = _token_position(data, start + idx)
            c, rem = divmod(idx, npts)
            i, j, k = rem % dims[0], (rem // dims[0]) % dims[1], rem // (dims[0] * dims[1])
            raise GridFormatError(f"{where}: line {line}, column {col}: non-finite coordinate "
                                  f"{'xyz'[c]} = {tok} at (i, j, k) = ({i + 1}, {j + 1}, {k + 1}) "
                                  "(1-based) (pass allow_nonfinite=True to accept)")
        ib = None
        if fmt.iblank:
            raw = vals[start + nd * npts:start + (nd + 1) * npts]
            ib = raw.astype(np.int32).reshape(dims, order="F")
        blocks.append(Block(xyz, ib, name=f"block{n + 1}", allow_nonfinite=True))
    return blocks


# ---------------------------------------------------------------- public read

def _fixed_fields(format, overrides) -> dict:
    """The fields the caller fixed: all of ``format`` (with overrides applied), or the overrides."""
    _check_names(overrides, "Plot3D read")
    if format is not None:
        if not isinstance(format, Plot3DFormat):
            raise GridFormatError(f"format must be a Plot3DFormat, got {type(format).__name__}")
        fmt = format.replace(**overrides)
        return {f: getattr(fmt, f) for f in _FIELD_NAMES}
    # validate the override values through the dataclass
    probe = Plot3DFormat().replace(**overrides)
    return {k: getattr(probe, k) for k in overrides}


def _mostly_text(fd, size) -> bool:
    """Nine in ten of the first 4 KiB are printable ASCII: text with a few stray bytes."""
    head = _pread(fd, min(size, 4096), 0)
    return len(head.translate(None, _TEXT_BYTES)) <= 0.1 * len(head)


def _open_and_dispatch(path, format, overrides, allow_nonfinite, mode: str = "read",
                       max_points=None, blocks=None):
    """Detect (and read) a file.

    ``mode``: ``"read"`` returns ``(fmt, blocks)`` (with ``blocks``, 0-based
    numbers: ``(fmt, (those blocks, their numbers))``), ``"faces"`` ``(fmt,
    GridFaces)``, ``"detect"`` ``(fmt, None)``,
    ``"all"`` ``([every variant that fits, preferred first], None)``.  A
    missing file, a folder or a file without read permission raise
    ``open``'s own FileNotFoundError, IsADirectoryError, PermissionError.
    """
    path = Path(os.fspath(path))
    fixed = _fixed_fields(format, overrides)
    with open(path, "rb", buffering=0) as fh:
        fd = fh.fileno()
        size = os.fstat(fd).st_size
        if size == 0:
            raise GridFormatError(f"{path}: the file is empty (0 bytes)")
        enc = fixed.get("encoding")
        text = enc == "ascii" or (enc is None and _looks_like_text(fd, size))
        if not text:
            try:
                fits = _detect_binary(fd, size, path, fixed, max_points)
            except GridFormatError as exc:
                if enc is not None or not _mostly_text(fd, size):
                    raise
                # a text file with a few bytes that are not printable ASCII (a non-ASCII
                # comment, a DOS end-of-file mark): the text reader names their line
                try:
                    return _dispatch_ascii(path, fh, size, fixed, allow_nonfinite, mode, max_points)
                except GridFormatError as texc:
                    raise GridFormatError(f"{texc} (the file is mostly text, but not all of it is "
                                          "printable ASCII; as binary no variant fits either)") from exc
            if mode == "all":
                return [f[1].canonical() for f in fits], None
            fmt, dims, layout = fits[0][1:]
            if mode == "detect":
                return fmt.canonical(), None
            if mode == "faces":
                ids = None if blocks is None else block_numbers(path, blocks, len(layout))
                return fmt.canonical(), _read_faces(fd, path, fmt.canonical(), layout, allow_nonfinite, ids)
            if blocks is not None:
                ids = block_numbers(path, blocks, len(layout))
                part = [layout[n] for n in ids]
                _check_size(path, fmt, sum(b.npoints for b in part), max_points)
                return fmt.canonical(), (_read_blocks(fd, path, fmt, part, allow_nonfinite, ids, len(layout)),
                                         ids)
            _check_size(path, fmt, sum(b.npoints for b in layout), max_points)
            return fmt.canonical(), _read_blocks(fd, path, fmt, layout, allow_nonfinite)
        # text: every number is parsed, then the blocks (faces) asked for are kept
        fmt, all_blocks = _dispatch_ascii(path, fh, size, fixed, allow_nonfinite,
                                          "read" if mode == "faces" else mode, max_points)
        if mode == "faces":
            ids = None if blocks is None else block_numbers(path, blocks, len(all_blocks))
            return fmt, GridFaces(fmt.ndim, [b.dims for b in all_blocks],
                                  [tuple(np.asfortranarray(b.face(f)) for f in faces_of(fmt.ndim))
                                   if ids is None or n in ids else None for n, b in enumerate(all_blocks)],
                                  [b.name for b in all_blocks], os.fspath(path), fmt,
                                  block_ids=None if ids is None else tuple(ids))
        if blocks is not None and mode == "read":
            ids = block_numbers(path, blocks, len(all_blocks))
            return fmt, ([all_blocks[n] for n in ids], ids)
        return fmt, all_blocks


def _check_size(path, fmt, npoints: int, max_points) -> None:
    """Refuse, before allocating, a grid of ``npoints`` points too large to hold."""
    check_points(str(path), npoints, max_points=max_points,
                 bytes_per_point=BYTES_PER_POINT if fmt.iblank else BYTES_PER_POINT - 4)


def _dispatch_ascii(path, fh, size, fixed, allow_nonfinite, mode, max_points=None):
    # the text and its numbers (8 bytes each, at most one per 2 bytes of text) are held at once
    have = available_memory()
    if 5 * size > have:
        raise GridFormatError(f"{path}: a text file of {size:,} bytes needs up to {5 * size:,} bytes "
                              f"of memory to read, more than the {have:,} bytes available")
    fh.seek(0)
    data = fh.read()
    vals, fits = _detect_ascii(path, data, fixed)
    if mode == "all":
        return [f[1].canonical() for f in fits], None
    _, fmt, (_, layout) = fits[0]
    if mode == "detect":
        return fmt.canonical(), None
    _check_size(path, fmt, sum(npts for _, _, npts in layout), max_points)
    return fmt.canonical(), _read_ascii(path, data, vals, fmt, layout, allow_nonfinite)


def detect(path, **overrides) -> Plot3DFormat:
    """Detect the Plot3D variant of a file.

    Parameters
    ----------
    path : str or path-like
    **overrides
        :class:`Plot3DFormat` fields to take as given (e.g. ``endian=">"``);
        the others are detected.

    Returns
    -------
    Plot3DFormat
        The variant (fields its encoding ignores at their defaults).  When
        several variants fit the file, the preferred one (see the module
        docstring).

    Raises
    ------
    GridFormatError
        Empty file, or no variant fits: the message lists what was tried and
        the closest misses with block and byte offset.
    """
    return _open_and_dispatch(path, None, overrides, True, "detect")[0]


def detect_all(path, **overrides) -> list[Plot3DFormat]:
    """Every Plot3D variant the file fits, the one :func:`detect` picks first.

    A file fits several variants when its sizes cannot tell them apart:
    always for 2-D files with 8-byte integers (float64 without IBLANK and
    float32 with 8-byte IBLANK both take 16 bytes a point), and for some tiny
    grids.  ``tfi-quat info`` lists the others, so the choice is never silent.

    Parameters
    ----------
    path : str or path-like
    **overrides
        :class:`Plot3DFormat` fields to take as given.

    Returns
    -------
    list of Plot3DFormat
        At least one; in preference order (see the module docstring).

    Raises
    ------
    GridFormatError
        As :func:`detect`.
    """
    return _open_and_dispatch(path, None, overrides, True, "all")[0]


def read(path, *, format: Plot3DFormat | None = None, allow_nonfinite: bool = False,
         max_points: int | None = None, blocks=None, **overrides) -> Grid:
    """Read a Plot3D grid file of any supported variant.

    Parameters
    ----------
    path : str or path-like
    format : Plot3DFormat, optional
        Read as exactly this variant (no detection; the file must fit it).
    blocks : list of int, optional
        Read only these blocks (0-based numbers in the file), in this order;
        the grid's ``block_ids`` records them.  A binary file is read at the
        offsets its header gives, those blocks' bytes only; a text file is
        parsed whole and the blocks kept.
    allow_nonfinite : bool
        Accept NaN and infinite coordinates (default: error naming the block).
    max_points : int, optional
        Refuse a file declaring more points than this (default: as many as
        fit in the memory available now), before allocating anything.
    **overrides
        :class:`Plot3DFormat` fields to take as given; the rest is detected
        (with ``format``: fields replaced in it).

    Returns
    -------
    Grid
        ``ndim`` from the variant; each block's ``xyz`` float64
        ``(ni, nj, nk, 3)`` Fortran order (z = 0 and nk = 1 for 2-D files),
        ``iblank`` int32 ``(ni, nj, nk)`` when the file has one;
        ``source_format`` the variant, ``source_path`` the path.

    Raises
    ------
    GridFormatError
        Empty, truncated or over-long file, bad dimensions, inconsistent
        Fortran record markers, a non-numeric token (with its line),
        non-finite coordinates, or no variant fits; the message names the
        file, block and byte offset or line.  A grid of more points than
        ``max_points`` (or than fit in the memory available), with its size.
    FileNotFoundError, IsADirectoryError, PermissionError
        The path is missing, a folder, or not readable.
    """
    fmt, got = _open_and_dispatch(path, format, overrides, allow_nonfinite, "read", max_points, blocks)
    if blocks is None:
        return Grid(got, fmt.ndim, source_format=fmt, source_path=path)
    grid = Grid(got[0], fmt.ndim, source_format=fmt, source_path=path)
    grid.block_ids = tuple(got[1])
    return grid


def read_faces(path, *, format: Plot3DFormat | None = None, allow_nonfinite: bool = False,
               blocks=None, **overrides) -> GridFaces:
    """Read the faces of every block of a Plot3D file, and the blocks' dims.

    Parameters
    ----------
    path : str or path-like
    format : Plot3DFormat, optional
        Read as exactly this variant (no detection).
    allow_nonfinite : bool
        Accept NaN and infinite coordinates on the faces.
    blocks : list of int, optional
        Read the faces of these blocks only (0-based); the dims of all.
    **overrides
        :class:`Plot3DFormat` fields to take as given.

    Returns
    -------
    GridFaces
        A binary file is read through a memory map, face values only (see
        :mod:`tfi_quat.io.partial`); a text file is parsed whole.

    Raises
    ------
    GridFormatError
        As :func:`read`; a non-finite face coordinate names block and face.
    """
    return _open_and_dispatch(path, format, overrides, allow_nonfinite, "faces", blocks=blocks)[1]


# ---------------------------------------------------------------- write

def write_format(grid: Grid, like=None, **options) -> Plot3DFormat:
    """The variant :func:`write` writes ``grid`` in (``like`` and ``options`` as there)."""
    _check_names(options, "Plot3D write")
    if like is None:
        base = grid.source_format if isinstance(grid.source_format, Plot3DFormat) else Plot3DFormat()
    elif isinstance(like, Plot3DFormat):
        base = like
    elif isinstance(getattr(like, "source_format", None), Plot3DFormat):
        base = like.source_format
    else:
        raise GridFormatError(f"like= must be a Plot3DFormat or a grid read from a Plot3D file, "
                              f"got {type(like).__name__}")
    opts = dict(options)
    opts.setdefault("ndim", grid.ndim)
    opts.setdefault("iblank", grid.has_iblank)
    return base.replace(**opts)


def write(path, grid: Grid, *, like: Plot3DFormat | None = None, overwrite: bool = False,
          **options) -> None:
    """Write a grid as a Plot3D file, atomically.

    Parameters
    ----------
    path : str or path-like
        Target file; written to a temporary file in its folder and renamed
        into place.
    grid : Grid
    like : Plot3DFormat or Grid, optional
        Variant to write (default: ``grid.source_format`` when it is a
        Plot3D variant, else C binary little-endian float64 multi-block).
    overwrite : bool
        Allow writing over ``grid.source_path``.
    **options
        :class:`Plot3DFormat` fields overriding ``like`` (``encoding``,
        ``endian``, ``precision``, ``ndim``, ``multiblock``, ``iblank``,
        ``records``, ``int_size``, ``marker_size``).  ``ndim`` defaults to
        ``grid.ndim``, ``iblank`` to ``grid.has_iblank`` (blocks without
        IBLANK are written as all 1).

    Raises
    ------
    GridFormatError
        Unknown option, several blocks in a single-block variant, a 3-D grid
        written as 2-D (unless nk == 1 and z == 0 everywhere), a Fortran
        record too long for its markers.
    OverwriteError
        ``path`` is the grid's own input file and ``overwrite`` is False.
    """
    if not isinstance(grid, Grid):
        raise GridValueError(f"write needs a Grid, got {type(grid).__name__}")
    fmt = write_format(grid, like, **options)
    dims = [b.dims for b in grid]
    check_write(path, fmt, dims, grid.blocks, range(len(grid)))
    target = check_target(path, overwrite=overwrite, protect=[grid.source_path])
    if fmt.encoding == "ascii":
        with atomic_output(target, "w") as fh:
            _write_ascii(fh, grid, fmt, path)
    else:
        with atomic_output(target, "wb") as fh:
            write_header(fh, fmt, dims)
            for n, b in enumerate(grid):
                write_block(fh, b, fmt, f"{path}: block {n + 1} of {len(grid)}")


def check_write(path, fmt: Plot3DFormat, dims, blocks, numbers) -> None:
    """Check that a grid of blocks with ``dims`` can be written as ``fmt``.

    ``dims`` lists the ``(ni, nj, nk)`` of every block of the file; ``blocks``
    the blocks whose coordinates are at hand (all of them in a serial write,
    a rank's own under MPI), ``numbers`` their 0-based block numbers.

    Raises
    ------
    GridFormatError
        Several blocks in a single-block variant, a 3-D block written as 2-D,
        a Fortran record too long for its markers.
    """
    if not fmt.multiblock and len(dims) > 1:
        raise GridFormatError(f"{path}: a single-block Plot3D variant cannot hold {len(dims)} blocks "
                              "(write with multiblock=True)")
    if fmt.ndim == 2:
        for n, b in zip(numbers, blocks):
            if b.dims[2] != 1 or has_z(b.xyz):
                raise GridFormatError(f"{path}: block {n + 1} is 3-D (nk = {b.dims[2]}, or z != 0); "
                                      "it cannot be written as a 2-D Plot3D file")
    if fmt.encoding == "fortran":
        limit = (1 << (8 * fmt.marker_size - 1)) - 1
        _, layouts, _, _ = _layout(fmt, dims)
        for n, lay in enumerate(layouts):
            longest = max(length for _, length in lay.markers)
            if longest > limit:
                raise GridFormatError(f"{path}: block {n + 1} needs a Fortran record of {longest} "
                                      f"bytes, more than {fmt.marker_size}-byte markers can frame; "
                                      "write with marker_size=8 or records='coordinate'")


def block_offsets(fmt: Plot3DFormat, dims) -> tuple[list[int], int]:
    """Where each block starts in a binary or Fortran file of ``fmt``, and the file size.

    ``dims`` lists every block's ``(ni, nj, nk)``.  The first block starts
    where the header (:func:`write_header`) ends; :func:`write_block` writes
    a block's bytes from its offset on.
    """
    if fmt.encoding == "ascii":
        raise GridFormatError("an ASCII Plot3D file has no fixed block offsets")
    _, layouts, size, _ = _layout(fmt, [tuple(d) for d in dims])
    return [lay.start for lay in layouts], size


def write_header(fh, fmt: Plot3DFormat, dims) -> None:
    """Write the header of a binary or Fortran file: block count (multi-block) and dims."""
    nd = fmt.ndim
    ms = fmt.marker_size if fmt.encoding == "fortran" else 0
    mdt = np.dtype(f"{fmt.endian}i{ms}") if ms else None
    idt = _int_dtype(fmt)

    def marker(length):
        if ms:
            fh.write(np.array([length], dtype=mdt).tobytes())

    if fmt.multiblock:
        marker(fmt.int_size)
        fh.write(np.array([len(dims)], dtype=idt).tobytes())
        marker(fmt.int_size)
    header = np.array([tuple(d)[:nd] for d in dims], dtype=idt).reshape(-1)
    marker(header.nbytes)
    fh.write(header.tobytes())
    marker(header.nbytes)


def write_block(fh, b: Block, fmt: Plot3DFormat, where: str) -> None:
    """Write one block's records (binary or Fortran) at the file's current position.

    ``where`` names the block in errors (a coordinate beyond float32).
    """
    nd = fmt.ndim
    ms = fmt.marker_size if fmt.encoding == "fortran" else 0
    mdt = np.dtype(f"{fmt.endian}i{ms}") if ms else None
    idt, fdt = _int_dtype(fmt), _float_dtype(fmt)

    def marker(length):
        if ms:
            fh.write(np.array([length], dtype=mdt).tobytes())

    n = b.npoints
    flat = b.xyz.reshape(-1, order="F")
    ib = None
    if fmt.iblank:
        # blocks without IBLANK are written as all 1 (only built when written)
        ib = b.iblank.reshape(-1, order="F") if b.iblank is not None else np.ones(n, dtype=np.int32)
    if fmt.encoding == "fortran" and fmt.records == "coordinate":
        for c in range(nd):
            marker(n * fmt.precision)
            _write_array(fh, flat[c * n:(c + 1) * n], fdt, where)
            marker(n * fmt.precision)
        if fmt.iblank:
            marker(n * fmt.int_size)
            _write_array(fh, ib, idt)
            marker(n * fmt.int_size)
    else:
        length = n * (nd * fmt.precision + (fmt.int_size if fmt.iblank else 0))
        marker(length)
        _write_array(fh, flat[:nd * n], fdt, where)
        if fmt.iblank:
            _write_array(fh, ib, idt)
        marker(length)


def _write_array(fh, arr: np.ndarray, dtype: np.dtype, where: str = "") -> None:
    """Write a contiguous 1-D array as ``dtype``, converting chunk by chunk when needed."""
    if arr.dtype == dtype:
        arr.tofile(fh)      # the buffer itself, as numpy writes it
        return
    for s in range(0, arr.shape[0], _CHUNK):
        fh.write(memoryview(_convert(arr[s:s + _CHUNK], dtype, where)).cast("B"))


def _convert(chunk: np.ndarray, dtype: np.dtype, where: str) -> np.ndarray:
    """``chunk`` as ``dtype``; float values beyond the float32 range are an error, not inf."""
    with np.errstate(over="ignore", invalid="ignore"):   # signalling NaNs stay NaN
        out = chunk.astype(dtype)
    if dtype.kind == "f" and dtype.itemsize == 4:
        lost = np.isinf(out) & np.isfinite(chunk)
        if lost.any():
            v = chunk[int(np.argmax(lost))]
            raise GridFormatError(f"{where}: coordinate {float(v)!r} is beyond the float32 range; "
                                  "write with precision=8")
    return out


_PER_LINE = 4
_ASCII_CHUNK = 1 << 16   # values formatted per string operation (a multiple of _PER_LINE)


def _write_values_text(fh, vals: np.ndarray, spec: str) -> None:
    line = " ".join([spec] * _PER_LINE) + "\n"
    for s in range(0, vals.shape[0], _ASCII_CHUNK):
        chunk = vals[s:s + _ASCII_CHUNK].tolist()
        full = len(chunk) // _PER_LINE * _PER_LINE
        text = (line * (full // _PER_LINE)) % tuple(chunk[:full])
        if full < len(chunk):
            rest = chunk[full:]
            text += " ".join([spec] * len(rest)) % tuple(rest) + "\n"
        fh.write(text)


def _write_ascii(fh, grid: Grid, fmt: Plot3DFormat, path="Plot3D file") -> None:
    nd = fmt.ndim
    if fmt.multiblock:
        fh.write(f"{len(grid)}\n")
    for b in grid:
        fh.write(" ".join(str(d) for d in b.dims[:nd]) + "\n")
    for bn, b in enumerate(grid):
        n = b.npoints
        flat = b.xyz.reshape(-1, order="F")
        for c in range(nd):
            vals = flat[c * n:(c + 1) * n]
            if fmt.precision == 4:
                single = _convert(vals, np.dtype(np.float32), f"{path}: block {bn + 1} of {len(grid)}")
                with np.errstate(invalid="ignore"):
                    _write_values_text(fh, single.astype(np.float64), "%.9g")
            else:
                _write_values_text(fh, vals, "%.17g")
        if fmt.iblank:
            ib = b.iblank.reshape(-1, order="F") if b.iblank is not None else np.ones(n, np.int32)
            _write_values_text(fh, ib, "%d")


register("plot3d", (".x", ".xyz", ".g", ".grd", ".p3d", ".p2dfmt", ".p3dfmt", ".fmt", ".bin", ".xyzb"),
         read, write, Plot3DFormat, read_faces)
