"""Benchmark of the TFI volume stage (docs/method.md §6): fused quaternion kernel, baseline, arclength.

Prints points per second, bytes moved per point and the ratio of the
kernel's effective bandwidth to the machine's streaming bandwidth, measured
in the same run by two parallel numba streams over the same bytes: ``add``
(``c = a + b`` on three arrays the size of ``R_u``: reads 48 and writes 24
bytes per point, exactly the volume stage's traffic, so its points/s is the
roofline) and a plain copy.  Every figure is the best of ``--repeat`` runs
(the machine is shared: the best run is the least disturbed one).

The Deformer's case is timed beside it: face values as rows of global
arrays, ``deform_block_gathered`` (faces gathered inside the compiled
set-up, tables kept in its plan) against the old path (a numpy gather per
face, then ``deform_block(..., check=False)``), whole call and the
O(surface) tables alone.

With ``--setup-wing SCALE`` it times instead the Deformer's volume-sized
set-up on the blocks of the multiblock wing (``tfi_quat.deform.twolevel.WallLayer.block``):
``tfi.arclength`` then ``blending.wall_layer_block(..., out=s)``, against the
kernels they replaced (frozen copies below, run in the same process,
interleaved) and against the fused ``blending.wall_layer_arclength``; it
checks that all three give the same bits.

With ``--old PATH`` (a checkout of an older version of the repository, e.g.
``git clone -q <repo> /tmp/old``) it times instead the fused volume kernels
of that version and of this one side by side in one process: the old
package is imported as ``tfi_quat_old``, both run on the same arrays and
tables, alternately (``best_interleaved``), and the script prints each
kernel's best time, the ratio old/new (>= 1: the new code is as fast) and
whether both give the same bits.

Usage::

    python3 benchmarks/bench_tfi.py                 # 10.1 M points (216^3)
    python3 benchmarks/bench_tfi.py --old /tmp/old --points 2e6 --repeat 7
    NUMBA_NUM_THREADS=1 python3 benchmarks/bench_tfi.py --old /tmp/old --cpu   # loaded machine
    python3 benchmarks/bench_tfi.py --points 2e5    # quick
    python3 benchmarks/bench_tfi.py --setup-wing 2.8 --repeat 9    # 10.9 M points, 4 blocks
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import pickle
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

# numba's parallel loops (the old code of --old, the streams) run on OpenMP, whose threads
# spin after each loop by default: interleaved with the package's thread pool, a spinning
# OpenMP thread holds the second core while the pool's thread wants it (measured: the new
# kernels at 0.58-0.65x of the old with spinning, 0.90-1.12x without).  Both sides wait
# passively here, as the package's pool always does; set OMP_WAIT_POLICY to override.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from tfi_quat import blending, tfi  # noqa: E402
from tfi_quat._jit import numba, threads  # noqa: E402

# the references this script compares against (streams, frozen old kernels) are numba
# parallel loops, as the package's kernels were before its own thread pool (tfi_quat._jit)
pjit = functools.partial(numba.njit, error_model="numpy", nogil=True, parallel=True)
prange = numba.prange
from tfi_quat.grid import Block  # noqa: E402
from tfi_quat.quaternion import normalize  # noqa: E402


@pjit

def dfun(p):
    """A smooth displacement field of the coordinates (face values that agree at the edges)."""
    return 0.01 * np.sin(p)


def qfun(p):
    """A smooth unit-quaternion field of the coordinates (small rotations)."""
    rv = 0.05 * np.cos(p)
    ang = np.linalg.norm(rv, axis=-1, keepdims=True)
    return normalize(np.concatenate([np.cos(ang / 2), np.sin(ang / 2) * rv / np.maximum(ang, 1e-300)], -1))

def _copy(src, dst):
    """Parallel copy (one flat ``prange``; a blocked loop ran at half the bandwidth)."""
    for m in prange(src.shape[0]):
        dst[m] = src[m]


@pjit
def _add(a, b, c):
    """STREAM add ``c = a + b``: two read streams and one write stream, as the volume stage."""
    for m in prange(a.shape[0]):
        c[m] = a[m] + b[m]


def best(fn, repeat):
    t = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return min(t)


#: the clock of best_interleaved: wall time, or with --cpu the calling thread's CPU time
_CLOCK = time.perf_counter


def best_interleaved(fns, repeat):
    """Best time of each function, the functions run in turn (A/B under the same load)."""
    t = [[] for _ in fns]
    for _ in range(repeat):
        for m, fn in enumerate(fns):
            t0 = _CLOCK()
            fn()
            t[m].append(_CLOCK() - t0)
    return [min(v) for v in t]


def make_block(n):
    """A stretched, sheared, warped box with n^3 points (float64, F order)."""
    u = np.linspace(0.0, 1.0, n)
    g = (np.exp(3.0 * u) - 1.0) / (np.exp(3.0) - 1.0)        # wall-clustered
    xyz = np.empty((n, n, n, 3), order="F")
    i, j, k = u[:, None, None], u[None, :, None], g[None, None, :]
    xyz[..., 0] = 2.0 * i + 0.3 * j + 0.05 * np.sin(3.0 * k)
    xyz[..., 1] = 1.5 * j + 0.2 * k + 0.02 * i * i
    xyz[..., 2] = 1.0 * k + 0.1 * i * j
    return xyz


def global_rows(xyz):
    """The block's face points as rows of global arrays, as the Deformer numbers them.

    Returns the six faces' row arrays (face ``f`` of shape ``Block.face(f).shape[:2]``;
    points shared by faces share a row, rows in the order of the block points)
    and the points of the rows (G, 3).
    """
    dims = xyz.shape[:3]
    flat = np.arange(int(np.prod(dims))).reshape(dims, order="F")
    keys = []
    for f in range(6):
        idx = [slice(None)] * 3
        idx[f // 2] = dims[f // 2] - 1 if f % 2 else 0
        keys.append(flat[tuple(idx)])
    uk = np.unique(np.concatenate([k.ravel() for k in keys]))
    rows = [np.searchsorted(uk, k).astype(np.int64) for k in keys]
    return rows, xyz.reshape(-1, 3, order="F")[uk]


# ------------------------------------------------- the Deformer's set-up on the wing
# Frozen copies of the kernels before the tiled rewrite (tfi._arclength_kernel,
# blending._layer_block_dir), the reference of the --setup-wing timings.
@numba.njit(inline="always")
def _old_dist(xyz, i0, j0, k0, i1, j1, k1):
    dx = xyz[i1, j1, k1, 0] - xyz[i0, j0, k0, 0]
    dy = xyz[i1, j1, k1, 1] - xyz[i0, j0, k0, 1]
    dz = xyz[i1, j1, k1, 2] - xyz[i0, j0, k0, 2]
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@numba.njit(inline="always")
def _old_mag(xyz, i0, j0, k0, i1, j1, k1):
    return max(abs(xyz[i0, j0, k0, 0]), abs(xyz[i0, j0, k0, 1]), abs(xyz[i0, j0, k0, 2]),
               abs(xyz[i1, j1, k1, 0]), abs(xyz[i1, j1, k1, 1]), abs(xyz[i1, j1, k1, 2]))


@pjit
def _old_arclength_kernel(xyz, s, rtol):
    ni, nj, nk = xyz.shape[0], xyz.shape[1], xyz.shape[2]
    for k in prange(nk):
        buf = np.empty(ni)
        acc = np.zeros(ni)
        col = np.empty((ni, nj))
        for j in range(nj):
            if ni == 1:
                s[0, j, k, 0] = 0.0
                continue
            a = 0.0
            buf[0] = 0.0
            for i in range(1, ni):
                a += _old_dist(xyz, i - 1, j, k, i, j, k)
                buf[i] = a
            if not a > rtol * _old_mag(xyz, 0, j, k, ni - 1, j, k):
                for i in range(ni):
                    buf[i] = i
                a = ni - 1.0
            for i in range(ni - 1):
                s[i, j, k, 0] = buf[i] / a
            s[ni - 1, j, k, 0] = 1.0
        if nj == 1:
            for i in range(ni):
                s[i, 0, k, 1] = 0.0
        else:
            for i in range(ni):
                col[i, 0] = 0.0
            for j in range(1, nj):
                for i in range(ni):
                    acc[i] += _old_dist(xyz, i, j - 1, k, i, j, k)
                    col[i, j] = acc[i]
            for i in range(ni):
                if not acc[i] > rtol * _old_mag(xyz, i, 0, k, i, nj - 1, k):
                    for j in range(nj):
                        col[i, j] = j
                    acc[i] = nj - 1.0
            for j in range(nj - 1):
                for i in range(ni):
                    s[i, j, k, 1] = col[i, j] / acc[i]
            for i in range(ni):
                s[i, nj - 1, k, 1] = 1.0
    for j in prange(nj):
        if nk == 1:
            for i in range(ni):
                s[i, j, 0, 2] = 0.0
            continue
        acc = np.zeros(ni)
        col = np.empty((ni, nk))
        for i in range(ni):
            col[i, 0] = 0.0
        for k in range(1, nk):
            for i in range(ni):
                acc[i] += _old_dist(xyz, i, j, k - 1, i, j, k)
                col[i, k] = acc[i]
        for i in range(ni):
            if not acc[i] > rtol * _old_mag(xyz, i, j, 0, i, j, nk - 1):
                for k in range(nk):
                    col[i, k] = k
                acc[i] = nk - 1.0
        for k in range(nk - 1):
            for i in range(ni):
                s[i, j, k, 2] = col[i, k] / acc[i]
        for i in range(ni):
            s[i, j, nk - 1, 2] = 1.0


@pjit
def _old_layer_block_dir(xyz, s, d, lam0, lam1, out):
    ni, nj, nk = xyz.shape[0], xyz.shape[1], xyz.shape[2]
    dims = (ni, nj, nk)
    n = dims[d]
    if d == 0:
        na, nb = nj, nk
    elif d == 1:
        na, nb = ni, nk
    else:
        na, nb = ni, nj
    for ab in prange(na * nb):
        a = ab % na
        b = ab // na
        line = np.empty(n)
        res = np.empty(n)
        length = 0.0
        px = py = pz = 0.0
        for m in range(n):
            if d == 0:
                i, j, k = m, a, b
            elif d == 1:
                i, j, k = a, m, b
            else:
                i, j, k = a, b, m
            line[m] = s[i, j, k, d]
            x = xyz[i, j, k, 0]
            y = xyz[i, j, k, 1]
            z = xyz[i, j, k, 2]
            if m > 0:
                length += math.sqrt((x - px) ** 2 + (y - py) ** 2 + (z - pz) ** 2)
            px, py, pz = x, y, z
        blending._layer_line(line, length, lam0[a, b], lam1[a, b], res)
        for m in range(n):
            if d == 0:
                out[m, a, b, d] = res[m]
            elif d == 1:
                out[a, m, b, d] = res[m]
            else:
                out[a, b, m, d] = res[m]


def _old_arclength(xyz):
    s = np.empty(xyz.shape, dtype=np.float64, order="F")
    _old_arclength_kernel(xyz, s, tfi.ZERO_LENGTH_RTOL)
    return s


def _old_wall_layer_block(xyz, s, lam, out):
    """The old ``wall_layer_block`` with ``out is s`` (the Deformer's call)."""
    dims = xyz.shape[:3]
    for d in range(3):
        others = tuple(dims[m] for m in range(3) if m != d)
        l0 = np.ascontiguousarray(lam[2 * d], dtype=np.float64).reshape(others)
        l1 = np.ascontiguousarray(lam[2 * d + 1], dtype=np.float64).reshape(others)
        _old_layer_block_dir(xyz, s, d, l0, l1, out)
    return out


def _wing_blocks(scale, pickled):
    """The wing's blocks and their layer thicknesses as ``tfi_quat.deform.twolevel.WallLayer.block`` builds them."""
    from tfi_quat import generate as gen, topology
    from tfi_quat.deform import Deformer
    if pickled:
        with open(pickled, "rb") as f:
            grid, _, conn = pickle.load(f)
    else:
        def odd4(n):
            n = int(round(n))
            return n + (-(n - 1)) % 4
        grid = gen.wing(ni=odd4(129 * scale), nj=int(49 * scale), nk_wing=int(45 * scale),
                        nk_cap=max(5, int(9 * scale)), nk_out=int(25 * scale))
        bp = gen.boundary_patches("wing", grid)
        conn = topology.connect(grid, walls=bp["walls"], symmetry=bp["symmetry"], fixed=bp["fixed"])
    d = Deformer(grid, connectivity=conn)
    ell = d.rotation_length
    out = []
    for b, blk in enumerate(grid):
        out.append((blk.xyz, [ell * d.two_level.layer.omega[g] for g in d.skeleton.blocks[b].face_gid]))
    return out


def setup_wing(scale, repeat, pickled=None):
    """Old kernels, new ones and the fused driver on the wing's blocks, interleaved; same bits."""
    blocks = _wing_blocks(scale, pickled)
    npts = sum(x.shape[0] * x.shape[1] * x.shape[2] for x, _ in blocks)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"wing {scale}: {len(blocks)} blocks, {npts / 1e6:.2f} M points; "
          f"threads {threads()}; best of {repeat}, interleaved; "
          f"load average {load:.1f} on {os.cpu_count()} CPUs")
    tot = {"old": np.zeros(3), "new": np.zeros(3), "fused": 0.0}
    for b, (xyz, lam) in enumerate(blocks):
        s_old = _old_arclength(xyz)
        s_new = tfi.arclength(xyz)
        same_s = np.array_equal(s_old.view(np.int64), s_new.view(np.int64))
        _old_wall_layer_block(xyz, s_old, lam, s_old)
        blending.wall_layer_block(xyz, s_new, lam, ndim=3, out=s_new)
        fused = blending.wall_layer_arclength(xyz, lam)
        same = (np.array_equal(s_old.view(np.int64), s_new.view(np.int64))
                and np.array_equal(s_old.view(np.int64), fused.view(np.int64)))
        del fused
        # out=s as the Deformer calls it: each repeat starts from a fresh copy of s (not timed)
        s0 = tfi.arclength(xyz)
        work = np.empty_like(s0, order="F")
        t = {k: [] for k in ("old_arc", "old_layer", "new_arc", "new_layer", "fused")}
        for _ in range(repeat):
            t0 = time.perf_counter()
            _old_arclength(xyz)
            t["old_arc"].append(time.perf_counter() - t0)
            work[...] = s0
            t0 = time.perf_counter()
            _old_wall_layer_block(xyz, work, lam, work)
            t["old_layer"].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            tfi.arclength(xyz)
            t["new_arc"].append(time.perf_counter() - t0)
            work[...] = s0
            t0 = time.perf_counter()
            blending.wall_layer_block(xyz, work, lam, ndim=3, out=work)
            t["new_layer"].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            blending.wall_layer_arclength(xyz, lam)
            t["fused"].append(time.perf_counter() - t0)
        m = {k: min(v) for k, v in t.items()}
        old = np.array([m["old_arc"], m["old_layer"], m["old_arc"] + m["old_layer"]])
        new = np.array([m["new_arc"], m["new_layer"], m["new_arc"] + m["new_layer"]])
        tot["old"] += old
        tot["new"] += new
        tot["fused"] += m["fused"]
        shape = "x".join(str(v) for v in xyz.shape[:3])
        print(f"block {b} {shape:>13s}: old arclength {old[0] * 1e3:6.1f} + layer {old[1] * 1e3:6.1f} = "
              f"{old[2] * 1e3:6.1f} ms | new {new[0] * 1e3:6.1f} + {new[1] * 1e3:6.1f} = "
              f"{new[2] * 1e3:6.1f} ms | fused {m['fused'] * 1e3:6.1f} ms | same bits: "
              f"arclength {same_s}, parameters {same}")
    o, n, f = tot["old"], tot["new"], tot["fused"]
    print(f"{'total':<21s}: old arclength {o[0] * 1e3:6.1f} + layer {o[1] * 1e3:6.1f} = {o[2] * 1e3:6.1f} ms "
          f"| new {n[0] * 1e3:6.1f} + {n[1] * 1e3:6.1f} = {n[2] * 1e3:6.1f} ms | fused {f * 1e3:6.1f} ms")
    print(f"speed-up: arclength {o[0] / n[0]:.2f}x, wall_layer_block {o[1] / n[1]:.2f}x, "
          f"set-up {o[2] / n[2]:.2f}x (fused {o[2] / f:.2f}x)")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"load average at the end {load:.1f}")
    return 0


