"""JSON connectivity files (CGNS-style 1-based ranges) and the text table.

Layout (all indices 1-based, inclusive; see ``docs/formats.md``)::

    {
      "format": "tfi_quat.connectivity", "version": 1, "ndim": 3,
      "blocks": [[ni, nj, nk], ...],
      "interfaces": [
        {"block": 1, "face": "imax", "donor": 2, "donor_face": "imin",
         "PointRange": [[i1, j1, k1], [i2, j2, k2]],
         "PointRangeDonor": [[...], [...]],
         "Transform": [1, 2, 3]}, ...],
      "patches": [
        {"block": 1, "face": "jmin", "PointRange": [[...], [...]], "kind": "wall",
         "name": null, "collapsed": false, "origin": "user",
         "plane": {"origin": [x, y, z], "normal": [nx, ny, nz]}}, ...],
      "notes": ["..."]
    }
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

from ..errors import ConnectivityError
from ..grid import FACES, face_axes, face_layer
from ..io._atomic import atomic_output, check_target, read_text
from ..spec import PatchSpec
from .model import MAX_DIM, Connectivity, Interface, Patch, check_dims

FORMAT = "tfi_quat.connectivity"
VERSION = 1


def _range_ijk(spec: PatchSpec, dims) -> list[list[int]]:
    d, a, b = face_axes(spec.face)
    fix = face_layer(dims, spec.face) + 1
    (a0, a1), (b0, b1) = spec.range
    lo, hi = [0, 0, 0], [0, 0, 0]
    lo[d] = hi[d] = fix
    lo[a], hi[a], lo[b], hi[b] = a0 + 1, a1 + 1, b0 + 1, b1 + 1
    return [lo, hi]


def to_dict(conn: Connectivity) -> dict:
    """The JSON document of a connectivity (plain dicts and lists)."""
    itfs = []
    for it in conn.interfaces:
        pr = [[v + 1 for v in c] for c in it.point_range]
        prd = [[v + 1 for v in c] for c in it.point_range_donor]
        itfs.append({"block": it.master.block + 1, "face": it.master.face,
                     "donor": it.slave.block + 1, "donor_face": it.slave.face,
                     "PointRange": pr, "PointRangeDonor": prd, "Transform": list(it.transform)})
    pats = []
    for p in conn.patches:
        d = {"block": p.spec.block + 1, "face": p.spec.face,
             "PointRange": _range_ijk(p.spec, conn.dims[p.spec.block]),
             "kind": p.kind, "name": p.name, "collapsed": p.collapsed, "origin": p.origin}
        if p.plane is not None:
            d["plane"] = {"origin": list(p.plane[0]), "normal": list(p.plane[1])}
        pats.append(d)
    return {"format": FORMAT, "version": VERSION, "ndim": conn.ndim,
            "blocks": [list(d) for d in conn.dims], "interfaces": itfs, "patches": pats,
            "notes": list(conn.notes)}


def write_json(conn: Connectivity, path, *, overwrite: bool = False) -> None:
    target = check_target(path, overwrite=overwrite, replace_existing=False)
    doc = to_dict(conn)
    # one interface / patch / note per line: easy to read, diff and edit
    parts = []
    for key, value in doc.items():
        if isinstance(value, list) and value:
            items = ",\n  ".join(json.dumps(v) for v in value)
            parts.append(f' "{key}": [\n  {items}\n ]')
        else:
            parts.append(f" {json.dumps(key)}: {json.dumps(value)}")
    with atomic_output(target, "w") as fh:
        fh.write("{\n" + ",\n".join(parts) + "\n}\n")


def _show(value) -> str:
    """``repr`` of a value for an error message, shortened."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _int(value, where: str, name: str) -> int:
    """A JSON integer (not a float such as 3.7 or 1e999, not a bool)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConnectivityError(f"{where}: {name} must be an integer, got {_show(value)}")
    return value


def _str(value, where: str, name: str) -> str:
    if not isinstance(value, str):
        raise ConnectivityError(f"{where}: {name} must be a string, got {_show(value)}")
    return value


def _field(entry: dict, key: str, where: str):
    if key not in entry:
        raise ConnectivityError(f"{where}: '{key}' is missing")
    return entry[key]


def _corners(pr, where: str, name: str) -> tuple[list[int], list[int]]:
    """The two 0-based corners of a 1-based ``[[i1, j1, k1], [i2, j2, k2]]``."""
    if not (isinstance(pr, list) and len(pr) == 2 and all(isinstance(c, list) and len(c) == 3 for c in pr)):
        raise ConnectivityError(f"{where}: '{name}' must be [[i1, j1, k1], [i2, j2, k2]], got {_show(pr)}")
    lo, hi = ([_int(v, where, f"'{name}'[{c}][{m}]") - 1 for m, v in enumerate(pr[c])] for c in (0, 1))
    return lo, hi


def _spec_from_range(where: str, block: int, face: str, pr, dims, name: str = "PointRange") -> tuple:
    """PatchSpec (0-based) from a 1-based range on a face, and the range's first corner.

    Checks the block, the face, the fixed index and the bounds.
    """
    if face not in FACES:
        raise ConnectivityError(f"{where}: unknown face {_show(face)} (expected one of {', '.join(FACES)})")
    if not 0 <= block < len(dims):
        raise ConnectivityError(f"{where}: block {block + 1} does not exist ({len(dims)} block(s))")
    lo, hi = _corners(pr, where, name)
    d, a, b = face_axes(face)
    fix = face_layer(dims[block], face)
    if lo[d] != fix or hi[d] != fix:
        raise ConnectivityError(f"{where}: {name} {pr} is not on face {face} of block {block + 1} "
                                f"(index {'ijk'[d]} should be {fix + 1})")
    rng = ((min(lo[a], hi[a]), max(lo[a], hi[a])), (min(lo[b], hi[b]), max(lo[b], hi[b])))
    if min(rng[0][0], rng[1][0]) < 0:
        raise ConnectivityError(f"{where}: {name} {pr} has indices below 1")
    if rng[0][1] >= dims[block][a] or rng[1][1] >= dims[block][b]:
        ni, nj, nk = dims[block]
        raise ConnectivityError(f"{where}: {name} {pr} exceeds block {block + 1} ({ni} x {nj} x {nk})")
    return PatchSpec(block, face, rng), tuple(lo)


def _plane(value, where: str) -> tuple:
    """``(origin, normal)`` of a patch's ``plane``: finite numbers, a non-zero normal."""
    if not isinstance(value, dict) or set(value) != {"origin", "normal"}:
        raise ConnectivityError(f"{where}: 'plane' must be {{\"origin\": [x, y, z], \"normal\": [nx, ny, nz]}}, "
                                f"got {_show(value)}")
    out = []
    for key in ("origin", "normal"):
        v = value[key]
        if not (isinstance(v, list) and len(v) == 3 and all(_finite_number(c) for c in v)):
            raise ConnectivityError(f"{where}: 'plane.{key}' must be 3 finite numbers, got {_show(v)}")
        out.append(tuple(float(c) for c in v))
    if not any(out[1]):
        raise ConnectivityError(f"{where}: 'plane.normal' must not be the zero vector")
    return tuple(out)


