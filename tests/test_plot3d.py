"""Plot3D reader and writer: round trips of every variant, foreign files, bad input."""

from __future__ import annotations

import itertools
import os
import struct
import tempfile
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import tfi_quat
from tfi_quat import Block, Grid, GridFormatError, OverwriteError
from tfi_quat.io import plot3d
from tfi_quat.io.plot3d import Plot3DFormat, detect, read, write

from conftest import annulus, sheared_box


# ---------------------------------------------------------------- helpers

def _snapshot(grid):
    return [(b.xyz.copy(), None if b.iblank is None else b.iblank.copy()) for b in grid], \
        grid.ndim, grid.source_format, grid.source_path


def write_read(grid: Grid, path, fmt: Plot3DFormat | None = None, **read_kw) -> Grid:
    """Write ``grid`` as ``fmt`` and read it back; check the input was not mutated.

    The file is read twice: as exactly ``fmt`` (returned), and with detection,
    which must find ``fmt`` or, when the file fits several variants, a
    variant preferred to ``fmt`` that really fits.
    """
    before = _snapshot(grid)
    kw = {} if fmt is None else {"like": fmt, "ndim": fmt.ndim, "iblank": fmt.iblank}
    write(path, grid, **kw)
    after = _snapshot(grid)
    for (x0, i0), (x1, i1) in zip(before[0], after[0]):
        assert np.array_equal(x0, x1, equal_nan=True)
        assert (i0 is None and i1 is None) or np.array_equal(i0, i1)
    assert before[1:] == after[1:]
    if fmt is None:
        return read(path, **read_kw)
    want = fmt.canonical()
    exact = read(path, format=want, **read_kw)
    assert exact.source_format == want
    assert exact.source_path == os.fspath(path)
    found = detect(path, **({"precision": 4} if want.encoding == "ascii" and want.precision == 4 else {}))
    if found != want:
        assert found._key() < want._key(), (found, want)
        read(path, format=found, allow_nonfinite=True)   # the preferred variant really fits
    return exact


def expected_xyz(xyz, fmt):
    return xyz.astype(np.float32).astype(np.float64) if fmt.precision == 4 else xyz


def assert_same_grid(got: Grid, grid: Grid, fmt: Plot3DFormat):
    assert got.ndim == fmt.ndim
    assert len(got) == len(grid)
    for a, b in zip(got, grid):
        assert a.xyz.dtype == np.float64 and a.xyz.flags.f_contiguous
        want = expected_xyz(b.xyz, fmt)
        assert a.xyz.shape == want.shape
        # bit-exact, signed zeros included
        assert np.array_equal(a.xyz.view(np.int64), want.view(np.int64))
        if fmt.iblank:
            ib = b.iblank if b.iblank is not None else np.ones(b.dims, np.int32)
            assert a.iblank.dtype == np.int32 and np.array_equal(a.iblank, ib)
        else:
            assert a.iblank is None


def fortran_record(payload: bytes, endian="<", ms=4) -> bytes:
    mark = struct.pack(f"{endian}{'i' if ms == 4 else 'q'}", len(payload))
    return mark + payload + mark


# ---------------------------------------------------------------- strategies

formats = st.builds(
    Plot3DFormat,
    encoding=st.sampled_from(["binary", "fortran", "ascii"]),
    endian=st.sampled_from(["<", ">"]),
    precision=st.sampled_from([4, 8]),
    ndim=st.sampled_from([2, 3]),
    multiblock=st.booleans(),
    iblank=st.booleans(),
    records=st.sampled_from(["block", "coordinate"]),
    int_size=st.sampled_from([4, 8]),
    marker_size=st.sampled_from([4, 8]),
)


@st.composite
def grids_for(draw, fmt):
    nb = draw(st.integers(1, 3)) if fmt.multiblock else 1
    seed = draw(st.integers(0, 2 ** 32 - 1))
    rng = np.random.default_rng(seed)
    blocks = []
    for n in range(nb):
        ni, nj = draw(st.integers(1, 4)), draw(st.integers(1, 4))
        nk = 1 if fmt.ndim == 2 else draw(st.integers(1, 4))
        # up to 36 decades in one block (float32 detection refuses more than 2**128)
        mag = 10.0 ** rng.integers(-18, 18, size=(ni, nj, nk, 3))
        xyz = np.asfortranarray(rng.standard_normal((ni, nj, nk, 3)) * mag)
        xyz.ravel(order="K")[rng.random(xyz.size) < 0.1] = -0.0
        if fmt.ndim == 2:
            xyz[..., 2] = 0.0
        ib = rng.integers(-3, 4, size=(ni, nj, nk)).astype(np.int32) if draw(st.booleans()) else None
        blocks.append(Block(xyz, ib, name=f"b{n}"))
    return Grid(blocks, fmt.ndim)


@settings(max_examples=150)
@given(data=st.data(), fmt=formats)
def test_round_trip_every_variant(data, fmt):
    grid = data.draw(grids_for(fmt))
    with tempfile.TemporaryDirectory() as d:
        got = write_read(grid, Path(d) / "g.x", fmt)
    assert_same_grid(got, grid, fmt)


def _every_variant() -> list[Plot3DFormat]:
    """Every distinct variant (fields an encoding ignores at their defaults)."""
    out = {}
    for values in itertools.product(*(plot3d._CHOICES[n] for n in plot3d._FIELD_NAMES)):
        f = Plot3DFormat(**dict(zip(plot3d._FIELD_NAMES, values))).canonical()
        out[f] = None
    return list(out)


EVERY_VARIANT = _every_variant()


