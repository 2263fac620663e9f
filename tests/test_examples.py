"""The examples run as written: ``examples/coupling_loop.py`` and the coupling page's code."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np

import tfi_quat as tq

ROOT = Path(__file__).resolve().parents[1]


def test_coupling_loop_example_runs(tmp_path):
    out = tmp_path / "loop"
    res = subprocess.run([sys.executable, str(ROOT / "examples" / "coupling_loop.py"), "--steps", "3",
                          "--every", "2", "--threads", "1", "--out", str(out)],
                         cwd=tmp_path, capture_output=True, text=True, timeout=1800)
    assert res.returncode == 0, f"{res.stdout[-3000:]}\n{res.stderr[-3000:]}"
    lines = res.stdout.splitlines()
    rows = [ln.split() for ln in lines if re.match(r"\s+\d+\s+\d", ln)]
    assert [int(r[0]) for r in rows] == [1, 2, 3]
    assert all(int(r[-1]) == 0 for r in rows)                # no negative cells
    assert all(0.0 < float(r[-2]) <= 1.5 for r in rows)      # min Jacobian ratio
    assert "peak memory" in lines[-2] and lines[-1] == f"wrote 2 grid file(s) to {out}/"
    # steps 2 and 3 written (every 2nd and the last); the wall moved as the model says
    assert sorted(p.name for p in out.iterdir()) == ["wing_0002.x", "wing_0003.x"]
    ref = tq.read(ROOT / "grids" / "wing_ch_501k.x")
    last = tq.read(out / "wing_0003.x")
    assert last.dims == ref.dims
    moved = max(float(np.abs(a.xyz - b.xyz).max()) for a, b in zip(last, ref))
    assert 0.0 < moved < 0.2


def _coupling_blocks() -> list[str]:
    """The ```python blocks of docs/coupling.md's "The coupling loop" section."""
    text = (ROOT / "docs" / "coupling.md").read_text(encoding="utf-8")
    start = text.index("## The coupling loop")
    nxt = re.search(r"^## ", text[start + 3:], flags=re.M)
    part = text[start:start + 3 + nxt.start()] if nxt else text[start:]
    return re.findall(r"^```python\n(.*?)^```$", part, flags=re.S | re.M)


def test_coupling_page_code_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    blocks = _coupling_blocks()
    assert len(blocks) >= 4
    ns = {"__name__": "coupling_page"}
    for i, block in enumerate(blocks):
        exec(compile(block, f"docs/coupling.md, block {i + 1}", "exec"), ns)
    # the solver's orders give the same grid as surface_ids() order
    for name in ("same", "same_again"):
        want = ns["d"].deform(ns["wall"] + (ns["disp"] if name == "same" else 0.0))
        assert all(np.array_equal(a.xyz, b.xyz) for a, b in zip(ns[name], want))
    assert ns["motion"].names == ("plunge", "pitch")
    assert (tmp_path / "MODES.h5").exists() and (tmp_path / "SURF.h5").exists()
