"""HDF5 grid files: layout contract, round trips, partial reads, bad input."""

from __future__ import annotations

import io
import os
import tempfile
import time
import tracemalloc

import h5py
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import tfi_quat
from tfi_quat import FACES, Block, Grid, GridFormatError, GridValueError, OverwriteError
from tfi_quat.io import format_for, hdf5
from tfi_quat.io.hdf5 import HDF5Format
from tfi_quat.grid import face_axis

from conftest import annulus, sheared_box


# ----------------------------------------------------------------------------- helpers

def two_block_grid(iblank=True):
    b1 = Block(sheared_box(5, 4, 3), name="wing")
    ib = (np.arange(6 * 2 * 7).reshape(6, 2, 7) % 3 - 1) if iblank else None
    b2 = Block(sheared_box(6, 2, 7, seed=1) + 10.0, iblank=ib, name="wake")
    return Grid([b1, b2])


def write_read(path, grid, **kw):
    """Write ``grid``, read it back, check the input grid was not changed."""
    before = [(b.xyz.copy(), None if b.iblank is None else b.iblank.copy()) for b in grid]
    hdf5.write(path, grid, **kw)
    for b, (xyz, ib) in zip(grid, before):
        np.testing.assert_array_equal(b.xyz, xyz)
        if ib is not None:
            np.testing.assert_array_equal(b.iblank, ib)
    return hdf5.read(path)


