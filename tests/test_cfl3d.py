"""Grid files and input-deck sections for NASA's CFL3D (tfi_quat.io.cfl3d, convert/connect --for cfl3d).

The file layout is checked by an independent reader (``scipy.io.FortranFile``)
and the deck's 1-1 lines by walking their index ranges the way CFL3D does
(``isva1``/``isva2``, start to end) over the file's own points.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.io import FortranFile

import tfi_quat as tq
from tfi_quat.case import load_case
from tfi_quat.cli import main
from tfi_quat.io import cfl3d
from tfi_quat.quality import cell_volumes
from tfi_quat.topology import connect

from conftest import annulus, sheared_box

GRIDS = Path(__file__).resolve().parent.parent / "grids"
CGRID = GRIDS / "naca0012_c_257x65.x"
TWO_BLOCK = GRIDS / "two_block_65x33.x"


def run_cli(capsys, *argv):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def fortran_records(path):
    """(block count, dims (n, 3), coordinate records) read by scipy, which checks every marker."""
    with FortranFile(path, "r", header_dtype=np.dtype("<u4")) as f:
        nb = f.read_ints(np.dtype("<i4"))
        dims = f.read_ints(np.dtype("<i4")).reshape(-1, 3)
        recs = [f.read_reals(np.dtype("<f8")) for _ in range(int(nb[0]))]
        with pytest.raises(Exception):      # nothing after the last block
            f.read_record(np.uint8)
    return int(nb[0]), dims, recs


def xyz_of(record, dims):
    """A block record as (idim, jdim, kdim, 3), i fastest (CFL3D's rp3d loop order)."""
    n = int(np.prod(dims))
    assert record.size == 3 * n
    return np.stack([record[c * n:(c + 1) * n].reshape(tuple(dims), order="F") for c in range(3)], axis=-1)


def three_d_two_blocks():
    """Two 3-D blocks sharing a face, the second with its i and j exchanged and j reversed."""
    box = sheared_box(7, 4, 3)
    b2 = np.asfortranarray(np.transpose(box[3:, ::-1], (1, 0, 2, 3)))
    return tq.Grid([tq.Block(box[:4]), tq.Block(b2)])


# ---------------------------------------------------------------- file layout

def test_2d_grid_is_one_block_of_two_planes_in_the_x_z_plane(tmp_path):
    g = tq.read(CGRID)
    p = tmp_path / "c.cfl3d"
    tq.write(p, g, target="cfl3d")
    raw = p.read_bytes()
    # record markers: 4-byte little-endian, framing the block count, then the dims
    assert raw[:12] == np.array([4, 1, 4], "<i4").tobytes()
    assert raw[12:32] == np.array([12, 2, 257, 65, 12], "<i4").tobytes()
    n = 2 * 257 * 65
    assert len(raw) == 12 + 20 + 8 + 3 * 8 * n
    nb, dims, recs = fortran_records(p)
    assert nb == 1 and dims.tolist() == [[2, 257, 65]]
    X = xyz_of(recs[0], dims[0])
    x, y = g[0].xyz[:, :, 0, 0], g[0].xyz[:, :, 0, 1]
    for s, span in enumerate((0.0, -1.0)):       # span first, decreasing with i
        assert np.array_equal(X[s, :, :, 0], x)
        assert np.array_equal(X[s, :, :, 2], y)
        assert np.all(X[s, :, :, 1] == span)


def test_2d_mapping_is_right_handed_in_cfl3d_index_order(tmp_path):
    # CFL3D stops on a left-handed grid: every cell of the written 3-D block has a positive volume
    for path in (CGRID, TWO_BLOCK):
        p = tmp_path / "g.cfl3d"
        tq.write(p, tq.read(path), target="cfl3d")
        _, dims, recs = fortran_records(p)
        for d, r in zip(dims, recs):
            vol = cell_volumes(np.asfortranarray(xyz_of(r, d)), ndim=3)
            assert vol.min() > 0


def test_3d_multiblock_layout_and_bit_identical_round_trip(tmp_path):
    g = tq.Grid([tq.Block(sheared_box(5, 4, 3)), tq.Block(sheared_box(3, 6, 2, seed=1) + 7.0)])
    before = [b.xyz.copy() for b in g]
    p = tmp_path / "box.x"
    tq.write(p, g, target="cfl3d")
    nb, dims, recs = fortran_records(p)
    assert nb == 2 and dims.tolist() == [[5, 4, 3], [3, 6, 2]]
    for b, d, r in zip(g, dims, recs):
        assert np.array_equal(xyz_of(r, d), b.xyz)      # as it is: same indices and axes
    back = tq.read(p, target="cfl3d")
    assert back == g and back.ndim == 3
    assert back.source_format == cfl3d.CFL3DFormat(3) and back.source_path == str(p)
    assert all(np.array_equal(a, b.xyz) for a, b in zip(before, g))      # input untouched


def test_2d_multiblock_round_trip_is_bit_identical(tmp_path):
    g = tq.read(TWO_BLOCK)
    p = tmp_path / "two.cfl3d"
    tq.write(p, g, target="cfl3d")
    back = tq.read(p, target="cfl3d")
    assert back.ndim == 2 and back.dims == g.dims and back == g
    assert all(b.dims[2] == 1 and not np.any(b.xyz[..., 2]) for b in back)
    assert back.source_format == cfl3d.CFL3DFormat(2)


def test_iblank_is_not_written(tmp_path):
    b = tq.Block(sheared_box(4, 3, 2), iblank=np.ones((4, 3, 2), np.int32))
    p = tmp_path / "ib.x"
    tq.write(p, tq.Grid([b]), target="cfl3d")
    _, dims, recs = fortran_records(p)
    assert recs[0].size == 3 * 24
    back = tq.read(p, target="cfl3d")
    assert back[0].iblank is None and np.array_equal(back[0].xyz, b.xyz)


def test_ndim_chooses_between_a_mapped_2d_grid_and_a_3d_grid_of_two_planes(tmp_path):
    g = tq.read(TWO_BLOCK)
    p = tmp_path / "two.cfl3d"
    tq.write(p, g, target="cfl3d")
    as3 = tq.read(p, target="cfl3d", ndim=3)
    assert as3.ndim == 3 and as3.dims == [(2, 65, 17), (2, 17, 65)]
    assert tq.read(p, target="cfl3d", ndim=2) == g
    # a genuine 3-D grid is not taken for a 2-D one, and ndim=2 names the block that is not
    q = tmp_path / "box.x"
    tq.write(q, tq.Grid([sheared_box(2, 4, 3)]), target="cfl3d")
    assert tq.read(q, target="cfl3d").ndim == 3
    with pytest.raises(tq.GridFormatError, match=r"box\.x: block 1 \(2 x 4 x 3\) is not a 2-D grid"):
        tq.read(q, target="cfl3d", ndim=2)


# ---------------------------------------------------------------- errors and like=

def test_left_handed_2d_block_is_refused_by_name_and_nothing_is_written(tmp_path):
    left = tq.Grid([annulus()])               # i counter-clockwise, j outwards: clockwise cells
    assert cell_volumes(left[0]).max() < 0
    with pytest.raises(tq.GridValueError, match=r"block 1: its cells turn clockwise.*reverse its i or j"):
        tq.write(tmp_path / "a.x", left, target="cfl3d")
    assert list(tmp_path.iterdir()) == []
    right = tq.Grid([np.asfortranarray(annulus()[:, ::-1])])
    tq.write(tmp_path / "a.x", right, target="cfl3d")
    assert tq.read(tmp_path / "a.x", target="cfl3d") == right


@pytest.mark.parametrize("variant", [dict(encoding="binary"), dict(encoding="fortran", precision=4),
                                     dict(encoding="fortran", marker_size=8),
                                     dict(encoding="fortran", endian=">"),
                                     dict(encoding="fortran", records="coordinate"),
                                     dict(encoding="ascii")])
def test_other_plot3d_variants_are_not_cfl3d_files(tmp_path, variant):
    p = tmp_path / "other.x"
    tq.write(p, tq.Grid([sheared_box()]), **variant)
    with pytest.raises(tq.GridFormatError, match=r"other\.x: not a CFL3D grid file \(CFL3D reads a "
                                                 r"PLOT3D-type grid: Fortran unformatted"):
        tq.read(p, target="cfl3d")


def test_non_grid_file_gives_a_format_error_naming_it(tmp_path):
    p = tmp_path / "notes.txt"
    p.write_text("hello\n")
    with pytest.raises(tq.GridFormatError, match=r"notes\.txt: not a CFL3D grid file"):
        tq.read(p, target="cfl3d")
    with pytest.raises(FileNotFoundError):
        tq.read(tmp_path / "missing.x", target="cfl3d")


def test_like_keeps_its_meaning_and_target_takes_no_variant_options(tmp_path):
    g = tq.read(CGRID)
    tq.write(tmp_path / "same.x", g, like=g)              # the shipped C-stream encoding, as before
    assert (tmp_path / "same.x").read_bytes() == CGRID.read_bytes()
    tq.write(tmp_path / "c.x", g, target="cfl3d")
    r = tq.read(tmp_path / "c.x", target="cfl3d")
    tq.write(tmp_path / "again.x", r, like=r)             # a grid read for CFL3D is written for it again
    assert (tmp_path / "again.x").read_bytes() == (tmp_path / "c.x").read_bytes()
    with pytest.raises(tq.GridFormatError, match="do not give like= too"):
        tq.write(tmp_path / "d.x", g, target="cfl3d", like=g)
    with pytest.raises(tq.GridFormatError, match=r"the option\(s\) precision do not apply"):
        tq.write(tmp_path / "d.x", g, target="cfl3d", precision=4)
    with pytest.raises(tq.GridFormatError, match="unknown target 'su2'"):
        tq.write(tmp_path / "d.x", g, target="su2")
    with pytest.raises(tq.GridFormatError, match=r"unknown format 'cfl3d'.*target='cfl3d'"):
        tq.write(tmp_path / "d.x", g, format="cfl3d")
    with pytest.raises(tq.GridFormatError, match="contradicts"):
        tq.read(tmp_path / "c.x", format="hdf5", target="cfl3d")
    assert not (tmp_path / "d.x").exists()


def test_refuses_to_overwrite_the_input(tmp_path):
    p = tmp_path / "c.x"
    tq.write(p, tq.read(CGRID), target="cfl3d")
    r = tq.read(p, target="cfl3d")
    with pytest.raises(tq.OverwriteError, match="input file"):
        tq.write(p, r, target="cfl3d")
    tq.write(p, r, target="cfl3d", overwrite=True)


# ---------------------------------------------------------------- input deck

def deck_one_to_one(text):
    """The 1-1 lines of a deck: [(side 1, side 2)], each (block, start, end, isva) 1-based."""
    lines = text.splitlines()
    at = lines.index("   1-1 blocking data:")
    nbli = int(lines[at + 2])
    first = [ln.split() for ln in lines[at + 4:at + 4 + nbli]]
    second = [ln.split() for ln in lines[at + 5 + nbli:at + 5 + 2 * nbli]]

    def side(v):
        v = [int(t) for t in v]
        return v[1], v[2:5], v[5:8], v[8:10]
    return [(side(a), side(b)) for a, b in zip(first, second)]


def walk(xyz, start, end, isva):
    """Points of a 1-1 side as CFL3D walks it: isva1 outer... both from start to end."""
    idx = [np.array([s - 1]) for s in start]
    for ax in isva:
        s, e = start[ax - 1], end[ax - 1]
        idx[ax - 1] = np.arange(s - 1, e - 2 if e < s else e, -1 if e < s else 1)
    a, b = isva[0] - 1, isva[1] - 1
    pts = xyz[np.ix_(*idx)]
    return np.moveaxis(pts.reshape([len(i) for i in idx] + [3]), [a, b], [0, 1]).reshape(
        len(idx[a]), len(idx[b]), 3)


def deck_segments(text):
    """{face: [(grid, segment, bctype, r1s, r1e, r2s, r2e, ndata)]} of the LT14-LT19 lines."""
    out, face = {}, None
    for ln in text.splitlines():
        head = ln.split(":")[0].strip()
        if head in ("i0", "idim", "j0", "jdim", "k0", "kdim") and ln.startswith(head + ":"):
            face = head
            out[face] = []
        elif ln.startswith("#"):
            face = None
        elif face and ln.split() and ln.split()[0].isdigit():
            out[face].append([int(t) for t in ln.split()])
    return out


@pytest.mark.parametrize("make, walls", [
    (lambda: tq.read(CGRID), ["1:jmin:65-193"]),
    (lambda: tq.read(TWO_BLOCK), ["1:jmin"]),
    (three_d_two_blocks, []),
])
def test_deck_one_to_one_lines_match_the_written_file(tmp_path, make, walls):
    g = make()
    conn = connect(g, walls=walls)
    assert conn.interfaces
    text = cfl3d.input_deck(conn)
    p = tmp_path / "g.x"
    tq.write(p, g, target="cfl3d")
    blocks = [b.xyz for b in tq.read(p, target="cfl3d", ndim=3)]
    pairs = deck_one_to_one(text)
    assert len(pairs) == len(conn.interfaces)
    for (b1, s1, e1, v1), (b2, s2, e2, v2) in pairs:
        assert all(s <= e for s, e in zip(s1, e1))                    # first side ascending
        p1, p2 = walk(blocks[b1 - 1], s1, e1, v1), walk(blocks[b2 - 1], s2, e2, v2)
        assert p1.shape == p2.shape and p1.shape[0] * p1.shape[1] > 1
        assert np.array_equal(p1, p2)


def test_deck_segments_tile_every_face_with_the_documented_bctypes():
    g = tq.read(CGRID)
    text = cfl3d.input_deck(connect(g, walls=["1:jmin:65-193"]))
    assert "# index mapping (2-D): CFL3D (i, j, k) = (span, our i, our j); X = x, Z = y" in text
    seg = deck_segments(text)
    rows = {f: [(s[2], s[3], s[4], s[5], s[6]) for s in v] for f, v in seg.items()}
    assert rows["k0"] == [(0, 1, 2, 1, 65), (1005, 1, 2, 65, 193), (0, 1, 2, 193, 257)]
    assert rows["kdim"] == [(1003, 1, 2, 1, 257)]
    assert rows["j0"] == rows["jdim"] == [(1003, 1, 2, 1, 65)]
    assert rows["i0"] == rows["idim"] == [(1002, 1, 257, 1, 65)]
    lt13 = text.splitlines()[text.splitlines().index(
        "      grid     nbci0   nbcidim     nbcj0   nbcjdim     nbck0   nbckdim    iovrlp") + 1]
    assert lt13.split() == ["1", "1", "1", "1", "1", "3", "1", "0"]
    assert "       2     257      65" in text.splitlines()      # LT8: idim jdim kdim
    # wake cut: the NASA NACA 4412 deck's form, j 1..65 against j 257..193, isva 1 2 on both sides
    assert deck_one_to_one(text) == [((1, [1, 1, 1], [2, 65, 1], [1, 2]), (1, [1, 257, 1], [2, 193, 1], [1, 2]))]


def test_deck_3d_segments_tile_each_face_once():
    g = three_d_two_blocks()
    text = cfl3d.input_deck(connect(g))
    seg = deck_segments(text)
    running = {"i": (1, 2), "j": (0, 2), "k": (0, 1)}
    for face, rows in seg.items():
        for n, d in enumerate(g.dims):
            a, b = running[face[0]]
            cover = np.zeros((d[a] - 1, d[b] - 1), int)
            for r in (r for r in rows if r[0] == n + 1):
                cover[r[3] - 1:r[4] - 1, r[5] - 1:r[6] - 1] += 1
            assert np.all(cover == 1), (face, n)
    assert "# index mapping (3-D): CFL3D (i, j, k) = our (i, j, k)" in text


def test_bctype_overrides_and_2004_data_lines():
    conn = connect(tq.read(CGRID), walls=["1:jmin:65-193"])
    text = cfl3d.input_deck(conn, {"wall": 2004, "fixed": 1000})
    lines = text.splitlines()
    at = next(n for n, ln in enumerate(lines) if ln.split()[:3] == ["1", "2", "2004"])
    assert lines[at].split()[-1] == "2" and lines[at + 2].split() == ["0.", "0."]
    assert "1003" not in "".join(ln for ln in lines if not ln.startswith("#"))
    for bad, msg in (({"wal": 2004}, "unknown patch kind 'wal'"), ({"wall": 2005}, "wall=2005 is not a bctype")):
        with pytest.raises(tq.ConnectivityError, match=msg):
            cfl3d.input_deck(conn, bad)


# ---------------------------------------------------------------- command line

def test_cli_convert_for_and_from_cfl3d(tmp_path, capsys):
    out = tmp_path / "c.cfl3d"
    rc, text, err = run_cli(capsys, "convert", CGRID, out, "--for", "cfl3d")
    assert rc == 0 and "cfl3d: CFL3D PLOT3D-type grid" in text and "(2-D: as two planes)" in text
    _, dims, _ = fortran_records(out)
    assert dims.tolist() == [[2, 257, 65]]
    back = tmp_path / "back.x"
    rc, text, err = run_cli(capsys, "convert", out, back, "--from", "cfl3d")
    assert rc == 0 and back.read_bytes() == CGRID.read_bytes()
    rc, text, err = run_cli(capsys, "info", out, "--from", "cfl3d")
    assert rc == 0 and "257 x 65 x 1" in text
    rc, text, err = run_cli(capsys, "convert", CGRID, tmp_path / "x.x", "--for", "cfl3d", "--single")
    assert rc == 2 and "--for cfl3d writes one fixed variant; --single/--double do not apply" in err
    rc, text, err = run_cli(capsys, "convert", CGRID, tmp_path / "x.x", "--for", "cfl3d", "--connect")
    assert rc == 2 and "connect GRID --for cfl3d" in err
    rc, text, err = run_cli(capsys, "info", CGRID, "--from", "cfl3d")
    assert rc == 2 and "naca0012_c_257x65.x: not a CFL3D grid file" in err
    assert not (tmp_path / "x.x").exists()


def test_cli_connect_for_cfl3d(tmp_path, capsys):
    rc, text, err = run_cli(capsys, "connect", CGRID, "--wall", "1:jmin:65-193", "--for", "cfl3d",
                            "--bc", "wall=2004")
    assert rc == 0 and err == ""
    assert text == cfl3d.input_deck(connect(tq.read(CGRID), walls=["1:jmin:65-193"]), {"wall": 2004})
    rc, text, err = run_cli(capsys, "connect", CGRID, "--for", "cfl3d", "-o", tmp_path / "map.json")
    assert rc == 0 and text.splitlines()[-1] == f"# wrote {tmp_path / 'map.json'}"
    assert (tmp_path / "map.json").exists()
    rc, text, err = run_cli(capsys, "connect", CGRID, "--bc", "wall=2004")
    assert rc == 2 and "--bc applies to --for cfl3d" in err
    rc, text, err = run_cli(capsys, "connect", CGRID, "--for", "cfl3d", "--bc", "wall")
    assert rc == 2 and "expected KIND=BCTYPE" in err


# ---------------------------------------------------------------- docs/coupling.md's sign statement

def test_rotate_plus_about_z_is_nose_down_for_flow_along_x():
    # the shipped case file's motion (rotate = 10 about +z through the quarter chord, then a plunge)
    motion = load_case(GRIDS / "naca0012_c_257x65.toml", check_grid=False).motion
    assert motion.rotate == 10.0 and tuple(motion.axis) == (0.0, 0.0, 1.0)
    wall = tq.read(CGRID)[0].xyz[64:193, 0, 0]
    le, te = wall[np.argmin(wall[:, 0])], wall[np.argmax(wall[:, 0])]
    new_le, new_te = motion.apply(np.array([le, te]))
    assert new_le[1] - le[1] < new_te[1] - te[1]            # the nose drops relative to the tail
    # the chord, from the leading edge aft, now climbs 10 deg: flow along +x (CFL3D: +X, with
    # Z = y up) meets it at an angle of attack 10 deg lower
    chord = new_te - new_le
    assert np.degrees(np.arctan2(chord[1], chord[0])) == pytest.approx(10.0)
    rigid = tq.rigid_motion(10.0, axis=(0, 0, 1), about=(0.25, 0, 0))
    assert np.allclose(rigid(np.array([le, te])) + [0, 0.05, 0], [new_le, new_te])


def test_to_and_from_cfl3d_in_memory():
    g = tq.read(TWO_BLOCK)
    mapped = cfl3d.to_cfl3d(g)
    assert mapped.ndim == 3 and mapped.dims == [(2, 65, 17), (2, 17, 65)]
    assert cfl3d.from_cfl3d(mapped) == g
    box = tq.Grid([sheared_box()])
    assert cfl3d.to_cfl3d(box) is box and cfl3d.from_cfl3d(box) is box
    with pytest.raises(tq.GridValueError, match="needs the 3-D grid CFL3D indexes, got a 2-D grid"):
        cfl3d.from_cfl3d(g)
    with pytest.raises(tq.GridValueError, match="block 1: 1 x 5 points"):
        cfl3d.to_cfl3d(tq.Grid([np.zeros((1, 5, 1, 3))], 2))


def test_cli_from_cfl3d_takes_no_variant_options(tmp_path, capsys):
    out = tmp_path / "c.cfl3d"
    tq.write(out, tq.read(CGRID), target="cfl3d")
    rc, text, err = run_cli(capsys, "convert", out, tmp_path / "b.x", "--from", "cfl3d", "--in-endian", "big")
    assert rc == 2 and "--from cfl3d reads one fixed variant; --in-endian do not apply" in err
    rc, text, err = run_cli(capsys, "info", out, "--from", "cfl3d", "--format", "plot3d")
    assert rc == 2 and "--format do not apply" in err
