"""Neutral Map Files: hand-written files, round trips, conventions, errors."""

from __future__ import annotations

import numpy as np
import pytest

from tfi_quat import ConnectivityError, Grid
from tfi_quat.spec import PatchSpec
from tfi_quat.topology import Connectivity, connect
from tfi_quat.topology.nmf import nmf_kind

from conftest import sheared_box
from test_topology import ORIENTS_3D, c_grid, check_interfaces, extrude, orient

HAND_3D = """\
# ===== Neutral Map File (hand-written) =====
# Block#   IDIM   JDIM   KDIM
  2
  1   5   5   4
  2   5   5   4
# Type          B1 F1  S1 E1  S2 E2   B2 F2  S1 E1  S2 E2  Swap
'ONE_TO_ONE'     1  4   1  5   1  4    2  5   1  4   1  5  TRUE
'VISCOUS'        1  5   1  4   1  5
'SYMMETRY-Z'     1  1   1  5   1  5
'SYMMETRY-Z'     2  1   1  5   1  5
FARFIELD         1  3   1  5   1  4    # the inflow
farfield         1  6   1  4   1  5
FARFIELD         1  2   1  5   1  5
FARFIELD         2  2   1  5   1  5
FARFIELD         2  3   1  5   1  4
FARFIELD         2  4   1  5   1  4
FARFIELD         2  6   1  4   1  5
"""


def two_blocks_swapped():
    """Block 2 holds the second half of a box with i and j exchanged."""
    big = sheared_box(9, 5, 4)
    return Grid([np.asfortranarray(big[:5]), orient(big[4:], (1, 0, 2), (False, False, False))])


def test_hand_written_3d_file_with_swap(tmp_path):
    g = two_blocks_swapped()
    path = tmp_path / "hand.nmf"
    path.write_text(HAND_3D)
    conn = Connectivity.from_nmf(path)
    assert conn.ndim == 3 and conn.dims == [(5, 5, 4), (5, 5, 4)]
    it, = conn.interfaces
    # block 1 imax (J primary, K secondary) <-> block 2 jmin (K primary, I secondary), J along I: swapped
    assert it.master == PatchSpec(0, "imax", ((0, 4), (0, 3)))
    assert it.slave == PatchSpec(1, "jmin", ((0, 4), (0, 3)))
    assert it.transform == (2, 1, 3)
    check_interfaces(g, conn, tol=0.0)
    assert connect(g).interfaces == conn.interfaces        # the search agrees with the file
    kinds = {(p.spec.block, p.spec.face): (p.kind, p.name) for p in conn.patches}
    assert kinds[(0, "jmin")] == ("wall", "VISCOUS")
    assert kinds[(0, "kmin")] == ("symmetry", "SYMMETRY-Z")
    assert kinds[(0, "jmax")] == ("fixed", "farfield")
    assert all(p.origin == "file" for p in conn.patches)
    # with the grid: the same kinds; the k = 1 faces of the sheared box are warped, which is noted
    conn_g = Connectivity.from_nmf(path, g)
    assert conn_g == conn
    assert sum("symmetry" in n and "not planar" in n for n in conn_g.notes) == 2


def test_hand_written_2d_construct2d_style_c_grid(tmp_path):
    g = Grid([c_grid()])
    ni = g[0].dims[0]
    path = tmp_path / "cgrid.nmf"
    path.write_text(f"""\
# Construct2D style: faces 1..4 = imin imax jmin jmax
1
1 {ni} 4 1
ONE_TO_ONE 1 3 1 5 1 1 1 3 {ni} {ni - 4} 1 1 FALSE
VISCOUS 1 3 5 {ni - 4} 1 1
FARFIELD 1 4 1 {ni} 1 1
OUTFLOW 1 1 1 4 1 1
OUTFLOW 1 2 1 4 1 1
""")
    conn = Connectivity.from_nmf(path, g)
    assert conn.ndim == 2
    assert conn == connect(g, walls=["1:jmin"])
    it, = conn.interfaces
    assert it.transform == (-1, -2, 3)
    check_interfaces(g, conn)


