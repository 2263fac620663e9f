"""Partial reads: ``read(path, blocks=)``, ``read_faces`` and ``partition``.

Every result is compared bit for bit with the matching blocks or faces of a
full read of the same file, for every format and Plot3D variant the registry
writes.
"""

from __future__ import annotations

import itertools
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import tfi_quat as tq
from tfi_quat import Block, Grid, GridFormatError, GridValueError
from tfi_quat.grid import FACES, faces_of
from tfi_quat.io import plot3d
from tfi_quat.io.partial import GridFaces
from tfi_quat.io.plot3d import Plot3DFormat

CGNS_DATA = Path(__file__).parent / "data" / "cgns"


def random_grid(dims, ndim=3, iblank=False, seed=0) -> Grid:
    """Blocks of random coordinates (z = 0 in 2-D), IBLANK when asked."""
    rng = np.random.default_rng(seed)
    blocks = []
    for n, d in enumerate(dims):
        xyz = np.asfortranarray(rng.standard_normal(tuple(d) + (3,)))
        if ndim == 2:
            xyz[..., 2] = 0.0
        ib = np.asfortranarray(rng.integers(-2, 3, size=tuple(d)).astype(np.int32)) if iblank else None
        blocks.append(Block(xyz, ib, name=f"block{n + 1}"))
    return Grid(blocks, ndim)


def check_against_full(path, full: Grid, ids, part: Grid, faces: GridFaces) -> None:
    """``part`` holds the blocks ``ids`` of ``full``; ``faces`` every face of every block."""
    assert part.block_ids == tuple(ids)
    assert part.ndim == full.ndim and len(part) == len(ids)
    for b, n in zip(part, ids):
        ref = full[n]
        assert b.name == ref.name
        assert b.xyz.flags.f_contiguous and b.xyz.dtype == np.float64
        assert np.array_equal(b.xyz.view(np.uint64), ref.xyz.view(np.uint64))   # bit for bit
        if ref.iblank is None:
            assert b.iblank is None
        else:
            assert np.array_equal(b.iblank, ref.iblank)
    assert faces.ndim == full.ndim and faces.dims == full.dims and faces.nblocks == len(full)
    assert faces.names == [b.name for b in full]
    assert faces.npoints == full.npoints
    for n, ref in enumerate(full):
        assert len(faces.faces[n]) == len(faces_of(full.ndim))
        for f, name in enumerate(faces_of(full.ndim)):
            got, want = faces.face(n, name), ref.face(f)
            assert got.shape == want.shape and got.dtype == np.float64
            assert np.array_equal(got.view(np.uint64), np.ascontiguousarray(want).view(np.uint64))


def all_plot3d_variants() -> list[Plot3DFormat]:
    """Every distinct Plot3D variant the writer writes (fields an encoding ignores at defaults)."""
    names = ("encoding", "endian", "precision", "ndim", "multiblock", "iblank", "records",
             "int_size", "marker_size")
    values = (("binary", "fortran", "ascii"), ("<", ">"), (8, 4), (3, 2), (True, False),
              (False, True), ("block", "coordinate"), (4, 8), (4, 8))
    seen = {}
    for combo in itertools.product(*values):
        v = Plot3DFormat(**dict(zip(names, combo))).canonical()
        seen[v] = None
    return list(seen)


PLOT3D_VARIANTS = all_plot3d_variants()


def test_variant_list_is_complete():
    # 64 binary, 256 Fortran (records x marker sizes), 16 text
    assert len(PLOT3D_VARIANTS) == 64 + 256 + 16


@pytest.mark.parametrize("variant", PLOT3D_VARIANTS, ids=lambda v: v.describe())
def test_plot3d_every_variant_matches_full_read(tmp_path, variant):
    dims = [(4, 3, 5), (2, 6, 3), (5, 4, 2)] if variant.ndim == 3 else [(4, 3, 1), (6, 2, 1), (3, 5, 1)]
    if not variant.multiblock:
        dims = dims[1:2]
    grid = random_grid(dims, variant.ndim, variant.iblank, seed=len(dims))
    path = tmp_path / "g.x"
    tq.write(path, grid, format="plot3d", like=variant)
    full = plot3d.read(path, format=variant)
    ids = [2, 0] if variant.multiblock else [0]
    part = plot3d.read(path, format=variant, blocks=ids)
    faces = plot3d.read_faces(path, format=variant)
    check_against_full(path, full, ids, part, faces)
    assert faces.source_format == full.source_format == part.source_format


