"""Hostile and damaged connectivity maps and case files (the robustness issue).

Inputs in ``tests/data/robustness/``, each named after what it does to a
reader that trusts it:

- ``huge.json``, ``huge_25000.nmf``, ``huge_60000.nmf``: maps of a few bytes
  declaring 25000^2 x 2 or 60000^2 x 2 points (the overlap check once
  allocated an array per face from them: 5.6 GB, or a 26.8 GiB MemoryError);
- ``k.nmf``: a KDIM of 2^31, one past the int32 range;
- ``inf.json``: ``1e999`` (a float infinity) as a block number (once an
  OverflowError);
- ``bad_utf8.json``: a 0xff byte in a note (once a UnicodeDecodeError);
- ``axis_overflow.toml``: the rotation axis ``[0, 0, 1e200]``, whose norm
  overflows (the rotation was once silently dropped).
"""

from __future__ import annotations

import copy
import json
import math
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import tfi_quat as tq
from tfi_quat import CaseError, ConnectivityError
from tfi_quat.case import Motion, load_case, unit_vector
from tfi_quat.io._atomic import read_text
from tfi_quat.spec import PatchSpec, parse_patch_spec
from tfi_quat.topology import Connectivity
from tfi_quat.topology.files import from_dict
from tfi_quat.topology.model import Patch

from conftest import sheared_box

DATA = Path(__file__).resolve().parent / "data" / "robustness"
GRIDS = Path(__file__).resolve().parents[1] / "grids"
#: what reading any map of this module may allocate (the big ones declare gigabytes)
PEAK = 20 << 20


def peak_bytes(fn, *args, **kw):
    """Run ``fn``; return (result or the exception raised, peak bytes traced meanwhile)."""
    tracemalloc.start()
    try:
        try:
            out = fn(*args, **kw)
        except Exception as exc:  # noqa: BLE001 - returned to the test, which checks its type
            out = exc
        return out, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def two_block():
    return tq.read(GRIDS / "two_block_65x33.x")


# ------------------------------------------------------------ declared sizes (item 2)
@pytest.mark.parametrize("name,reader", [("huge.json", Connectivity.from_json),
                                         ("huge_25000.nmf", Connectivity.from_nmf),
                                         ("huge_60000.nmf", Connectivity.from_nmf)])
def test_huge_declared_maps_are_read_without_allocating_them(name, reader):
    conn, peak = peak_bytes(reader, DATA / name)
    assert isinstance(conn, Connectivity), conn
    assert conn.dims[0][0] in (25000, 60000) and [p.kind for p in conn.patches] == ["wall"]
    assert peak < PEAK, peak


@pytest.mark.parametrize("name,reader", [("huge.json", Connectivity.from_json),
                                         ("huge_25000.nmf", Connectivity.from_nmf),
                                         ("huge_60000.nmf", Connectivity.from_nmf)])
def test_huge_declared_maps_are_refused_against_the_grid_before_anything_is_built(name, reader):
    g = two_block()
    err, peak = peak_bytes(reader, DATA / name, g)
    assert isinstance(err, ConnectivityError), err
    assert name in str(err) and "connectivity is for" in str(err)
    assert peak < PEAK, peak


def test_a_dimension_past_int32_names_the_line():
    with pytest.raises(ConnectivityError, match=r"k\.nmf:6: block 1: sizes must be from 1 to 2147483647, "
                                                r"got 5 x 4 x 2147483648"):
        Connectivity.from_nmf(DATA / "k.nmf")


def test_overlap_of_two_huge_patches_is_found_by_their_ranges(tmp_path):
    p = tmp_path / "two.nmf"
    p.write_text("1\n1 60000 60000 2\nWALL 1 1 1 60000 1 60000\nFARFIELD 1 1 5 9 5 9\n")
    err, peak = peak_bytes(Connectivity.from_nmf, p)
    assert isinstance(err, ConnectivityError) and "two.nmf:4: overlaps the entry on line 3" in str(err)
    assert peak < PEAK


