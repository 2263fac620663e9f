"""Plot3D reader on damaged, hostile and large input; OS errors of every reader.

Regression inputs from the robustness issue live in ``tests/data/robustness``:
``a.x`` is a two-block float32 C binary file, ``t.x`` the same cut to 972
bytes (which once read "successfully" as one float64 block).
"""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
import tempfile
import textwrap
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

import tfi_quat as tq
from tfi_quat import Block, Grid, GridFormatError
from tfi_quat.io import plot3d
from tfi_quat.io._limits import available_memory
from tfi_quat.io.plot3d import Plot3DFormat

DATA = Path(__file__).parent / "data" / "robustness"
ROOT = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------- damaged files

def test_truncated_two_block_file_is_not_read_as_one_float64_block():
    whole = tq.read(DATA / "a.x")
    assert whole.source_format == Plot3DFormat(precision=4)
    assert [b.dims for b in whole] == [(5, 4, 3), (4, 4, 3)]
    with pytest.raises(GridFormatError) as exc:
        tq.read(DATA / "t.x")
    msg = str(exc.value)
    assert "t.x: no Plot3D variant fits this 972-byte file" in msg
    # the closest misses: the variant it was cut from, and the one it used to be read as
    assert ("as C binary, little-endian, float32, 3-D, multi-block, no iblank, int32: the file is "
            "truncated: block 2 of 2 (4x4x3)") in msg
    assert "single-block, no iblank, int32: block 1: x value" in msg
    assert "is no coordinate" in msg


@pytest.mark.parametrize("token", ["inf", "-inf", "nan", "1e999", "9" * 400, "2.5", "0"])
def test_ascii_header_value_that_is_no_count_is_named(tmp_path, token):
    # found by the fuzzer: inf/nan/huge header values once escaped as OverflowError/ValueError
    path = tmp_path / "h.x"
    path.write_text(f"1\n2 2 {token}\n" + "0 1 0 1 0 0 1 1 0 0 0 0\n")
    with pytest.raises(GridFormatError, match=r"line 2: block 1 dimension k = .* must be an integer >= 1"):
        tq.read(path)


def _grid_for(fmt: Plot3DFormat, rng) -> Grid:
    blocks = []
    for _ in range(int(rng.integers(1, 4)) if fmt.multiblock else 1):
        dims = tuple(int(v) for v in rng.integers(3, 7, 3))
        if fmt.ndim == 2:
            dims = dims[:2] + (1,)
        xyz = np.asfortranarray(rng.random(dims + (3,)) * 10.0 ** rng.integers(-3, 4))
        if fmt.ndim == 2:
            xyz[..., 2] = 0.0
        ib = rng.integers(-2, 3, dims).astype(np.int32) if fmt.iblank else None
        blocks.append(Block(xyz, ib))
    return Grid(blocks, fmt.ndim)


def _same_values_or_error(path, grid: Grid, fmt: Plot3DFormat, what: str) -> None:
    """A damaged file is an error, or reads as values the file really holds.

    A cut exactly at the end of an array leaves a valid file of a variant
    with fewer arrays (no IBLANK; x, y of a 3-D block with ni = 1): its
    values are the original's, so that is no silent garbage.
    """
    try:
        got = plot3d.read(path, allow_nonfinite=True)
    except GridFormatError:
        return
    assert len(got) <= len(grid), what
    for a, b in zip(got, grid):
        nd = got.ndim
        want = b.xyz.astype(np.float32).astype(float) if fmt.precision == 4 else b.xyz
        for c in range(nd):
            assert np.array_equal(a.xyz[..., c].ravel(order="F"), want[..., c].ravel(order="F")), \
                (what, got.source_format.describe(), a.dims, b.dims)


BINARY_VARIANTS = sorted({Plot3DFormat(**dict(zip(plot3d._FIELD_NAMES, v))).canonical()
                          for v in itertools.product(*(plot3d._CHOICES[n] for n in plot3d._FIELD_NAMES))
                          if v[0] != "ascii"}, key=lambda f: f._key())


