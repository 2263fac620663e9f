"""Mutation fuzz test of the readers and the CLI (``tests/fuzzing.py``).

Deterministic: campaign seed 2024, the same mutants on every run.  Every
Plot3D variant, HDF5 layout, connectivity JSON / NMF and case file gets
:data:`READER_MUTANTS` damaged copies, every CLI target :data:`CLI_MUTANTS`;
they are checked in two worker processes, each mutant under a 4 GiB address
space limit and a 10 s timeout.  Each target must end every mutant in ``ok``
or ``error``: no crash, hang, memory blow-up, foreign exception (CLI
traceback) or silently wrong result.  The long campaign is
``benchmarks/fuzz_campaign.py``.
"""

from __future__ import annotations

import pytest

import fuzzing

CAMPAIGN_SEED = 2024
READER_MUTANTS = 80
CLI_MUTANTS = 12


def _count(target: fuzzing.Target) -> int:
    return CLI_MUTANTS if target.check == "cli" else READER_MUTANTS


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    return fuzzing.make_seeds(tmp_path_factory.mktemp("seeds"))


@pytest.fixture(scope="module")
def campaign(tmp_path_factory, seeds):
    workdir = tmp_path_factory.mktemp("fuzz")
    return fuzzing.run_campaign(_count, campaign_seed=CAMPAIGN_SEED, workdir=workdir, jobs=2,
                                keep_cap=5, seeds=seeds)


@pytest.mark.parametrize("name", list(fuzzing.TARGETS))
def test_no_crash_hang_overmem_foreign_or_wrong(campaign, name):
    mine = [r for r in campaign if r.target == name]
    target = fuzzing.TARGETS[name]
    assert len(mine) == _count(target)
    counts = fuzzing.tally(mine)[name]
    bad = {o: counts[o] for o in fuzzing.FAILURES if counts[o]}
    assert not bad, (f"{name}: {bad} of {len(mine)} mutants\n"
                     + fuzzing.failure_report(mine))
    # the mutants are not all rejected outright: some damage leaves a readable file (checked on
    # the readers' 80 mutants; a dozen CLI mutants of a strictly checked map can all be errors)
    if target.check != "cli":
        assert counts["error"] < len(mine)


def test_mutants_are_deterministic(seeds):
    for name in ("p3d-bin-le-f8", "p3d-ascii", "h5-gzip", "json", "case"):
        t = fuzzing.TARGETS[name]
        a = [fuzzing.mutate(seeds[t.seed], name, 7, i) for i in range(20)]
        b = [fuzzing.mutate(seeds[t.seed], name, 7, i) for i in range(20)]
        assert a == b
        assert len({m.data for m in a}) > 15          # the mutants differ from each other
        assert sum(m.data != seeds[t.seed].path.read_bytes() for m in a) > 15


def test_header_intact_flag(seeds):
    seed = seeds["p3d-bin-le-f8"]
    original = seed.path.read_bytes()
    for i in range(200):
        m = fuzzing.mutate(seed, seed.name, 3, i)
        if m.header_intact:
            assert m.data[:seed.header_end] == original[:seed.header_end]


def test_classifier_sees_each_failure_kind(seeds, tmp_path):
    """The checks can fail: a silently wrong grid, a non-finite coordinate, a dropped rotation."""
    import numpy as np
    import tfi_quat as tq
    grid = str(seeds["json"].path.parent / "grid.x")
    # a Plot3D read that returns other dims than the seed while the header is intact -> wrong
    t = fuzzing.TARGETS["p3d-bin-single"]
    ref = {"dims": [[9, 4, 2]], "grid": grid}
    assert fuzzing.classify(t, seeds["p3d-bin-single"].path, ref, True, tmp_path)[0] == "wrong"
    # the same with a damaged header: only the invariants count
    assert fuzzing.classify(t, seeds["p3d-bin-single"].path, ref, False, tmp_path)[0] == "ok"
    # a grid reader's own error -> error
    bad = tmp_path / "bad.x"
    bad.write_bytes(b"\x01\x02\x03")
    assert fuzzing.classify(t, bad, ref, False, tmp_path)[0] == "error"
    # a non-finite coordinate slipping through would be wrong
    g = tq.read(seeds["p3d-bin-single"].path)
    g[0].xyz[0, 0, 0, 0] = np.nan
    assert "non-finite" in fuzzing.grid_problems(g)
    # the independent rotation agrees with a plain one
    p = fuzzing.reference_rotation([[1.0, 0.0, 0.0]], [0.0, 0.0, 1e200], 90.0, [0.0, 0.0, 0.0])
    assert np.allclose(p, [[0.0, 1.0, 0.0]])
    # a CLI that ends in a usage error is "error", a good command "ok"
    cli = fuzzing.Target("x", "json", "cli", ("info", "{mutant}"))
    assert fuzzing.classify(cli, seeds["p3d-bin-le-f8"].path, ref, True, tmp_path)[0] == "ok"
    assert fuzzing.classify(cli, tmp_path / "missing.x", ref, True, tmp_path)[0] == "error"


def test_classifier_foreign_and_memory(seeds, tmp_path, monkeypatch):
    import tfi_quat as tq
    t = fuzzing.TARGETS["h5-plain"]
    ref = {"dims": [[9, 4, 3], [4, 9, 3]], "grid": str(seeds["json"].path.parent / "grid.x")}
    assert fuzzing.classify(t, seeds["h5-plain"].path, ref, False, tmp_path)[0] == "ok"

    def raises(exc):
        def read(*args, **kw):
            raise exc
        return read

    for exc, outcome in ((KeyError("x"), "foreign"), (OSError("damaged"), "foreign"),
                         (MemoryError(), "overmem"), (FileNotFoundError("gone"), "error"),
                         (tq.GridFormatError("bad"), "error")):
        monkeypatch.setattr(tq, "read", raises(exc))
        assert fuzzing.classify(t, seeds["h5-plain"].path, ref, False, tmp_path)[0] == outcome


def test_runner_sees_crash_hang_and_memory(seeds, tmp_path):
    seed = seeds["case"]
    jobs = []
    for n, what in enumerate(("ok", "crash", "hang", "memory", "ok")):
        t = fuzzing.Target(f"self-{what}", "case", "selftest", (what,))
        jobs.append((t, fuzzing.Mutant(t.name, n, b"x", False), seed, {}))
    results = fuzzing.run_mutants(jobs, seed_folder=seed.path.parent, workdir=tmp_path / "m", jobs=2,
                                  timeout=3.0, targets=[])
    got = {r.target: r.outcome for r in results}
    assert got == {"self-ok": "ok", "self-crash": "crash", "self-hang": "hang", "self-memory": "overmem"}