def _oracle_overlaps(conn):
    """The pairs of :meth:`Connectivity.overlaps`, by painting every cell of every face."""
    items = [(("master", n), it.master) for n, it in enumerate(conn.interfaces)]
    items += [(("slave", n), it.slave) for n, it in enumerate(conn.interfaces)]
    items.sort(key=lambda x: (x[0][1], x[0][0] != "master"))
    items += [(("patch", n), p.spec) for n, p in enumerate(conn.patches)]
    cells = {}
    for k, (item, s) in enumerate(items):
        d = "ijk".index(s.face[0])
        na, nb = [n for m, n in enumerate(conn.dims[s.block]) if m != d]
        (a0, a1), (b0, b1) = s.range
        sa = slice(a0, a1) if na > 1 else slice(0, 1)
        sb = slice(b0, b1) if nb > 1 else slice(0, 1)
        for a in range(max(na - 1, 1))[sa]:
            for b in range(max(nb - 1, 1))[sb]:
                cells.setdefault((s.block, s.face, a, b), []).append(k)
    pairs = {}
    for owners in cells.values():
        for m in owners[1:]:
            pairs[m] = min(pairs.get(m, m), owners[0])
    return [(items[j][0], items[m][0]) for m, j in sorted(pairs.items())]


@given(st.lists(st.tuples(st.sampled_from(["imin", "jmax", "kmin"]),
                          st.integers(0, 5), st.integers(0, 5), st.integers(0, 4), st.integers(0, 4)),
                min_size=1, max_size=8))
def test_overlaps_by_ranges_agree_with_painting_the_cells(rects):
    dims = [(6, 6, 5)]
    patches = []
    for face, a0, a1, b0, b1 in rects:
        na, nb = (6, 5) if face != "kmin" else (6, 6)
        rng = ((min(a0, a1), min(max(a0, a1), na - 1)), (min(b0, b1), min(max(b0, b1), nb - 1)))
        patches.append(Patch(PatchSpec(0, face, rng), "wall"))
    conn = Connectivity([], patches, 3, dims)
    assert conn.overlaps() == _oracle_overlaps(conn)


# ------------------------------------------------------------ foreign exceptions, loose values (5, 9)
def test_infinite_block_number_names_the_entry_and_field():
    with pytest.raises(ConnectivityError, match=r"inf\.json:1: patch 1: 'block' must be an integer, got inf"):
        Connectivity.from_json(DATA / "inf.json")


def test_non_utf8_map_names_line_and_offset(tmp_path):
    with pytest.raises(ConnectivityError, match=r"bad_utf8\.json:1: not UTF-8 text \(byte 0xff at offset 138\)"):
        Connectivity.from_json(DATA / "bad_utf8.json")
    nmf = tmp_path / "bad.nmf"
    nmf.write_bytes(b"1\n1 5 5 4\n# caf\xe9\nWALL 1 1 1 5 1 5\n")
    with pytest.raises(ConnectivityError, match=r"bad\.nmf:3: not UTF-8"):
        Connectivity.from_nmf(nmf)


def _doc():
    """A valid 2-block document: one interface, two patches (one with a plane)."""
    return {"format": "tfi_quat.connectivity", "version": 1, "ndim": 3,
            "blocks": [[5, 5, 4], [5, 5, 4]],
            "interfaces": [{"block": 1, "face": "imax", "donor": 2, "donor_face": "imin",
                            "PointRange": [[5, 1, 1], [5, 5, 4]], "PointRangeDonor": [[1, 1, 1], [1, 5, 4]],
                            "Transform": [1, 2, 3]}],
            "patches": [{"block": 1, "face": "jmin", "PointRange": [[1, 1, 1], [5, 1, 4]], "kind": "wall",
                         "name": "VISCOUS", "collapsed": False, "origin": "file"},
                        {"block": 1, "face": "kmin", "PointRange": [[1, 1, 1], [5, 5, 1]], "kind": "symmetry",
                         "plane": {"origin": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]}}],
            "notes": ["hand-made"]}


def test_the_reference_document_is_valid():
    conn = from_dict(_doc())
    assert len(conn.interfaces) == 1 and [p.kind for p in conn.patches] == ["wall", "symmetry"]