class CountingFile(io.FileIO):
    """A file object that counts the bytes h5py reads through it."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.nread = 0

    def readinto(self, b):
        n = super().readinto(b)
        self.nread += n or 0
        return n

    def read(self, n=-1):
        data = super().read(n)
        self.nread += len(data)
        return data


def big_block_file(path, dims=(80, 60, 50), compression=None):
    """A small block, then a large-ish one (5.8 MB), then another small one."""
    small = Block(sheared_box(4, 3, 2), name="small")
    rng = np.random.default_rng(7)
    big = Block(np.asfortranarray(rng.random(dims + (3,))), name="big")
    grid = Grid([small, big, small.copy()])
    hdf5.write(path, grid, compression=compression)
    return grid


def assert_same_grid(a: Grid, b: Grid):
    assert a.ndim == b.ndim and len(a) == len(b)
    for x, y in zip(a, b):
        assert x.name == y.name
        assert x.xyz.dtype == np.float64 and x.xyz.flags.f_contiguous
        assert x.xyz.tobytes(order="F") == y.xyz.tobytes(order="F")  # bit-exact, -0.0 included
        assert (x.iblank is None) == (y.iblank is None)
        if x.iblank is not None:
            assert x.iblank.dtype == np.int32 and x.iblank.flags.f_contiguous
            np.testing.assert_array_equal(x.iblank, y.iblank)


# ----------------------------------------------------------------------------- round trips

@given(
    dims=st.lists(st.tuples(st.integers(1, 6), st.integers(1, 5), st.integers(1, 4)),
                  min_size=1, max_size=4),
    twod=st.booleans(),
    iblank=st.lists(st.booleans(), min_size=4, max_size=4),
    compression=st.sampled_from([None, "gzip"]),
    names=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_round_trip_is_bit_exact(dims, twod, iblank, compression, names, seed):
    rng = np.random.default_rng(seed)
    blocks = []
    for n, (ni, nj, nk) in enumerate(dims):
        nk = 1 if twod else nk
        xyz = np.asfortranarray(rng.normal(size=(ni, nj, nk, 3)) * 10.0 ** rng.integers(-8, 8))
        if twod:
            xyz[..., 2] = 0.0
        xyz.flat[0] = -0.0
        ib = rng.integers(-2, 3, size=(ni, nj, nk)) if iblank[n] else None
        blocks.append(Block(xyz, ib, name=f"b{n}" if names else None))
    grid = Grid(blocks, 2 if twod else 3)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "g.h5")
        back = write_read(path, grid, compression=compression)
        assert_same_grid(back, grid)
        assert back.ndim == grid.ndim
        assert back.source_path == path
        assert isinstance(back.source_format, HDF5Format)
        assert back.source_format.compression == compression
        for b in range(len(grid)):
            assert hdf5.read_block(path, b) == grid[b]
            for f in FACES:
                np.testing.assert_array_equal(hdf5.read_face(path, b, f), grid[b].face(f))


def test_2d_grid_round_trip(tmp_path):
    grid = Grid([annulus(), annulus(5, 3)])
    back = write_read(tmp_path / "a.hdf5", grid)
    assert back.ndim == 2
    assert_same_grid(back, grid)


def test_registered_for_its_extensions(tmp_path):
    grid = two_block_grid()
    for ext in (".h5", ".hdf5", ".hdf", ".H5"):
        p = tmp_path / f"g{ext}"
        tfi_quat.write(p, grid)
        assert h5py.is_hdf5(p)
        assert_same_grid(tfi_quat.read(p), grid)
    assert format_for(like=tfi_quat.read(tmp_path / "g.h5")).name == "hdf5"
    assert format_for(like=HDF5Format()).name == "hdf5"


# ----------------------------------------------------------------------------- layout contract

def test_layout_matches_the_documentation(tmp_path):
    grid = two_block_grid()
    grid.source_path = "/data/wing.x"
    p = tmp_path / "g.h5"
    hdf5.write(p, grid)
    with h5py.File(p, "r") as f:
        # HDF5 1.10 file-format objects: superblock version 3, checksummed metadata
        assert f.id.get_create_plist().get_version()[0] == 3
        # strings: fixed-length UTF-8 (kept in the checksummed object header), bytes in h5py
        text = {k: f.attrs[k].decode() for k in ("format", "creator", "created", "source")}
        for k in text:
            info = h5py.check_string_dtype(f.attrs.get_id(k).dtype)
            assert (info.encoding, info.length) == ("utf-8", len(text[k]))
        assert text["format"] == "tfi_quat-grid"
        assert f.attrs["version"] == 1
        assert f.attrs["ndim"] == 3
        assert f.attrs["nblocks"] == 2
        assert text["creator"] == f"tfi_quat {tfi_quat.__version__}"
        assert text["created"].endswith("Z") and text["created"][:2] == "20"
        assert text["source"] == "/data/wing.x"
        assert list(f["blocks"]) == ["000001", "000002"]
        for n, b in enumerate(grid):
            g = f["blocks"][f"{n + 1:06d}"]
            assert g.attrs["name"].decode() == b.name
            assert list(g.attrs["dims"]) == list(b.dims)
            ds = g["xyz"]
            ni, nj, nk = b.dims
            assert ds.shape == (3, nk, nj, ni) and ds.dtype == np.float64
            assert ds.chunks is None  # HDF5 contiguous layout
            i, j, k = ni - 1, nj // 2, nk - 1
            assert ds[1, k, j, i] == b.xyz[i, j, k, 1]
        assert "iblank" not in f["blocks/000001"]
        ib = f["blocks/000002/iblank"]
        assert ib.shape == (7, 2, 6) and ib.dtype == np.int32
        np.testing.assert_array_equal(ib[()], grid[1].iblank.T)
        offset = f["blocks/000002/xyz"].id.get_offset()
    # the block's bytes lie in the file in the Plot3D whole-block order
    raw = np.fromfile(p, dtype="<f8", count=grid[1].npoints * 3, offset=offset)
    assert raw.tobytes() == grid[1].xyz.tobytes(order="F")


def test_reads_a_file_built_from_the_documented_layout(tmp_path):
    """A file written with plain h5py (not by tfi_quat) following docs/formats.md."""
    xyz = sheared_box(4, 3, 2)
    p = tmp_path / "hand.h5"
    with h5py.File(p, "w") as f:
        f.attrs.update(format="tfi_quat-grid", version=1, ndim=3, nblocks=1)
        g = f.create_group("blocks/000001")
        g.attrs["name"] = "hand"
        g.attrs["dims"] = np.array([4, 3, 2], dtype=np.int32)
        # C-order (3, nk, nj, ni) built explicitly, float32 accepted
        g["xyz"] = np.transpose(xyz, (3, 2, 1, 0)).astype(np.float32)
        g["iblank"] = np.ones((2, 3, 4), dtype=np.int8)
    grid = hdf5.read(p)
    np.testing.assert_array_equal(grid[0].xyz, xyz.astype(np.float32))
    assert grid[0].name == "hand" and grid[0].iblank.dtype == np.int32
    assert np.all(grid[0].iblank == 1) and grid[0].iblank.shape == (4, 3, 2)


def test_read_allocates_only_the_grid(tmp_path):
    """HDF5 fills the Fortran arrays in place: no temporary copy of the coordinates."""
    grid = Grid([Block(sheared_box(100, 50, 40))])
    p = tmp_path / "g.h5"
    hdf5.write(p, grid)
    nbytes = grid[0].xyz.nbytes
    tracemalloc.start()
    try:
        back = hdf5.read(p)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert back == grid
    assert nbytes <= peak < 1.1 * nbytes


# ----------------------------------------------------------------------------- compression

def test_gzip_compression_and_like(tmp_path):
    x = np.linspace(0, 1, 40)
    xyz = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1)
    grid = Grid([Block(np.asfortranarray(xyz))])
    plain, packed = tmp_path / "plain.h5", tmp_path / "packed.h5"
    hdf5.write(plain, grid)
    hdf5.write(packed, grid, compression="gzip", compression_level=6)
    assert packed.stat().st_size < 0.5 * plain.stat().st_size
    with h5py.File(packed, "r") as f:
        ds = f["blocks/000001/xyz"]
        assert ds.compression == "gzip" and ds.compression_opts == 6 and ds.shuffle
        assert ds.chunks == (1, 40, 40, 40)
    back = hdf5.read(packed)
    assert back.source_format == HDF5Format("gzip", 6, True)
    assert_same_grid(back, grid)
    # like= keeps the compression; explicit arguments override it
    again = tmp_path / "again.h5"
    tfi_quat.write(again, back, like=back)
    assert hdf5.info(again).format == HDF5Format("gzip", 6, True)
    hdf5.write(again, back, like=back, compression=False, overwrite=True)
    assert hdf5.info(again).format == HDF5Format()
    hdf5.write(again, back, like=back, compression_level=1, overwrite=True)
    assert hdf5.info(again).format == HDF5Format("gzip", 1, True)


@pytest.mark.parametrize("kw", [{"compression": "lzf"}, {"compression": "gzip", "compression_level": 12},
                                {"compression": True, "compression_level": 2.5}])
def test_bad_compression_arguments(tmp_path, kw):
    with pytest.raises(GridValueError, match="compression"):
        hdf5.write(tmp_path / "g.h5", two_block_grid(), **kw)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("shape, chunks", [
    ((3, 50, 60, 80), (1, 40, 40, 40)), ((3, 1, 300, 500), (1, 1, 256, 256)),
    ((3, 4, 1000, 9), (1, 4, 1000, 9)), ((3, 1, 1, 10**6), (1, 1, 1, 65536)),
    ((7, 2, 6), (7, 2, 6)), ((3, 1, 2, 3), (1, 1, 2, 3))])
def test_chunks_are_near_cubic_and_bounded(shape, chunks):
    assert hdf5._chunks(shape) == chunks
    assert np.prod(chunks) <= 1 << 16


# ----------------------------------------------------------------------------- partial reads

@pytest.mark.parametrize("compression", [None, "gzip"])
def test_read_face_reads_only_the_face(tmp_path, monkeypatch, compression):
    p = tmp_path / "big.h5"
    monkeypatch.setattr(hdf5, "_CHUNK_VALUES", 4096)  # 16**3: several chunks per axis
    grid = big_block_file(p, compression=compression)
    big = grid[1]
    face_bytes = {"imin": 60 * 50 * 24, "jmin": 80 * 50 * 24, "kmin": 80 * 60 * 24}
    for face in FACES:
        with CountingFile(p, "rb") as fh:
            got = hdf5.read_face(fh, 1, face)
            nread = fh.nread
        np.testing.assert_array_equal(got, big.face(face))
        assert got.flags.f_contiguous and got.dtype == np.float64
        if compression is None:
            # the face's own bytes plus file metadata, nothing of the block's interior
            assert nread < face_bytes[face[0] + "min"] + 64 * 1024, (face, nread)
        else:
            # only the chunks along the face, not the rest of the block
            with h5py.File(p, "r") as f:
                chunks = f["blocks/000002/xyz"].chunks
            axis = 3 - face_axis(face)[0]  # dataset axes (c, k, j, i)
            shape = (3, 50, 60, 80)
            n_face = np.prod([-(-n // c) for a, (n, c) in enumerate(zip(shape, chunks)) if a != axis])
            chunk_bytes = 8 * np.prod(chunks)
            assert nread < 1.01 * n_face * chunk_bytes + 64 * 1024, (face, nread)
            assert chunks == (1, 16, 16, 16)
            assert nread < 0.4 * big.xyz.nbytes, (face, nread)
    tracemalloc.start()
    try:
        hdf5.read_face(p, "big", "imax")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 0.1 * big.xyz.nbytes


def test_read_block_reads_only_that_block(tmp_path):
    p = tmp_path / "big.h5"
    grid = big_block_file(p)
    with CountingFile(p, "rb") as fh:
        b = hdf5.read_block(fh, 0)
        nread = fh.nread
    assert b == grid[0] and b.name == "small"
    assert nread < 64 * 1024  # the big block's 5.8 MB are not touched
    with CountingFile(p, "rb") as fh:
        assert hdf5.read_block(fh, 1) == grid[1]
        assert fh.nread < grid[1].xyz.nbytes + 64 * 1024
    with CountingFile(p, "rb") as fh:
        inf = hdf5.info(fh)
        assert fh.nread < 64 * 1024
    assert inf.dims == [(4, 3, 2), (80, 60, 50), (4, 3, 2)]
    assert inf.names == ["small", "big", "small"] and inf.iblank == [False] * 3
    assert inf.npoints == grid.npoints and inf.nblocks == 3 and inf.ndim == 3


def test_read_block_ignores_broken_other_blocks(tmp_path):
    """A NaN on block 2's kmin face makes read() fail; the rest still reads."""
    p = tmp_path / "g.h5"
    grid = big_block_file(p)
    with h5py.File(p, "r+") as f:
        f["blocks/000002/xyz"][0, 0, 4, 5] = np.nan  # (c, k, j, i)
    with pytest.raises(GridFormatError, match=r"block 2.*/blocks/000002/xyz.*\(6, 5, 1\).*component x"):
        hdf5.read(p)
    assert hdf5.read_block(p, 0) == grid[0]
    assert hdf5.read_block(p, -1) == grid[2]
    np.testing.assert_array_equal(hdf5.read_face(p, 1, "kmax"), grid[1].face("kmax"))
    with pytest.raises(GridFormatError, match=r"block 2 face kmin.*\(6, 5, 1\).*component x"):
        hdf5.read_face(p, 1, "kmin")
    back = hdf5.read(p, allow_nonfinite=True)
    assert np.isnan(back[1].xyz[5, 4, 0, 0])
    assert np.isnan(hdf5.read_face(p, 1, 4, allow_nonfinite=True)[5, 4, 0])


