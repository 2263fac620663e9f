"""Damaged and hostile HDF5 files: every one ends in a clear error, never a crash, hang,
unbounded allocation or silently wrong grid.

The files under ``tests/data/robustness`` are byte-flipped copies of ``g.h5`` (a two-block
grid written by an earlier tfi_quat) on which libhdf5 itself segfaults (``segv_*``), loops
forever (``hang``) or allocates gigabytes (``heap_3GB``) when their attributes are read, and
two files that an earlier reader accepted silently (``a``: ``nblocks`` smaller than the stored
blocks; ``b``: an int64 IBLANK beyond int32).  The crash and hang cases run the read in a
subprocess with a timeout (the read there is in-process, guarded): if the guard regressed,
that subprocess would die, not the test session.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
import threading
import tracemalloc
import zlib
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import tfi_quat
from tfi_quat import Block, Grid, GridFormatError
from tfi_quat.io import hdf5

from conftest import sheared_box

DATA = Path(__file__).parent / "data" / "robustness"
ROOT = Path(__file__).resolve().parents[1]


def run_python(code: str, timeout: float = 120, **kw) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter (the project on its path) and return the result."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT, env=env, **kw)


READ_ALL = """
    import sys
    import tfi_quat as tq
    from tfi_quat.io import hdf5
    hdf5.GUARD_CPU_SECONDS = {cpu}
    path = sys.argv[1] if len(sys.argv) > 1 else {path!r}
    for name, fn in [("read", tq.read), ("info", hdf5.info), ("read_block", lambda p: hdf5.read_block(p, 1)),
                     ("read_face", lambda p: hdf5.read_face(p, 1, "jmax")), ("read_extra", hdf5.read_extra)]:
        try:
            fn(path)
            print(name, "READ WITHOUT ERROR")
        except tq.GridFormatError as exc:
            print(name, "GridFormatError:", exc)