def _set(doc, path, value):
    d = doc
    for key in path[:-1]:
        d = d[key]
    d[path[-1]] = value
    return doc


@pytest.mark.parametrize("path,value,match", [
    (("patches", 0, "PointRange", 1, 0), 3.7, r"patch 1: 'PointRange'\[1\]\[0\] must be an integer, got 3\.7"),
    (("patches", 0, "PointRange", 1, 0), True, r"patch 1: 'PointRange'\[1\]\[0\] must be an integer, got True"),
    (("patches", 0, "PointRange", 0, 2), math.inf, r"'PointRange'\[0\]\[2\] must be an integer, got inf"),
    (("interfaces", 0, "donor"), math.inf, r"interface 1: 'donor' must be an integer, got inf"),
    (("interfaces", 0, "block"), 1.0, r"interface 1: 'block' must be an integer, got 1\.0"),
    (("interfaces", 0, "PointRangeDonor", 0, 0), "1", r"'PointRangeDonor'\[0\]\[0\] must be an integer"),
    (("interfaces", 0, "Transform", 0), 1.5, r"interface 1: 'Transform'\[0\] must be an integer"),
    (("interfaces", 0, "Transform"), "123", r"interface 1: 'Transform' must be \[t1, t2, t3\]"),
    (("interfaces", 0, "face"), 4, r"interface 1: 'face' must be a string, got 4"),
    (("patches", 1, "plane", "origin", 0), math.nan, r"patch 2: 'plane\.origin' must be 3 finite numbers"),
    (("patches", 1, "plane", "normal", 2), math.inf, r"patch 2: 'plane\.normal' must be 3 finite numbers"),
    (("patches", 1, "plane", "origin", 1), 10 ** 400, r"patch 2: 'plane\.origin' must be 3 finite numbers"),
    (("patches", 1, "plane", "normal"), [0, 0, 0], r"patch 2: 'plane\.normal' must not be the zero vector"),
    (("patches", 1, "plane"), [0, 0, 1], r"patch 2: 'plane' must be"),
    (("patches", 0, "collapsed"), 1, r"patch 1: 'collapsed' must be true or false, got 1"),
    (("patches", 0, "collapsed"), "yes", r"patch 1: 'collapsed' must be true or false, got 'yes'"),
    (("patches", 0, "name"), 7, r"patch 1: 'name' must be a string, got 7"),
    (("patches", 0, "kind"), None, r"patch 1: 'kind' must be a string, got None"),
    (("patches", 0), "wall", r"patch 1: expected an object"),
    (("blocks", 1, 2), 4.0, r"'blocks'\[1\]\[2\] must be an integer, got 4\.0"),
    (("blocks", 1), [5, 5], r"'blocks'\[1\] must be \[ni, nj, nk\]"),
    (("blocks",), [], r"'blocks' must be a non-empty list"),
    (("blocks", 0, 0), 2**31, r"'blocks'\[0\]: sizes must be from 1 to 2147483647"),
    (("ndim",), 3.0, r"'ndim' must be an integer, got 3\.0"),
    (("version",), "1", r"'version' must be an integer"),
    (("notes", 0), 5, r"'notes'\[0\] must be a string"),
])
def test_loose_values_are_refused_naming_the_field(path, value, match):
    with pytest.raises(ConnectivityError, match=match):
        from_dict(_set(_doc(), path, value), "map.json")


_JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-2**70, 2**70) | st.integers(10**308, 10**400) | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
    max_leaves=8)


def _leaf_paths(obj, prefix=()):
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _leaf_paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for n, v in enumerate(obj):
            yield from _leaf_paths(v, prefix + (n,))


_PATHS = [p for p in _leaf_paths(_doc()) if p]


@given(st.sampled_from(_PATHS), _JSON_VALUES)
def test_any_value_anywhere_gives_a_connectivity_or_a_connectivity_error(path, value):
    doc = _set(copy.deepcopy(_doc()), path, value)
    try:
        conn = from_dict(doc, "map.json")
    except ConnectivityError as exc:
        assert str(exc).startswith("map.json")
        return
    assert isinstance(conn, Connectivity)       # e.g. a new note text or a patch name