def test_read_block_by_name_and_bad_indices(tmp_path):
    p = tmp_path / "g.h5"
    grid = two_block_grid()
    hdf5.write(p, grid)
    assert hdf5.read_block(p, "wake") == grid[1]
    assert hdf5.read_block(p, np.int64(1)) == grid[1]
    with pytest.raises(GridValueError, match=r"block 2 out of range.*2 block"):
        hdf5.read_block(p, 2)
    with pytest.raises(GridValueError, match="no block named 'tail'"):
        hdf5.read_block(p, "tail")
    with pytest.raises(GridValueError, match="unknown face"):
        hdf5.read_face(p, 0, "lmin")


# ----------------------------------------------------------------------------- extra JSON

def test_extra_json_round_trip(tmp_path):
    p = tmp_path / "g.h5"
    extra = {"connectivity": [{"block1": 1, "range": [[1, 1], [1, 5]], "transform": [1, 2, 3]}],
             "note": "caf\u00e9"}
    hdf5.write(p, two_block_grid(), extra_json=extra)
    assert hdf5.read_extra(p) == extra
    assert hdf5.info(p).has_extra
    q = tmp_path / "none.h5"
    hdf5.write(q, two_block_grid())
    assert hdf5.read_extra(q) is None and not hdf5.info(q).has_extra