def import_old(path):
    """The package of the checkout at ``path``, imported as ``tfi_quat_old`` (its own numba
    cache, next to its files)."""
    import importlib.util
    root = os.path.join(os.path.abspath(path), "tfi_quat")
    spec = importlib.util.spec_from_file_location("tfi_quat_old", os.path.join(root, "__init__.py"),
                                                  submodule_search_locations=[root])
    if spec is None or not os.path.exists(os.path.join(root, "__init__.py")):
        raise SystemExit(f"--old {path}: no tfi_quat package there")
    pkg = importlib.util.module_from_spec(spec)
    sys.modules["tfi_quat_old"] = pkg
    spec.loader.exec_module(pkg)
    import importlib
    return importlib.import_module("tfi_quat_old.tfi")


def _volume_call(mod, hasn, hasq, based):
    """The volume kernel of one kind of the ``tfi`` module ``mod`` as a call on the whole
    block, ``(xyz, s, out, cx, cy, cz, L, M, N, 8 tables, lineB, gB, hB, bad)``: the kernel
    itself (numba's parallel loops), or its task kernel run by its package's
    ``_jit.parallel_for`` over the k-planes (3-D) or rows (2-D)."""
    kern = mod._volume_kernel(hasn, hasq, based)
    jit = sys.modules[mod.__name__.rsplit(".", 1)[0] + "._jit"]
    if not hasattr(jit, "parallel_for"):
        return kern

    def call(xyz, *rest):
        jit.parallel_for(kern, xyz.shape[2] if hasn else xyz.shape[1], xyz, *rest)
    return call