@pytest.mark.parametrize("n", range(len(BINARY_VARIANTS)),
                         ids=lambda n: BINARY_VARIANTS[n].describe().replace(", ", "-"))
def test_damaged_binary_file_is_an_error_never_another_variant(tmp_path, n):
    """Truncated anywhere, or a Fortran record marker changed: an error, or the file's own values."""
    fmt = BINARY_VARIANTS[n]
    rng = np.random.default_rng(n)
    grid = _grid_for(fmt, rng)
    p, d = tmp_path / "g.x", tmp_path / "d.x"
    plot3d.write(p, grid, like=fmt)
    data = p.read_bytes()
    _, layouts, total, header_markers = plot3d._layout(fmt, [b.dims for b in grid])
    cuts = set(int(c) for c in rng.integers(1, len(data), 6))
    cuts |= {lay.start for lay in layouts[1:]} | {lay.iblank for lay in layouts if lay.iblank}
    cuts |= {lay.end - 1 for lay in layouts} | {off for lay in layouts for off, _, _ in lay.runs}
    for cut in sorted(cuts - {0, len(data)}):
        d.write_bytes(data[:cut])
        _same_values_or_error(d, grid, fmt, f"cut at {cut}")
    if fmt.encoding == "fortran":
        order = "little" if fmt.endian == "<" else "big"
        markers = header_markers + [m for lay in layouts for m in lay.markers]
        for off, length in [markers[int(k)] for k in rng.integers(0, len(markers), 4)]:
            for bad in (length + 4, length - fmt.int_size, int(rng.integers(-2 ** 31, 2 ** 31))):
                if bad == length:
                    continue
                raw = bytearray(data)
                raw[off:off + fmt.marker_size] = bad.to_bytes(fmt.marker_size, order, signed=True)
                d.write_bytes(bytes(raw))
                with pytest.raises(GridFormatError, match="record marker|no Plot3D variant"):
                    plot3d.read(d)


@pytest.mark.parametrize("fmt", [Plot3DFormat(encoding="ascii"),
                                 Plot3DFormat(encoding="ascii", ndim=2, iblank=True),
                                 Plot3DFormat(encoding="ascii", multiblock=False, precision=4)],
                         ids=lambda f: f.describe().replace(", ", "-"))
