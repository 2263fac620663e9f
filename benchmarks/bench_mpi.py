"""Distributed deformation benchmark: 1 vs N MPI ranks on a generated multiblock wing.

Generates the wing (``tfi_quat.generate.wing``, 4 blocks; ``--scale`` multiplies its
resolution per direction, the wall-normal one at most 2.8x: 1 is ~0.5 M points, 3.8
~20 M), writes it as binary
Plot3D, then runs ``mpiexec -n R`` for each R of ``--ranks``: every rank builds
``Deformer(path, ..., comm=COMM_WORLD)`` (balanced partition, one thread per rank),
runs a warm-up step, times the best of ``--repeat`` steps and one collective write
of the result, and reports its figures; the driver prints them side by side (the
slowest rank's times, each rank's peak memory) and checks that every rank count
wrote the same bytes.

Then the figures a weak-scaling model needs, per rank: volume-stage seconds per own
point, seconds per point of the rank's part of the skeleton (faces stage), per wall
point (the wall work: split or replicated), per free-vertex source pair (split by rows), the set-up
per boundary point, and the bytes of the set-up's collectives; and the model of a
step for ``--model-points`` points on 256 and 1024 ranks (assumptions printed).

    python benchmarks/bench_mpi.py --scale 1            # develop: ~0.5 M points
    python benchmarks/bench_mpi.py --scale 3.8          # ~20 M points
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

import numpy as np

MOTION = dict(bend=0.15, twist=5.0, about=(0.25, 0.0, 0.0), span_axis=(0, 1, 0), span=1.5)


def _odd4(n):
    n = int(round(n))
    return n + (-(n - 1)) % 4


def worker(folder: Path, repeat: int) -> None:
    """One rank: set-up, steps, write; its figures to ``folder/rank<r>.json``."""
    from mpi4py import MPI

    from tfi_quat.case import Motion
    from tfi_quat.deform import Deformer
    comm = MPI.COMM_WORLD
    spec = json.loads((folder / "case.json").read_text())
    move = Motion(**MOTION).apply
    comm.Barrier()
    t0 = time.perf_counter()
    d = Deformer(str(folder / "grid.x"), walls=spec["walls"], symmetry=spec["symmetry"],
                 fixed=spec["fixed"], comm=comm)
    setup = time.perf_counter() - t0
    out = d.deform(move)                            # warm: numba cache loaded, pages touched
    best = None
    for _ in range(repeat):
        out = None
        comm.Barrier()
        t0 = time.perf_counter()
        out = d.deform(move)
        dt = time.perf_counter() - t0
        if best is None or dt < best[0]:
            best = (dt, d.timings)
    comm.Barrier()
    t0 = time.perf_counter()
    d.write(str(folder / f"out{comm.size}.x"), out, overwrite=True)
    write = time.perf_counter() - t0
    full, part = d.full_skeleton, d.skeleton
    # the wall work of a step, per wall point, on the whole walls (one rank: it owns them all):
    # split over the ranks (the fits' part sums, the patches' quaternions, the merge and the
    # row copies at the points a rank reads) or replicated (a motion callable's result
    # checked, and fingerprinted for the ranks' comparison)
    from tfi_quat.deform import stages, twolevel
    from tfi_quat.deform.distributed import fingerprint
    from tfi_quat.deform.walls import motion_targets
    P, wall = full.points.P, full.points.wall
    rd, y = P.copy(), P.copy()
    rd[wall] = move(P[wall])
    two = d.two_level
    parts = {}
    allp = range(len(full.walls.patches))
    qs = stages.patch_quaternions(full, y, d.centre, allp)
    gq, K, pos = np.zeros((P.shape[0], 4)), P.copy(), P.copy()
    qw = stages.merge_wall_quaternions(full, qs)
    new = motion_targets(full, move)
    order = np.arange(wall.size)

    def copies():
        rd[wall] = new
        gq[wall] = qw
        K[wall] = y[wall]
        pos[wall] = y[wall]
        pos[wall] = rd[wall]

    for name, fn in (("motion", lambda: move(P[wall])),
                     ("targets", lambda: motion_targets(full, move)),
                     ("digest", lambda: fingerprint(new.view(np.uint64), order, np.zeros(2, np.uint64))),
                     ("copies", copies),
                     ("fit", lambda: twolevel.fit_bodies(full, two, rd, y)),
                     ("wallq", lambda: stages.patch_quaternions(full, y, d.centre, allp)),
                     ("merge", lambda: stages.merge_wall_quaternions(full, qs))):
        fn()
        t0 = time.perf_counter()
        for _ in range(5):
            fn()
        parts[name] = (time.perf_counter() - t0) / 5
    parts["targets"] = max(parts["targets"] - parts["motion"], 0.0)
    parts["nparts"] = int(two.part_body.size)
    faces = [int(np.prod(g.shape)) for plan in full.blocks for g in plan.face_gid]
    dt, tm = best
    fig = dict(rank=comm.rank, blocks=list(d.blocks), own_points=sum(b.npoints for b in d.grid),
               setup=setup, step=dt, walls=tm.walls, skeleton=tm.skeleton, faces=tm.faces,
               volumes=tm.volumes, write=write,
               peak_rss=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
               n_global=full.n_global, wall=int(full.points.wall.size),
               part_derived=int(part.derived.size), full_derived=int(full.derived.size),
               free_vertices=int(full.vertices.free.size),
               idw_sources=0 if full.vertices.idw is None else int(full.vertices.idw[0].size),
               face_copies=sum(faces), **parts)
    (folder / f"rank{comm.rank}.json").write_text(json.dumps(fig))


def mpiexec() -> str:
    here = Path(sysconfig.get_path("scripts")) / "mpiexec"
    return str(here) if here.exists() else (shutil.which("mpiexec") or "mpiexec")


def vertex_cost(nv=2000, ns=2000, repeat=3) -> float:
    """Seconds per (free vertex x source) pair of the vertex stage (Δ and Q, row by row: a
    rank computes the rows its blocks read)."""
    from types import SimpleNamespace

    from tfi_quat._jit import use_threads
    from tfi_quat.deform import stages
    from tfi_quat.deform.skeleton import Vertices
    rng = np.random.default_rng(0)
    G = nv + ns
    src = np.arange(ns)
    w = rng.random((nv, ns))
    w /= w.sum(axis=1, keepdims=True)
    vx = Vertices(np.arange(ns, G), np.arange(ns, G),
                  (src, w, rng.random(nv), rng.integers(0, ns, nv)))
    sk = SimpleNamespace(vertices=vx)
    gd = rng.standard_normal((G, 3))
    gq = rng.standard_normal((G, 4))
    gq /= np.linalg.norm(gq, axis=1, keepdims=True)
    best = np.inf
    with use_threads(1):
        stages.vertex_stage(sk, gd, gq)
        for _ in range(repeat):
            t0 = time.perf_counter()
            stages.vertex_stage(sk, gd, gq)
            best = min(best, time.perf_counter() - t0)
    return best / (nv * ns)


def replicated_cost(n_wall: int, spread: int = 15, repeat: int = 5) -> float:
    """Seconds per wall point of what every rank does with a motion callable's wall input,
    measured at the modelled size (``n_wall`` wall points among ``spread`` times as many
    boundary points): the contiguous copy of the wall points handed to the callable, its
    result checked, the fingerprint (the callable itself, the caller's, is an identity)."""
    from types import SimpleNamespace

    from tfi_quat.deform.distributed import fingerprint
    from tfi_quat.deform.walls import motion_targets
    rng = np.random.default_rng(0)
    n = int(n_wall)
    P = rng.standard_normal((spread * n, 3))
    wall = np.sort(rng.choice(P.shape[0], n, replace=False))
    sk = SimpleNamespace(points=SimpleNamespace(P=P, wall=wall), ndim=3)
    ref = P[wall]
    order = np.arange(n)

    def once():
        new = motion_targets(sk, lambda p: p, ref)
        fingerprint(new.view(np.uint64), order, np.zeros(2, dtype=np.uint64))

    once()
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        once()
        best = min(best, time.perf_counter() - t0)
    return best / n


def model(figs1: list, n_points: float, ranks, blocks_per_rank: int, vtx: float, wall_1: int,
          points_1: int) -> None:
    """A step of ``n_points`` points on each rank count, from the 1-rank figures."""
    f = figs1[0]
    v = f["volumes"] / f["own_points"]
    k_face = f["faces"] / max(f["part_derived"], 1)
    nw = max(f["wall"], 1)
    setup_per = f["setup"] / f["n_global"]
    k_split = (f["fit"] + f["wallq"]) / nw          # per wall point of the rank's wall patches
    k_merge = (f["merge"] + f["copies"]) / nw       # per wall point the rank reads
    wall = wall_1 * (n_points / points_1) ** (2.0 / 3.0)
    k_rep = replicated_cost(wall)
    const = max(f["step"] - f["volumes"] - f["faces"] - f["fit"] - f["wallq"] - f["merge"]
                - f["motion"] - f["targets"] - f["digest"] - f["copies"], 0.0)
    ns = 2000
    print(f"\nmeasured per rank (1 rank, one thread, under load): volume stage {v * 1e9:.1f} ns per "
          f"own point; faces stage {k_face * 1e9:.0f} ns per derived boundary point of the rank's part; "
          f"split wall work: rigid fits' part sums + pull-back and the wall patches' quaternions "
          f"{k_split * 1e9:.0f} ns per wall point of the rank's wall patches, the merge and the "
          f"row copies {k_merge * 1e9:.0f} ns per wall point it reads; replicated: the motion's "
          f"input copied, its result checked and fingerprinted {k_rep * 1e9:.1f} ns per wall point "
          f"(measured with {wall / 1e6:.2f} M wall points, the modelled size; at this grid's size "
          f"{(f['targets'] + f['digest']) / nw * 1e9:.0f} ns; the motion callable "
          f"{f['motion'] / nw * 1e9:.0f} ns more, the user's); free-vertex blend {vtx * 1e9:.2f} ns "
          f"per vertex x source pair (the rows a rank reads); the rest of a step {const * 1e3:.1f} ms "
          f"(Python, small arrays); set-up {setup_per * 1e6:.1f} us per boundary point")
    print(f"model of one step for {n_points / 1e9:g} G points (assumptions: {blocks_per_rank} equal "
          f"cubic blocks per rank; the walls scale as the wing's, points^(2/3) from {wall_1} wall "
          f"points at {points_1 / 1e6:.2f} M; {ns} IDW sources, a rank reads at most 8 free vertices "
          f"per block (its corners) and the {ns} sources' merged quaternions; the rank's part of "
          f"the skeleton = its blocks' faces; a rank holds at most one n x n wall face per block; "
          f"the collectives of a step: five allgathers (16 B fingerprint, the fits' two passes: 48 + 72 "
          f"B per part, the wall quaternions: 32 B per wall point, 10 GB/s into each rank, the "
          f"cell reports), latency 5 us x log2(ranks) each; the measured per-point costs hold at "
          f"scale)")
    for p in ranks:
        per = n_points / p
        n = (per / blocks_per_rank) ** (1.0 / 3.0)
        part = blocks_per_rank * 6 * n * n
        nblocks = blocks_per_rank * p
        own_wall = min(wall, blocks_per_rank * n * n)
        t_vol = v * per
        t_part = k_face * part
        t_split = k_split * own_wall + k_merge * (own_wall + ns)
        t_vtx = vtx * 8 * blocks_per_rank * ns
        t_rep = k_rep * wall
        t_coll = 5 * 5e-6 * np.log2(p) + 32 * wall / 1e10
        total = t_vol + t_part + t_split + t_vtx + t_rep + t_coll + const
        print(f"  {p:5d} ranks: {per / 1e6:.2f} M points/rank, {nblocks} blocks of {n:.0f}^3: "
              f"volume {t_vol:.3f} s, own faces {t_part:.3f} s, walls (split) {t_split:.4f} s, "
              f"vertices (split) {t_vtx:.4f} s, the rest {const:.3f} s, collectives "
              f"{t_coll * 1e3:.2f} ms; step {total:.3f} s; replicated (the motion's input copied, "
              f"its result checked and fingerprinted) {t_rep:.4f} s = {100 * t_rep / total:.1f} % (with the "
              f"collectives {100 * (t_rep + t_coll) / total:.1f} %; the user's motion callable on "
              f"every wall point would add {f['motion'] / nw * wall:.3f} s)")
        copies = nblocks * 6 * n * n
        print(f"         set-up (replicated) {setup_per * copies / 2:.0f} s; memory per rank "
              f"{(100 * per + 600 * copies) / 1e9:.1f} GB (100 B per own point, 600 B per boundary "
              f"point copy of the whole grid: {copies / 1e6:.0f} M copies)")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scale", type=float, default=1.0, help="wing resolution factor per direction")
    ap.add_argument("--ranks", default="1,2", help="comma list of rank counts")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--model-points", type=float, default=1e9)
    ap.add_argument("--blocks-per-rank", type=int, default=4)
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        return worker(Path(args.worker), args.repeat)
    import tfi_quat as tq
    from tfi_quat import generate as gen
    f = args.scale
    folder = Path(tempfile.mkdtemp(prefix="bench_mpi_", dir=os.environ.get("TMPDIR")))
    try:
        t0 = time.perf_counter()
        # the wall-normal direction at most 2.8x (the marcher folds cells beyond)
        grid = gen.wing(ni=_odd4(129 * f), nj=int(49 * min(f, 2.8)), nk_wing=int(45 * f),
                        nk_cap=max(5, int(9 * f)), nk_out=int(25 * f))
        bp = gen.boundary_patches("wing", grid)
        tq.write(folder / "grid.x", grid)
        npts = grid.npoints
        dims = grid.dims
        del grid
        (folder / "case.json").write_text(json.dumps({k: [str(s) for s in bp[k]]
                                                      for k in ("walls", "symmetry", "fixed")}))
        print(f"wing: {len(dims)} blocks {dims}, {npts / 1e6:.2f} M points, generated and written "
              f"in {time.perf_counter() - t0:.1f} s; load average {os.getloadavg()[0]:.1f}")
        env = dict(os.environ, OMP_NUM_THREADS="1",
                   PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                               os.environ.get("PYTHONPATH", "")]))
        results = {}
        for r in [int(x) for x in args.ranks.split(",")]:
            cmd = [mpiexec(), "-n", str(r), sys.executable, __file__, "--worker", str(folder),
                   "--repeat", str(args.repeat)]
            subprocess.run(cmd, check=True, env=env)
            results[r] = [json.loads((folder / f"rank{k}.json").read_text()) for k in range(r)]
        ranks = list(results)
        print(f"\n{'':28s}" + "".join(f"{f'{r} rank(s)':>22s}" for r in ranks))

        def row(name, fn):
            print(f"{name:28s}" + "".join(f"{fn(results[r]):>22s}" for r in ranks))

        row("set-up (s, slowest rank)", lambda fs: f"{max(x['setup'] for x in fs):.2f}")
        row("step (s, slowest rank)", lambda fs: f"{max(x['step'] for x in fs):.3f}")
        for stage in ("walls", "skeleton", "faces", "volumes"):
            row(f"  {stage} (s, slowest)", lambda fs, s=stage: f"{max(x[s] for x in fs):.4f}")
        row("write (s, slowest rank)", lambda fs: f"{max(x['write'] for x in fs):.2f}")
        row("points per rank (M)", lambda fs: " / ".join(f"{x['own_points'] / 1e6:.2f}" for x in fs))
        row("peak RSS per rank (MB)", lambda fs: " / ".join(f"{x['peak_rss'] / 1e6:.0f}" for x in fs))
        row("derived bdry pts in part", lambda fs: " / ".join(str(x["part_derived"]) for x in fs))
        same = {(folder / f"out{r}.x").read_bytes() == (folder / f"out{ranks[0]}.x").read_bytes()
                for r in ranks}
        f1 = results[ranks[0]][0]
        print(f"\noutputs identical for every rank count: {same == {True}}; boundary points "
              f"{f1['n_global']} ({f1['wall']} wall, {f1['full_derived']} derived, "
              f"{f1['free_vertices']} free vertices), face point copies {f1['face_copies']}")
        print(f"set-up collectives: boundary shells {2 * 24 * f1['face_copies'] / 1e6:.1f} MB "
              f"(faces and next layers of every block, one allgather), face parameters "
              f"{24 * f1['face_copies'] / 1e6:.1f} MB (one allgather); a step: five allgathers "
              f"(16 B fingerprint, the rigid fits' two passes over {f1['nparts']} parts, the wall "
              f"quaternions, the cell reports)")
        model(results[ranks[0]], args.model_points, (256, 1024), args.blocks_per_rank,
              vertex_cost(), f1["wall"], npts)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