@pytest.mark.parametrize("extra", [[1, 2], {"x": np.float64}, {"x": float("nan")}])
def test_extra_json_must_be_a_json_object(tmp_path, extra):
    with pytest.raises(GridValueError, match="extra_json"):
        hdf5.write(tmp_path / "g.h5", two_block_grid(), extra_json=extra)
    assert not list(tmp_path.iterdir())


def test_read_extra_rejects_bad_json(tmp_path):
    p = tmp_path / "g.h5"
    hdf5.write(p, two_block_grid())
    with h5py.File(p, "r+") as f:
        f["extra"] = "{not json"
    with pytest.raises(GridFormatError, match=r"g.h5.*/extra is not valid JSON"):
        hdf5.read_extra(p)


# ----------------------------------------------------------------------------- safety

def test_never_overwrites_the_input_unless_asked(tmp_path):
    p = tmp_path / "g.h5"
    hdf5.write(p, two_block_grid())
    grid = hdf5.read(p)
    before = p.read_bytes()
    with pytest.raises(OverwriteError, match="input"):
        hdf5.write(p, grid)
    assert p.read_bytes() == before
    grid[0].xyz[0, 0, 0, 0] = 42.0
    hdf5.write(p, grid, overwrite=True)
    assert hdf5.read(p)[0].xyz[0, 0, 0, 0] == 42.0