def test_registry_read_detects_the_variant(tmp_path):
    grid = random_grid([(3, 4, 5), (5, 4, 3)])
    path = tmp_path / "g.g"
    tq.write(path, grid, encoding="fortran", endian=">", precision=4)
    full = tq.read(path)
    check_against_full(path, full, [1], tq.read(path, blocks=[1]), tq.read_faces(path))


@settings(max_examples=20, deadline=None)
@given(fmt=st.sampled_from(["plot3d-binary", "plot3d-fortran", "hdf5", "hdf5-gzip", "cgns", "cgns-r4"]),
       ndim=st.sampled_from([2, 3]),
       dims=st.lists(st.tuples(st.integers(1, 6), st.integers(1, 6), st.integers(1, 6)),
                     min_size=1, max_size=5),
       data=st.data())
def test_random_grids_every_format(tmp_path_factory, fmt, ndim, dims, data):
    if ndim == 2:
        dims = [(a, b, 1) for a, b, _ in dims]
    grid = random_grid(dims, ndim, seed=len(dims))
    folder = tmp_path_factory.mktemp("g")
    opts = {"plot3d-binary": dict(encoding="binary"), "plot3d-fortran": dict(encoding="fortran"),
            "hdf5": {}, "hdf5-gzip": dict(compression="gzip"), "cgns": {}, "cgns-r4": dict(single=True)}[fmt]
    ext = {"plot3d": ".x", "hdf5": ".h5", "cgns": ".cgns"}[fmt.split("-")[0]]
    path = folder / f"g{ext}"
    tq.write(path, grid, **opts)
    full = tq.read(path)
    ids = data.draw(st.permutations(range(len(dims))).flatmap(
        lambda p: st.integers(1, len(p)).map(lambda k: list(p[:k]))))
    check_against_full(path, full, ids, tq.read(path, blocks=ids), tq.read_faces(path))


@pytest.mark.parametrize("name", ["multiblock.cgns", "cgrid2d.cgns"])
def test_cgns_files_and_their_connectivity(name):
    path = CGNS_DATA / name
    full = tq.read(path)
    ids = list(range(len(full)))[::-1]
    part = tq.read(path, blocks=ids)
    faces = tq.read_faces(path)
    check_against_full(path, full, ids, part, faces)
    assert part.connectivity is None                       # made for all the zones
    assert faces.connectivity is not None
    assert faces.connectivity.interfaces == full.connectivity.interfaces
    assert faces.connectivity.patches == full.connectivity.patches


# ----------------------------------------------------------------------------- errors

def write_each_format(folder, grid) -> list[Path]:
    paths = []
    for name, opts in (("g.x", dict(encoding="binary")), ("g.fmt", dict(encoding="ascii")),
                       ("g.h5", {}), ("g.cgns", {})):
        p = Path(folder) / name
        tq.write(p, grid, **opts)
        paths.append(p)
    return paths


@pytest.mark.parametrize("blocks, words", [
    ([3], ["block 3 out of range", "holds 3 block(s)", "0..2"]),
    ([-1], ["block -1 out of range"]),
    ([0, 2, 0], ["block 0 is given twice"]),
    ([], ["blocks= is empty"]),
    ([1.0], ["block 1.0", "not an integer"]),
    ([True], ["block True", "not an integer"]),
    (1, ["must be a list"]),
])
def test_bad_block_numbers_name_file_and_block(tmp_path, blocks, words):
    grid = random_grid([(3, 3, 3), (2, 3, 4), (4, 2, 2)])
    for path in write_each_format(tmp_path, grid):
        with pytest.raises(GridValueError) as err:
            tq.read(path, blocks=blocks)
        msg = str(err.value)
        assert str(path) in msg, msg
        for w in words:
            assert w in msg, msg


def test_blocks_with_a_target_is_refused(tmp_path):
    path = tmp_path / "g.x"
    tq.write(path, random_grid([(3, 3, 3)]), target="cfl3d")
    with pytest.raises(GridFormatError, match="target='cfl3d'"):
        tq.read(path, target="cfl3d", blocks=[0])