def _old_volume(old, hasn, hasq, based):
    """The old version's volume kernel of one kind, called with the new kernels' signature
    ``(xyz, s, out, cx, cy, cz, L, M, N, 8 tables, lineB, gB, hB)``."""
    if hasattr(old, "_volume_kernel"):            # an old copy that already has one definition
        kern = _volume_call(old, hasn, hasq, based)
        flags = {}

        def with_flags(xyz, *rest):               # its own fallback flags, made once per shape
            bad = flags.get(xyz.shape)
            if bad is None:
                bad = flags[xyz.shape] = np.zeros(xyz.shape[1] * xyz.shape[2], dtype=bool)
            return kern(xyz, *rest, bad)
        return with_flags
    if hasn:
        k = {(True, False): old._deform3_q, (False, False): old._deform3_d,
             (True, True): old._deform3_qb}[hasq, based]
    else:
        k = {(True, False): old._deform2_q, (False, False): old._deform2_d,
             (True, True): old._deform2_qb}[hasq, based]

    def call(xyz, s, out, cx, cy, cz, L, M, N, lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN, lB, gB, hB):
        lmn = (L, M, N) if hasn else (L, M)
        if not hasq:
            return k(xyz, s, out, *lmn, lineD, gD, hD)
        tabs = (lineD, lineQ, gD, gQ, hD, hQ, fbM, fbN)
        return k(xyz, s, out, cx, cy, cz, *lmn, *tabs, *((lB, gB, hB) if based else ()))
    return call