def test_failed_write_leaves_target_untouched(tmp_path, monkeypatch):
    p = tmp_path / "g.h5"
    hdf5.write(p, two_block_grid())
    before = p.read_bytes()
    calls = []

    def failing(g, key, data, comp, level):
        calls.append(key)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        g.create_dataset(key, data=data)

    monkeypatch.setattr(hdf5, "_write_array", failing)
    with pytest.raises(OSError, match="No space"):
        hdf5.write(p, Grid([Block(sheared_box(3, 3, 3))] * 2))
    assert p.read_bytes() == before
    assert [q.name for q in tmp_path.iterdir()] == ["g.h5"]


def test_write_needs_a_grid(tmp_path):
    with pytest.raises(GridValueError, match="Grid"):
        hdf5.write(tmp_path / "g.h5", sheared_box())


# ----------------------------------------------------------------------------- bad input

def test_not_an_hdf5_file(tmp_path):
    p = tmp_path / "g.h5"
    p.write_text("3\n1 2 3\n")
    with pytest.raises(GridFormatError, match=r"g\.h5: not an HDF5 file"):
        tfi_quat.read(p)
    e = tmp_path / "empty.h5"
    e.write_bytes(b"")
    with pytest.raises(GridFormatError, match=r"empty\.h5: empty file"):
        hdf5.read(e)


def test_truncated_file(tmp_path):
    p = tmp_path / "g.h5"
    big_block_file(p)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(GridFormatError, match=r"g\.h5"):
        hdf5.read(p)


def _edit(path, fn):
    with h5py.File(path, "r+") as f:
        fn(f)


def _set_dims(f, dims):
    f["blocks/000002"].attrs["dims"] = np.array(dims)


def _replace(f, name, data):
    del f[name]
    f[name] = data


@pytest.mark.parametrize("edit, message", [
    (lambda f: f.attrs.__delitem__("format"), r"root group has no attribute 'format'"),
    (lambda f: f.attrs.__setitem__("format", "other-grid"), r"format = 'other-grid'"),
    (lambda f: f.attrs.__delitem__("version"), r"no attribute 'version'"),
    (lambda f: f.attrs.__setitem__("version", 2), r"layout version 2 is not supported"),
    (lambda f: f.attrs.__setitem__("version", "1"), r"'version' must be one integer"),
    (lambda f: f.attrs.__setitem__("ndim", 4), r"ndim = 4"),
    (lambda f: f.attrs.__delitem__("nblocks"), r"no attribute 'nblocks'"),
    (lambda f: f.attrs.__setitem__("nblocks", 3), r"block 3: group /blocks/000003 is missing"),
    (lambda f: f.__delitem__("blocks"), r"group /blocks is missing"),
    (lambda f: f["blocks/000002"].attrs.__delitem__("dims"), r"block 2 .*no attribute 'dims'"),
    (lambda f: _set_dims(f, [6, 2]), r"block 2 .*dims must be 3 integers"),
    (lambda f: _set_dims(f, [6, 0, 7]), r"block 2 .*must all be >= 1"),
    (lambda f: _set_dims(f, [6, 3, 7]), r"block 2 .*/blocks/000002/xyz: shape \(3, 7, 2, 6\) does not "
                                        r"match .*\(3, 7, 3, 6\)"),
    (lambda f: f["blocks/000002"].__delitem__("xyz"), r"block 2 .*dataset 'xyz' is missing"),
    (lambda f: _replace(f, "blocks/000002/xyz", np.zeros((3, 7, 2, 6), dtype=np.int32)),
     r"block 2.*/blocks/000002/xyz: dtype int32 is not a float"),
    (lambda f: _replace(f, "blocks/000002/iblank", np.zeros((7, 2, 6))),
     r"block 2.*/blocks/000002/iblank: dtype float64 is not an integer"),
    (lambda f: _replace(f, "blocks/000002/iblank", np.zeros((6, 2, 7), dtype=np.int32)),
     r"/blocks/000002/iblank: shape \(6, 2, 7\) does not match"),
    (lambda f: f.attrs.__setitem__("ndim", 2), r"block 1 .*2-D grid needs nk = 1"),
])
def test_bad_layout_is_named(tmp_path, edit, message):
    p = tmp_path / "bad.h5"
    hdf5.write(p, two_block_grid())
    _edit(p, edit)
    with pytest.raises(GridFormatError, match=r"bad\.h5: .*" + message):
        hdf5.read(p)


