"""The long mutation-fuzz campaign of the readers and the CLI.

Damages tiny seed files of every format (Plot3D: twelve binary variants and
three ASCII ones; HDF5 plain, gzip and 2-D; connectivity JSON and NMF; case
TOML) and checks every mutant in worker processes under a 4 GiB address-space
limit and a 10 s timeout; the CLI targets run ``tfi-quat`` commands on
mutants.  The mutators, the checks and the outcome classes (``ok``, ``error``,
``foreign``, ``crash``, ``hang``, ``overmem``, ``wrong``) are documented in
``tests/fuzzing.py`` and ``docs/robustness.md``.

Prints the counts per target and outcome as a table, writes them with the
settings and the failing mutants to a JSON file, and keeps up to
``--keep-cap`` failing mutant files per target and outcome in ``--keep`` for
triage.  Exit status 1 when any mutant failed.

Usage::

    python benchmarks/fuzz_campaign.py --mutants 30000 --seed 1 --jobs 2
    python benchmarks/fuzz_campaign.py --mutants 600 --targets json,nmf,case --label short
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import fuzzing  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mutants", type=int, default=30000, help="mutants in all, split evenly over the targets")
    ap.add_argument("--seed", type=int, default=1, help="campaign seed (same seed, same mutants)")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes")
    ap.add_argument("--timeout", type=float, default=fuzzing.TIMEOUT, help="seconds per mutant")
    ap.add_argument("--mem-gib", type=float, default=fuzzing.MEM_LIMIT / 2**30,
                    help="address-space limit per worker, GiB")
    ap.add_argument("--targets", default=None,
                    help=f"comma-separated subset of: {', '.join(fuzzing.TARGETS)}")
    ap.add_argument("--out", default=None,
                    help="result JSON (default benchmarks/results/fuzz-YYYY-MM-DD[-LABEL].json)")
    ap.add_argument("--label", default="", help="added to the default result name and stored in it")
    ap.add_argument("--keep", default=None, help="folder for the failing mutants (default: fuzz-failures-DATE)")
    ap.add_argument("--keep-cap", type=int, default=20, help="failing mutant files kept per target and outcome")
    args = ap.parse_args(argv)

    names = args.targets.split(",") if args.targets else list(fuzzing.TARGETS)
    unknown = [n for n in names if n not in fuzzing.TARGETS]
    if unknown:
        ap.error(f"unknown target(s): {', '.join(unknown)}")
    targets = [fuzzing.TARGETS[n] for n in names]
    per_target = max(1, args.mutants // len(targets))
    today = datetime.date.today().isoformat()
    suffix = f"-{args.label}" if args.label else ""
    out = Path(args.out) if args.out else ROOT / "benchmarks" / "results" / f"fuzz-{today}{suffix}.json"
    keep = Path(args.keep) if args.keep else Path(f"fuzz-failures-{today}{suffix}")

    total = per_target * len(targets)
    done = [0]
    t0 = time.monotonic()

    def progress(res):
        done[0] += 1
        if res.outcome in fuzzing.FAILURES:
            print(f"  {res.target} #{res.index} {res.outcome}: {'; '.join(res.ops)} -> {res.detail[:160]}",
                  flush=True)
        if done[0] % 500 == 0:
            print(f"[{done[0]}/{total}] {time.monotonic() - t0:.0f} s", flush=True)

    print(f"fuzz campaign: {len(targets)} targets x {per_target} mutants, seed {args.seed}, "
          f"{args.jobs} workers, {args.timeout:g} s and {args.mem_gib:g} GiB per mutant", flush=True)
    with tempfile.TemporaryDirectory(prefix="tfi_quat_fuzz_") as tmp:
        results = fuzzing.run_campaign(per_target, campaign_seed=args.seed, workdir=tmp, jobs=args.jobs,
                                       targets=targets, timeout=args.timeout,
                                       mem_limit=int(args.mem_gib * 2**30), keep_cap=args.keep_cap,
                                       progress=progress)
        failures = []
        for r in results:
            if r.outcome not in fuzzing.FAILURES:
                continue
            kept = None
            if r.path is not None:
                dest = keep / r.outcome / r.path.name
                dest.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(r.path, dest)
                kept = str(dest)
            failures.append({"target": r.target, "index": r.index, "outcome": r.outcome,
                             "ops": list(r.ops), "detail": r.detail, "file": kept})
    elapsed = time.monotonic() - t0
    counts = fuzzing.tally(results, targets)
    print()
    print(fuzzing.table(counts))
    print(f"\n{len(results)} mutants in {elapsed:.0f} s; {len(failures)} failing"
          + (f", files in {keep}/" if failures else ""))

    import h5py
    import numpy
    import tfi_quat
    doc = {
        "label": args.label or "campaign",
        "date": today,
        "settings": {"mutants_per_target": per_target, "seed": args.seed, "jobs": args.jobs,
                     "timeout_s": args.timeout, "mem_limit_gib": args.mem_gib, "targets": names},
        "versions": {"tfi_quat": tfi_quat.__version__, "python": platform.python_version(),
                     "numpy": numpy.__version__, "h5py": h5py.__version__,
                     "hdf5": h5py.version.hdf5_version},
        "elapsed_s": round(elapsed, 1),
        "mutants": len(results),
        "counts": counts,
        "totals": {o: sum(c[o] for c in counts.values()) for o in fuzzing.OUTCOMES},
        "failures": failures[:2000],
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {out}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