def _finite_number(c) -> bool:
    """Whether a JSON value is a number (not a boolean) with a finite float value."""
    if isinstance(c, bool) or not isinstance(c, (int, float)):
        return False
    try:
        return math.isfinite(float(c))
    except OverflowError:               # an integer beyond the float range
        return False


def _entry_lines(text: str, key: str) -> list[int]:
    """1-based line numbers of the elements of the top-level array ``key`` in a JSON text.

    Best effort (for error messages): an empty list when the array cannot be
    located.
    """
    m = re.search(r'"%s"\s*:\s*\[' % re.escape(key), text)
    if m is None:
        return []
    dec = json.JSONDecoder()
    pos, out = m.end(), []
    try:
        while True:
            pos = _WS.match(text, pos).end()
            if text[pos] == "]":
                return out
            out.append(text.count("\n", 0, pos) + 1)
            _, pos = dec.raw_decode(text, pos)
            pos = _WS.match(text, pos).end()
            if text[pos] == ",":
                pos += 1
    except (ValueError, IndexError):
        return []


_WS = re.compile(r"\s*")


def from_dict(doc: dict, where: str = "connectivity", lines: dict | None = None, grid=None) -> Connectivity:
    """Build a connectivity from its JSON document (see :func:`to_dict`).

    ``where`` names the source in error messages; ``lines`` maps
    ``"interfaces"`` and ``"patches"`` to the line number of each entry
    (errors then read ``FILE:LINE: interface N: ...``).  With ``grid``, the
    declared block sizes are checked against it first.

    Every value is checked for its JSON type: integers must be integers
    (``3.7``, ``true`` and ``1e999`` are refused, never truncated), ``plane``
    numbers finite, ``collapsed`` a boolean; the error names the entry and
    the field.
    """
    lines = lines or {}

    def at(key: str, n: int) -> str:
        ln = lines.get(key, [])
        what = "interface" if key == "interfaces" else "patch"
        return f"{where}:{ln[n]}: {what} {n + 1}" if n < len(ln) else f"{where}: {what} {n + 1}"

    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ConnectivityError(f"{where}: not a tfi_quat connectivity file (format {FORMAT!r} expected)")
    version = _int(doc.get("version", 0), where, "'version'")
    if version > VERSION:
        raise ConnectivityError(f"{where}: file version {version} is newer than this reader ({VERSION})")
    ndim = _int(_field(doc, "ndim", where), where, "'ndim'")
    if ndim not in (2, 3):
        raise ConnectivityError(f"{where}: 'ndim' must be 2 or 3, got {ndim}")
    blocks = _field(doc, "blocks", where)
    if not isinstance(blocks, list) or not blocks:
        raise ConnectivityError(f"{where}: 'blocks' must be a non-empty list of [ni, nj, nk], got {_show(blocks)}")
    dims = []
    for n, d in enumerate(blocks):
        if not (isinstance(d, list) and len(d) == 3):
            raise ConnectivityError(f"{where}: 'blocks'[{n}] must be [ni, nj, nk], got {_show(d)}")
        d = tuple(_int(v, where, f"'blocks'[{n}][{m}]") for m, v in enumerate(d))
        if not all(1 <= v <= MAX_DIM for v in d):
            raise ConnectivityError(f"{where}: 'blocks'[{n}]: sizes must be from 1 to {MAX_DIM}, got {list(d)}")
        dims.append(d)
    if grid is not None:    # the declared sizes against the grid, before anything is built from them
        try:
            check_dims(ndim, dims, grid)
        except ConnectivityError as exc:
            raise ConnectivityError(f"{where}: {exc}") from None
    for key in ("interfaces", "patches", "notes"):
        if not isinstance(doc.get(key, []), list):
            raise ConnectivityError(f"{where}: '{key}' must be a list")
    notes = doc.get("notes", [])
    for n, text in enumerate(notes):
        _str(text, where, f"'notes'[{n}]")
    itfs = []
    for n, it in enumerate(doc.get("interfaces", [])):
        w = at("interfaces", n)
        if not isinstance(it, dict):
            raise ConnectivityError(f"{w}: expected an object, got {_show(it)}")
        mb = _int(_field(it, "block", w), w, "'block'") - 1
        sb = _int(_field(it, "donor", w), w, "'donor'") - 1
        master, begin = _spec_from_range(w, mb, _str(_field(it, "face", w), w, "'face'"),
                                         _field(it, "PointRange", w), dims)
        slave, sbeg = _spec_from_range(w + " (donor)", sb, _str(_field(it, "donor_face", w), w, "'donor_face'"),
                                       _field(it, "PointRangeDonor", w), dims, "PointRangeDonor")
        t = _field(it, "Transform", w)
        if not isinstance(t, list) or len(t) not in (2, 3):
            raise ConnectivityError(f"{w}: 'Transform' must be [t1, t2, t3], got {_show(t)}")
        t = tuple(_int(v, w, f"'Transform'[{m}]") for m, v in enumerate(t))
        if len(t) == 2:
            t = t + (3,)
        try:
            itfs.append(Interface(master, slave, t, begin, sbeg))
        except ConnectivityError as exc:
            hint = " (PointRange must run from the lowest corner)" if "first corner" in str(exc) else ""
            raise ConnectivityError(f"{w}: {exc}{hint}") from None
    pats = []
    for n, p in enumerate(doc.get("patches", [])):
        w = at("patches", n)
        if not isinstance(p, dict):
            raise ConnectivityError(f"{w}: expected an object, got {_show(p)}")
        spec, _ = _spec_from_range(w, _int(_field(p, "block", w), w, "'block'") - 1,
                                   _str(_field(p, "face", w), w, "'face'"), _field(p, "PointRange", w), dims)
        kind = _str(_field(p, "kind", w), w, "'kind'")
        name = p.get("name")
        if name is not None:
            _str(name, w, "'name'")
        collapsed = p.get("collapsed", False)
        if not isinstance(collapsed, bool):
            raise ConnectivityError(f"{w}: 'collapsed' must be true or false, got {_show(collapsed)}")
        origin = _str(p.get("origin", "file"), w, "'origin'")
        plane = p.get("plane")
        if plane is not None:
            plane = _plane(plane, w)
        try:
            pats.append(Patch(spec, kind, name, collapsed, origin, plane))
        except ConnectivityError as exc:
            raise ConnectivityError(f"{w}: {exc}") from None
    try:
        conn = Connectivity(itfs, pats, ndim, dims, notes)
    except ConnectivityError as exc:
        raise ConnectivityError(f"{where}: {exc}") from None
    overlaps = conn.overlaps()
    if overlaps:
        first, second = overlaps[0]
        (a, la), (b, lb) = _item(second, lines), _item(first, lines)
        spec = conn.item_spec(second)
        raise ConnectivityError(f"{where}{f':{la}' if la else ''}: {a} overlaps {b}"
                                f"{f' (line {lb})' if lb else ''} on block {spec.block + 1} face {spec.face}")
    return conn


