"""Mutation fuzzing of the readers and the command line.

Shared by ``tests/test_fuzz.py`` (a few hundred mutants per format, deterministic)
and ``benchmarks/fuzz_campaign.py`` (the long campaign).  No project-private names
are used: seeds are written with the public ``tfi_quat.write`` and
``tfi_quat.cli.main``, mutants are read with the public readers.

How it works
------------
1. :func:`make_seeds` writes tiny seed files (a few hundred points each) in every
   format: Plot3D in twelve binary variants and three ASCII ones, HDF5 plain,
   gzip and 2-D, a connectivity JSON and an NMF (from ``tfi-quat connect``) and a
   case TOML.  Each :data:`TARGETS` entry pairs a seed with a check (a reader,
   or a CLI command run in-process).
2. :func:`mutate` damages a seed deterministically (``random.Random`` seeded with
   the campaign seed, target name and mutant number): bit flips, overwrites with
   interesting values (0, 0xff, 0x7f, int32/int64 extremes, NaN/inf patterns),
   truncation, extension, chunk duplication and deletion; for text formats also
   token-level changes (numbers to huge/negative/fractional/boolean/string
   values, deleted and duplicated lines, non-UTF-8 bytes).  Each mutant records
   whether it left the seed's *header* intact (for Plot3D: the bytes or tokens up
   to the end of the block dimensions).
3. :func:`run_mutants` reads the mutants in worker processes (fresh interpreters,
   ``jobs`` of them, each warmed up once so a mutant costs a read, not a
   Python start-up) under an address-space limit (``RLIMIT_AS``, default 4 GiB)
   and a per-mutant wall-clock timeout (default 10 s); a worker that dies or
   does not answer in time is replaced.  Each mutant gets one outcome:

   ``ok``       the read succeeded and the result is plausible;
   ``error``    a ``TfiQuatError``, or ``FileNotFoundError`` /
                ``IsADirectoryError`` / ``NotADirectoryError`` / ``PermissionError``;
                for the CLI: one line on stderr, no traceback, exit status 2
                (bad input) or 1 (the result failed a check: a folded grid);
   ``foreign``  any other exception (including a bare ``OSError``), or a CLI
                traceback / any other exit status: a bug;
   ``crash``    the worker died (a signal, or an exit without an answer);
   ``hang``     no answer within the timeout (the worker is killed);
   ``overmem``  ``MemoryError`` (the address-space limit was hit);
   ``wrong``    the read succeeded but the result is silently wrong (below).

What counts as ``wrong``
------------------------
Coordinate values may change legitimately (a flipped byte in a float is a
different but valid grid), so ``wrong`` is reserved for what a reader must
notice:

* every grid (Plot3D, HDF5): the :class:`~tfi_quat.Grid` breaks an invariant:
  non-finite coordinates (read without ``allow_nonfinite``), a 2-D grid with
  ``nk != 1`` or non-zero z, coordinates that are not float64 ``(ni, nj, nk, 3)``,
  an IBLANK array of another shape or type;
* Plot3D: the mutant left the seed's header intact (block count and dimensions
  bytes or tokens unchanged, wherever the damage lies after them, including
  truncation and extension), yet the reader returned another block count or
  other block dimensions than the seed (the header was re-interpreted: a
  truncated multi-block file read as a single-block grid, for instance).  A
  changed precision, IBLANK presence or record layout with the *same* block
  dimensions is accepted: the damaged file is then a valid file of that variant;
* HDF5: another block count or other block dimensions than the seed (the file
  describes its blocks twice, in attributes and in dataset shapes, so one
  localised mutation cannot change them consistently);
* connectivity JSON / NMF (read against the seed grid): the map has other block
  dimensions than the grid, or ``Connectivity.check(grid)`` rejects what the
  reader accepted;
* case TOML (loaded, then checked against its grid): the rigid part of the
  motion disagrees with an independent rotation (overflow-safe normalisation)
  by more than a relative 1e-9: a rotation silently dropped or distorted;
* CLI: only tracebacks, crashes, hangs and memory (the readers above judge the
  data).
"""

from __future__ import annotations

import io
import json
import math
import os
import random
import re
import resource
import select
import shutil
import signal
import struct
import subprocess
import sys
import time
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass
from pathlib import Path

import numpy as np

OUTCOMES = ("ok", "error", "foreign", "crash", "hang", "overmem", "wrong")
#: outcomes that are bugs
FAILURES = ("foreign", "crash", "hang", "overmem", "wrong")
MEM_LIMIT = 4 << 30
#: the seed of the CGNS targets: a file written by the CGNS library (tests/data/cgns/README.md)
CGNS_SEED = Path(__file__).resolve().parent / "data" / "cgns" / "multiblock.cgns"
TIMEOUT = 10.0


# ----------------------------------------------------------------------------- seeds

@dataclass(frozen=True)
class Seed:
    """One seed file: its bytes, kind and where its header ends."""

    name: str
    path: Path
    suffix: str
    text: bool
    #: bytes from the start that hold the header (Plot3D: block count and dims); 0: not used
    header_end: int = 0


def _seed_grids():
    """The grids the seeds hold: a 2-D two-block channel and its 3-D extrusion (3 planes)."""
    from tfi_quat import Block, Grid
    from tfi_quat.generate import two_block
    g2 = two_block(ni=9, nj=7)                       # blocks 9x4 and 4x9
    blocks = []
    for b in g2:
        xy = b.xyz[:, :, 0, :]
        xyz = np.repeat(xy[:, :, None, :], 3, axis=2).copy(order="F")
        xyz[:, :, :, 2] = np.array([0.0, 0.1, 0.25])[None, None, :]
        blocks.append(Block(xyz, name=b.name))
    g3 = Grid(blocks, ndim=3)
    return g2, g3