@pytest.mark.parametrize("name,line,perm,flips,cut_axis", [
    # block 1 imax (J, K) <-> block 2 imin (J, K), J reversed: S1 > E1 on the second side
    ("reversed", "ONE_TO_ONE 1 4 1 5 1 4  2 3 5 1 1 4  FALSE", (0, 1, 2), (False, True, False), 0),
    # j faces: primary K, secondary I; block 2's I reversed
    ("j faces", "ONE_TO_ONE 1 6 1 4 1 9  2 5 1 4 9 1  FALSE", (0, 1, 2), (True, False, False), 1),
    # block 1 imax (J, K) <-> block 2 jmin (K, I): J along I (swapped), K reversed
    ("swapped and reversed", "ONE_TO_ONE 1 4 1 5 1 4  2 5 4 1 1 5  TRUE", (1, 0, 2), (False, False, True), 0),
])
def test_hand_written_one_to_one_lines_match_the_geometry(tmp_path, name, line, perm, flips, cut_axis):
    """S/E of the second side are the indices matching the first side's start/end corners."""
    big = sheared_box(9, 5, 4)
    if cut_axis == 0:
        a, b = np.asfortranarray(big[:5]), orient(big[4:], perm, flips)
    else:
        a, b = np.asfortranarray(big[:, :3]), orient(big[:, 2:], perm, flips)
    g = Grid([a, b])
    dims = "\n".join(f"{n + 1} {d[0]} {d[1]} {d[2]}" for n, d in enumerate(g.dims))
    path = tmp_path / "one.nmf"
    path.write_text(f"# {name}\n2\n{dims}\n{line}\n")
    conn = Connectivity.from_nmf(path)
    assert conn.interfaces == connect(g).interfaces
    check_interfaces(g, conn, tol=0.0)
    # the writer gives the same line back
    conn.to_nmf(tmp_path / "back.nmf")
    written = [ln.split() for ln in (tmp_path / "back.nmf").read_text().splitlines() if ln.startswith("ONE_TO_ONE")]
    assert written == [line.split()]


def test_faces_the_file_leaves_out_are_derived_with_the_grid(tmp_path):
    g = Grid([extrude(c_grid(), nk=3)])
    ni = g[0].dims[0]
    path = tmp_path / "part.nmf"
    # only the wake cut and the airfoil (j = 1: K primary, I secondary)
    path.write_text(f"1\n1 {ni} 4 3\nONE_TO_ONE 1 5 1 3 1 5  1 5 1 3 {ni} {ni - 4}  FALSE\n"
                    f"WALL 1 5 1 3 5 {ni - 4}\n")
    bare = Connectivity.from_nmf(path)
    assert len(bare.patches) == 1 and len(bare.interfaces) == 1
    conn = Connectivity.from_nmf(path, g)
    kinds = {p.spec.face: (p.kind, p.origin) for p in conn.patches}
    assert kinds["jmin"] == ("wall", "file")
    assert kinds["jmax"] == kinds["imin"] == kinds["imax"] == ("fixed", "default")
    assert kinds["kmin"] == kinds["kmax"] == ("symmetry", "auto")         # planar and touching the wall
    assert conn == connect(g, walls=["1:jmin"])


def test_one_to_one_that_does_not_match_the_grid_names_file_and_line(tmp_path):
    big = sheared_box(9, 5, 4)
    g = Grid([np.asfortranarray(big[:5]), orient(big[4:], (0, 1, 2), (False, True, False))])
    path = tmp_path / "wrong.nmf"
    # J runs backwards on block 2; this line says forwards (a valid file, the wrong grid)
    path.write_text("2\n1 5 5 4\n2 5 5 4\n# interfaces\nONE_TO_ONE 1 4 1 5 1 4  2 3 1 5 1 4  FALSE\n")
    assert Connectivity.from_nmf(path).interfaces[0].transform == (1, 2, 3)      # no grid: not checked
    with pytest.raises(ConnectivityError, match=r"wrong.nmf:5: ONE_TO_ONE: 1:imax:1-5,1-4 -> 2:imin:1-5,1-4 "
                                                r"\[\+1,\+2,\+3\] does not match the grid: point \(5, 1, \d\) of block 1 "
                                                r"is [0-9.]+ from its partner \(1, 1, \d\) of block 2"):
        Connectivity.from_nmf(path, g)
    with pytest.raises(ConnectivityError, match=r"wrong.nmf: block 2: connectivity is for 5 x 5 x 4"):
        Connectivity.from_nmf(path, Grid([g[0].xyz, np.asfortranarray(big[3:])]))


@pytest.mark.parametrize("perm,flips", ORIENTS_3D)
def test_round_trip_connect_to_nmf_from_nmf(tmp_path, perm, flips):
    big = sheared_box(9, 5, 4)
    g = Grid([np.asfortranarray(big[:5]), orient(big[4:], perm, flips)])
    conn = connect(g, walls=["1:jmin"], symmetry=["1:kmin"])
    path = tmp_path / "map.nmf"
    conn.to_nmf(path)
    assert Connectivity.from_nmf(path, g) == conn
    assert Connectivity.from_nmf(path).interfaces == conn.interfaces
    text = path.read_text()
    assert "ONE_TO_ONE" in text and "WALL" in text and "SYMMETRY " in text


@pytest.mark.parametrize("convention", ["3d", "2d"])
def test_round_trip_2d_c_grid_both_numberings(tmp_path, convention):
    g = Grid([c_grid()])
    conn = connect(g, walls=["1:jmin"])
    path = tmp_path / "c.nmf"
    conn.to_nmf(path, convention=convention)
    back = Connectivity.from_nmf(path, g)
    assert back == conn
    faces = {int(line.split()[2]) for line in path.read_text().splitlines() if line and not line.startswith("#")
             and len(line.split()) > 6}
    assert max(faces) == (4 if convention == "2d" else 6)


