"""Benchmark of the TFI volume stage (DESIGN 6): fused quaternion kernel, baseline, arclength.

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

Usage::

    python3 benchmarks/bench_tfi.py                 # 10.1 M points (216^3)
    python3 benchmarks/bench_tfi.py --points 2e5    # quick
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from tfi_quat import tfi  # noqa: E402
from tfi_quat._jit import numba, pjit, prange  # noqa: E402
from tfi_quat.grid import Block  # noqa: E402
from tfi_quat.quaternion import normalize  # noqa: E402


@pjit
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


def best_interleaved(fns, repeat):
    """Best time of each function, the functions run in turn (A/B under the same load)."""
    t = [[] for _ in fns]
    for _ in range(repeat):
        for m, fn in enumerate(fns):
            t0 = time.perf_counter()
            fn()
            t[m].append(time.perf_counter() - t0)
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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=float, default=216 ** 3, help="block size in points (cube)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--order", default="2,0,1", help="direction order L,M,N")
    args = ap.parse_args(argv)
    n = max(4, int(round(args.points ** (1.0 / 3.0))))
    npts = n ** 3
    order = tuple(int(v) for v in args.order.split(","))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"block {n}^3 = {npts / 1e6:.2f} M points; threads {numba.get_num_threads()}; "
          f"order {order}; best of {args.repeat}; load average {load:.1f} on {os.cpu_count()} CPUs")

    xyz = make_block(n)
    b = Block(xyz)
    # face fields from one smooth volume function, so the edges agree
    def dfun(p):
        return 0.01 * np.sin(p)

    def qfun(p):
        rv = 0.05 * np.cos(p)
        ang = np.linalg.norm(rv, axis=-1, keepdims=True)
        return normalize(np.concatenate([np.cos(ang / 2), np.sin(ang / 2) * rv / np.maximum(ang, 1e-300)], -1))

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
    t_kq = best(lambda: tfi._deform3_q(xyz, s, out, *c, *order, *tq), args.repeat)
    t_kd = best(lambda: tfi._deform3_d(xyz, s, out, *order, td[0], td[2], td[4]), args.repeat)

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