def _with_iblank(grid):
    from tfi_quat import Block, Grid
    blocks = []
    for n, b in enumerate(grid):
        ib = np.ones(b.dims, dtype=np.int32)
        ib.flat[::3] = -(n + 1)        # overset-style negative values, legal IBLANK
        ib.flat[1::5] = 0
        blocks.append(Block(b.xyz, iblank=ib, name=b.name))
    return Grid(blocks, ndim=grid.ndim)


#: Plot3D seeds: name -> (grid kind, write options)
PLOT3D_VARIANTS = {
    "p3d-bin-le-f8": ("3d", dict(encoding="binary", endian="<", precision=8)),
    "p3d-bin-be-f4": ("3d", dict(encoding="binary", endian=">", precision=4)),
    "p3d-bin-single": ("3d1", dict(encoding="binary", multiblock=False)),
    "p3d-bin-2d": ("2d", dict(encoding="binary", ndim=2)),
    "p3d-bin-iblank": ("3di", dict(encoding="binary", iblank=True)),
    "p3d-bin-int8": ("3di", dict(encoding="binary", int_size=8, iblank=True)),
    "p3d-ftn-le-f8": ("3d", dict(encoding="fortran", endian="<")),
    "p3d-ftn-be-f4": ("3d", dict(encoding="fortran", endian=">", precision=4)),
    "p3d-ftn-coord": ("3d", dict(encoding="fortran", records="coordinate")),
    "p3d-ftn-mark8": ("3d", dict(encoding="fortran", marker_size=8)),
    "p3d-ftn-2d-single-iblank": ("2d1i", dict(encoding="fortran", ndim=2, multiblock=False, iblank=True)),
    "p3d-ftn-int8-iblank": ("3di", dict(encoding="fortran", int_size=8, iblank=True)),
    "p3d-ascii": ("3d", dict(encoding="ascii")),
    "p3d-ascii-2d-single": ("2d1", dict(encoding="ascii", ndim=2, multiblock=False)),
    "p3d-ascii-iblank": ("3di", dict(encoding="ascii", iblank=True)),
}


def _plot3d_header_end(opts: dict, nblocks: int) -> int:
    """Bytes of a binary/Fortran Plot3D header (block count and dimension records)."""
    isz = opts.get("int_size", 4)
    ms = opts.get("marker_size", 4) if opts.get("encoding") == "fortran" else 0
    nd = opts.get("ndim", 3)
    end = (isz + 2 * ms) if opts.get("multiblock", True) else 0
    return end + nblocks * nd * isz + 2 * ms


def _text_header_end(data: bytes, ntokens: int) -> int:
    """Byte offset just past the ``ntokens``-th whitespace-separated token."""
    tokens = list(re.finditer(rb"\S+", data))
    return tokens[ntokens - 1].end()


CASE_TEXT = """\
# tfi_quat case file (fuzz seed)
grid = "grid.x"
output = "moved.x"
walls = ["1:jmin"]
symmetry = []
fixed = ["1:imin", "1:imax", "2:imin", "2:jmin", "2:jmax"]

[motion]
rotate = 2.0
axis = [0.0, 0.0, 1.0]
about = [0.25, 0.0, 0.0]
translate = [0.0, 0.01, 0.0]
bend = 0.01
span_axis = [1.0, 0.0, 0.0]
direction = [0.0, 1.0, 0.0]
span = 1.5
"""


def make_seeds(folder) -> dict[str, Seed]:
    """Write every seed file into ``folder``; returns name -> :class:`Seed`.

    ``folder/grid.x`` (the 2-D two-block grid, C binary) is the grid the
    connectivity and case seeds refer to.
    """
    import tfi_quat as tq
    from tfi_quat.cli import main
    from tfi_quat import Grid
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    g2, g3 = _seed_grids()
    grids = {"2d": g2, "3d": g3, "3di": _with_iblank(g3), "3d1": Grid([g3[0]], ndim=3),
             "2d1": Grid([g2[0]], ndim=2), "2d1i": _with_iblank(Grid([g2[0]], ndim=2))}
    seeds = {}
    for name, (kind, opts) in PLOT3D_VARIANTS.items():
        path = folder / f"{name}.x"
        tq.write(path, grids[kind], format="plot3d", overwrite=True, **opts)
        nb = len(grids[kind])
        text = opts["encoding"] == "ascii"
        if text:
            nd = opts.get("ndim", 3)
            ntok = (1 if opts.get("multiblock", True) else 0) + nb * nd
            hend = _text_header_end(path.read_bytes(), ntok)
        else:
            hend = _plot3d_header_end(opts, nb)
        seeds[name] = Seed(name, path, ".x", text, hend)
    for name, grid, kw in (("h5-plain", g3, {}), ("h5-gzip", _with_iblank(g3), {"compression": "gzip"}),
                           ("h5-2d", g2, {})):
        path = folder / f"{name}.h5"
        tq.write(path, grid, overwrite=True, **kw)
        seeds[name] = Seed(name, path, ".h5", False)
    # the CGNS library's own multiblock file: BCs, families, 1-to-1 records, a second base
    path = folder / "cgns.cgns"
    shutil.copyfile(CGNS_SEED, path)
    seeds["cgns"] = Seed("cgns", path, ".cgns", False)
    grid_x = folder / "grid.x"
    tq.write(grid_x, g2, overwrite=True)
    for ext in ("json", "nmf"):
        path = folder / f"map.{ext}"
        with redirect_stdout(io.StringIO()):
            rc = main(["connect", str(grid_x), "--wall", "1:jmin", "-o", str(path), "--force"])
        if rc != 0:
            raise RuntimeError(f"tfi-quat connect failed writing the {ext} seed")
        seeds[ext] = Seed(ext, path, f".{ext}", True)
    path = folder / "case.toml"
    path.write_text(CASE_TEXT)
    seeds["case"] = Seed("case", path, ".toml", True)
    return seeds