def side_by_side(path, points, repeat, order):
    """Old and new volume kernels (and arclength) on the same inputs, interleaved."""
    old = import_old(path)
    n3 = max(4, int(round(points ** (1.0 / 3.0))))
    n2 = max(4, int(round(points ** 0.5)))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"old: {os.path.dirname(old.__file__)}  new: {os.path.dirname(tfi.__file__)}")
    clock = "CPU time" if _CLOCK is time.thread_time else "wall time"
    print(f"3-D block {n3}^3, 2-D block {n2}^2 x 1; threads {threads()}; {clock}; order {order}; "
          f"best of {repeat}, old and new alternating; load average {load:.1f} on {os.cpu_count()} CPUs")

    def bfun(p):
        return 0.003 * np.cos(2.0 * p)

    c = np.array([0.5, 0.5, 0.0])
    rows = []
    for hasn in (True, False):
        if hasn:
            xyz = make_block(n3)
            o = order
        else:
            xyz = _plane(n2)
            o = order[:2] if sorted(order[:2]) == [0, 1] else (0, 1)
        dims = xyz.shape[:3]
        b = Block(xyz)
        s = tfi.arclength(xyz)
        nf = 6 if hasn else 4
        faces = [b.face(f) for f in range(nf)]
        if hasn:
            fdd = tfi._faces([dfun(f) for f in faces], dims, 3, "fd")
            fqq = tfi._faces([qfun(f) for f in faces], dims, 4, "fq")
            fbb = tfi._faces([bfun(f) for f in faces], dims, 3, "fb")
        else:
            fdd = tfi._sides_as_faces([dfun(f[:, 0]) for f in faces], dims, 3, "fd")
            fqq = tfi._sides_as_faces([qfun(f[:, 0]) for f in faces], dims, 4, "fq")
            fbb = tfi._sides_as_faces([bfun(f[:, 0]) for f in faces], dims, 3, "fb")
        fs = tfi.face_params(s)[:nf]
        o3 = o if hasn else o + (2,)
        tq = tfi._tables(dims, o3, fdd, fqq, fs, hasn)
        td = tfi._tables(dims, o3, fdd, None, fs, hasn)
        tb = tfi._tables(dims, o3, fbb, None, fs, hasn)
        base = (tb[0], tb[2], tb[4])
        for hasq, based in ((True, False), (False, False), (True, True)):
            tabs = tq if hasq else td
            lB, gB, hB = base if based else (tabs[0], tabs[2], tabs[4])
            args = (xyz, s)
            new_k = _volume_call(tfi, hasn, hasq, based)
            old_k = _old_volume(old, hasn, hasq, based)
            out_n = np.empty_like(xyz, order="F")
            out_o = np.empty_like(xyz, order="F")
            tail = (*c, *o3, *tabs, lB, gB, hB)
            bad = np.zeros(dims[1] * dims[2], dtype=bool)   # the new kernels' fallback flags
            new_k(*args, out_n, *tail, bad)               # compile / load
            old_k(*args, out_o, *tail)
            same = np.array_equal(out_n.view(np.int64), out_o.view(np.int64)) and not bad.any()
            t_n, t_o = best_interleaved([lambda: new_k(*args, out_n, *tail, bad),
                                         lambda: old_k(*args, out_o, *tail)], repeat)
            kind = f"{'3' if hasn else '2'}-D {'quaternion' if hasq else 'baseline'}{' based' if based else ''}"
            rows.append((kind, xyz.shape[0] * xyz.shape[1] * xyz.shape[2], t_n, t_o, same))
        # arclength (tile walker) on the same block
        so = old.arclength(xyz)
        same = np.array_equal(s.view(np.int64), so.view(np.int64))
        t_n, t_o = best_interleaved([lambda: tfi.arclength(xyz), lambda: old.arclength(xyz)], repeat)
        rows.append((f"{'3' if hasn else '2'}-D arclength", xyz.shape[0] * xyz.shape[1] * xyz.shape[2],
                     t_n, t_o, same))
    print(f"{'kernel':<24s} {'points':>9s} {'new ms':>9s} {'old ms':>9s} {'old/new':>8s}  same bits")
    worst = float("inf")
    for kind, npts, t_n, t_o, same in rows:
        worst = min(worst, t_o / t_n)
        print(f"{kind:<24s} {npts:9d} {t_n * 1e3:9.2f} {t_o * 1e3:9.2f} {t_o / t_n:8.3f}  {same}")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"lowest old/new ratio {worst:.3f} (>= 0.95: no slower); load average at the end {load:.1f}")
    return 0 if all(r[4] for r in rows) else 1