def _item(item, lines) -> tuple[str, int | None]:
    """Name and line of an item of :meth:`Connectivity.overlaps`."""
    role, n = item
    ln = lines.get("patches" if role == "patch" else "interfaces", [])
    side = "donor" if role == "slave" else "master"
    name = f"patch {n + 1}" if role == "patch" else f"interface {n + 1} {side} side"
    return name, (ln[n] if n < len(ln) else None)


def read_json(path, grid=None) -> Connectivity:
    """Read a JSON connectivity file; with ``grid``, check its dimensions and that every
    interface's points coincide (errors name the file and line).

    Raises
    ------
    FileNotFoundError, IsADirectoryError, PermissionError
        The file cannot be opened (the path is in the exception).
    ConnectivityError
        Anything wrong with the contents, naming the file, the entry and the field.
    """
    p = Path(os.fspath(path))
    text = read_text(p, ConnectivityError)
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConnectivityError(f"{p}:{exc.lineno}: not valid JSON (column {exc.colno}): {exc.msg}") from None
    except (ValueError, RecursionError) as exc:     # a number with thousands of digits, absurd nesting
        raise ConnectivityError(f"{p}: not a JSON file this reader accepts: {exc}") from None
    lines = {key: _entry_lines(text, key) for key in ("interfaces", "patches")}
    conn = from_dict(doc, str(p), lines, grid)
    if grid is not None:
        from .search import check_interfaces
        ln = lines["interfaces"]
        check_interfaces(conn, grid, lambda n: f"{p}:{ln[n]}: interface {n + 1}" if n < len(ln)
                         else f"{p}: interface {n + 1}")
    return conn