# ----------------------------------------------------------------------------- targets

@dataclass(frozen=True)
class Target:
    """A fuzz target: which seed is mutated and how a mutant is checked."""

    name: str
    seed: str
    check: str          # "plot3d", "hdf5", "cgns", "json", "nmf", "case" or "cli"
    argv: tuple = ()    # CLI: arguments, "{mutant}", "{grid}", "{out}" are filled in


TARGETS: dict[str, Target] = {}
for _name in PLOT3D_VARIANTS:
    TARGETS[_name] = Target(_name, _name, "plot3d")
for _name in ("h5-plain", "h5-gzip", "h5-2d"):
    TARGETS[_name] = Target(_name, _name, "hdf5")
TARGETS["cgns"] = Target("cgns", "cgns", "cgns")
TARGETS["json"] = Target("json", "json", "json")
TARGETS["nmf"] = Target("nmf", "nmf", "nmf")
TARGETS["case"] = Target("case", "case", "case")
TARGETS["cli-info-p3d"] = Target("cli-info-p3d", "p3d-ftn-le-f8", "cli", ("info", "{mutant}"))
TARGETS["cli-info-h5"] = Target("cli-info-h5", "h5-gzip", "cli", ("info", "{mutant}"))
TARGETS["cli-info-cgns"] = Target("cli-info-cgns", "cgns", "cli", ("info", "{mutant}"))
TARGETS["cli-convert-ascii"] = Target("cli-convert-ascii", "p3d-ascii", "cli",
                                      ("convert", "{mutant}", "{out}.h5"))
TARGETS["cli-connect-p3d"] = Target("cli-connect-p3d", "p3d-bin-2d", "cli",
                                    ("connect", "{mutant}", "--wall", "1:jmin", "-o", "{out}.json"))
# the seed grid is tiny and coarse: some motions fold a cell, which is not what these targets test
# (parsing hostile maps and case files), so the deformed grid is written regardless
TARGETS["cli-deform-json"] = Target("cli-deform-json", "json", "cli",
                                    ("deform", "{grid}", "--connectivity", "{mutant}", "--rotate", "1",
                                     "-o", "{out}.x", "--allow-negative"))
TARGETS["cli-deform-nmf"] = Target("cli-deform-nmf", "nmf", "cli",
                                   ("deform", "{grid}", "--nmf", "{mutant}", "--rotate", "1",
                                    "-o", "{out}.x", "--allow-negative"))
TARGETS["cli-deform-case"] = Target("cli-deform-case", "case", "cli",
                                    ("deform", "--case", "{mutant}", "-o", "{out}.x", "--force",
                                     "--allow-negative"))
del _name


# ----------------------------------------------------------------------------- mutators

@dataclass(frozen=True)
class Mutant:
    """A damaged copy of a seed."""

    target: str
    index: int
    data: bytes
    #: the seed's header (first ``Seed.header_end`` bytes) is unchanged and still at offset 0
    header_intact: bool
    ops: tuple = ()


_INT_VALUES = (0, 1, -1, 2, 3, 255, 256, 0x7F, 0x80, 0xFF, 0x7FFF, 0xFFFF, 1 << 16, 1 << 24,
               (1 << 31) - 1, -(1 << 31), 1 << 20, 12345678)
_INT64_VALUES = (0, -1, (1 << 63) - 1, -(1 << 63), 1 << 32, 1 << 40, (1 << 31), 1 << 62)
_FLOAT_VALUES = (float("nan"), float("inf"), -float("inf"), 0.0, -0.0, 1e308, -1e308, 5e-324,
                 2.2250738585072014e-308, 1e-300)
_TEXT_VALUES = ("0", "-1", "1", "2", "-2147483648", "2147483647", "4294967296", "99999999999999999999",
                "1e999", "-1e999", "1e308", "5e-324", "nan", "inf", "-inf", "NaN", "1.5", "-0.0", "0x10",
                "1e", "1..2", "+-1", "true", "false", "null", '"x"', '""', "[]", "{}", "[1, 2]",
                "1_000", "\u00e9", "\\ud800", "\x00", "1" * 400, "-" + "9" * 30, "Infinity")
_TEXT_BYTES = (b"\xff", b"\xfe\xff", b"\x00", b"\xc3", b"\xed\xa0\x80", b"\x80\x80", b"\r", b"\t",
               b"\x0c", b"\x1a", b"{", b"}", b"[", b"]", b'"', b",", b"=", b"#", b"\n", b"\\")


