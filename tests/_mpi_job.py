"""One MPI job of tests/test_mpi.py: every rank writes its share of a grid collectively.

Run as ``mpiexec -n N python tests/_mpi_job.py SPEC.json``.  Every rank builds
the same grid (:func:`make_grid`), keeps its blocks (the partition of the
spec), and for each entry of ``spec["writes"]`` calls ``tfi_quat.write(path,
local, comm=MPI.COMM_WORLD, ...)``; rank r stores ``"OK"`` or ``"ERROR Type:
message"`` per write in ``SPEC.json.rank<r>`` (a JSON list): the ranks go on
after an error.  With ``spec["trace"]`` a success reads ``"OK <bytes>"``: the
peak of the memory traced by tracemalloc during the write.
"""

from __future__ import annotations

import json
import sys
import tracemalloc

import numpy as np


def make_grid(kind: str):
    """A multiblock grid of varied block sizes: ``3d`` (one block with IBLANK), ``2d``,
    ``pair`` and ``one`` (the first
    two blocks of ``3d``, the first), ``big`` (six blocks of 40^3 points)."""
    from tfi_quat import Block, Grid
    rng = np.random.default_rng(17)
    if kind == "2d":
        dims = [(7, 5, 1), (4, 9, 1), (6, 6, 1), (3, 4, 1)]
    else:
        dims = [(5, 4, 3), (3, 6, 2), (7, 3, 4), (2, 2, 2), (4, 5, 6)]
    blocks = []
    for n, d in enumerate(dims):
        xyz = rng.standard_normal((*d, 3))
        if kind == "2d":
            xyz[..., 2] = 0.0
        iblank = None
        if kind == "3d" and n == 2:
            iblank = rng.integers(-1, 2, size=d).astype(np.int32)
        blocks.append(Block(np.asfortranarray(xyz), iblank, name=f"b{n}"))
    if kind in ("pair", "one"):
        blocks = blocks[:2 if kind == "pair" else 1]
    if kind == "big":       # six blocks of 1.5 MB each: memory measurements
        blocks = [Block(np.asfortranarray(np.random.default_rng(n).standard_normal((40, 40, 40, 3))),
                        name=f"big{n}") for n in range(6)]
    return Grid(blocks, ndim=2 if kind == "2d" else 3)


def partition(spec, nblocks: int, rank: int, size: int):
    """This rank's 0-based block numbers and the ``blocks=`` argument to pass."""
    how = spec.get("partition", "default")
    if how == "default":            # contiguous ranges in rank order, no blocks=
        per = [nblocks // size + (r < nblocks % size) for r in range(size)]
        start = sum(per[:rank])
        return list(range(start, start + per[rank])), None
    if how == "given":              # round robin, from the last block down: not in rank order
        mine = [n for n in reversed(range(nblocks)) if n % size == rank]
        return mine, mine
    raise ValueError(how)


def main() -> None:
    from mpi4py import MPI

    import tfi_quat as tq
    import tfi_quat.io.mpi  # noqa: F401
    tq.io.format_for("any.x")       # every format module imported before any tracing
    comm = MPI.COMM_WORLD
    with open(sys.argv[1], encoding="utf-8") as fh:
        spec = json.load(fh)
    whole = make_grid(spec["grid"])
    mine, given = partition(spec, len(whole), comm.rank, comm.size)
    local = [whole.blocks[n] for n in mine]
    report = []
    for i, w in enumerate(spec["writes"]):
        grid, blocks = local, given
        if w.get("fail") == "float32_on_rank1" and comm.rank == 1:
            grid = [tq.Block(np.full(local[0].xyz.shape, 1e300), name="huge")] + local[1:]
        elif w.get("fail") == "duplicate_block0" and comm.rank == 1:
            grid, blocks = [whole.blocks[0]] + local, [0] + mine
        grid = whole.with_blocks(grid) if grid else None
        if w.get("fail") == "not_a_grid_on_rank1" and comm.rank == 1:
            grid = {"blocks": local}
        options = dict(w.get("options", {}))
        if w.get("fail") == "ndim3_on_rank1" and comm.rank == 1:
            grid = tq.Grid(grid.blocks, ndim=3)
        if w.get("fail") == "float32_variant_on_rank1" and comm.rank == 1:
            options["precision"] = 4
        if spec.get("trace"):       # the bytes numpy and Python allocate during the write
            tracemalloc.start()
        try:
            tq.write(w["path"], grid, comm=comm, blocks=blocks, **options)
        except Exception as exc:    # noqa: BLE001  (the test reads the line)
            report.append(f"ERROR {type(exc).__name__}: {exc}")
        else:
            report.append(f"OK {tracemalloc.get_traced_memory()[1]}" if spec.get("trace") else "OK")
        tracemalloc.stop()
    # one file per rank: the ranks' standard outputs interleave
    with open(f"{sys.argv[1]}.rank{comm.rank}", "w", encoding="utf-8") as fh:
        json.dump(report, fh)

if __name__ == "__main__":
    main()