def test_links_are_not_followed(tmp_path):
    """A block group that is an external link: refused by name, the other blocks still read."""
    p = tmp_path / "bad.h5"
    hdf5.write(p, two_block_grid())
    with h5py.File(p, "r+") as f:
        del f["blocks/000002"]
        f["blocks/000002"] = h5py.ExternalLink("nowhere.h5", "/blocks/000002")
    for fn in (hdf5.read, hdf5.info, lambda q: hdf5.read_block(q, 1), lambda q: hdf5.read_face(q, 1, "imin")):
        with pytest.raises(GridFormatError, match=r"bad\.h5: block 2: /blocks/000002 is an external link, "
                                                  r"not a group \(links are not followed\)"):
            fn(p)
    assert hdf5.read_block(p, 0) == two_block_grid()[0]


def test_2d_grid_with_z_is_an_error(tmp_path):
    p = tmp_path / "bad.h5"
    hdf5.write(p, Grid([Block(sheared_box(3, 3, 1))], 3))
    _edit(p, lambda f: f.attrs.__setitem__("ndim", 2))
    with pytest.raises(GridFormatError, match=r"bad\.h5: .*z == 0"):
        hdf5.read(p)


@pytest.mark.parametrize("chunked", [False, True])
def test_incomplete_dataset_is_an_error(tmp_path, chunked):
    """A dataset declared with its full shape but never (fully) written."""
    p = tmp_path / "bad.h5"
    hdf5.write(p, two_block_grid(iblank=False))

    def edit(f):
        del f["blocks/000002/xyz"]
        ds = f.create_dataset("blocks/000002/xyz", shape=(3, 7, 2, 6), dtype="f8",
                              chunks=(1, 7, 2, 6) if chunked else None)
        if chunked:
            ds[0] = 1.0  # one of three chunks written
    _edit(p, edit)
    with pytest.raises(GridFormatError, match=r"bad\.h5: block 2.*/blocks/000002/xyz.*incomplete"):
        hdf5.read(p)
    assert hdf5.read_block(p, 0) == two_block_grid()[0]


def test_infinite_values(tmp_path):
    p = tmp_path / "g.h5"
    grid = two_block_grid()
    grid[0].xyz[1, 2, 0, 2] = np.inf
    hdf5.write(p, grid)
    with pytest.raises(GridFormatError, match=r"g\.h5: block 1, dataset /blocks/000001/xyz: 1 non-finite"
                                              r".*\(2, 3, 1\).*component z"):
        hdf5.read(p)
    assert np.isinf(hdf5.read_block(p, 0, allow_nonfinite=True).xyz[1, 2, 0, 2])
    # huge finite values whose sum overflows are not mistaken for infinities
    grid[0].xyz[1, 2, 0, 2] = 1.7e308
    grid[0].xyz[2, 2, 0, 2] = 1.7e308
    hdf5.write(p, grid, overwrite=True)
    assert hdf5.read(p)[0].xyz[2, 2, 0, 2] == 1.7e308


def test_source_date_epoch_makes_files_reproducible(tmp_path, monkeypatch):
    """SOURCE_DATE_EPOCH fixes the `created` stamp: two writes give the same bytes."""
    grid = two_block_grid()
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    hdf5.write(tmp_path / "a.h5", grid)
    time.sleep(1.1)                             # a later second would show in `created`
    hdf5.write(tmp_path / "b.h5", grid)
    assert (tmp_path / "a.h5").read_bytes() == (tmp_path / "b.h5").read_bytes()
    with h5py.File(tmp_path / "a.h5", "r") as f:
        assert f.attrs["created"].decode() == "2023-11-14T22:13:20Z"
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "yesterday")
    with pytest.raises(GridValueError, match="SOURCE_DATE_EPOCH='yesterday'"):
        hdf5.write(tmp_path / "c.h5", grid)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.h5", "b.h5"]