def _interesting_bytes(rng: random.Random) -> bytes:
    kind = rng.randrange(6)
    if kind == 0:
        return bytes([rng.choice((0x00, 0xFF, 0x7F, 0x80, 0x01, 0xFE))])
    endian = rng.choice("<>")
    if kind == 1:
        return struct.pack(endian + "i", rng.choice(_INT_VALUES) if rng.random() < 0.8
                           else rng.randrange(-(1 << 31), 1 << 31))
    if kind == 2:
        return struct.pack(endian + "q", rng.choice(_INT64_VALUES))
    if kind == 3:
        return struct.pack(endian + "d", rng.choice(_FLOAT_VALUES))
    if kind == 4:
        return struct.pack(endian + "f", rng.choice(_FLOAT_VALUES[:5]))
    return bytes(rng.randrange(256) for _ in range(rng.randint(1, 8)))


def _offset(rng: random.Random, size: int, header_end: int, align: bool = True) -> int:
    """A random offset, biased towards the header and 4-byte alignment."""
    if size <= 0:
        return 0
    if header_end and rng.random() < 0.4:
        off = rng.randrange(min(header_end + 8, size))
    else:
        off = rng.randrange(size)
    if align and rng.random() < 0.7:
        off -= off % 4
    return off


def _binary_op(rng: random.Random, data: bytearray, header_end: int):
    """Apply one byte-level mutation in place; returns (description, first changed byte or None)."""
    size = len(data)
    op = rng.choice(("flip", "flip", "overwrite", "overwrite", "overwrite", "truncate", "extend",
                     "duplicate", "delete", "zero-run"))
    if op == "flip" or size == 0:
        nbits = rng.choice((1, 1, 2, 3, 8))
        first = None
        for _ in range(nbits):
            off = _offset(rng, size, header_end, align=False) if size else 0
            if size:
                data[off] ^= 1 << rng.randrange(8)
                first = off if first is None else min(first, off)
        return f"flip {nbits} bit(s)", first
    if op == "overwrite":
        val = _interesting_bytes(rng)
        off = _offset(rng, size, header_end)
        data[off:off + len(val)] = val
        return f"overwrite {val.hex()} at {off}", off
    if op == "truncate":
        cut = _offset(rng, size, header_end, align=rng.random() < 0.5)
        del data[cut:]
        return f"truncate at {cut}", cut
    if op == "extend":
        n = rng.choice((1, 4, 8, 12, 16, 24, 64, 1000))
        extra = bytes(n) if rng.random() < 0.5 else bytes(rng.randrange(256) for _ in range(n))
        data.extend(extra)
        return f"extend by {n}", size
    if op == "zero-run":
        off = _offset(rng, size, header_end)
        n = rng.randint(1, 64)
        data[off:off + n] = bytes(min(n, size - off))
        return f"zero {n} bytes at {off}", off
    a = _offset(rng, size, header_end)
    n = min(rng.choice((1, 4, 8, 16, 64, 256)), size - a)
    if op == "duplicate":
        chunk = bytes(data[a:a + n])
        at = _offset(rng, size, header_end)
        data[at:at] = chunk
        return f"duplicate {n} bytes from {a} at {at}", at
    del data[a:a + n]
    return f"delete {n} bytes at {a}", a


_TOKEN = re.compile(rb"[^\s,=\[\]{}:]+")


def _text_op(rng: random.Random, data: bytearray, header_end: int):
    """Apply one text-level mutation in place; returns (description, first changed byte or None)."""
    op = rng.choice(("token", "token", "token", "token", "line-delete", "line-dup", "bytes", "swap"))
    if op in ("token", "swap"):
        toks = list(_TOKEN.finditer(bytes(data)))
        if not toks:
            return "no token", None
        if header_end and rng.random() < 0.4:
            head = [t for t in toks if t.start() < header_end + 1]
            toks = head or toks
        t = rng.choice(toks)
        if op == "swap":
            u = rng.choice(toks)
            a, b = sorted((t, u), key=lambda m: m.start())
            if a.start() == b.start():
                return "swap no-op", None
            data[b.start():b.end()] = a.group()
            data[a.start():a.end()] = b.group()
            return f"swap tokens at {a.start()} and {b.start()}", a.start()
        new = rng.choice(_TEXT_VALUES).encode("utf-8", "surrogatepass")
        data[t.start():t.end()] = new
        return f"token at {t.start()} -> {new[:40]!r}", t.start()
    if op in ("line-delete", "line-dup"):
        lines = bytes(data).splitlines(keepends=True)
        if not lines:
            return "no line", None
        n = rng.randrange(len(lines))
        start = sum(len(x) for x in lines[:n])
        if op == "line-delete":
            del data[start:start + len(lines[n])]
            return f"delete line {n + 1}", start
        data[start:start] = lines[n]
        return f"duplicate line {n + 1}", start
    b = rng.choice(_TEXT_BYTES)
    off = _offset(rng, len(data), header_end, align=False)
    if rng.random() < 0.5:
        data[off:off] = b
        return f"insert {b!r} at {off}", off
    data[off:off + len(b)] = b
    return f"overwrite {b!r} at {off}", off


def mutate(seed: Seed, target: str, campaign_seed: int, index: int) -> Mutant:
    """Mutant number ``index`` of ``seed`` (deterministic in all arguments)."""
    rng = random.Random(f"{campaign_seed}:{target}:{index}")
    data = bytearray(seed.path.read_bytes())
    nops = rng.choice((1, 1, 1, 1, 2, 2, 3))
    ops, first = [], None
    for _ in range(nops):
        text_level = seed.text and rng.random() < 0.75
        desc, at = (_text_op if text_level else _binary_op)(rng, data, seed.header_end)
        ops.append(desc)
        if at is not None:
            first = at if first is None else min(first, at)
    intact = bool(seed.header_end) and (first is None or first >= seed.header_end)
    return Mutant(target, index, bytes(data), intact, tuple(ops))