def _plane(n):
    """A 2-D (n, n, 1, 3) sheared, wall-clustered plane without forming an n^3 block."""
    u = np.linspace(0.0, 1.0, n)
    g = (np.exp(3.0 * u) - 1.0) / (np.exp(3.0) - 1.0)
    xyz = np.empty((n, n, 1, 3), order="F")
    i, j = u[:, None], g[None, :]
    xyz[:, :, 0, 0] = 2.0 * i + 0.3 * j
    xyz[:, :, 0, 1] = 1.5 * j + 0.02 * i * i
    xyz[:, :, 0, 2] = 0.1 * i * j
    return xyz


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=float, default=216 ** 3, help="block size in points (cube)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--order", default="2,0,1", help="direction order L,M,N")
    ap.add_argument("--setup-wing", type=float, metavar="SCALE", default=None,
                    help="time the Deformer's set-up kernels on the wing of this scale instead")
    ap.add_argument("--wing-pickle", default=None, metavar="PATH",
                    help="with --setup-wing: load (grid, patches, connectivity) from this pickle")
    ap.add_argument("--old", default=None, metavar="PATH",
                    help="time the volume kernels of the checkout at PATH and of this one side by side")
    ap.add_argument("--cpu", action="store_true",
                    help="with --old: time the calls by the calling thread's CPU time, on one "
                         "thread (NUMBA_NUM_THREADS=1): steadier than wall time on a loaded "
                         "machine, where a descheduled call waits without using CPU")
    args = ap.parse_args(argv)
    if args.cpu:
        global _CLOCK
        if threads() != 1:
            raise SystemExit("--cpu needs one thread: run with NUMBA_NUM_THREADS=1")
        _CLOCK = time.thread_time
    if args.old is not None:
        return side_by_side(args.old, args.points, args.repeat,
                            tuple(int(v) for v in args.order.split(",")))
    if args.setup_wing is not None:
        return setup_wing(args.setup_wing, args.repeat, args.wing_pickle)
    n = max(4, int(round(args.points ** (1.0 / 3.0))))
    npts = n ** 3
    order = tuple(int(v) for v in args.order.split(","))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"block {n}^3 = {npts / 1e6:.2f} M points; threads {threads()}; "
          f"order {order}; best of {args.repeat}; load average {load:.1f} on {os.cpu_count()} CPUs")

    xyz = make_block(n)
    b = Block(xyz)
    # face fields from one smooth volume function, so the edges agree
    fd = [dfun(b.face(f)) for f in range(6)]
    fq = [qfun(b.face(f)) for f in range(6)]
    c = np.array([0.5, 0.5, 0.0])

    # arclength set-up
    s = tfi.arclength(xyz)
    t_arc = best(lambda: tfi.arclength(xyz), args.repeat)

    out = np.empty_like(xyz, order="F")
    fs = tfi.face_params(s)                  # once per grid, as the Deformer does
    tfi.deform_block(xyz, s, fd, fq, c, order, out=out, face_s=fs)
    tfi.deform_block(xyz, s, fd, None, c, order, out=out, face_s=fs)
    t_q = best(lambda: tfi.deform_block(xyz, s, fd, fq, c, order, out=out, face_s=fs), args.repeat)
    t_d = best(lambda: tfi.deform_block(xyz, s, fd, None, c, order, out=out, face_s=fs), args.repeat)
    t_q0 = best(lambda: tfi.deform_block(xyz, s, fd, fq, c, order, out=out), args.repeat)

    # the Deformer's case: face values as rows of global arrays (G distinct face points)
    dims = xyz.shape[:3]
    gid, P = global_rows(xyz)
    gd, gq = dfun(P), qfun(P)
    plan = tfi.gather_plan(gid, s, order, face_s=fs)

    def old_tables(q):
        # the O(surface) part of the old path: per-face gathers, then deform_block's tables
        fdg = tuple(gd[g] for g in gid)
        fqg = tuple(gq[g] for g in gid) if q else None
        return tfi._tables(dims, order, fdg, fqg, fs, True)

    def old_whole(q):
        # the old path as the Deformer took it
        fdg = tuple(gd[g] for g in gid)
        fqg = tuple(gq[g] for g in gid) if q else None
        tfi.deform_block(xyz, s, fdg, fqg, c, order, out=out, face_s=fs, check=False)

    for q in (gq, None):
        tfi.deform_block_gathered(xyz, s, gd, q, plan, c, out)
    t_gq, t_oq, t_gd, t_od = best_interleaved([
        lambda: tfi.deform_block_gathered(xyz, s, gd, gq, plan, c, out), lambda: old_whole(True),
        lambda: tfi.deform_block_gathered(xyz, s, gd, None, plan, c, out), lambda: old_whole(False)],
        args.repeat)
    t_tgq, t_toq, t_tgd, t_tod = best_interleaved([
        lambda: plan._fill(gd, gq), lambda: old_tables(True),
        lambda: plan._fill(gd, None), lambda: old_tables(False)], args.repeat)

    # the volume loops alone, with the O(surface) tables built once (what the set-up costs)
    fdd, fqq = tfi._faces(fd, dims, 3, "fd"), tfi._faces(fq, dims, 4, "fq")
    tq = tfi._tables(dims, order, fdd, fqq, fs, True)
    td = tfi._tables(dims, order, fdd, None, fs, True)
    kq, kd = _volume_call(tfi, True, True, False), _volume_call(tfi, True, False, False)
    bad = np.zeros(n * n, dtype=bool)
    t_kq = best(lambda: kq(xyz, s, out, *c, *order, *tq, tq[0], tq[2], tq[4], bad), args.repeat)
    t_kd = best(lambda: kd(xyz, s, out, *c, *order, *td, td[0], td[2], td[4], bad), args.repeat)

    # streaming bandwidth of the same bytes (read R_u and s, write R_d), same run
    sb = s.itemsize * 3
    nbytes = 24 + sb + 24
    a = np.ones(3 * npts)
    b2 = np.ones(3 * npts)
    c2 = np.empty(3 * npts)
    _add(a, b2, c2)
    t_add = best(lambda: _add(a, b2, c2), args.repeat)
    src = np.ones(npts * (24 + sb) // 8)
    dst = np.empty_like(src)
    _copy(src, dst)
    t_copy = best(lambda: _copy(src, dst), args.repeat)
    del a, b2, c2, src, dst
    bw = nbytes * npts / t_add                 # bytes read + written per second (write-allocate not counted)
    bw_copy = 2.0 * (24 + sb) * npts / t_copy

    def line(name, t, bpp):
        pps = npts / t
        print(f"{name:<34s} {t * 1e3:9.2f} ms  {pps / 1e6:8.1f} M points/s  {bpp:3d} B/point  "
              f"{pps * bpp / 1e9:6.2f} GB/s  = {pps * bpp / bw:5.2f} x stream")

    print(f"{'stream add c = a + b':<34s} {t_add * 1e3:9.2f} ms  {npts / t_add / 1e6:8.1f} M points/s  "
          f"{nbytes:3d} B/point  {bw / 1e9:6.2f} GB/s  (the roofline)")
    print(f"{'stream copy':<34s} {t_copy * 1e3:9.2f} ms  {'':19s}  {'':9s}  {bw_copy / 1e9:6.2f} GB/s")
    line("deform_block quaternion", t_q, nbytes)
    line("  same without face_s", t_q0, nbytes)
    line("deform_block baseline", t_d, nbytes)
    line("  quaternion loop only", t_kq, nbytes)
    line("  baseline loop only", t_kd, nbytes)
    line("deform_block_gathered, whole call", t_gq, nbytes)
    line("  old path, whole call", t_oq, nbytes)
    line("  baseline, whole call", t_gd, nbytes)
    line("  old path baseline", t_od, nbytes)
    print(f"{'  tables (O(surface)):':<34s} quaternion {t_tgq * 1e3:.2f} ms (old path {t_toq * 1e3:.2f} ms), "
          f"baseline {t_tgd * 1e3:.2f} ms (old {t_tod * 1e3:.2f} ms); plan {plan.nbytes / 1e6:.1f} MB")
    line("arclength set-up", t_arc, 24 * 2 + sb)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"load average at the end {load:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
