import numpy as np
import pytest

from tfi_quat import Block, Grid, GridValueError
from tfi_quat.grid import face_index

from conftest import annulus, sheared_box


def test_block_is_fortran_float64_and_keeps_plot3d_order():
    xyz = np.ascontiguousarray(sheared_box(4, 3, 2)).astype(np.float32)
    b = Block(xyz)
    assert b.xyz.dtype == np.float64 and b.xyz.flags.f_contiguous
    assert b.dims == (4, 3, 2)
    # Plot3D whole-block order: all x (i fastest), then all y, then all z
    flat = b.xyz.ravel(order="K")
    np.testing.assert_array_equal(flat[:24], b.xyz[..., 0].ravel(order="F"))
    np.testing.assert_array_equal(flat[24:48], b.xyz[..., 1].ravel(order="F"))


def test_block_does_not_copy_fortran_float64_unless_asked():
    xyz = sheared_box()
    assert Block(xyz).xyz is xyz
    assert Block(xyz, copy=True).xyz is not xyz


def test_block_2d_inputs():
    b = Block(np.ones((3, 4, 2)))
    assert b.dims == (3, 4, 1)
    assert np.all(b.z == 0)
    assert Grid([b]).ndim == 2


@pytest.mark.parametrize("shape", [(3, 4, 5), (3, 4, 5, 2), (0, 4, 5, 3), (3, 4, 5, 3, 1)])
def test_block_bad_shapes(shape):
    with pytest.raises(GridValueError, match="block"):
        Block(np.zeros(shape))


def test_block_nonfinite_is_an_error_naming_the_point():
    xyz = sheared_box()
    xyz[2, 1, 0, 1] = np.nan
    with pytest.raises(GridValueError, match=r"\(3, 2, 1\).*component y"):
        Block(xyz, name="wing")
    assert np.isnan(Block(xyz, allow_nonfinite=True).xyz).any()


def test_iblank_checked_and_stored_int32():
    xyz = sheared_box(3, 3, 2)
    b = Block(xyz, iblank=np.ones((3, 3, 2), dtype=np.int64))
    assert b.iblank.dtype == np.int32 and b.iblank.flags.f_contiguous
    with pytest.raises(GridValueError, match="iblank shape"):
        Block(xyz, iblank=np.ones((3, 3)))
    with pytest.raises(GridValueError, match="integers"):
        Block(xyz, iblank=np.full((3, 3, 2), 0.5))


def test_grid_ndim_rules():
    assert Grid([annulus()]).ndim == 2
    assert Grid([sheared_box()]).ndim == 3
    assert Grid([annulus()], ndim=3).ndim == 3
    with pytest.raises(GridValueError, match="nk == 1"):
        Grid([sheared_box()], ndim=2)
    lifted = annulus()
    lifted[..., 2] = 1.0
    with pytest.raises(GridValueError, match="z == 0"):
        Grid([lifted], ndim=2)
    with pytest.raises(GridValueError, match="at least one"):
        Grid([])
    with pytest.raises(GridValueError, match="ndim"):
        Grid([sheared_box()], ndim=4)


def test_faces_and_bbox():
    b = Block(sheared_box(5, 4, 3))
    assert b.face("imin").shape == (4, 3, 3)
    assert b.face("jmax").shape == (5, 3, 3)
    assert b.face(5).shape == (5, 4, 3)
    np.testing.assert_array_equal(b.face("kmax"), b.xyz[:, :, -1])
    lo, hi = Grid([b]).bbox()
    np.testing.assert_array_equal(lo, b.xyz.reshape(-1, 3).min(0))
    with pytest.raises(GridValueError, match="unknown face"):
        face_index("top")


def test_copy_is_deep_and_equal():
    g = Grid([sheared_box(), sheared_box(3, 3, 3)])
    h = g.copy()
    assert h == g
    h[0].xyz[0, 0, 0, 0] += 1.0
    assert h != g


@pytest.mark.parametrize("bad", [np.zeros((2, 2, 2, 3), dtype=complex), np.full((2, 2, 2, 3), "1.0"),
                                 np.zeros((2, 2, 2, 3), dtype=bool), np.zeros((2, 2, 2, 3), dtype=object)])
def test_block_rejects_non_real_dtypes(bad):
    with pytest.raises(GridValueError, match=rf"block 'b': xyz must be real numbers, got dtype {bad.dtype}"):
        Block(bad, name="b")


def test_integer_and_float32_coordinates_become_float64():
    b = Block(np.arange(24, dtype=np.int16).reshape(2, 2, 2, 3))
    assert b.xyz.dtype == np.float64 and b.xyz.flags.f_contiguous and b.xyz[1, 1, 1, 2] == 23


@pytest.mark.parametrize("bad", [np.inf, -np.inf])
def test_block_infinite_is_an_error_too(bad):
    xyz = sheared_box()
    xyz[0, 3, 2, 2] = bad
    with pytest.raises(GridValueError, match=r"block 'w': 1 non-finite .*\(1, 4, 3\).*component z"):
        Block(xyz, name="w")


def test_grid_wraps_arrays_with_names_and_keeps_block_names():
    g = Grid([sheared_box(), Block(sheared_box(2, 2, 2), name="tip")])
    assert [b.name for b in g] == ["block1", "tip"]
    assert g.npoints == 60 + 8 and g.dims == [(5, 4, 3), (2, 2, 2)] and not g.has_iblank


def test_error_classes():
    import tfi_quat
    from tfi_quat import errors
    assert issubclass(tfi_quat.GridFormatError, ValueError)
    assert issubclass(tfi_quat.GridFormatError, errors.TfiQuatError)
    assert issubclass(GridValueError, ValueError) and issubclass(GridValueError, errors.TfiQuatError)
    assert issubclass(errors.OverwriteError, FileExistsError)