# ----------------------------------------------------------------------------- checks (child side)

_OS_ERRORS = (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError)


class Wrong(Exception):
    """A read succeeded but its result is silently wrong."""


def _dims(grid) -> list:
    return [tuple(int(v) for v in b.xyz.shape[:3]) for b in grid]


def grid_problems(grid) -> str | None:
    """Why a grid read without ``allow_nonfinite`` is implausible (None when it is fine)."""
    if grid.ndim not in (2, 3) or len(grid) < 1:
        return f"ndim {grid.ndim}, {len(grid)} block(s)"
    for n, b in enumerate(grid):
        x = b.xyz
        if x.dtype != np.float64 or x.ndim != 4 or x.shape[3] != 3 or min(x.shape[:3]) < 1:
            return f"block {n + 1}: xyz {x.dtype} {x.shape}"
        if not np.isfinite(x).all():
            return f"block {n + 1}: non-finite coordinates"
        if grid.ndim == 2 and (x.shape[2] != 1 or np.any(x[..., 2] != 0.0)):
            return f"block {n + 1}: a 2-D grid with nk = {x.shape[2]} or non-zero z"
        if b.iblank is not None and (b.iblank.shape != x.shape[:3] or b.iblank.dtype != np.int32):
            return f"block {n + 1}: iblank {b.iblank.dtype} {b.iblank.shape}"
    return None


def _check_grid(path, ref, structure_must_match: bool) -> None:
    """``path``: a grid file to read, or a grid read already."""
    import tfi_quat as tq
    g = path if isinstance(path, tq.Grid) else tq.read(path)
    why = grid_problems(g)
    if why:
        raise Wrong(why)
    if structure_must_match and [list(d) for d in _dims(g)] != [list(d) for d in ref["dims"]]:
        raise Wrong(f"read as {len(g)} block(s) {_dims(g)} "
                    f"({getattr(g.source_format, 'describe', lambda: '')()}); the seed has "
                    f"{len(ref['dims'])} block(s) {ref['dims']} and its header is intact")


def _check_cgns(path, ref) -> None:
    """A CGNS mutant: a plausible grid of the seed's zones, and a connectivity that fits it."""
    import tfi_quat as tq
    g = tq.read(path)
    _check_grid(g, ref, True)
    conn = getattr(g, "connectivity", None)
    if conn is not None:
        try:
            conn.check(g)
        except Exception as exc:  # noqa: BLE001 - the reader let a misfit connectivity through
            raise Wrong(f"the reader returned a connectivity that check(grid) rejects: {exc}")
        if conn.overlaps():
            raise Wrong(f"the reader returned overlapping connectivity items {conn.overlaps()[:2]}")


def _check_map(path, ref, kind: str) -> None:
    import tfi_quat as tq
    from tfi_quat import Connectivity
    grid = tq.read(ref["grid"])
    conn = (Connectivity.from_json if kind == "json" else Connectivity.from_nmf)(path, grid=grid)
    dims = [tuple(int(v) for v in d) for d in conn.dims]
    if dims != _dims(grid):
        raise Wrong(f"map block dims {dims} accepted for a grid with {_dims(grid)}")
    try:
        conn.check(grid)
    except Exception as exc:  # noqa: BLE001 - any rejection here means the reader let it through
        raise Wrong(f"the reader accepted a map that check(grid) rejects: {type(exc).__name__}: {exc}")


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    s = np.max(np.abs(v))
    v = v / s
    return v / math.sqrt(float(v @ v))


def reference_rotation(points, axis, angle_deg: float, about) -> np.ndarray:
    """Rotate ``points`` (n, 3) about the line through ``about`` along ``axis`` (overflow-safe)."""
    k = _unit(axis)
    t = math.radians(angle_deg)
    r = np.asarray(points, dtype=np.float64) - np.asarray(about)
    rot = r * math.cos(t) + np.cross(k, r) * math.sin(t) + np.outer(r @ k, k) * (1.0 - math.cos(t))
    return rot + np.asarray(about)


def _check_case(path, ref) -> None:
    import tfi_quat as tq
    from tfi_quat.case import Motion, load_case
    case = load_case(path)
    case.check(tq.read(case.grid))      # patches against the grid: a CaseError is a clean error
    m = case.motion
    if m is None:
        return
    rigid = Motion(rotate=m.rotate, axis=m.axis, about=m.about)
    pts = np.array([[0.3, 0.2, 0.1], [1.0, -0.5, 0.25], [2.0, 0.7, -0.3]])
    got = rigid.apply(pts)
    want = reference_rotation(pts, m.axis, m.rotate, m.about)
    if np.all(np.isfinite(want)):
        scale = 1.0 + float(np.max(np.abs(want)))
        if not np.all(np.isfinite(got)) or float(np.max(np.abs(got - want))) > 1e-9 * scale:
            raise Wrong(f"rotation {m.rotate} deg about axis {m.axis}: moved points differ from an "
                        f"independent rotation by {float(np.max(np.abs(got - want))):.3g}")


