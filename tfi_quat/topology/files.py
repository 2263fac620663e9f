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
import os
import re
from pathlib import Path

from ..errors import ConnectivityError, OverwriteError
from ..grid import FACES
from ..io._atomic import atomic_output
from ..spec import PatchSpec
from .model import Connectivity, Interface, Patch, face_axes

FORMAT = "tfi_quat.connectivity"
VERSION = 1


def _check_target(path, overwrite: bool) -> Path:
    target = Path(os.fspath(path))
    if target.is_dir():
        raise OverwriteError(f"{target}: is a directory")
    if target.exists() and not overwrite:
        raise OverwriteError(f"{target}: exists (pass overwrite=True, or --force on the command line)")
    return target


def _range_ijk(spec: PatchSpec, dims) -> list[list[int]]:
    d, a, b = face_axes(spec.face)
    fix = dims[d] if FACES.index(spec.face) % 2 else 1
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
    target = _check_target(path, overwrite)
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


def _spec_from_range(where: str, block: int, face: str, pr, dims) -> PatchSpec:
    """PatchSpec (0-based) from a 1-based PointRange on a face; checks the fixed index."""
    try:
        lo = [int(v) - 1 for v in pr[0]]
        hi = [int(v) - 1 for v in pr[1]]
    except (TypeError, ValueError, IndexError):
        raise ConnectivityError(f"{where}: PointRange must be [[i1, j1, k1], [i2, j2, k2]], got {pr!r}") from None
    if len(lo) != 3 or len(hi) != 3:
        raise ConnectivityError(f"{where}: PointRange must be [[i1, j1, k1], [i2, j2, k2]], got {pr!r}")
    if face not in FACES:
        raise ConnectivityError(f"{where}: unknown face {face!r}")
    if not 0 <= block < len(dims):
        raise ConnectivityError(f"{where}: block {block + 1} does not exist ({len(dims)} block(s))")
    d, a, b = face_axes(face)
    fix = dims[block][d] - 1 if FACES.index(face) % 2 else 0
    if lo[d] != fix or hi[d] != fix:
        raise ConnectivityError(f"{where}: PointRange {pr} is not on face {face} of block {block + 1} "
                                f"(index {'ijk'[d]} should be {fix + 1})")
    rng = ((min(lo[a], hi[a]), max(lo[a], hi[a])), (min(lo[b], hi[b]), max(lo[b], hi[b])))
    if min(rng[0][0], rng[1][0]) < 0:
        raise ConnectivityError(f"{where}: PointRange {pr} has indices below 1")
    if rng[0][1] >= dims[block][a] or rng[1][1] >= dims[block][b]:
        ni, nj, nk = dims[block]
        raise ConnectivityError(f"{where}: PointRange {pr} exceeds block {block + 1} ({ni} x {nj} x {nk})")
    return PatchSpec(block, face, rng)


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


def from_dict(doc: dict, where: str = "connectivity", lines: dict | None = None) -> Connectivity:
    """Build a connectivity from its JSON document (see :func:`to_dict`).

    ``where`` names the source in error messages; ``lines`` maps
    ``"interfaces"`` and ``"patches"`` to the line number of each entry
    (errors then read ``FILE:LINE: interface N: ...``).
    """
    lines = lines or {}

    def at(key: str, n: int) -> str:
        ln = lines.get(key, [])
        what = "interface" if key == "interfaces" else "patch"
        return f"{where}:{ln[n]}: {what} {n + 1}" if n < len(ln) else f"{where}: {what} {n + 1}"

    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ConnectivityError(f"{where}: not a tfi_quat connectivity file (format {FORMAT!r} expected)")
    try:
        version = int(doc.get("version", 0))
    except (TypeError, ValueError):
        raise ConnectivityError(f"{where}: bad 'version' {doc.get('version')!r}") from None
    if version > VERSION:
        raise ConnectivityError(f"{where}: file version {version} is newer than this reader ({VERSION})")
    try:
        ndim = int(doc["ndim"])
        dims = [tuple(int(n) for n in d) for d in doc["blocks"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise ConnectivityError(f"{where}: missing or bad 'ndim'/'blocks': {exc}") from None
    if ndim not in (2, 3):
        raise ConnectivityError(f"{where}: 'ndim' must be 2 or 3, got {ndim}")
    if any(len(d) != 3 or min(d) < 1 for d in dims):
        raise ConnectivityError(f"{where}: 'blocks' must list [ni, nj, nk] >= 1 per block")
    for key in ("interfaces", "patches"):
        if not isinstance(doc.get(key, []), list):
            raise ConnectivityError(f"{where}: '{key}' must be a list")
    itfs = []
    for n, it in enumerate(doc.get("interfaces", [])):
        w = at("interfaces", n)
        try:
            mb, sb = int(it["block"]) - 1, int(it["donor"]) - 1
            master = _spec_from_range(w, mb, str(it["face"]), it["PointRange"], dims)
            slave = _spec_from_range(w + " (donor)", sb, str(it["donor_face"]), it["PointRangeDonor"], dims)
            begin = tuple(int(v) - 1 for v in it["PointRange"][0])
            sbeg = tuple(int(v) - 1 for v in it["PointRangeDonor"][0])
            t = tuple(int(v) for v in it["Transform"])
        except ConnectivityError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise ConnectivityError(f"{w}: missing or bad entry: {exc}") from None
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
        try:
            spec = _spec_from_range(w, int(p["block"]) - 1, str(p["face"]), p["PointRange"], dims)
            plane = p.get("plane")
            if plane is not None:
                plane = (tuple(float(v) for v in plane["origin"]), tuple(float(v) for v in plane["normal"]))
            pats.append(Patch(spec, str(p["kind"]), p.get("name"), bool(p.get("collapsed", False)),
                              str(p.get("origin", "file")), plane))
        except ConnectivityError as exc:
            msg = str(exc)
            raise ConnectivityError(msg if msg.startswith(w) else f"{w}: {msg}") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise ConnectivityError(f"{w}: missing or bad entry: {exc}") from None
    try:
        conn = Connectivity(itfs, pats, ndim, dims, doc.get("notes", []))
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
    interface's points coincide (errors name the file and line)."""
    p = Path(os.fspath(path))
    text = p.read_text(encoding="utf-8")
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConnectivityError(f"{p}:{exc.lineno}: not valid JSON (column {exc.colno}): {exc.msg}") from None
    lines = {key: _entry_lines(text, key) for key in ("interfaces", "patches")}
    conn = from_dict(doc, str(p), lines)
    if grid is not None:
        from .search import check_interfaces
        try:
            conn.check(grid)
        except ConnectivityError as exc:
            raise ConnectivityError(f"{p}: {exc}") from None
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