@pytest.mark.parametrize("text,match", [
    ("[" * 100000 + "]" * 100000, "not a JSON file this reader accepts"),
    ('{"format": "tfi_quat.connectivity", "version": 1' + "9" * 5000 + "}", "not a JSON file this reader accepts"),
])
def test_pathological_json_text_is_a_connectivity_error(tmp_path, text, match):
    p = tmp_path / "deep.json"
    p.write_text(text)
    with pytest.raises(ConnectivityError, match=match):
        Connectivity.from_json(p)


@pytest.mark.parametrize("line", ["WALL 1 1 1 5 1 5_0", "WALL 1 1 1 \u0665 1 5", "WALL 1 1 1 5.0 1 5"])
def test_nmf_numbers_are_plain_decimal_integers(tmp_path, line):
    p = tmp_path / "n.nmf"
    p.write_text(f"1\n1 5 5 4\n{line}\n", encoding="utf-8")
    with pytest.raises(ConnectivityError, match=r"n\.nmf:3: WALL needs 6 integers"):
        Connectivity.from_nmf(p)


def test_nmf_block_sizes_are_plain_integers(tmp_path):
    p = tmp_path / "n.nmf"
    p.write_text("1\n1 5 5 4_0\n")
    with pytest.raises(ConnectivityError, match=r"n\.nmf:2: expected 'BLOCK IDIM JDIM \[KDIM\]'"):
        Connectivity.from_nmf(p)


def test_patch_strings_and_specs_take_integers_only():
    with pytest.raises(CaseError, match="expected BLOCK:FACE"):
        parse_patch_spec("\u00b2:jmin")
    with pytest.raises(CaseError, match="bad range"):
        parse_patch_spec("1:jmin:\u00b9-3")
    with pytest.raises(CaseError, match="block: expected an integer, got 0.5"):
        PatchSpec(0.5, "jmin")
    with pytest.raises(CaseError, match="range: expected integers"):
        PatchSpec(0, "jmin", ((0, 3.7), (0, 0)))
    with pytest.raises(CaseError, match="range: expected integers"):
        PatchSpec(0, "jmin", ((True, 3), (0, 0)))
    assert PatchSpec(np.int64(1), "jmin", ((np.int32(0), 3), (0, 0))).block == 1


# ------------------------------------------------------------ OS errors (item 10)
@pytest.mark.parametrize("reader", [Connectivity.from_json, Connectivity.from_nmf, load_case])
def test_missing_file_and_directory_are_the_standard_os_errors_with_the_path(tmp_path, reader):
    with pytest.raises(FileNotFoundError) as info:
        reader(tmp_path / "nothing.here")
    assert info.value.filename == str(tmp_path / "nothing.here")
    with pytest.raises(IsADirectoryError) as info:
        reader(tmp_path)
    assert info.value.filename == str(tmp_path)


@pytest.mark.parametrize("reader", [Connectivity.from_json, Connectivity.from_nmf, load_case])
def test_no_permission_is_a_permission_error_with_the_path(tmp_path, monkeypatch, reader):
    # the tests may run as root, who reads a chmod 000 file: deny the open itself
    import tfi_quat.io._atomic as atomic
    target = tmp_path / "locked"
    target.write_text("{}")

    def deny(path, *args, **kw):
        raise PermissionError(13, "Permission denied", str(path))
    monkeypatch.setattr(atomic, "open", deny, raising=False)
    with pytest.raises(PermissionError) as info:
        reader(target)
    assert info.value.filename == str(target)


def test_text_reads_are_bounded(tmp_path):
    p = tmp_path / "big.json"
    p.write_bytes(b" " * 2000)
    with pytest.raises(ConnectivityError, match=r"big\.json: larger than 1,000 bytes"):
        read_text(p, ConnectivityError, limit=1000)
    assert read_text(p, ConnectivityError, limit=2000) == " " * 2000
    err, peak = peak_bytes(read_text, "/dev/zero", CaseError, limit=1 << 20)     # an endless "file"
    assert isinstance(err, CaseError) and peak < 4 << 20