def _check_cli(argv, outdir) -> tuple[str, str]:
    from tfi_quat.cli import EXIT_CHECK, EXIT_INPUT, main
    out, err = io.StringIO(), io.StringIO()
    try:
        with redirect_stdout(out), redirect_stderr(err):
            try:
                rc = main(list(argv))
            except SystemExit as exc:
                rc = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    except MemoryError as exc:
        return "overmem", f"MemoryError escaped main(): {exc}"
    except BaseException as exc:  # noqa: BLE001 - a traceback the user would see
        return "foreign", f"traceback: {type(exc).__name__}: {exc}"
    text = err.getvalue()
    if "Traceback" in text:
        return "foreign", "traceback on stderr: " + text[-300:]
    if rc == 0:
        return "ok", ""
    if rc in (EXIT_CHECK, EXIT_INPUT) and len(text.strip().splitlines()) == 1:
        # 2: bad input; 1: the result failed a check (a folded grid, not written)
        return "error", text.strip()[:300]
    return "foreign", f"exit status {rc}: {text.strip()[:300]}"


def classify(target: Target, path: Path, ref: dict, header_intact: bool, outdir: Path) -> tuple[str, str]:
    """Run ``target``'s check on the mutant at ``path``; returns ``(outcome, detail)``."""
    from tfi_quat import TfiQuatError
    try:
        if target.check == "cli":
            argv = [a.format(mutant=path, grid=ref["grid"], out=outdir / "out") for a in target.argv]
            return _check_cli(argv, outdir)
        if target.check == "plot3d":
            _check_grid(path, ref, header_intact)
        elif target.check == "hdf5":
            _check_grid(path, ref, True)
        elif target.check == "cgns":
            _check_cgns(path, ref)
        elif target.check in ("json", "nmf"):
            _check_map(path, ref, target.check)
        elif target.check == "case":
            _check_case(path, ref)
        elif target.check == "selftest":        # the runner's own tests: misbehave on purpose
            if target.argv[0] == "crash":
                os.kill(os.getpid(), signal.SIGSEGV)
            elif target.argv[0] == "hang":
                time.sleep(3600)
            elif target.argv[0] == "memory":
                bytearray(2 * MEM_LIMIT)
        else:
            raise ValueError(f"unknown check {target.check!r}")
    except Wrong as exc:
        return "wrong", str(exc)
    except MemoryError as exc:
        return "overmem", f"{type(exc).__name__}: {exc}"
    except (TfiQuatError,) + _OS_ERRORS as exc:
        return "error", f"{type(exc).__name__}: {exc}"[:300]
    except Exception as exc:  # noqa: BLE001 - any other exception type is a bug
        return "foreign", f"{type(exc).__name__}: {exc}"[:300]
    return "ok", ""


def reference(seeds: dict[str, Seed], target: Target) -> dict:
    """What a check compares against: the seed grid's block dims and the connectivity grid path."""
    import tfi_quat as tq
    ref = {"grid": str(seeds["json"].path.parent / "grid.x")}
    if target.check in ("plot3d", "hdf5", "cgns"):
        ref["dims"] = _dims(tq.read(seeds[target.seed].path))
    return ref


# ----------------------------------------------------------------------------- runner

@dataclass
class Result:
    """The outcome of one mutant."""

    target: str
    index: int
    outcome: str
    detail: str
    ops: tuple
    header_intact: bool
    seconds: float
    path: Path | None = None


def warm_up(folder, targets) -> None:
    """Import and load what ``targets`` use (numba kernels from the cache) before timing.

    Run once per worker, before its first mutant, so that the per-mutant timeout
    measures the read and not the start-up.
    """
    import tfi_quat as tq
    folder = Path(folder)
    checks = {t.check for t in targets}
    commands = {t.argv[0] for t in targets if t.check == "cli"}
    for t in targets:
        if t.check in ("plot3d", "hdf5", "cgns"):
            suffix = {"h5": ".h5", "cg": ".cgns"}.get(t.seed[:2], ".x")
            tq.read(folder / f"{t.seed}{suffix}")
    if checks & {"json", "nmf", "case", "cli"}:
        from tfi_quat.case import load_case
        grid = tq.read(folder / "grid.x")
        tq.Connectivity.from_json(folder / "map.json", grid=grid)
        tq.Connectivity.from_nmf(folder / "map.nmf", grid=grid)
        load_case(folder / "case.toml")
    if commands:
        from tfi_quat.cli import main
        with redirect_stdout(io.StringIO()), redirect_stderr(io.StringIO()):
            main(["info", str(folder / "grid.x")])
            if "deform" in commands:
                main(["deform", "--case", str(folder / "case.toml"), "-o", str(folder / "warm.x"),
                      "--force"])
            if "connect" in commands:
                main(["connect", str(folder / "grid.x"), "-o", str(folder / "warm.json"), "--force"])


def worker_main(argv=None) -> None:
    """A worker process: ``fuzzing.py --worker SEED_FOLDER MEM_LIMIT TARGET,...``.

    Limits its address space, warms up, prints ``ready``, then reads one job per
    line on stdin (JSON: target, path, intact, ref, outdir) and answers one JSON
    line ``{"outcome", "detail"}`` per job.  Crashes and hangs are the parent's
    to see (end of file on the pipe, or no answer in time).
    """
    argv = sys.argv[1:] if argv is None else argv
    folder, mem_limit = argv[1], int(argv[2])
    names = [n for n in argv[3].split(",") if n]
    resource.setrlimit(resource.RLIMIT_AS, (mem_limit, mem_limit))
    proto = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)               # start-up output goes to the log
    warm_up(folder, [TARGETS[n] for n in names])
    devnull = os.open(os.devnull, os.O_RDWR)
    for fd in (1, 2):           # then silence C libraries (HDF5 diagnostics) and stray prints
        os.dup2(devnull, fd)
    proto.write("ready\n")
    for line in sys.stdin:
        job = json.loads(line)
        target = Target(job["target"], "", job["check"], tuple(job["argv"]))
        outcome, detail = classify(target, Path(job["path"]), job["ref"], job["intact"], Path(job["outdir"]))
        proto.write(json.dumps({"outcome": outcome, "detail": detail[:2000]}) + "\n")


