"""Benchmark of the TFI volume stage (DESIGN 6): fused quaternion kernel, baseline, arclength.

Prints points per second, bytes moved per point and the ratio of the
kernel's effective bandwidth to the machine's streaming bandwidth, measured
in the same run by a parallel numba copy of the same number of bytes.  Every
figure is the best of ``--repeat`` runs (the machine is shared: the best run
is the least disturbed one).

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
def _stream(src, dst):
    """Parallel copy: reads and writes ``src.size`` float64 each, like the kernels' streams."""
    n = src.shape[0]
    for b in prange(n // 8192 + 1):
        for m in range(b * 8192, min(n, (b + 1) * 8192)):
            dst[m] = src[m]


def best(fn, repeat):
    t = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return min(t)


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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=float, default=216 ** 3, help="block size in points (cube)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--order", default="2,0,1", help="direction order L,M,N")
    args = ap.parse_args(argv)
    n = max(4, int(round(args.points ** (1.0 / 3.0))))
    npts = n ** 3
    order = tuple(int(v) for v in args.order.split(","))
    print(f"block {n}^3 = {npts / 1e6:.2f} M points; threads {numba.get_num_threads()}; "
          f"order {order}; best of {args.repeat}")

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

    # the volume loops alone, with the O(surface) tables built once (what the set-up costs)
    dims = xyz.shape[:3]
    fdd, fqq = tfi._faces(fd, dims, 3, "fd"), tfi._faces(fq, dims, 4, "fq")
    tq = tfi._tables(dims, order, fdd, fqq, fs, True)
    td = tfi._tables(dims, order, fdd, None, fs, True)
    t_kq = best(lambda: tfi._deform3_q(xyz, s, out, *c, *order, *tq), args.repeat)
    t_kd = best(lambda: tfi._deform3_d(xyz, s, out, *order, td[0], td[2], td[4]), args.repeat)

    # streaming bandwidth: copy the bytes the volume stage moves (read R_u and s, write R_d)
    sb = s.itemsize * 3
    nbytes = 24 + sb + 24
    src = np.ones(npts * (24 + sb) // 8 // 2 * 2)
    dst = np.empty_like(src)
    _stream(src, dst)
    t_copy = best(lambda: _stream(src, dst), args.repeat)
    bw = 2.0 * src.nbytes / t_copy            # bytes read + written per second

    def line(name, t, bpp):
        pps = npts / t
        print(f"{name:<28s} {t * 1e3:9.2f} ms  {pps / 1e6:8.1f} M points/s  {bpp:3d} B/point  "
              f"{pps * bpp / 1e9:6.2f} GB/s  = {pps * bpp / bw:5.2f} x stream")

    print(f"{'stream copy (numba)':<28s} {t_copy * 1e3:9.2f} ms  {bw / 1e9:6.2f} GB/s "
          f"(read + write of {src.nbytes / 1e6:.0f} MB)")
    line("deform_block quaternion", t_q, nbytes)
    line("  same without face_s", t_q0, nbytes)
    line("deform_block baseline", t_d, nbytes)
    line("  quaternion loop only", t_kq, nbytes)
    line("  baseline loop only", t_kd, nbytes)
    line("arclength set-up", t_arc, 24 * 2 + sb)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
