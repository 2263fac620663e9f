"""The documentation cannot rot: the tutorials run as written, every public name has a
docstring, ``docs/api.md`` is what ``docs/gen_api.py`` writes, and the docs' links and
section references point at something that exists."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _gen_api():
    spec = importlib.util.spec_from_file_location("gen_api", DOCS / "gen_api.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def code_blocks(path: Path, lang: str) -> list[str]:
    """The fenced ```lang blocks of a Markdown file, in order."""
    text = path.read_text(encoding="utf-8")
    return re.findall(rf"^```{lang}\n(.*?)^```$", text, flags=re.S | re.M)


def test_code_blocks_found():
    # the extraction itself: a wrong pattern would make the tutorial tests pass vacuously
    assert len(code_blocks(DOCS / "tutorial-python.md", "python")) >= 4
    assert len(code_blocks(DOCS / "tutorial-cli.md", "sh")) >= 6
    assert code_blocks(DOCS / "tutorial-cli.md", "sh")[0].startswith("tfi-quat generate")


def test_python_tutorial_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "tutorial"}
    for i, block in enumerate(code_blocks(DOCS / "tutorial-python.md", "python")):
        exec(compile(block, f"docs/tutorial-python.md, block {i + 1}", "exec"), namespace)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step_000.x", "step_010.x", "step_020.x"]
    assert len(namespace["history"]) == 21


def test_getting_started_python_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "getting_started"}
    for i, block in enumerate(code_blocks(DOCS / "getting-started.md", "python")):
        exec(compile(block, f"docs/getting-started.md, block {i + 1}", "exec"), namespace)


def test_cli_tutorial_runs(tmp_path):
    """Every ```sh block of the CLI tutorial, in order, as one bash script in an empty folder."""
    script = "set -euo pipefail\n" + "\n".join(code_blocks(DOCS / "tutorial-cli.md", "sh"))
    # `tfi-quat` runs this checkout's sources (and their numba cache) whether the project
    # is installed editable or not; tests/test_install.py tests the installed command
    bindir = tmp_path.parent / (tmp_path.name + "_bin")
    bindir.mkdir()
    (bindir / "tfi-quat").write_text(f'#!/bin/sh\nexec "{sys.executable}" -m tfi_quat.cli "$@"\n')
    (bindir / "tfi-quat").chmod(0o755)
    env = dict(os.environ)
    env["PATH"] = str(bindir) + os.pathsep + env.get("PATH", "")
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    res = subprocess.run(["bash", "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=1800)
    assert res.returncode == 0, f"tutorial failed:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}"
    for name in ("naca0012.x", "naca0012.toml", "pitched.x", "pitched_tfi.x", "pitched.png",
                 "quality_tfi.json"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert "0 negative cells" in res.stdout


def test_every_public_name_has_a_docstring():
    missing = _gen_api().undocumented()
    assert not missing, "public names without a docstring: " + ", ".join(missing)


def test_api_reference_is_up_to_date():
    gen = _gen_api()
    current = (DOCS / "api.md").read_text(encoding="utf-8")
    assert current == gen.render(), "docs/api.md is out of date: run  python docs/gen_api.py"


def test_undocumented_names_are_caught():
    gen = _gen_api()
    assert gen.docstring_md("Summary.\n\nParameters\n----------\nx : int\n    The x.\n") == \
        "Summary.\n\n**Parameters**\n\n- `x` : int\n  The x."
    assert gen._data_comment("tfi_quat.grid", "FACES")
    assert gen._data_comment("tfi_quat.grid", "no_such_name") is None


def _markdown_files() -> list[Path]:
    return sorted([ROOT / "README.md", ROOT / "CHANGELOG.md", *DOCS.glob("*.md")])


@pytest.mark.parametrize("path", _markdown_files(), ids=lambda p: p.name)
def test_docs_point_at_files_that_exist(path):
    """Backquoted repository paths (`docs/x.md`, `grids/...`, `benchmarks/...`, `tests/...`)
    and Markdown links to local files name files that exist."""
    text = path.read_text(encoding="utf-8")
    named = set(re.findall(r"`((?:docs|benchmarks|tests|grids|tfi_quat)/[\w./-]+\.(?:md|py|json|toml|x|png))`",
                           text))
    named |= {m for m in re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", text) if not m.startswith("http")}
    base = {ROOT / "README.md": ROOT, ROOT / "CHANGELOG.md": ROOT}.get(path, DOCS)
    for name in sorted(named):
        candidates = [ROOT / name, base / name]
        assert any(c.exists() for c in candidates), f"{path.name} names {name}, which does not exist"


def test_method_sections_cited_exist():
    """Every "docs/method.md §x.y" cited in the code, tests and docs is a heading of docs/method.md."""
    headings = set(re.findall(r"^#{2,3} (\d+(?:\.\d+)?)\.? ", (DOCS / "method.md").read_text(encoding="utf-8"),
                              flags=re.M))
    cited = {}
    files = [*ROOT.glob("tfi_quat/**/*.py"), *ROOT.glob("tests/*.py"), *ROOT.glob("benchmarks/*.py"),
             *DOCS.glob("*.md"), ROOT / "README.md"]
    for f in files:
        for m in re.finditer(r"method\.md`? ?§ ?(\d+(?:\.\d+)?)((?:,? ?(?:and )?§ ?\d+(?:\.\d+)?)*)",
                             f.read_text(encoding="utf-8")):
            for sec in [m.group(1), *re.findall(r"§ ?(\d+(?:\.\d+)?)", m.group(2))]:
                cited.setdefault(sec, f.relative_to(ROOT))
    assert cited, "no citations found: the pattern is wrong"
    unknown = {s: str(f) for s, f in cited.items() if s not in headings}
    assert not unknown, f"cited sections missing from docs/method.md: {unknown}"


def test_no_pointer_outside_the_repository():
    """The repository stands alone: nothing cites the founding design file or ../shared."""
    files = [*ROOT.glob("tfi_quat/**/*.py"), *ROOT.glob("tests/*.py"), *ROOT.glob("benchmarks/*.py"),
             *DOCS.glob("*.md"), ROOT / "README.md", ROOT / "CHANGELOG.md"]
    pattern = re.compile(r"DESIGN(?:\.md| \d| section| property)|\.\./shared|/work/")
    bad = [f"{f.relative_to(ROOT)}:{i}" for f in files if f.resolve() != Path(__file__).resolve()
           for i, line in enumerate(f.read_text(encoding="utf-8").splitlines(), 1) if pattern.search(line)]
    assert not bad, "pointers outside the repository: " + ", ".join(bad)


def test_ci_runs_the_readme_test_command():
    """`.ci/run` runs exactly the README's install-and-test command, and the README's
    set-up commands are regular (non-editable) installs."""
    blocks = code_blocks(ROOT / "README.md", "sh")
    test_cmd = [b.strip() for b in blocks if "pytest" in b]
    demo_cmd = [b.strip() for b in blocks if "tfi-quat demo" in b]
    assert len(test_cmd) == 1 and len(demo_cmd) == 1
    assert test_cmd[0] in (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()
    assert " -e " not in test_cmd[0] and " -e " not in demo_cmd[0]