def test_every_variant_is_enumerated():
    # binary 2 endian x 2 int x 2 multiblock x 2 ndim x 2 precision x 2 iblank,
    # fortran that x 2 records x 2 marker sizes, ascii 2 x 2 x 2 x 2
    assert len(EVERY_VARIANT) == 64 + 256 + 16


@pytest.mark.parametrize("n", range(len(EVERY_VARIANT)),
                         ids=lambda n: EVERY_VARIANT[n].describe().replace(", ", "-"))
def test_round_trip_each_variant(tmp_path, n):
    """Each variant at least once, whatever hypothesis draws: 1 or 3 blocks, iblank in some."""
    fmt = EVERY_VARIANT[n]
    rng = np.random.default_rng(n)
    blocks = []
    for b in range(3 if fmt.multiblock else 1):
        dims = (int(rng.integers(1, 5)), int(rng.integers(1, 5)),
                1 if fmt.ndim == 2 else int(rng.integers(1, 5)))
        xyz = np.asfortranarray(rng.standard_normal(dims + (3,)) * 10.0 ** rng.integers(-18, 18, dims + (3,)))
        if fmt.ndim == 2:
            xyz[..., 2] = 0.0
        xyz.ravel(order="K")[0] = -0.0
        ib = rng.integers(-2, 3, size=dims).astype(np.int32) if b != 1 else None
        blocks.append(Block(xyz, ib))
    grid = Grid(blocks, fmt.ndim)
    assert_same_grid(write_read(grid, tmp_path / "g.x", fmt), grid, fmt)


@given(seed=st.integers(0, 2 ** 32 - 1), multiblock=st.booleans(), ndim=st.sampled_from([2, 3]))
def test_ascii_float64_round_trip_is_exact_for_awkward_values(seed, multiblock, ndim):
    rng = np.random.default_rng(seed)
    vals = np.concatenate([rng.standard_normal(20) * 10.0 ** rng.integers(-300, 300, 20),
                           [5e-324, -2.2250738585072014e-308, 1.7976931348623157e308, 0.1, 1 / 3]])
    xyz = np.zeros((len(vals), 1, 1, 3), order="F")
    xyz[:, 0, 0, 0] = vals
    xyz[:, 0, 0, 1] = vals[::-1]
    if ndim == 3:
        xyz[:, 0, 0, 2] = -vals
    grid = Grid([xyz], ndim)
    fmt = Plot3DFormat(encoding="ascii", ndim=ndim, multiblock=multiblock)
    with tempfile.TemporaryDirectory() as d:
        got = write_read(grid, Path(d) / "g.p3dfmt", fmt)
    assert_same_grid(got, grid, fmt)


def test_ascii_single_precision_reads_back_exact_after_float32_cast(tmp_path):
    grid = Grid([sheared_box(4, 3, 2)])
    p = tmp_path / "g.fmt"
    write(p, grid, encoding="ascii", precision=4)
    text = p.read_text()
    digits = [t.split("e")[0].lstrip("-").replace(".", "").lstrip("0") for t in text.split()]
    assert max(map(len, digits)) == 9
    got = read(p, precision=4)
    assert np.array_equal(got[0].xyz, grid[0].xyz.astype(np.float32).astype(np.float64))
    # detection keeps float64 (the text holds the digits, not the width)
    assert read(p).source_format.precision == 8


def test_binary_read_lands_file_bytes_in_fortran_arrays(tmp_path):
    xyz = sheared_box(6, 5, 4)
    p = tmp_path / "g.x"
    write(p, Grid([xyz, sheared_box(2, 3, 4)]))
    raw = np.fromfile(p, dtype="<f8", offset=4 + 24, count=xyz.size)
    g = read(p)
    assert g[0].xyz.flags.f_contiguous and g[0].xyz.dtype == np.float64
    assert np.array_equal(g[0].xyz.ravel(order="K"), raw)
    assert np.array_equal(g[0].xyz, xyz)


def test_large_read_uses_chunks_and_threads_and_stays_exact(tmp_path, monkeypatch):
    monkeypatch.setattr(plot3d, "_CHUNK", 1000)
    monkeypatch.setattr(plot3d, "_PARALLEL_BYTES", 1000)
    rng = np.random.default_rng(3)
    blocks = [np.asfortranarray(rng.random((17, 13, 11, 3))), np.asfortranarray(rng.random((9, 8, 7, 3)))]
    grid = Grid(blocks)
    for fmt in (Plot3DFormat(), Plot3DFormat(endian=">", precision=4, iblank=True),
                Plot3DFormat(encoding="fortran", records="coordinate", int_size=8, iblank=True)):
        got = write_read(grid, tmp_path / "g.x", fmt)
        assert_same_grid(got, grid, fmt)


def test_read_without_positioned_reads(tmp_path, monkeypatch):
    # platforms without os.pread/os.preadv: seek + read, one thread
    monkeypatch.setattr(plot3d, "_HAVE_PREAD", False)
    monkeypatch.setattr(plot3d, "_CHUNK", 100)
    monkeypatch.setattr(plot3d, "_PARALLEL_BYTES", 100)
    grid = Grid([sheared_box(9, 8, 7), Block(sheared_box(3, 2, 4), np.arange(24).reshape(3, 2, 4))])
    for fmt in (Plot3DFormat(iblank=True),
                Plot3DFormat(encoding="fortran", endian=">", precision=4, iblank=True)):
        assert_same_grid(write_read(grid, tmp_path / "g.x", fmt), grid, fmt)


@pytest.mark.parametrize("fmt", [Plot3DFormat(), Plot3DFormat(endian=">"),
                                 Plot3DFormat(precision=4, iblank=True),
                                 Plot3DFormat(encoding="fortran", iblank=True)])
