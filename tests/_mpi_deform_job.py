"""One MPI job of tests/test_mpi_deform.py: distributed deformations, each written collectively.

Run as ``mpiexec -n N python tests/_mpi_deform_job.py SPEC.json``.  For each
entry of ``spec["cases"]`` every rank builds ``Deformer(grid, ..., comm=COMM_WORLD,
blocks=...)``, deforms its blocks and writes them with the collective write
(or runs ``tfi-quat deform`` in-process: ``"cli"``; ``"out"``: into the rank's own C-order
buffers); rank r stores one result
per case in ``SPEC.json.rank<r>`` (a JSON list of dicts: ``"ok"`` or
``"error"`` with ``"Type: message"``, the blocks, the quality text, and with
``"trace"`` the peak of the memory tracemalloc saw during the set-up and the
step).  The ranks go on after an error: the test checks that every rank met
the same one.
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
import tracemalloc

import numpy as np


def motion(kind: str):
    """The wall motions of the cases: ``rigid`` (a rotation and a translation), ``bend`` (a
    non-rigid bend and twist), ``fold`` (a rotation far too large: folded cells)."""
    from tfi_quat.deform import rigid_motion
    if kind == "rigid":
        return rigid_motion(3.0, about=(0.25, 0.0, 0.0), translate=(0.01, 0.02, 0.0))
    if kind == "fold":
        return rigid_motion(60.0, about=(0.25, 0.0, 0.0))
    if kind == "bend":
        def bend(p):
            out = p.copy()
            out[:, 1] += 0.02 * np.sin(2.0 * p[:, 0]) + 0.01 * p[:, 0] ** 2
            return out
        return bend
    raise ValueError(kind)


def main() -> None:
    from mpi4py import MPI

    import tfi_quat as tq
    from tfi_quat.deform import Deformer
    comm = MPI.COMM_WORLD
    with open(sys.argv[1], encoding="utf-8") as fh:
        spec = json.load(fh)
    results = []
    for case in spec["cases"]:
        res = {}
        blocks = case.get("blocks")
        if blocks is not None:
            blocks = blocks[comm.rank]
        if case.get("cli"):
            from tfi_quat.cli import main as cli
            buf, err = io.StringIO(), io.StringIO()
            saved = sys.stdout, sys.stderr      # the CLI silences the ranks but 0 for good
            with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(err):
                res["rc"] = cli(case["cli"])
            sys.stdout, sys.stderr = saved
            res["stdout"], res["stderr"] = buf.getvalue(), err.getvalue()
            results.append(res)
            continue
        if case.get("trace"):
            tracemalloc.start()
        try:
            d = Deformer(case["grid"], walls=case["walls"], symmetry=case.get("symmetry", ()),
                         fixed=case.get("fixed", ()), method=case.get("method", "two-level"),
                         comm=comm, blocks=blocks)
            moved = motion(case["motion"])
            fail = case.get("fail")
            if fail == "shape_on_rank1" and comm.rank == 1:
                moved = np.zeros((3, 3))
            elif fail == "differ_on_rank1" and comm.rank == 1:
                moved = motion("bend")
            elif case.get("array"):     # the array form, ids in global block numbers
                ids = d.surface_ids()
                moved = moved(d.surface_points())
                perm = np.random.default_rng(5).permutation(ids.shape[0])
                out = d.deform(moved[perm], ids=ids[perm], check=case.get("check", True))
            elif case.get("out"):       # the rank's own buffers, C order: through the scratch
                buf = d.new_grid(order="C")
                d.deform(moved, out=buf, check=case.get("check", True))
                out = tq.Grid([tq.Block(b, name=r.name) for b, r in zip(buf, d.grid)], ndim=d.grid.ndim,
                              source_format=d.grid.source_format)
            if not (case.get("array") or case.get("out")) or fail:
                out = d.deform(moved, check=case.get("check", True))
            if case.get("jvp"):         # the derivatives are serial only: a clear refusal
                try:
                    d.jvp(np.zeros((d.surface_ids().shape[0], 3)))
                except Exception as exc:    # noqa: BLE001  (the test reads it)
                    res["jvp_error"] = f"{type(exc).__name__}: {exc}"
            res["blocks"] = list(d.blocks)
            res["quality"] = str(d.quality)
            res["free_rows"] = (int(d.skeleton.vertices.free.size),
                                int(d.full_skeleton.vertices.free.size))
            if case.get("trace"):
                res["peak"] = tracemalloc.get_traced_memory()[1]
                res["own_points"] = sum(b.npoints for b in d.grid)
                res["surface_points"] = int(d.skeleton.points.copies_key.size)
                tracemalloc.stop()
            for path in case.get("outputs", []):
                d.write(path, out, overwrite=True)
            res["ok"] = True
        except Exception as exc:    # noqa: BLE001  (the test reads it)
            res["error"] = f"{type(exc).__name__}: {exc}"
        tracemalloc.stop()
        results.append(res)
    with open(f"{sys.argv[1]}.rank{comm.rank}", "w", encoding="utf-8") as fh:
        json.dump(results, fh)


if __name__ == "__main__":
    main()
