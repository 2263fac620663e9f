import numpy as np
import pytest

from tfi_quat import CaseError, Grid
from tfi_quat.grid import face_shape
from tfi_quat.spec import PatchSpec, parse_patch_spec

from conftest import sheared_box


def test_parse_whole_face_and_range():
    assert parse_patch_spec("1:jmin") == PatchSpec(0, "jmin")
    p = parse_patch_spec(" 3:IMAX:2-5,1-4 ")
    assert p == PatchSpec(2, "imax", ((1, 4), (0, 3)))
    assert str(p) == "3:imax:2-5,1-4"
    assert parse_patch_spec(str(p)) == p
    assert parse_patch_spec("1:jmin:1-129").range == ((0, 128), (0, 0))


@pytest.mark.parametrize("text", ["jmin", "0:jmin", "1:top", "1:jmin:5-2,1-1", "1:jmin:a-b,1-2",
                                  "1:jmin:1-2,1-2,1-2", "x:jmin"])
def test_parse_rejects(text):
    with pytest.raises(CaseError, match="patch"):
        parse_patch_spec(text)


def test_resolve_checks_the_grid():
    g = Grid([sheared_box(5, 4, 3)])
    assert PatchSpec(0, "imin").resolve(g).range == ((0, 3), (0, 2))
    assert face_shape((5, 4, 3), "kmax") == (5, 4)
    with pytest.raises(CaseError, match="exceeds"):
        PatchSpec(0, "imin", ((0, 4), (0, 2))).resolve(g)
    with pytest.raises(CaseError, match="block"):
        PatchSpec(1, "imin").resolve(g)
    g2 = Grid([np.zeros((3, 3, 1, 3))], ndim=2)
    with pytest.raises(CaseError, match="no k faces"):
        PatchSpec(0, "kmin").resolve(g2)