"""


# ----------------------------------------------------------------------------- crash, hang, heap

@pytest.mark.parametrize("name, message", [
    ("segv_plain.h5", r"libhdf5 crashed \(SIGSEGV\) reading attribute 'name' of /blocks/000001"),
    ("segv_gzip.h5", r"libhdf5 crashed \(SIGSEGV\) reading attribute 'format' of the root group"),
    ("hang.h5", r"libhdf5 used more than 1 s of CPU reading attribute 'created' of the root group"),
    ("heap_3GB.h5", r"reading attribute 'name' of /blocks/000002: .*memory allocation failed"),
])
def test_damaged_metadata_is_refused_by_every_reader(name, message):
    """libhdf5 crashes, loops or allocates GBs on these files; each reader refuses them, named."""
    out = run_python(READ_ALL.format(cpu=1, path=str(DATA / name)), timeout=300)
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])
    lines = out.stdout.splitlines()
    assert [ln.split()[0] for ln in lines] == ["read", "info", "read_block", "read_face", "read_extra"]
    for ln in lines:
        assert f"GridFormatError: {DATA / name}: damaged HDF5 file: " in ln
        assert __import__("re").search(message, ln), ln


def test_crash_case_in_process(tmp_path):
    """The point of the guard: the read runs in this very process and gets an error."""
    with pytest.raises(GridFormatError, match=r"segv_gzip\.h5: damaged HDF5 file: libhdf5 crashed "
                                              r"\(SIGSEGV\) reading attribute 'format' of the root group"):
        hdf5.read(DATA / "segv_gzip.h5")


def test_heap_case_under_an_address_space_limit():
    """The 3 GB case under a 4 GiB limit of the whole process: a clean error, fast."""
    code = f"""
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))
        import tfi_quat as tq
        try:
            tq.read({str(DATA / 'heap_3GB.h5')!r})
        except tq.GridFormatError as exc:
            print(exc)
    """
    out = run_python(code)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "heap_3GB.h5: damaged HDF5 file: reading attribute 'name' of /blocks/000002" in out.stdout


def test_hang_case_in_process(monkeypatch):
    monkeypatch.setattr(hdf5, "GUARD_CPU_SECONDS", 1)
    with pytest.raises(GridFormatError, match=r"hang\.h5: damaged HDF5 file: libhdf5 used more than 1 s "
                                              r"of CPU reading attribute 'created'.*GUARD_CPU_SECONDS"):
        hdf5.info(DATA / "hang.h5")


def test_wall_clock_limit_names_the_step(monkeypatch):
    """A step that makes no progress for GUARD_WALL_SECONDS (here: the CPU loop) is ended too."""
    monkeypatch.setattr(hdf5, "GUARD_CPU_SECONDS", 600)
    monkeypatch.setattr(hdf5, "GUARD_WALL_SECONDS", 1)
    with pytest.raises(GridFormatError, match=r"hang\.h5: damaged HDF5 file: reading attribute 'created' "
                                              r"of the root group did not end within 1 s"):
        hdf5.read(DATA / "hang.h5")


def test_the_seed_file_reads():
    """The undamaged file the mutants came from (an earlier writer's layout) still reads."""
    grid = hdf5.read(DATA / "g.h5")
    assert [b.dims for b in grid] == [(5, 4, 3), (4, 4, 3)]


def test_guard_child_limits_do_not_leak_into_the_caller():
    import resource
    before = [resource.getrlimit(r) for r in (resource.RLIMIT_AS, resource.RLIMIT_CPU, resource.RLIMIT_CORE)]
    with pytest.raises(GridFormatError):
        hdf5.read(DATA / "segv_plain.h5")
    hdf5.read(DATA / "g.h5")
    after = [resource.getrlimit(r) for r in (resource.RLIMIT_AS, resource.RLIMIT_CPU, resource.RLIMIT_CORE)]
    assert before == after


def test_guard_with_numba_and_h5py_threads(tmp_path):
    """Forking while numba's pool and other h5py users run: reads still succeed, repeatedly."""
    import numba

    @numba.njit(parallel=True, cache=False)
    def psum(a):
        s = 0.0
        for i in numba.prange(a.size):
            s += a[i]
        return s

    assert psum(np.ones(100_000)) == 100_000.0  # starts numba's worker threads
    p = tmp_path / "g.h5"
    grid = Grid([Block(sheared_box(6, 5, 4))])
    hdf5.write(p, grid)
    stop = threading.Event()
    errors = []

    def busy():  # another thread in and out of h5py's lock the whole time
        while not stop.is_set():
            try:
                with h5py.File(p, "r") as f:
                    f["blocks/000001/xyz"][0, 0, 0, 0]
            except Exception as exc:  # pragma: no cover
                errors.append(exc)

    t = threading.Thread(target=busy)
    t.start()
    try:
        for _ in range(10):
            assert hdf5.read(p) == grid
    finally:
        stop.set()
        t.join()
    assert not errors


def test_damage_to_files_we_write_is_caught_by_checksums(tmp_path):
    """Flipped bytes in a file written now: the metadata checksums catch them; never a crash.

    Runs in a subprocess (a crash there cannot end the session); checks that the guard's
    child never had to stop libhdf5 (no crash, no CPU overrun): the checksums did the work.
    """
    code = f"""
        import numpy as np
        import tfi_quat as tq
        from tfi_quat.io import hdf5
        hdf5.GUARD_CPU_SECONDS = 2
        rng = np.random.default_rng(5)
        xyz = np.asfortranarray(rng.random((5, 4, 3, 3)))
        g = tq.Grid([tq.Block(xyz, name="wing"), tq.Block(xyz[:4] + 1.0, np.ones((4, 4, 3), int))])
        for comp in (None, "gzip"):
            src = {str(tmp_path)!r} + f"/src_{{comp}}.h5"
            hdf5.write(src, g, compression=comp)
            data = open(src, "rb").read()
            for t in range(25):
                m = bytearray(data)
                for _ in range(int(rng.integers(1, 8))):
                    m[int(rng.integers(0, len(m)))] ^= 1 << int(rng.integers(0, 8))
                p = {str(tmp_path)!r} + "/m.h5"
                open(p, "wb").write(m)
                try:
                    hdf5.read(p)
                    print("read")
                except tq.GridFormatError as exc:
                    print("crashed" if "crashed" in str(exc) or "CPU" in str(exc) else "error")
    """
    out = run_python(code, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    outcomes = out.stdout.split()
    assert len(outcomes) == 50
    assert "crashed" not in outcomes
    assert outcomes.count("error") >= 25


# ----------------------------------------------------------------------------- silent drops

def test_nblocks_smaller_than_the_stored_blocks():
    with pytest.raises(GridFormatError, match=r"a\.h5: /blocks holds /blocks/000002, beyond the root "
                                              r"attribute nblocks = 1"):
        tfi_quat.read(DATA / "a.h5")


def test_more_than_three_extra_blocks_are_counted(tmp_path):
    p = tmp_path / "g.h5"
    hdf5.write(p, Grid([Block(sheared_box(3, 3, 2))] * 6))
    with h5py.File(p, "r+") as f:
        f.attrs["nblocks"] = 1
    with pytest.raises(GridFormatError, match=r"holds /blocks/000002, /blocks/000003, /blocks/000004 "
                                              r"\(and 2 more\), beyond the root attribute nblocks = 1"):
        hdf5.read_block(p, 0)


def test_iblank_beyond_int32():
    with pytest.raises(GridFormatError, match=r"b\.h5: block 1, dataset /blocks/000001/iblank: 60 IBLANK "
                                              r"value\(s\) beyond int32, first 1099511627781 at point "
                                              r"\(1, 1, 1\)"):
        tfi_quat.read(DATA / "b.h5")


@given(values=st.lists(st.integers(-2**63, 2**64 - 1), min_size=12, max_size=12),
       dtype=st.sampled_from(["<i8", ">i8", "<u4", "<u8", "<i4", "<i2", "<u2"]),
       gzip=st.booleans())
def test_iblank_of_any_integer_type_reads_exactly_or_is_refused(tmp_path_factory, values, dtype, gzip):
    dt = np.dtype(dtype)
    info = np.iinfo(dt)
    arr = np.array([min(max(v, info.min), info.max) for v in values], dtype=object).astype(dt)
    p = tmp_path_factory.mktemp("ib") / "g.h5"
    hdf5.write(p, Grid([Block(sheared_box(3, 2, 2))]))
    with h5py.File(p, "r+") as f:
        f["blocks/000001"].create_dataset("iblank", data=arr.reshape(2, 2, 3),
                                          compression="gzip" if gzip else None)
    fits = all(-2**31 <= int(v) < 2**31 for v in arr)
    if fits:
        ib = hdf5.read(p)[0].iblank
        assert ib.dtype == np.int32
        assert [int(v) for v in ib.T.ravel()] == [int(v) for v in arr]
    else:
        with pytest.raises(GridFormatError, match=r"IBLANK value\(s\) beyond int32"):
            hdf5.read(p)


# ----------------------------------------------------------------------------- size cap

@pytest.fixture(scope="module")
def bomb(tmp_path_factory):
    """A 12 MB file whose one block declares 800^3 points (gzip chunks of a constant)."""
    p = tmp_path_factory.mktemp("bomb") / "bomb.h5"
    n, chunk = 800, (1, 100, 800, 800)
    z = zlib.compressobj(1)
    piece = np.ones(1 << 20, dtype="<f8").tobytes()
    stream = b"".join(z.compress(piece) for _ in range(int(np.prod(chunk)) * 8 // len(piece))) + z.flush()
    with h5py.File(p, "w") as f:
        f.attrs.update(format="tfi_quat-grid", version=1, ndim=3, nblocks=1)
        g = f.create_group("blocks/000001")
        g.attrs["name"] = "bomb"
        g.attrs["dims"] = np.array([n, n, n])
        ds = g.create_dataset("xyz", shape=(3, n, n, n), dtype="<f8", chunks=chunk, compression="gzip")
        for c in range(3):
            for k in range(0, n, chunk[1]):
                ds.id.write_direct_chunk((c, k, 0, 0), stream)
    return p


def test_declared_size_beyond_max_points(bomb):
    tracemalloc.start()
    try:
        with pytest.raises(GridFormatError, match=r"bomb\.h5: 1 block\(s\): declares 512,000,000 points, "
                                                  r"more than max_points=100,000,000"):
            tfi_quat.read(bomb, max_points=10**8)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 10 << 20
    with pytest.raises(GridFormatError, match=r"bomb\.h5: block 1: declares 512,000,000 points"):
        hdf5.read_block(bomb, 0, max_points=10**6)
    with pytest.raises(GridFormatError, match=r"bomb\.h5: block 1 face kmax: declares 640,000 points"):
        hdf5.read_face(bomb, 0, "kmax", max_points=10**5)
    assert hdf5.info(bomb).npoints == 800**3  # metadata only: no cap


def test_declared_size_beyond_memory(bomb, monkeypatch):
    """Without max_points the cap is the memory available (here: pretended to be 1 GiB)."""
    from tfi_quat.io import _limits
    monkeypatch.setattr(_limits, "available_memory", lambda: 1 << 30)
    with pytest.raises(GridFormatError, match=r"bomb\.h5: 1 block\(s\): declares 512,000,000 points "
                                              r"\(13\.4 GiB\), more than the 1\.0 GiB of memory available"):
        hdf5.read(bomb)


def test_bomb_under_an_address_space_limit(bomb):
    """The reproducer: a 4 GiB limit on the process; a GridFormatError, not numpy's MemoryError."""
    code = f"""
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))
        import tfi_quat as tq
        try:
            tq.read({str(bomb)!r})
        except tq.GridFormatError as exc:
            print("GridFormatError:", exc)
    """
    out = run_python(code)
    assert out.returncode == 0, out.stderr[-2000:]
    assert f"GridFormatError: {bomb}: " in out.stdout
    assert "declares 512,000,000 points" in out.stdout or "cannot allocate 12,288,000,000 bytes" in out.stdout


def _chunked_file(path, stream, n=8):
    """A valid gzip file of one n^3 block whose xyz chunk (0, 0, 0, 0) is replaced by ``stream``."""
    grid = Grid([Block(sheared_box(n, n, n))])
    hdf5.write(path, grid, compression="gzip")
    with h5py.File(path, "r+") as f:
        f["blocks/000001/xyz"].id.write_direct_chunk((0, 0, 0, 0), stream)
    return grid


def test_gzip_chunk_that_inflates_beyond_its_size(tmp_path):
    """libhdf5 would inflate it to 64 MiB and return without error; the reader stops at 500 KB.

    The block is 50^3 in chunks of 40^3: face kmax does not touch chunk (0, 0, 0, 0).
    """
    p = tmp_path / "g.h5"
    _chunked_file(p, zlib.compress(bytes(64 << 20), 9), n=50)
    tracemalloc.start()
    try:
        with pytest.raises(GridFormatError, match=r"g\.h5: block 1, dataset /blocks/000001/xyz: chunk "
                                                  r"\(0, 0, 0, 0\): inflates to more than the chunk's 512000 "
                                                  r"bytes \(a decompression bomb\)"):
            hdf5.read(p)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 50**3 * 3 * 8 + (2 << 20)  # the grid and a few chunks, not 64 MiB
    with pytest.raises(GridFormatError, match="decompression bomb"):
        hdf5.read_face(p, 0, "imin")
    hdf5.read_face(p, 0, "kmax")  # other chunks only


def test_gzip_chunk_larger_than_any_compressed_chunk(tmp_path):
    p = tmp_path / "g.h5"
    _chunked_file(p, zlib.compress(np.random.default_rng(1).bytes(64 << 10), 0))
    with pytest.raises(GridFormatError, match=r"g\.h5: damaged HDF5 file: reading the chunk index of dataset "
                                              r"/blocks/000001/xyz: .*chunk \(0, 0, 0, 0\) of \d+ bytes"):
        hdf5.read(p)


@pytest.mark.parametrize("stream, message", [
    (b"\x78\x9c" + b"garbage" * 10, r"corrupt gzip data"),
    (zlib.compress(bytes(4096))[:-8], r"the gzip stream is cut short"),
    (zlib.compress(bytes(1000)), r"holds 1000 bytes after decompression, expected 4096"),
])
def test_corrupt_gzip_chunks(tmp_path, stream, message):
    p = tmp_path / "g.h5"
    _chunked_file(p, stream)
    with pytest.raises(GridFormatError, match=r"g\.h5: block 1, dataset /blocks/000001/xyz: chunk "
                                              r"\(0, 0, 0, 0\): " + message):
        hdf5.read(p)


def test_gzip_without_shuffle_and_unfiltered_chunks_read(tmp_path):
    """Foreign gzip files: without shuffle, and with a chunk stored unfiltered (filter mask)."""
    xyz = sheared_box(8, 8, 8)
    p = tmp_path / "g.h5"
    with h5py.File(p, "w") as f:
        f.attrs.update(format="tfi_quat-grid", version=1, ndim=3, nblocks=1)
        g = f.create_group("blocks/000001")
        g.attrs.update(name="", dims=np.array([8, 8, 8]))
        ds = g.create_dataset("xyz", data=xyz.T, chunks=(1, 8, 8, 4), compression="gzip")
        raw = np.ascontiguousarray(xyz.T[1, :, :, 4:]).tobytes()
        ds.id.write_direct_chunk((1, 0, 0, 4), raw, filter_mask=1)
    np.testing.assert_array_equal(hdf5.read(p)[0].xyz, xyz)
    np.testing.assert_array_equal(hdf5.read_face(p, 0, "imax"), xyz[-1])


def test_filters_outside_the_layout_are_refused(tmp_path):
    p = tmp_path / "g.h5"
    hdf5.write(p, Grid([Block(sheared_box(4, 4, 4))]))
    with h5py.File(p, "r+") as f:
        xyz = f["blocks/000001/xyz"][()]
        del f["blocks/000001/xyz"]
        f["blocks/000001"].create_dataset("xyz", data=xyz, compression="lzf")
    with pytest.raises(GridFormatError, match=r"dataset /blocks/000001/xyz: filter 'lzf' is not part of "
                                              r"the layout"):
        hdf5.read(p)


# ----------------------------------------------------------------------------- OS errors

READERS = [hdf5.read, hdf5.info, hdf5.read_extra, lambda p: hdf5.read_block(p, 0),
           lambda p: hdf5.read_face(p, 0, 0)]


@pytest.mark.parametrize("fn", [tfi_quat.read] + READERS)
def test_missing_file_is_a_file_not_found_error(tmp_path, fn):
    with pytest.raises(FileNotFoundError, match=r"missing\.h5"):
        fn(tmp_path / "missing.h5")


@pytest.mark.parametrize("fn", READERS)
def test_folder_is_an_is_a_directory_error(tmp_path, fn):
    folder = tmp_path / "folder.h5"
    folder.mkdir()
    with pytest.raises(IsADirectoryError, match=r"folder\.h5"):
        fn(folder)


def _outcome_as_nobody(fn) -> str:
    """``fn()``'s outcome (its exception, as text) with no privilege to bypass file modes.

    As root (who may read anything) ``fn`` runs in a forked child that has switched to
    the user nobody; otherwise here.
    """
    def outcome():
        try:
            fn()
            return "no error"
        except Exception as exc:
            return f"{type(exc).__name__}: {exc}"

    if os.geteuid() != 0:
        return outcome()
    import resource  # noqa: F401  (imported before the switch: nobody cannot read the stdlib here)
    rfd, wfd = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover
        try:
            os.close(rfd)
            os.setgroups([])
            os.setgid(65534)
            os.setuid(65534)
            os.write(wfd, outcome().encode())
        finally:
            os._exit(0)
    os.close(wfd)
    with os.fdopen(rfd, "rb") as fh:
        text = fh.read().decode()
    os.waitpid(pid, 0)
    return text


def test_unreadable_file_is_a_permission_error():
    """Not 'no HDF5 signature': the OS's PermissionError, naming the path."""
    import tempfile
    folder = Path(tempfile.mkdtemp(prefix="tfi_quat_perm_"))
    try:
        folder.chmod(0o755)
        p = folder / "locked.h5"
        hdf5.write(p, Grid([Block(sheared_box(3, 3, 3))]))
        p.chmod(0)
        for fn in (hdf5.read, hdf5.info, lambda q: hdf5.read_face(q, 0, 0)):
            assert _outcome_as_nobody(lambda: fn(p)) == \
                f"PermissionError: [Errno 13] Permission denied: '{p}'"
    finally:
        shutil.rmtree(folder)


def test_copy_of_a_reproducer_keeps_its_outcome(tmp_path):
    """The guard looks at the bytes, not the name or place: a copy is refused the same way."""
    q = tmp_path / "copy.hdf5"
    shutil.copy(DATA / "segv_plain.h5", q)
    with pytest.raises(GridFormatError, match=r"copy\.hdf5: damaged HDF5 file: libhdf5 crashed"):
        tfi_quat.read(q)


def test_guard_runs_once_per_unchanged_file(tmp_path, monkeypatch):
    """A file that passed is not walked again until it changes; a changed file is walked."""
    forks = []
    fork = os.fork

    def counting_fork():
        forks.append(1)
        return fork()

    monkeypatch.setattr(os, "fork", counting_fork)
    p = tmp_path / "g.h5"
    hdf5.write(p, Grid([Block(sheared_box(4, 3, 2))]))
    hdf5.read(p)
    hdf5.info(p)
    hdf5.read_face(p, 0, "imin")
    assert len(forks) == 1
    # the same path, now holding damaged bytes: walked again, refused
    p.write_bytes((DATA / "segv_plain.h5").read_bytes())
    with pytest.raises(GridFormatError, match=r"g\.h5: damaged HDF5 file: libhdf5 crashed"):
        hdf5.read(p)
    assert len(forks) == 2
    with pytest.raises(GridFormatError, match=r"libhdf5 crashed"):
        hdf5.read(p)  # a refusal is not remembered
    assert len(forks) == 3


def test_file_objects_are_guarded_too():
    with open(DATA / "segv_gzip.h5", "rb") as fh:
        with pytest.raises(GridFormatError, match=r"damaged HDF5 file: libhdf5 crashed \(SIGSEGV\) reading "
                                                  r"attribute 'format' of the root group"):
            hdf5.info(fh)
        with open(DATA / "g.h5", "rb") as good:
            assert hdf5.info(good).nblocks == 2