# ------------------------------------------------------------------ table
def _rng1(spec: PatchSpec) -> str:
    (a0, a1), (b0, b1) = spec.range
    return f"{a0 + 1}-{a1 + 1},{b0 + 1}-{b1 + 1}"


def format_table(conn: Connectivity) -> str:
    """Interfaces, patches and notes as a text table (1-based ranges)."""
    lines = [f"{len(conn.dims)} block(s), {conn.ndim}-D: {len(conn.interfaces)} interface(s), "
             f"{len(conn.patches)} patch(es)"]
    if conn.interfaces:
        lines.append("")
        lines.append("interfaces (master -> slave, face ranges 1-based A1-A2,B1-B2)")
        lines.append(f"  {'#':>3}  {'master':<8} {'face':<5} {'range':<17} {'slave':<8} {'face':<5} "
                     f"{'range':<17} transform")
        for n, it in enumerate(conn.interfaces):
            t = " ".join(f"{v:+d}" for v in it.transform)
            lines.append(f"  {n + 1:>3}  {it.master.block + 1:<8} {it.master.face:<5} {_rng1(it.master):<17} "
                         f"{it.slave.block + 1:<8} {it.slave.face:<5} {_rng1(it.slave):<17} {t}")
    if conn.patches:
        lines.append("")
        lines.append("patches")
        lines.append(f"  {'#':>3}  {'kind':<9} {'block':<6} {'face':<5} {'range':<17} from")
        for n, p in enumerate(conn.patches):
            extra = p.origin + (" collapsed" if p.collapsed else "") + (f" {p.name}" if p.name else "")
            lines.append(f"  {n + 1:>3}  {p.kind:<9} {p.spec.block + 1:<6} {p.spec.face:<5} "
                         f"{_rng1(p.spec):<17} {extra}")
    if conn.notes:
        lines.append("")
        lines.append("notes")
        lines.extend(f"  - {s}" for s in conn.notes)
    return "\n".join(lines)