def test_nonfinite_face_names_block_and_face(tmp_path):
    grid = random_grid([(3, 3, 3), (4, 3, 2)])
    grid[1].xyz[3, 1, 1, 0] = np.nan          # on face imax of block 2 (0-based 1)
    grid = Grid([Block(b.xyz, name=b.name, allow_nonfinite=True) for b in grid], 3, allow_nonfinite=True)
    for path in (tmp_path / "g.x", tmp_path / "g.h5", tmp_path / "g.cgns"):
        tq.write(path, grid)
        with pytest.raises(GridFormatError) as err:
            tq.read_faces(path)
        msg = str(err.value)
        assert str(path) in msg and "imax" in msg and "non-finite" in msg, msg
        faces = tq.read_faces(path, allow_nonfinite=True)
        assert np.isnan(faces.face(1, "imax")[1, 1, 0])
        # the other block reads cleanly on its own
        assert tq.read(path, blocks=[0])[0] == tq.read(path, allow_nonfinite=True)[0]


def test_grid_faces_face_checks_its_arguments(tmp_path):
    path = tmp_path / "g.x"
    tq.write(path, random_grid([(3, 4, 1)], ndim=2))
    faces = tq.read_faces(path)
    assert len(faces.faces[0]) == 4 and faces.ndim == 2
    with pytest.raises(GridValueError, match="no face 'kmin'"):
        faces.face(0, "kmin")
    with pytest.raises(GridValueError, match="block 1 out of range"):
        faces.face(1, "imin")


def test_copy_keeps_block_ids(tmp_path):
    path = tmp_path / "g.h5"
    tq.write(path, random_grid([(3, 3, 3), (2, 2, 2)]))
    part = tq.read(path, blocks=[1])
    assert part.copy().block_ids == (1,)
    assert tq.read(path).block_ids is None


# ----------------------------------------------------------------------------- memory

@pytest.mark.parametrize("name", ["g.x", "g.g", "g.h5", "g.cgns"])
def test_reading_one_of_four_blocks_allocates_a_quarter(tmp_path, name):
    n = 40                                         # 64,000 points, 1.5 MB of float64 per block
    grid = random_grid([(n, n, n)] * 4)
    path = tmp_path / name
    tq.write(path, grid, **(dict(encoding="fortran") if name == "g.g" else {}))
    del grid

    def peak(**kw):
        tracemalloc.start()
        try:
            g = tq.read(path, **kw)
            return tracemalloc.get_traced_memory()[1], g
        finally:
            tracemalloc.stop()

    full_peak, full = peak()
    part_peak, part = peak(blocks=[2])
    block_bytes = n ** 3 * 3 * 8
    assert full_peak >= 4 * block_bytes
    assert block_bytes <= part_peak < 1.25 * block_bytes, (part_peak, full_peak)
    assert part_peak < 0.32 * full_peak
    assert part[0] == full[2]


# ----------------------------------------------------------------------------- partition

def loads(dims, parts):
    return [sum(int(np.prod(dims[n])) for n in p) for p in parts]


@settings(max_examples=40, deadline=None)
@given(dims=st.lists(st.tuples(st.integers(1, 30), st.integers(1, 30), st.integers(1, 30)),
                     min_size=1, max_size=40),
       data=st.data())
def test_partition_is_a_balanced_cover(dims, data):
    nparts = data.draw(st.integers(1, len(dims)))
    parts = tq.partition(dims, nparts)
    assert len(parts) == nparts and all(parts)
    assert sorted(n for p in parts for n in p) == list(range(len(dims)))
    assert all(p == sorted(p) for p in parts)
    load = loads(dims, parts)
    sizes = [int(np.prod(d)) for d in dims]
    # greedy largest-first: no part exceeds the mean by more than the largest block
    assert max(load) <= sum(sizes) / nparts + max(sizes)
    # and no block would make a lighter part heavier than it makes its own (list scheduling)
    for p, part in enumerate(parts):
        last = min(part, key=lambda n: (sizes[n], -n))
        assert load[p] - sizes[last] <= min(load)
    assert tq.partition(dims, nparts) == parts                       # deterministic
    assert tq.partition([tuple(np.int64(v) for v in d) for d in dims], np.int32(nparts)) == parts