# ------------------------------------------------------------ motions (item 4, 9)
def test_the_overflowing_axis_of_the_reproducer_rotates_about_z():
    case = load_case(DATA / "axis_overflow.toml")
    pts = sheared_box(4, 3, 2).reshape(-1, 3)
    assert np.array_equal(case.motion.apply(pts), Motion(rotate=5.0, axis=(0, 0, 1)).apply(pts))


@given(st.sampled_from(["axis", "span_axis", "direction"]),
       st.integers(-300, 300), st.sampled_from([(0, 0, 1), (1, 0, 0), (1, 0, 1), (3, -4, 12)]))
def test_vectors_of_any_magnitude_mean_their_direction(name, exponent, direction):
    v = tuple(c * 10.0 ** exponent for c in direction)
    np.testing.assert_allclose(unit_vector(v, name), np.asarray(direction) / np.linalg.norm(direction),
                               rtol=0, atol=1e-15)
    kw = {"rotate": 5.0, "twist": 3.0}
    if name == "direction":
        kw["bend"] = 0.1            # none of the directions is parallel to the default span axis (y)
    pts = sheared_box(4, 3, 2).reshape(-1, 3)
    with np.errstate(all="raise"):
        got = Motion(**kw, **{name: v}).apply(pts)
        ref = Motion(**kw, **{name: direction}).apply(pts)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("motion,match", [
    ("axis = [0, 0, 0]", "motion.axis: must not be the zero vector"),
    ("axis = [0.0, -0.0, 0.0]", "motion.axis: must not be the zero vector"),
    ('axis = "001"', r"motion.axis: expected 3 numbers \[x, y, z\], got '001'"),
    ("axis = [true, 0, 0]", r"motion.axis: expected 3 numbers"),
    ('about = ["0", 0, 0]', r"motion.about: expected 3 numbers"),
    ("translate = [nan, 0, 0]", r"motion.translate: expected 3 finite numbers"),
    ("span_axis = [0, inf, 0]", r"motion.span_axis: expected 3 finite numbers"),
    ("span = 5e-324\nbend = 0.1", r"motion.span: 5e-324 is too small"),
    ("span = 5e-324", r"motion.span: 5e-324 is too small"),
    ("span = 1e-300\nbend = 1e300", r"motion.span: 1e-300 is too small"),
    ("span = 0", r"motion.span: must be > 0"),
    ("bend = nan", "motion.bend: expected a finite number"),
    ("rotate = true", "motion.rotate: expected a number, got True"),
    ("rotate = " + "9" * 400, "motion.rotate: expected a finite number"),
    ("translate = [0.0, 0.01, " + "1" * 400 + "]", r"motion.translate: expected 3 finite numbers"),
    ('deformation = "bend"\namplitude = nan', "motion.amplitude: expected a finite number"),
    ("bend = 0.1\ndirection = [0, 1e-200, 0]", "motion.direction: must not be parallel"),
])
def test_bad_motions_are_refused_at_load_naming_the_key(tmp_path, motion, match):
    (tmp_path / "g.x").write_bytes(b"")
    p = tmp_path / "c.toml"
    p.write_text(f'grid = "g.x"\n[motion]\n{motion}\n')
    with pytest.raises(CaseError, match=match) as info:
        load_case(p)
    assert str(p) in str(info.value)


def test_a_motion_that_overflows_on_the_geometry_is_a_case_error_not_a_warning():
    pts = sheared_box(4, 3, 2).reshape(-1, 3) * 1e10
    with pytest.raises(CaseError, match=r"motion: moves \d+ point\(s\) to non-finite positions"):
        Motion(twist=1e308).apply(pts)           # pytest turns any RuntimeWarning into an error


def test_case_file_not_utf8_or_nested_too_deeply(tmp_path):
    p = tmp_path / "c.toml"
    p.write_bytes(b'grid = "g.x"\n# \xff\n')
    with pytest.raises(CaseError, match=r"c\.toml:2: not UTF-8"):
        load_case(p, check_grid=False)
    p.write_text('grid = "g.x"\nwalls = ' + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(CaseError, match=r"c\.toml"):
        load_case(p, check_grid=False)