class _Worker:
    """One worker subprocess with its current job."""

    def __init__(self, folder, mem_limit, targets, log):
        self.log = log
        with open(log, "ab") as err:      # start-up errors (the worker silences itself once ready)
            self.proc = subprocess.Popen(
                [sys.executable, os.path.abspath(__file__), "--worker", str(folder), str(mem_limit),
                 ",".join(t.name for t in targets)],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err, text=True, bufsize=1,
                env=dict(os.environ, PYTHONHASHSEED="0", OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1"))
        self.ready = False
        self.job = None
        self.t0 = time.monotonic()

    def fileno(self):
        return self.proc.stdout.fileno()

    def send(self, job):
        self.job = job
        self.t0 = time.monotonic()
        self.proc.stdin.write(json.dumps(job["wire"]) + "\n")
        self.proc.stdin.flush()

    def close(self, kill: bool = False):
        """End the worker (``kill``: at once; else close its input and wait a little)."""
        if kill:
            self.proc.kill()
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.proc.stdout.close()


def run_mutants(jobs_iter, *, seed_folder, workdir, jobs: int = 2, timeout: float = TIMEOUT,
                mem_limit: int = MEM_LIMIT, keep=None, progress=None, targets=None,
                startup_timeout: float = 1800.0) -> list[Result]:
    """Check every mutant in worker processes, ``jobs`` at a time.

    Each worker is a fresh interpreter with ``RLIMIT_AS = mem_limit`` that has
    imported and warmed up the readers (:func:`warm_up`), then checks one mutant
    after another; a worker that dies (``crash``) or does not answer within
    ``timeout`` seconds (``hang``, killed) is replaced by a new one.

    Parameters
    ----------
    jobs_iter : iterable of (Target, Mutant, Seed, dict)
        The mutant with its target, seed and :func:`reference`.
    seed_folder : path
        The folder :func:`make_seeds` wrote (``grid.x`` is copied next to case mutants).
    workdir : path
        Scratch folder for the mutant files (deleted unless ``keep`` says otherwise).
    keep : callable(Result) -> bool, optional
        Keep this mutant's file (its path is then in ``Result.path``).
    progress : callable(Result), optional
        Called for every result as it arrives.
    targets : list of Target, optional
        What the workers warm up for (default: every target).
    """
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    targets = list(TARGETS.values()) if targets is None else list(targets)
    results: list[Result] = []
    grid_copy = workdir / "grid.x"
    grid_copy.write_bytes((Path(seed_folder) / "grid.x").read_bytes())
    workers = [_Worker(seed_folder, mem_limit, targets, workdir / "workers.log") for _ in range(jobs)]
    pending = iter(jobs_iter)
    exhausted = False

    def finish(w, outcome, detail):
        job = w.job
        w.job = None
        mutant = job["mutant"]
        res = Result(job["target"].name, mutant.index, outcome, detail, mutant.ops,
                     mutant.header_intact, time.monotonic() - w.t0)
        path = job["path"]
        if keep is not None and keep(res):
            res.path = path
        else:
            path.unlink(missing_ok=True)
        outdir = job["outdir"]
        for p in outdir.glob("*"):
            if p.is_file():
                p.unlink()
        try:
            outdir.rmdir()
        except OSError:
            pass
        results.append(res)
        if progress is not None:
            progress(res)

    def next_job():
        nonlocal exhausted
        try:
            target, mutant, seed, ref = next(pending)
        except StopIteration:
            exhausted = True
            return None
        path = workdir / f"{target.name}-{mutant.index:06d}{seed.suffix}"
        path.write_bytes(mutant.data)
        outdir = workdir / f"out-{target.name}-{mutant.index:06d}"
        outdir.mkdir(exist_ok=True)
        wire = {"target": target.name, "check": target.check, "argv": list(target.argv), "path": str(path), "intact": mutant.header_intact, "ref": ref,
                "outdir": str(outdir)}
        return {"target": target, "mutant": mutant, "path": path, "outdir": outdir, "wire": wire}

    try:
        while True:
            for n, w in enumerate(workers):
                if w.ready and w.job is None and not exhausted:
                    job = next_job()
                    if job is not None:
                        w.send(job)
            busy = [w for w in workers if w.job is not None or not w.ready]
            if exhausted and not any(w.job is not None for w in workers):
                break
            readable, _, _ = select.select(busy, [], [], 0.05)
            now = time.monotonic()
            for n, w in enumerate(workers):
                line = w.proc.stdout.readline() if w in readable else None
                if line == "":                       # end of file: the worker died
                    w.close()
                    rc = w.proc.returncode
                    if w.job is not None:
                        how = (f"killed by signal {-rc} ({signal.Signals(-rc).name})" if rc < 0
                               else f"exited with status {rc} without a result")
                        finish(w, "crash", how)
                    elif not w.ready:
                        tail = w.log.read_text(errors="replace")[-2000:]
                        raise RuntimeError(f"a fuzz worker failed to start (exit status {rc}):\n{tail}")
                    workers[n] = _Worker(seed_folder, mem_limit, targets, workdir / "workers.log")
                elif line is not None:
                    if not w.ready:
                        w.ready = line.strip() == "ready"
                    else:
                        msg = json.loads(line)
                        finish(w, msg["outcome"], msg["detail"])
                elif w.job is not None and now - w.t0 > timeout:
                    w.close(kill=True)
                    finish(w, "hang", f"no answer after {timeout:g} s (killed)")
                    workers[n] = _Worker(seed_folder, mem_limit, targets, workdir / "workers.log")
                elif not w.ready and now - w.t0 > startup_timeout:
                    raise RuntimeError(f"a fuzz worker did not start within {startup_timeout:g} s")
    finally:
        for w in workers:
            w.close()
    return results


def run_campaign(per_target, *, campaign_seed: int, workdir, jobs: int = 2, targets=None,
                 timeout: float = TIMEOUT, mem_limit: int = MEM_LIMIT, keep_cap: int = 0,
                 progress=None, seeds: dict | None = None) -> list[Result]:
    """Make the seeds, mutate them and check every mutant.

    Parameters
    ----------
    per_target : int or callable(Target) -> int
        Mutants per target.
    campaign_seed : int
        Seed of every mutation (the same seed gives the same mutants).
    workdir : path
        ``workdir/seeds`` holds the seeds, ``workdir/mutants`` the mutants being
        read; failing mutants are moved to ``workdir/failures`` (at most
        ``keep_cap`` per target and outcome; ``Result.path`` says where).
    seeds : dict, optional
        Seeds :func:`make_seeds` wrote earlier (default: write them now).
    """
    workdir = Path(workdir)
    targets = list(TARGETS.values()) if targets is None else list(targets)
    if seeds is None:
        seeds = make_seeds(workdir / "seeds")
    seed_folder = seeds["json"].path.parent
    count = per_target if callable(per_target) else (lambda t: per_target)
    refs = {t.name: reference(seeds, t) for t in targets}
    kept: dict[tuple, int] = {}
    failures = workdir / "failures"

    def jobs_iter():
        most = max(count(t) for t in targets)
        for i in range(most):
            for t in targets:
                if i < count(t):
                    seed = seeds[t.seed]
                    yield t, mutate(seed, t.name, campaign_seed, i), seed, refs[t.name]

    def keep(res: Result) -> bool:
        key = (res.target, res.outcome)
        if res.outcome not in FAILURES or kept.get(key, 0) >= keep_cap:
            return False
        kept[key] = kept.get(key, 0) + 1
        return True

    results = run_mutants(jobs_iter(), seed_folder=seed_folder, workdir=workdir / "mutants",
                          jobs=jobs, timeout=timeout, mem_limit=mem_limit, keep=keep,
                          progress=progress, targets=targets)
    for res in results:
        if res.path is not None:
            dest = failures / res.outcome / res.path.name
            dest.parent.mkdir(parents=True, exist_ok=True)
            res.path.replace(dest)
            res.path = dest
    return results


def failure_report(results, limit: int = 5) -> str:
    """The failing mutants, ``limit`` per target and outcome: operations and detail."""
    lines, shown = [], {}
    for r in results:
        if r.outcome not in FAILURES:
            continue
        key = (r.target, r.outcome)
        shown[key] = shown.get(key, 0) + 1
        if shown[key] <= limit:
            where = f" [{r.path}]" if r.path is not None else ""
            lines.append(f"{r.target} #{r.index} {r.outcome}: {'; '.join(r.ops)} -> {r.detail}{where}")
    return "\n".join(lines)


def tally(results, targets=None) -> dict[str, dict[str, int]]:
    """target -> outcome -> count (every outcome present, zeros included), in target order."""
    names = [t.name for t in targets] if targets is not None else []
    out: dict[str, dict[str, int]] = {n: {o: 0 for o in OUTCOMES} for n in names}
    for r in results:
        out.setdefault(r.target, {o: 0 for o in OUTCOMES})[r.outcome] += 1
    return out


def table(counts: dict[str, dict[str, int]]) -> str:
    """A text table of the counts per target and outcome, with a total row."""
    names = list(counts)
    width = max([len(n) for n in names] + [6])
    lines = [f"{'target':<{width}} " + " ".join(f"{o:>8}" for o in OUTCOMES) + f" {'total':>8}"]
    total = {o: 0 for o in OUTCOMES}
    for n in names:
        row = counts[n]
        for o in OUTCOMES:
            total[o] += row[o]
        lines.append(f"{n:<{width}} " + " ".join(f"{row[o]:>8}" for o in OUTCOMES)
                     + f" {sum(row.values()):>8}")
    lines.append(f"{'TOTAL':<{width}} " + " ".join(f"{total[o]:>8}" for o in OUTCOMES)
                 + f" {sum(total.values()):>8}")
    return "\n".join(lines)


if __name__ == "__main__" and sys.argv[1:2] == ["--worker"]:
    # the checkout's package first, as pytest's pythonpath = "." gives the tests (an older
    # installed copy must not be the code under test)
    _here = os.path.dirname(os.path.abspath(__file__))
    sys.path[:0] = [os.path.dirname(_here), _here]
    worker_main()