def test_round_trip_collapsed_and_extruded(tmp_path):
    g = Grid([extrude(c_grid(), nk=3)])
    conn = connect(g, walls=["1:jmin"])
    path = tmp_path / "e.nmf"
    conn.to_nmf(path)
    assert Connectivity.from_nmf(path, g) == conn


def test_types_and_kind_table():
    assert nmf_kind("'VISCOUS'") == "wall" and nmf_kind("inviscid_wall") == "wall"
    assert nmf_kind("SYMMETRY-Y") == "symmetry" and nmf_kind("sym_z") == "symmetry"
    assert nmf_kind("FARFIELD") == "fixed" and nmf_kind("subsonic-inflow") == "fixed"
    assert nmf_kind("ONE-TO-ONE") == "interface" and nmf_kind("POLE_DIR1") == "collapsed"
    assert nmf_kind("PATCHED") is None and nmf_kind("XSPLINE") is None
    assert nmf_kind("XSPLINE", {"xspline": "fixed"}) == "fixed"


@pytest.mark.parametrize("body,match", [
    ("2\n1 5 5 4\n", "2 block"),
    ("x\n", "number of blocks"),
    ("1\n1 5\n", "IDIM JDIM"),
    ("1\n1 5 5 4\nPATCHED 1 1 1 5 1 5\n", r"bad.nmf:4: unknown boundary type 'PATCHED'"),
    ("1\n1 5 5 4\nWALL 1 7 1 5 1 5\n", r"bad.nmf:4: face 7"),
    ("1\n1 5 5 4\nWALL 1 1 1 6 1 5\n", r"bad.nmf:4: range 1-6,1-5 on face 1 \(kmin\) of block 1 exceeds"),
    ("1\n1 5 5 4\nWALL 2 1 1 5 1 5\n", r"bad.nmf:4: block 2 does not exist"),
    ("1\n1 5 5 4\nWALL 1 1 1 5\n", r"bad.nmf:4: WALL needs 6 integers"),
    ("1\n1 5 5 4\nONE_TO_ONE 1 3 1 5 1 4 1 4 1 4 1 4 FALSE\n", r"bad.nmf:4: ONE_TO_ONE sides differ in size"),
    ("1\n1 5 5 4\nONE_TO_ONE 1 3 1 5 1 4 1 4 1 5 1 4 MAYBE\n", r"bad.nmf:4: swap flag"),
    ("1\n1 5 5 4\nWALL 1 1 1 5 1 5\nFARFIELD 1 1 3 5 1 2\n",
     r"bad.nmf:5: overlaps the entry on line 4 \(block 1 face kmin, face 1 in the file\)"),
    ("1\n1 5 5 4\nONE_TO_ONE 1 3 1 5 1 4 1 4 1 5 1 4 FALSE\nWALL 1 4 1 2 1 2\n",
     r"bad.nmf:5: overlaps the entry on line 4 \(block 1 face imax, face 4"),
    ("2\n1 5 5 4\n2 5 5 4\nONE_TO_ONE 1 4 1 5 1 4 2 3 1 5 1 4 FALSE\nONE_TO_ONE 1 4 1 3 1 4 2 3 1 3 1 4 FALSE\n",
     r"bad.nmf:6: overlaps the entry on line 5 \(block 1 face imax"),
])
def test_bad_files_name_file_and_line(tmp_path, body, match):
    path = tmp_path / "bad.nmf"
    path.write_text("# header\n" + body)
    with pytest.raises(ConnectivityError, match=match):
        Connectivity.from_nmf(path)


def test_types_argument_and_overwrite(tmp_path):
    path = tmp_path / "t.nmf"
    path.write_text("1\n1 5 5 4\nXSPLINE 1 1 1 5 1 5\n")
    conn = Connectivity.from_nmf(path, types={"XSPLINE": "fixed"})
    assert conn.patches[0].kind == "fixed" and conn.patches[0].name == "XSPLINE"
    with pytest.raises(ConnectivityError, match="kind 'moving'"):
        Connectivity.from_nmf(path, types={"XSPLINE": "moving"})
    with pytest.raises(Exception, match="exists"):
        conn.to_nmf(path)
    conn.to_nmf(path, overwrite=True)
    assert Connectivity.from_nmf(path) == conn


def test_checked_against_the_grid(tmp_path):
    path = tmp_path / "hand.nmf"
    path.write_text(HAND_3D)
    with pytest.raises(ConnectivityError, match="2 block"):
        Connectivity.from_nmf(path, Grid([sheared_box(5, 5, 4)]))