def test_partition_examples_and_ties():
    assert tq.partition([(10, 10, 10), (10, 10, 5), (10, 10, 5), (4, 4, 4)], 2) == [[0, 3], [1, 2]]
    # equal blocks: dealt round-robin in block order
    assert tq.partition([(2, 2, 2)] * 5, 2) == [[0, 2, 4], [1, 3]]
    assert tq.partition([(2, 2, 2)] * 3, 3) == [[0], [1], [2]]
    assert tq.partition([(5, 1, 1)], 1) == [[0]]
    grid = random_grid([(3, 3, 3), (5, 5, 5), (2, 2, 2)])
    assert tq.partition(grid, 2) == tq.partition(grid.dims, 2) == [[1], [0, 2]]


@pytest.mark.parametrize("nparts, match", [(0, "nparts must be >= 1"), (-2, "nparts must be >= 1"),
                                           (4, "4 parts for 3 block"), (2.0, "must be an integer"),
                                           (True, "must be an integer")])
def test_partition_errors(nparts, match):
    with pytest.raises(GridValueError, match=match):
        tq.partition([(2, 2, 2)] * 3, nparts)


def test_partition_bad_dims():
    with pytest.raises(GridValueError, match="block 1: dims"):
        tq.partition([(2, 2, 2), (2, 0, 2)], 1)
    with pytest.raises(GridValueError, match="block 0: dims"):
        tq.partition([(2, 2)], 1)


@pytest.mark.parametrize("module, name", [("hdf5", "g.h5"), ("cgns", "g.cgns")])
def test_hyperslab_faces_match_the_mapped_ones(tmp_path, monkeypatch, module, name):
    # datasets that cannot be memory-mapped (chunked, filtered, external) are read by hyperslabs
    import importlib
    grid = random_grid([(4, 3, 5), (2, 6, 3)], seed=3)
    path = tmp_path / name
    tq.write(path, grid)
    mod = importlib.import_module(f"tfi_quat.io.{module}")
    offsets = []
    real = mod.mapped_offset
    monkeypatch.setattr(mod, "mapped_offset", lambda *a: offsets.append(real(*a)) or offsets[-1])
    mapped = tq.read_faces(path)
    assert offsets and None not in offsets          # the files tfi_quat writes are mapped
    monkeypatch.setattr(mod, "mapped_offset", lambda *a: None)
    slabs = tq.read_faces(path)
    check_against_full(path, tq.read(path), [1], tq.read(path, blocks=[1]), slabs)
    for a, b in zip(mapped.faces, slabs.faces):
        assert all(np.array_equal(x, y) for x, y in zip(a, b))


@pytest.mark.parametrize("name", ["g.x", "g.g", "g.fmt", "g.h5", "g.cgns"])
def test_faces_of_some_blocks(tmp_path, name):
    grid = random_grid([(3, 4, 5), (5, 4, 3), (2, 2, 2)], seed=5)
    path = tmp_path / name
    tq.write(path, grid, **{"g.g": dict(encoding="fortran"), "g.fmt": dict(encoding="ascii")}.get(name, {}))
    full, every = tq.read(path), tq.read_faces(path)
    assert name != "g.fmt" or full.source_format.encoding == "ascii"
    some = tq.read_faces(path, blocks=[2, 0])
    assert some.block_ids == (2, 0) and every.block_ids is None
    assert some.dims == every.dims and some.names == every.names
    assert some.faces[1] is None
    for n in (0, 2):
        for f in FACES:
            assert np.array_equal(some.face(n, f), full[n].face(f))
    with pytest.raises(GridValueError, match=r"block 1 were not read \(read_faces with blocks=\[2, 0\]\)"):
        some.face(1, "imin")
    with pytest.raises(GridValueError, match="block 3 out of range"):
        tq.read_faces(path, blocks=[3])


@pytest.mark.parametrize("name", ["g.x", "g.h5", "g.cgns"])
def test_faces_allocate_the_faces_only(tmp_path, name):
    n = 40
    grid = random_grid([(n, n, n)] * 4)
    path = tmp_path / name
    tq.write(path, grid)
    del grid
    tracemalloc.start()
    try:
        faces = tq.read_faces(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    face_bytes = 4 * 6 * n * n * 3 * 8                  # 0.9 MB, against 6.1 MB of volume
    assert face_bytes <= peak < 1.5 * face_bytes + (256 << 10), peak
    assert faces.npoints == 4 * n ** 3