def test_binary_read_peak_memory_is_the_grid_size(tmp_path, fmt):
    rng = np.random.default_rng(0)
    grid = Grid([np.asfortranarray(rng.random((100, 100, 50, 3))),
                 np.asfortranarray(rng.random((50, 40, 30, 3)))])
    p = tmp_path / "big.x"
    write(p, grid, like=fmt, iblank=fmt.iblank)
    size = sum(b.xyz.nbytes + (b.xyz.nbytes // 6 if fmt.iblank else 0) for b in grid)
    tracemalloc.start()
    try:
        g = read(p)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert g.source_format == fmt
    assert peak <= 1.1 * size, (peak, size)


# ---------------------------------------------------------------- foreign files

def test_reads_handmade_2d_single_block_ascii(tmp_path):
    # ni nj, then x(i, j) with i fastest, then y; any line layout, Fortran D exponents
    text = ("  3  2\n"
            " 0.0 1.0 2.0\n 0.0 1.0\n"
            "     2.5 0.0\n1.0D-30 0.0000000E+00 1.0 1.0 1.25\n")
    p = tmp_path / "airfoil.p2dfmt"
    p.write_text(text)
    g = read(p)
    assert g.source_format == Plot3DFormat(encoding="ascii", ndim=2, multiblock=False)
    assert g.ndim == 2 and g.dims == [(3, 2, 1)]
    assert np.array_equal(g[0].x[:, :, 0], [[0.0, 0.0], [1.0, 1.0], [2.0, 2.5]])
    assert np.array_equal(g[0].y[:, :, 0], [[0.0, 1.0], [1e-30, 1.0], [0.0, 1.25]])
    assert not g[0].z.any() and g[0].iblank is None


def test_reads_handmade_big_endian_fortran_multiblock_with_iblank(tmp_path):
    dims = [(3, 2, 2), (2, 2, 1)]
    rng = np.random.default_rng(1)
    payload = [fortran_record(struct.pack(">i", 2), ">"),
               fortran_record(struct.pack(">6i", *dims[0], *dims[1]), ">")]
    want = []
    for d in dims:
        n = d[0] * d[1] * d[2]
        xyz = rng.random((3, n))
        ib = rng.integers(-1, 3, n)
        want.append((xyz, ib))
        payload.append(fortran_record(xyz.astype(">f8").tobytes() + ib.astype(">i4").tobytes(), ">"))
    p = tmp_path / "wing.g"
    p.write_bytes(b"".join(payload))
    g = read(p)
    assert g.source_format == Plot3DFormat(encoding="fortran", endian=">", iblank=True)
    assert g.dims == dims
    for b, (xyz, ib) in zip(g, want):
        for c in range(3):
            assert np.array_equal(b.xyz[..., c].ravel(order="F"), xyz[c])
        assert np.array_equal(b.iblank.ravel(order="F"), ib)


def test_reads_handmade_fortran_three_records_per_block(tmp_path):
    dims = [(2, 3, 2), (4, 1, 2)]
    parts = [fortran_record(struct.pack("<i", 2)),
             fortran_record(struct.pack("<6i", *dims[0], *dims[1]))]
    want = []
    for m, d in enumerate(dims):
        n = d[0] * d[1] * d[2]
        xyz = np.arange(3 * n, dtype=float).reshape(3, n) + 100 * m
        want.append(xyz)
        parts += [fortran_record(xyz[c].astype("<f8").tobytes()) for c in range(3)]
    p = tmp_path / "old.xyz"
    p.write_bytes(b"".join(parts))
    g = read(p)
    assert g.source_format == Plot3DFormat(encoding="fortran", records="coordinate")
    for b, xyz in zip(g, want):
        assert np.array_equal(np.stack([b.xyz[..., c].ravel(order="F") for c in range(3)]), xyz)


def test_reads_handmade_c_binary_single_block_float32(tmp_path):
    ni, nj, nk = 4, 3, 2
    vals = (np.arange(3 * ni * nj * nk, dtype=np.float32) * np.float32(0.1)).astype("<f4")
    p = tmp_path / "box.bin"
    p.write_bytes(struct.pack("<3i", ni, nj, nk) + vals.tobytes())
    g = read(p)
    assert g.source_format == Plot3DFormat(precision=4, multiblock=False)
    n = ni * nj * nk
    for c in range(3):
        assert np.array_equal(g[0].xyz[..., c].ravel(order="F"), vals[c * n:(c + 1) * n].astype(float))


def test_reads_handmade_fortran_64bit_integers_and_markers(tmp_path):
    dims = (2, 2, 2)
    xyz = np.linspace(-1, 1, 24)
    ib = np.array([1, 0, 1, 1, 2, 1, -1, 1])
    data = fortran_record(struct.pack("<q", 1), ms=8) + fortran_record(struct.pack("<3q", *dims), ms=8) + \
        fortran_record(xyz.tobytes() + ib.astype("<i8").tobytes(), ms=8)
    p = tmp_path / "i8.x"
    p.write_bytes(data)
    g = read(p)
    assert g.source_format == Plot3DFormat(encoding="fortran", int_size=8, marker_size=8, iblank=True)
    assert np.array_equal(g[0].xyz.ravel(order="K"), xyz)
    assert np.array_equal(g[0].iblank.ravel(order="F"), ib)


# ---------------------------------------------------------------- detection

def _ambiguous_2d_file(path):
    """A 2-D single-block float64 file, 64-bit integers, that is also float32 with int64 IBLANK.

    Both variants take 16 bytes a point, so the sizes cannot tell them apart;
    neither can the contents here: x is dyadic (the low halves of its float64
    values are float32 zeros, the high halves plausible float32 values) and
    y = 0 (IBLANK 0 when read as int64).
    """
    xyz = np.zeros((3, 2, 1, 3), order="F")
    xyz[..., 0, 0] = [[1.0, 2.0], [3.0, 0.5], [0.25, 4.0]]
    write(path, Grid([xyz], 2), int_size=8, multiblock=False)
    return xyz


def test_equal_sizes_told_apart_by_the_contents(tmp_path):
    # 2-D, 64-bit integers: float64 without iblank and float32 with int64 iblank are
    # both 16 bytes a point; float32 pairs are no float64 coordinates (about 1e-150),
    # float64 coordinates no IBLANK codes
    grid = Grid([annulus(3, 2)], 2)
    p = tmp_path / "f32.x"
    write(p, grid, precision=4, iblank=True, int_size=8, multiblock=False)
    assert plot3d.detect_all(p) == [Plot3DFormat(precision=4, iblank=True, ndim=2, int_size=8,
                                                 multiblock=False)]
    q = tmp_path / "f64.x"
    write(q, grid, int_size=8, multiblock=False)
    assert plot3d.detect_all(q) == [Plot3DFormat(ndim=2, int_size=8, multiblock=False)]
    with pytest.raises(GridFormatError, match="IBLANK value .* is no blanking code"):
        read(q, precision=4)
    assert np.array_equal(read(p)[0].xyz, annulus(3, 2).astype(np.float32).astype(float))


def test_ambiguous_file_prefers_common_variant_and_override_picks_the_other(tmp_path):
    p = tmp_path / "amb.x"
    xyz = _ambiguous_2d_file(p)
    assert detect(p) == Plot3DFormat(precision=8, ndim=2, int_size=8, multiblock=False)
    assert np.array_equal(read(p)[0].xyz, xyz)
    g = read(p, precision=4)
    assert g.source_format == Plot3DFormat(precision=4, iblank=True, ndim=2, int_size=8, multiblock=False)
    assert np.all(g[0].iblank == 0)


def test_detect_all_lists_every_fit_preferred_first(tmp_path):
    p = tmp_path / "amb.x"
    _ambiguous_2d_file(p)
    both = [Plot3DFormat(precision=8, ndim=2, int_size=8, multiblock=False),
            Plot3DFormat(precision=4, iblank=True, ndim=2, int_size=8, multiblock=False)]
    assert plot3d.detect_all(p) == both
    assert plot3d.detect_all(p, iblank=True) == both[1:]
    q = tmp_path / "one.x"
    write(q, Grid([sheared_box()]), encoding="fortran")
    assert plot3d.detect_all(q) == [detect(q)] == [Plot3DFormat(encoding="fortran")]
    a = tmp_path / "t.fmt"
    # one 3-D block of one point, or single-block with IBLANK (one value a line, so that
    # either header ends at a line end)
    a.write_text("1\n" * 7)
    fits = plot3d.detect_all(a)
    assert fits == [Plot3DFormat(encoding="ascii"), Plot3DFormat(encoding="ascii", multiblock=False, iblank=True)]
    assert fits[0] == detect(a)
    for f in fits:
        assert read(a, format=f).source_format == f


def test_override_that_does_not_fit_is_an_error(tmp_path):
    p = tmp_path / "g.x"
    write(p, Grid([sheared_box()]))
    with pytest.raises(GridFormatError, match="g.x"):
        read(p, endian=">")
    with pytest.raises(GridFormatError, match="endian"):
        read(p, endian="middle")
    with pytest.raises(GridFormatError, match="colour"):
        read(p, colour="red")


def test_explicit_format_plus_overrides(tmp_path):
    p = tmp_path / "g.x"
    write(p, Grid([sheared_box()]), encoding="fortran", endian="big")
    fmt = Plot3DFormat(encoding="fortran")
    assert read(p, format=fmt, endian=">").source_format == fmt.replace(endian=">")
    with pytest.raises(GridFormatError, match="not a Fortran unformatted, little-endian"):
        read(p, format=fmt)


def test_format_validation_and_describe():
    f = Plot3DFormat(encoding="Fortran", endian="big", precision=np.int64(4))
    assert (f.encoding, f.endian, f.precision) == ("fortran", ">", 4)
    assert "big-endian" in f.describe() and "float32" in f.describe()
    for bad in ({"precision": 2}, {"ndim": 1}, {"multiblock": 1}, {"records": "x"}, {"int_size": True}):
        with pytest.raises(GridFormatError):
            Plot3DFormat(**bad)
    assert Plot3DFormat(encoding="binary", records="coordinate").canonical() == Plot3DFormat()


# ---------------------------------------------------------------- bad input

def _binary_box(tmp_path, name="g.x", **fmt):
    p = tmp_path / name
    write(p, Grid([sheared_box(5, 4, 3), sheared_box(4, 3, 2)]), **fmt)
    return p


def test_truncated_file(tmp_path):
    p = _binary_box(tmp_path)
    data = p.read_bytes()
    p.write_bytes(data[:-10])
    with pytest.raises(GridFormatError, match=r"(?s)g\.x.*truncated: block 2 of 2.*byte offset"):
        read(p)
    with pytest.raises(GridFormatError, match=r"truncated: block 2 of 2 .* ends at byte offset "
                                              f"{len(data) - 10}"):
        read(p, format=Plot3DFormat())


def test_truncated_fortran_file(tmp_path):
    p = _binary_box(tmp_path, encoding="fortran")
    p.write_bytes(p.read_bytes()[:-50])
    with pytest.raises(GridFormatError, match=r"truncated: block 2 of 2"):
        read(p)


def test_trailing_bytes_are_an_error(tmp_path):
    p = _binary_box(tmp_path)
    p.write_bytes(p.read_bytes() + b"\0" * 8)
    with pytest.raises(GridFormatError, match=r"8 unexpected bytes after the last block"):
        read(p, format=Plot3DFormat())


def test_zero_dimension_in_header(tmp_path):
    p = tmp_path / "zero.x"
    vals = sheared_box(5, 2, 3).ravel(order="K")
    p.write_bytes(struct.pack("<3i", 5, 0, 3) + vals.tobytes())
    with pytest.raises(GridFormatError,
                       match=r"(?s)zero\.x.*block 1 dimension j = 0 at byte offset 4 must be >= 1"):
        read(p)
    p.write_bytes(struct.pack("<i3i", 1, 5, -2, 3) + vals.tobytes())
    with pytest.raises(GridFormatError, match=r"block 1 dimension j = -2 at byte offset 8"):
        read(p, format=Plot3DFormat())


@pytest.mark.parametrize("encoding", ["binary", "fortran"])
def test_header_claiming_more_than_the_file_holds_fails_before_allocating(tmp_path, encoding):
    p = tmp_path / "huge.x"
    if encoding == "binary":
        p.write_bytes(struct.pack("<i3i", 1, 100000, 100000, 100000) + np.zeros(30).tobytes())
    else:
        p.write_bytes(fortran_record(struct.pack("<i", 1)) +
                      fortran_record(struct.pack("<3i", 100000, 100000, 100000)) +
                      fortran_record(np.zeros(30).tobytes()))
    tracemalloc.start()
    try:
        with pytest.raises(GridFormatError, match=r"(?s)huge\.x.*truncated: block 1 of 1.*claims "
                                                  r"1000000000000000 points"):
            read(p)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20
    with pytest.raises(GridFormatError, match=r"block 1 of 1 \(100000x100000x100000\)"):
        read(p, format=Plot3DFormat(encoding=encoding))


def test_inconsistent_fortran_record_markers(tmp_path):
    p = _binary_box(tmp_path, encoding="fortran")
    data = bytearray(p.read_bytes())
    n1 = 5 * 4 * 3
    # trailing marker of block 1's record
    off = 12 + 32 + 4 + 24 * n1
    assert struct.unpack_from("<i", data, off)[0] == 24 * n1
    struct.pack_into("<i", data, off, 7)
    p.write_bytes(bytes(data))
    with pytest.raises(GridFormatError, match=rf"block 1: inconsistent Fortran record marker at byte "
                                              rf"offset {off}: reads 7, the record holds {24 * n1} bytes"):
        read(p)


@pytest.mark.parametrize("records", ["block", "coordinate"])
@pytest.mark.parametrize("where", ["count lead", "count trail", "dims lead", "dims trail",
                                   "block 1 lead", "block 2 trail"])
def test_every_fortran_record_marker_is_checked(tmp_path, records, where):
    p = _binary_box(tmp_path, encoding="fortran", records=records)
    data = bytearray(p.read_bytes())
    n1, n2 = 5 * 4 * 3, 4 * 3 * 2
    rec1 = 24 * n1 if records == "block" else 8 * n1       # first record of block 1
    offsets = {"count lead": 0, "count trail": 8, "dims lead": 12, "dims trail": 12 + 4 + 24,
               "block 1 lead": 44, "block 2 trail": len(data) - 4}
    off = offsets[where]
    want = {"count lead": 4, "count trail": 4, "dims lead": 24, "dims trail": 24,
            "block 1 lead": rec1, "block 2 trail": 24 * n2 if records == "block" else 8 * n2}[where]
    assert struct.unpack_from("<i", data, off)[0] == want
    struct.pack_into("<i", data, off, want + 8)
    p.write_bytes(bytes(data))
    with pytest.raises(GridFormatError) as e:
        read(p)
    assert str(e.value).startswith(f"{p}: no Plot3D variant fits")
    # told it is this kind of Fortran file, the reader names the marker, its offset and value
    with pytest.raises(GridFormatError) as e:
        read(p, encoding="fortran", records=records, ndim=3, multiblock=True)
    msg = str(e.value)
    assert f"byte offset {off}" in msg and f"reads {want + 8}" in msg, msg
    if where.startswith("block"):
        assert f"block {where[6]}: inconsistent Fortran record marker at byte offset {off}" in msg


def test_fortran_dimension_below_one(tmp_path):
    p = tmp_path / "neg.x"
    p.write_bytes(fortran_record(struct.pack(">i", 1), ">") + fortran_record(struct.pack(">3i", 2, -1, 2), ">")
                  + fortran_record(np.zeros(3 * 4, ">f8").tobytes(), ">"))
    with pytest.raises(GridFormatError, match=r"neg\.x: not a Fortran unformatted, big-endian.*: header: "
                                              r"block 1 dimension j = -1 at byte offset 20 must be >= 1"):
        read(p, format=Plot3DFormat(encoding="fortran", endian=">"))
    with pytest.raises(GridFormatError, match=r"(?s)neg\.x: no Plot3D variant fits.*dimension j = -1 at "
                                              r"byte offset 20"):
        read(p)


def test_nonfinite_in_fortran_coordinate_records_names_the_byte(tmp_path):
    xyz = sheared_box(3, 2, 2)
    xyz[2, 1, 0, 2] = np.nan   # z of point (3, 2, 1): value 3 + 1 * 3 = 5 of the z record
    p = tmp_path / "nan.x"
    write(p, Grid([Block(xyz, allow_nonfinite=True)]), encoding="fortran", records="coordinate",
          endian=">", multiblock=False)
    n = 12
    # dims record (4 + 12 + 4), then x and y records (4 + 8n + 4 each), then z's lead marker
    off = 20 + 2 * (8 + 8 * n) + 4 + 8 * 5
    assert np.isnan(np.frombuffer(p.read_bytes()[off:off + 8], ">f8")[0])
    with pytest.raises(GridFormatError, match=rf"nan\.x: block 1 of 1: non-finite coordinate z = nan at "
                                              rf"\(i, j, k\) = \(3, 2, 1\) \(1-based\), byte offset {off} "):
        read(p)


def test_text_file_with_stray_bytes_names_their_line(tmp_path):
    p = tmp_path / "g.fmt"
    write(p, Grid([sheared_box(3, 2, 2)]), encoding="ascii")
    lines = p.read_bytes().split(b"\n")
    # a non-ASCII comment and a DOS end-of-file mark: not printable ASCII, so not taken as text,
    # and no binary variant fits either: the text reader says where
    lines[3] = lines[3] + " caf\u00e9".encode()
    p.write_bytes(b"\n".join(lines) + b"\x1a")
    with pytest.raises(GridFormatError, match=r"g\.fmt: line 4, column \d+: non-numeric token 'caf.*mostly "
                                              r"text"):
        read(p)
    p.write_bytes(b"\n".join(lines[:3] + lines[4:]) + b"\x1a")
    with pytest.raises(GridFormatError, match=r"g\.fmt: line \d+, column 1: non-numeric token '\\x1a'"):
        read(p)


def test_non_numeric_ascii_token_reports_its_line(tmp_path):
    p = tmp_path / "g.fmt"
    write(p, Grid([sheared_box(3, 2, 2), sheared_box(2, 2, 2)]), encoding="ascii")
    lines = p.read_text().splitlines()
    lines[12] = lines[12].split()[0] + " 1.0x5 " + " ".join(lines[12].split()[2:])
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(GridFormatError, match=r"g\.fmt: line 13, column \d+: non-numeric token "
                                              r"'1\.0x5' \(value number \d+, in block 2 of 2\)"):
        read(p)


def test_fortran_d_exponents_are_read(tmp_path):
    p = tmp_path / "d.fmt"
    p.write_text("1\n2 1 1\n1.5D+00 -2.0d-01\n0.0D0 1D1\n0 0\n")
    g = read(p)
    assert np.array_equal(g[0].xyz[:, 0, 0, :2], [[1.5, 0.0], [-0.2, 10.0]])


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_coordinates_binary(tmp_path, bad):
    xyz = sheared_box(4, 3, 2)
    xyz2 = sheared_box(3, 3, 3)
    xyz2[1, 2, 0, 1] = bad
    p = tmp_path / "nan.x"
    write(p, Grid([xyz, Block(xyz2, allow_nonfinite=True)]))
    with pytest.raises(GridFormatError, match=r"nan\.x: block 2 of 2: non-finite coordinate y = .* at "
                                              r"\(i, j, k\) = \(2, 3, 1\).*byte offset "
                                              + str(4 + 24 + 24 * 24 + 8 * (27 + 1 + 2 * 3))):
        read(p)
    g = read(p, allow_nonfinite=True)
    assert np.array_equal(g[1].xyz, xyz2, equal_nan=True)


def test_nonfinite_coordinates_ascii(tmp_path):
    p = tmp_path / "nan.fmt"
    p.write_text("2\n1 1 1\n2 1 1\n0 0 0\n1 2\n3 inf\n5 6\n")
    with pytest.raises(GridFormatError, match=r"nan\.fmt: block 2 of 2: line 6, column 3: non-finite "
                                              r"coordinate y = inf at \(i, j, k\) = \(2, 1, 1\)"):
        read(p)
    assert np.isinf(read(p, allow_nonfinite=True)[1].xyz[1, 0, 0, 1])


def test_empty_file(tmp_path):
    p = tmp_path / "empty.x"
    p.write_bytes(b"")
    with pytest.raises(GridFormatError, match=r"empty\.x: the file is empty"):
        read(p)


def test_file_that_fits_no_variant_lists_what_was_tried(tmp_path):
    p = tmp_path / "noise.x"
    p.write_bytes(np.random.default_rng(5).integers(0, 256, 1001, dtype=np.uint8).tobytes())
    with pytest.raises(GridFormatError) as e:
        read(p)
    msg = str(e.value)
    assert "noise.x: no Plot3D variant fits this 1001-byte file" in msg
    assert "encoding in {binary, fortran}" in msg and "endian in {<, >}" in msg
    assert "precision in {8, 4}" in msg and "records in {block, coordinate}" in msg


def test_ascii_counts_that_fit_no_variant(tmp_path):
    p = tmp_path / "short.fmt"
    p.write_text("1\n2 2 1\n" + "0.5 " * 9 + "\n")
    with pytest.raises(GridFormatError, match=r"(?s)short\.fmt: no Plot3D variant fits.*\(13 values of text\)"
                                              r".*truncated: block 1 of 1"):
        read(p)
    p.write_text("1\n2 0 1\n1 2\n")
    with pytest.raises(GridFormatError, match=r"line 2: block 1 dimension j = 0 must be an integer >= 1"):
        read(p, format=Plot3DFormat(encoding="ascii"))


def test_binary_bytes_forced_as_ascii_report_a_token(tmp_path):
    p = tmp_path / "g.x"
    write(p, Grid([sheared_box()]))
    with pytest.raises(GridFormatError, match="non-numeric token"):
        read(p, encoding="ascii")


# ---------------------------------------------------------------- write options

def test_write_defaults_and_like(tmp_path):
    g = Grid([sheared_box(), sheared_box(2, 2, 2)])
    p = tmp_path / "a.x"
    write(p, g)
    assert detect(p) == Plot3DFormat()
    src = read(p)
    q = tmp_path / "b.x"
    write(q, src, encoding="fortran", endian=">")           # defaults from source_format
    assert detect(q) == Plot3DFormat(encoding="fortran", endian=">")
    r = tmp_path / "c.x"
    write(r, g, like=read(q))                                 # like= a grid
    assert detect(r) == Plot3DFormat(encoding="fortran", endian=">")
    s = tmp_path / "d.x"
    write(s, g, like=Plot3DFormat(encoding="ascii"), iblank=True)
    got = read(s)
    assert got.source_format.iblank and all(np.all(b.iblank == 1) for b in got)


def test_write_2d_from_flat_3d_grid_and_refusals(tmp_path):
    flat = Grid([annulus()], 3)
    write(tmp_path / "a.x", flat, ndim=2)
    assert read(tmp_path / "a.x").ndim == 2
    with pytest.raises(GridFormatError, match=r"block 1 is 3-D"):
        write(tmp_path / "b.x", Grid([sheared_box()]), ndim=2)
    with pytest.raises(GridFormatError, match=r"single-block Plot3D variant cannot hold 2 blocks"):
        write(tmp_path / "c.x", Grid([sheared_box(), sheared_box()]), multiblock=False)
    with pytest.raises(GridFormatError, match=r"unknown option"):
        write(tmp_path / "d.x", flat, compress=True)
    assert not (tmp_path / "b.x").exists() and not (tmp_path / "c.x").exists()


@pytest.mark.parametrize("encoding", ["binary", "fortran", "ascii"])
def test_float32_overflow_is_an_error_not_inf(tmp_path, encoding):
    xyz = sheared_box()
    xyz[2, 1, 1, 2] = 1e39
    p = tmp_path / "o.x"
    p.write_bytes(b"old")
    with pytest.raises(GridFormatError,
                       match=r"o\.x: block 2 of 2: coordinate 1e\+?39 is beyond the float32"):
        write(p, Grid([sheared_box(), xyz]), precision=4, encoding=encoding)
    assert p.read_bytes() == b"old"
    write(p, Grid([sheared_box(), xyz]), encoding=encoding, overwrite=True)
    assert read(p)[1].xyz[2, 1, 1, 2] == 1e39


def test_fortran_record_too_long_for_4_byte_markers(tmp_path):
    class Huge:
        dims = (2 ** 11, 2 ** 10, 2 ** 9)
    with pytest.raises(GridFormatError, match=r"more than 4-byte markers can frame"):
        plot3d.write(tmp_path / "h.x", _FakeGrid([Huge()]), encoding="fortran")


class _FakeGrid(Grid):
    """A grid of dimension-only blocks (no coordinates): enough for the size checks."""

    def __init__(self, blocks):
        self.blocks, self.ndim, self.source_format, self.source_path = blocks, 3, None, None

    @property
    def has_iblank(self):
        return False


@pytest.mark.parametrize("fmt", [Plot3DFormat(), Plot3DFormat(encoding="fortran", endian=">"),
                                 Plot3DFormat(precision=4, iblank=True)])
def test_binary_write_allocates_no_copy_of_the_grid(tmp_path, fmt):
    """Native float64 blocks go out from their own memory, others in 2 MiB chunks."""
    rng = np.random.default_rng(2)
    grid = Grid([np.asfortranarray(rng.random((100, 100, 60, 3)))])      # 14.4 MB
    tracemalloc.start()
    try:
        write(tmp_path / "w.x", grid, like=fmt, iblank=fmt.iblank)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    chunk = plot3d._CHUNK * 8
    # an IBLANK the grid lacks is written as ones (2.4 MB of int32 here); without IBLANK nothing
    limit = (chunk if fmt.precision == 4 or fmt.endian == ">" else 0) + (1 << 20) + \
        (grid.npoints * 4 if fmt.iblank else 0)
    assert peak <= limit, (peak, limit)
    assert read(tmp_path / "w.x").source_format == fmt


def test_failed_write_leaves_target_untouched_and_no_temp_file(tmp_path, monkeypatch):
    p = tmp_path / "t.x"
    p.write_bytes(b"precious")

    def broken(fh, arr, dtype, where=""):
        fh.write(b"partial")
        raise OSError("disk full")
    monkeypatch.setattr(plot3d, "_write_array", broken)
    with pytest.raises(OSError, match="disk full"):
        write(p, Grid([sheared_box()]))
    assert p.read_bytes() == b"precious"
    assert sorted(os.listdir(tmp_path)) == ["t.x"]


def test_writing_over_the_source_needs_overwrite(tmp_path):
    p = tmp_path / "in.x"
    write(p, Grid([sheared_box()]))
    g = read(p)
    before = p.read_bytes()
    with pytest.raises(OverwriteError, match="in.x"):
        write(p, g)
    assert p.read_bytes() == before
    write(p, g, overwrite=True, precision=4)
    assert detect(p).precision == 4


def test_package_level_read_write_dispatch(tmp_path):
    g2 = Grid([sheared_box()], source_format=Plot3DFormat(encoding="fortran", endian=">"))
    p = tmp_path / "f.x"
    tfi_quat.write(p, Grid([sheared_box(3, 3, 3)]), like=g2)
    g = tfi_quat.read(p)
    assert g.source_format == Plot3DFormat(encoding="fortran", endian=">")
    assert g.source_path == os.fspath(p)
    assert np.array_equal(g[0].xyz, sheared_box(3, 3, 3))
    assert tfi_quat.read(p, endian=">", multiblock=True).dims == [(3, 3, 3)]


# ---------------------------------------------------------------- text number parser

def _parse(text: str) -> np.ndarray:
    return plot3d._parse_text(text.encode(), "t.fmt")


def _assert_parses_like_python(tokens):
    got = _parse(" \n".join(tokens))
    want = np.array([float(t.replace("d", "e").replace("D", "E")) for t in tokens])
    assert got.shape == want.shape
    same = (got.view(np.uint64) == want.view(np.uint64)) | (np.isnan(got) & np.isnan(want))
    assert same.all(), [t for t, ok in zip(tokens, same) if not ok][:5]


@given(st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=1, max_size=50),
       st.sampled_from(["%r", "%.17g", "%.16g", "%.9g", "%.25e", "%.3f", "%.17E", "%.0f"]))
def test_text_parser_is_correctly_rounded_for_formatted_floats(values, spec):
    _assert_parses_like_python([spec % v for v in values])


_DECIMAL = r"\A[-+]?([0-9]{1,22}(\.[0-9]{0,22})?|\.[0-9]{1,22})([eEdD][-+]?[0-9]{1,3})?\Z"


@given(st.lists(st.from_regex(_DECIMAL), min_size=1, max_size=30))
def test_text_parser_is_correctly_rounded_for_arbitrary_decimals(tokens):
    _assert_parses_like_python(tokens)


def test_text_parser_hard_cases():
    _assert_parses_like_python([
        "9007199254740993", "9007199254740992.5", "2.2250738585072011e-308", "2.2250738585072014e-308",
        "4.9406564584124654e-324", "2.4703282292062328e-324", "1e-400", "1e23", "8.98846567431158e307",
        "1.7976931348623157e308", "1.7976931348623158e308", "1.7976931348623159e308", "1e309",
        "0.1", "-0", "-0.0e0", "+.5", "5.", "1D-3", "123456789012345678901234567890",
        "0.000000000000000000000000000001", "7.2057594037927933e16", "3.0517578125e-05",
        "1.00000000000000011102230246251565404236316680908203125", "nan", "-inf", "Infinity"])


def test_text_parser_many_random_values_bit_exact():
    rng = np.random.default_rng(11)
    a = np.concatenate([rng.standard_normal(20000) * 10.0 ** rng.integers(-300, 300, 20000),
                        rng.integers(0, 2 ** 63, 20000).astype(np.uint64).view(np.float64)])
    a = a[np.isfinite(a)]
    for spec in ("%.17g", "%r"):
        got = _parse(" ".join(spec % v for v in a.tolist()))
        assert np.array_equal(got.view(np.uint64), a.view(np.uint64))


def test_fortran_exponent_without_e_letter(tmp_path):
    p = tmp_path / "f.fmt"
    p.write_text("2 1\n0.1234567-100 1.5+002\n0 0\n")
    g = read(p)
    assert g[0].xyz[0, 0, 0, 0] == 0.1234567e-100 and g[0].xyz[1, 0, 0, 0] == 150.0


@pytest.mark.parametrize("endian", ["<", ">"])
def test_signalling_nan_in_a_float32_file_is_reported_not_warned(tmp_path, endian):
    # widening a signalling NaN raises the FPU's invalid flag: numpy warns, and warnings are errors here
    vals = np.arange(12, dtype=np.uint32).astype(np.float32).view(np.uint32)
    vals[5] = 0x7F800001
    p = tmp_path / "snan.x"
    p.write_bytes(struct.pack(f"{endian}3i", 2, 2, 1) + vals.astype(f"{endian}u4").tobytes())
    with pytest.raises(GridFormatError, match=r"snan\.x: block 1 of 1: non-finite coordinate y = nan at "
                                              r"\(i, j, k\) = \(2, 1, 1\).*byte offset 32"):
        read(p)
    g = read(p, allow_nonfinite=True)
    assert g.source_format.precision == 4 and np.isnan(g[0].xyz[1, 0, 0, 1])
    # and back out as float32, binary and text
    write(tmp_path / "o.x", g, endian=endian)
    write(tmp_path / "o.fmt", g, encoding="ascii")
    assert np.isnan(read(tmp_path / "o.fmt", precision=4, allow_nonfinite=True)[0].xyz[1, 0, 0, 1])
    snan64 = np.array([0x7FF0000000000001], np.uint64).view(np.float64)[0]
    h = Grid([Block(np.full((2, 1, 1, 3), snan64), allow_nonfinite=True)])
    write(tmp_path / "s.x", h, precision=4)
    assert np.isnan(read(tmp_path / "s.x", allow_nonfinite=True)[0].xyz).all()


def test_long_tokens_are_converted_by_the_compiled_scanner():
    # "%.24e" has 25 significant digits: past the 19 a uint64 holds; the first 19 decide the
    # rounding except in rare halfway cases, which fall back to Python's float
    rng = np.random.default_rng(4)
    a = rng.standard_normal(2000) * 10.0 ** rng.integers(-300, 300, 2000)
    data = " ".join("%.24e" % v for v in a.tolist()).encode()
    buf = np.frombuffer(data, np.uint8)
    out = np.empty(a.size)
    hi, lo, exact10 = plot3d._decimal_tables()
    fb = np.empty((3, a.size), np.int64)
    k, nfb = plot3d._parse_decimals(buf, out, out.view(np.uint64), hi, lo, exact10, fb)
    assert k == a.size and nfb < 10
    assert np.array_equal(plot3d._parse_text(data, "t")[:], a)
    # 1 + 2**-53 exactly, the halfway point between 1 and the next float64: decided by digit 54
    halfway = "1.00000000000000011102230246251565404236316680908203125"
    k, nfb = plot3d._parse_decimals(np.frombuffer(halfway.encode(), np.uint8), out, out.view(np.uint64),
                                    hi, lo, exact10, fb)
    assert nfb == 1 and _parse(halfway)[0] == float(halfway) == 1.0
    assert _parse(halfway + "1")[0] == float(halfway + "1") == 1.0000000000000002