def test_damaged_ascii_file_is_an_error_naming_a_line(tmp_path, fmt):
    rng = np.random.default_rng(7)
    grid = _grid_for(fmt, rng)
    p, d = tmp_path / "g.fmt", tmp_path / "d.fmt"
    plot3d.write(p, grid, like=fmt)
    text = p.read_bytes()
    lines = text.splitlines(keepends=True)
    # cut at line ends (a cut inside the last token leaves a shorter number: undetectable)
    for k in sorted(set(int(v) for v in rng.integers(1, len(lines) - 1, 12))):
        d.write_bytes(b"".join(lines[:k]))
        try:
            got = plot3d.read(d, allow_nonfinite=True)
        except GridFormatError as exc:
            assert "line" in str(exc), str(exc)
            continue
        # only a cut at an array boundary can fit: the file's own values
        _same_values_or_error(d, grid, fmt, f"{k} lines: {got.source_format.describe()}")
    bad = lines[:]
    bad[len(bad) // 2] = b"1.0 2.0 x3 4.0\n"
    d.write_bytes(b"".join(bad))
    with pytest.raises(GridFormatError, match=f"line {len(bad) // 2 + 1}, column 9: non-numeric token 'x3'"):
        plot3d.read(d)


def test_truncated_multiblock_ascii_is_not_read_as_one_block(tmp_path):
    # two blocks (2, 2, 3) and (1, 1, 1) cut after 20 values: 27 numbers, as many as one
    # block of dims (2, 2, 2) read from "2 / 2 2 ..." needs
    xyz = np.asfortranarray(np.random.default_rng(1).random((2, 2, 3, 3)))
    p = tmp_path / "g.fmt"
    p.write_text("2\n2 2 3\n1 1 1\n" + "\n".join(repr(float(v)) for v in xyz.ravel(order="F")[:20]) + "\n")
    with pytest.raises(GridFormatError) as exc:
        plot3d.read(p)
    assert "line 2: the header ends after 3 value(s) in the middle of the line" in str(exc.value)
    assert "the file is truncated" in str(exc.value)


# ---------------------------------------------------------------- large valid files, size cap

_MEASURE = textwrap.dedent("""
    import json, resource, sys, tracemalloc
    from tfi_quat.io import plot3d

    def rchar():
        with open("/proc/self/io") as fh:
            return int(next(l for l in fh if l.startswith("rchar")).split()[1])

    def rss():
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * resource.getpagesize()

    path = sys.argv[1]
    out = {}
    r0 = rchar(); tracemalloc.start()
    out["detect"] = plot3d.detect(path).describe()
    out["detect_read"] = rchar() - r0
    out["detect_peak"] = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")          # the peak resident size starts again from now
    base = rss(); r0 = rchar(); tracemalloc.start()
    g = plot3d.read(path)
    out["read_peak"] = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    out["read_read"] = rchar() - r0
    with open("/proc/self/status") as fh:
        hwm = int(next(l for l in fh if l.startswith("VmHWM")).split()[1]) * 1024
    out["rss_growth"] = hwm - base
    out["grid"] = sum(b.xyz.nbytes + (b.iblank.nbytes if b.iblank is not None else 0) for b in g)
    out["dims"] = [b.dims for b in g]
    out["zeros"] = all(not b.xyz.any() for b in g)
    print(json.dumps(out))
""")


def _sparse_plot3d(path, dims, endian="<", precision=4) -> int:
    """A C binary multi-block file of zeros, sparse: only the header is written."""
    ints = np.array([len(dims)] + [d for ijk in dims for d in ijk], dtype=f"{endian}i4")
    size = ints.nbytes + sum(3 * precision * int(np.prod(d)) for d in dims)
    with open(path, "wb") as fh:
        fh.write(ints.tobytes())
        fh.truncate(size)
    return size


@pytest.mark.parametrize("dims, endian, precision", [
    ([(200, 200, 200)], "<", 4),                       # 96 MB of float32, 192 MB grid
    ([(150, 100, 100), (80, 80, 80), (100, 100, 40), (60, 60, 60)], ">", 8),   # 4 blocks, 72 MB
])
def test_large_sparse_file_detection_reads_the_header_and_read_peaks_at_the_grid(
        tmp_path, dims, endian, precision):
    p = tmp_path / "big.x"
    size = _sparse_plot3d(p, dims, endian, precision)
    run = subprocess.run([sys.executable, "-c", _MEASURE, str(p)], capture_output=True, text=True,
                         cwd=ROOT, timeout=600)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert out["detect"] == Plot3DFormat(endian=endian, precision=precision).describe()
    assert [tuple(d) for d in out["dims"]] == dims and out["zeros"]
    # detection: a few header chunks for each of the 320 variants, never a data-sized read
    assert out["detect_read"] < 1 << 20, out
    assert out["detect_peak"] < 1 << 20, out
    # the read: the file once, and memory within 10 % of the grid
    assert size <= out["read_read"] <= size + (1 << 20), out
    assert out["read_peak"] <= 1.1 * out["grid"], out
    assert out["rss_growth"] <= 1.1 * out["grid"], out


def test_declared_grid_beyond_max_points_is_refused_before_allocating(tmp_path):
    p = tmp_path / "g.x"
    _sparse_plot3d(p, [(100, 100, 100), (50, 50, 50)])
    tracemalloc.start()
    try:
        with pytest.raises(GridFormatError, match=r"declares 1,125,000 points, more than max_points=1,000,000"):
            tq.read(p, max_points=1_000_000)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20
    g = tq.read(p, max_points=1_125_000)
    assert [b.dims for b in g] == [(100, 100, 100), (50, 50, 50)]
    # ASCII too
    a = tmp_path / "g.fmt"
    a.write_text("1\n2 2 2\n" + "0 " * 24 + "\n")
    with pytest.raises(GridFormatError, match="declares 8 points, more than max_points=7"):
        tq.read(a, max_points=7)
    assert tq.read(a, max_points=8)[0].dims == (2, 2, 2)


def test_declared_grid_beyond_memory_is_a_format_error_not_memory_error(tmp_path):
    # a sparse float32 file whose grid needs more memory than there is (12 bytes a point
    # on disk, 24 in memory): costs no disk
    points = available_memory() // 20 + 1
    n = int(round(points ** (1 / 3))) + 1
    p = tmp_path / "huge.x"
    _sparse_plot3d(p, [(n, n, n)])
    with pytest.raises(GridFormatError, match=rf"declares {n ** 3:,} points \(.*\), more than the .* "
                                              "of memory available"):
        tq.read(p)


def test_many_blocks_declared_beyond_max_points_stop_the_header_read(tmp_path):
    nb = 100_000
    p = tmp_path / "g.x"
    _sparse_plot3d(p, [(2, 2, 2)] * nb)
    with pytest.raises(GridFormatError, match=r"header: blocks 1\.\.8192 of 100000: declares 65,536 points"):
        plot3d.read(p, max_points=1000)


# ---------------------------------------------------------------- OS errors

@pytest.mark.parametrize("name", ["g.x", "g.h5", "g.fmt"])
def test_missing_file_and_folder_raise_the_standard_errors(tmp_path, name):
    missing = tmp_path / name
    folder = tmp_path / ("dir" + Path(name).suffix)
    folder.mkdir()
    for fn in (tq.read, plot3d.read, plot3d.detect, plot3d.detect_all):
        with pytest.raises(FileNotFoundError, match="No such file") as exc:
            fn(missing)
        assert exc.value.filename == str(missing) and str(missing) in str(exc.value)
        with pytest.raises(IsADirectoryError, match="Is a directory") as exc:
            fn(folder)
        assert exc.value.filename == str(folder) and str(folder) in str(exc.value)


def _errors_of_readers(path) -> list[str]:
    out = []
    for fn in (tq.read, plot3d.read, plot3d.detect):
        try:
            fn(path)
        except PermissionError as exc:
            ok = exc.filename == str(path) and str(path) in str(exc)
            out.append("PermissionError" if ok else f"bad message {exc}")
        else:
            out.append("read")
    return out


def _as_unprivileged(fn, *args):
    """``fn(*args)`` as an unprivileged user: root reads anything (a forked child drops root)."""
    if os.geteuid() != 0:
        return fn(*args)
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        try:
            os.close(r)
            os.setgid(65534)
            os.setuid(65534)
            os.write(w, json.dumps(fn(*args)).encode())
        finally:
            os._exit(0)
    os.close(w)
    with os.fdopen(r) as fh:
        text = fh.read()
    os.waitpid(pid, 0)
    return json.loads(text)


@pytest.mark.parametrize("name", ["g.x", "g.h5"])
def test_unreadable_file_raises_permission_error(name):
    with tempfile.TemporaryDirectory() as d:
        os.chmod(d, 0o755)   # reachable for the unprivileged user
        p = Path(d) / name
        plot3d.write(Path(d) / "g.x", Grid([np.zeros((2, 2, 2, 3), order="F")]))
        if name != "g.x":
            (Path(d) / "g.x").rename(p)
        p.chmod(0)
        assert _as_unprivileged(_errors_of_readers, str(p)) == ["PermissionError"] * 3
