"""Write ``docs/api.md``, the API reference, from the package's docstrings.

    python docs/gen_api.py           # rewrite docs/api.md
    python docs/gen_api.py --check   # exit 1 if docs/api.md is stale or a public name is undocumented

The public names are the ``__all__`` of ``tfi_quat`` and of every public
module under it (no leading underscore in its dotted name).  Functions,
classes and numba kernels are documented by their docstrings; data (tuples,
constants) by the ``#:`` comment above their assignment.  A name re-exported
from another public module is listed with a link to its home, so every
object is described once.  ``tests/test_docs.py`` runs :func:`render` and
:func:`undocumented` and fails when either disagrees with the repository.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import inspect
import pkgutil
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
API_MD = ROOT / "docs" / "api.md"

#: numpydoc sections whose entries are ``name : type`` lines with indented descriptions
ENTRY_SECTIONS = {"Parameters", "Other Parameters", "Returns", "Yields", "Raises", "Warns",
                  "Attributes", "Receives"}
#: dotted names skipped by the walk: data shipped with the package, not an API
SKIP = ("tfi_quat.grids",)


def public_modules() -> list[str]:
    """Dotted names of the public modules that define ``__all__``, ``tfi_quat`` first."""
    import tfi_quat
    names = ["tfi_quat"]
    for info in pkgutil.walk_packages(tfi_quat.__path__, "tfi_quat."):
        if any(part.startswith("_") for part in info.name.split(".")):
            continue
        if any(info.name == s or info.name.startswith(s + ".") for s in SKIP):
            continue
        names.append(info.name)
    return [n for n in sorted(names, key=lambda n: (n != "tfi_quat", n))
            if hasattr(importlib.import_module(n), "__all__")]


def modules_without_all() -> list[str]:
    """Public modules that define no ``__all__`` (their names are not part of the reference)."""
    import tfi_quat
    out = []
    for info in pkgutil.walk_packages(tfi_quat.__path__, "tfi_quat."):
        if any(part.startswith("_") for part in info.name.split(".")):
            continue
        if any(info.name == s or info.name.startswith(s + ".") for s in SKIP):
            continue
        if not hasattr(importlib.import_module(info.name), "__all__"):
            out.append(info.name)
    return sorted(out)


# --------------------------------------------------------------------------- inspection
def _func(obj):
    """The Python function behind a numba dispatcher, else ``obj``."""
    return getattr(obj, "py_func", obj)


def _kind(obj) -> str:
    if inspect.isclass(obj):
        return "class"
    if callable(_func(obj)):
        return "function"
    return "data"


def _home(obj, modname: str, name: str | None = None) -> str:
    """The module an object is defined in; for data, the module whose source assigns it
    (followed through ``from .x import name``)."""
    if _kind(obj) != "data":
        return getattr(_func(obj), "__module__", modname) or modname
    if name is None:
        return modname
    try:
        source = inspect.getsource(importlib.import_module(modname))
    except (OSError, TypeError):
        return modname
    for node in ast.parse(source).body:
        if isinstance(node, ast.ImportFrom) and any(a.name == name and a.asname is None for a in node.names):
            package = modname if hasattr(importlib.import_module(modname), "__path__") \
                else modname.rpartition(".")[0]
            target = importlib.util.resolve_name("." * node.level + (node.module or ""), package) \
                if node.level else node.module
            return _home(obj, target, name)
    return modname


def _data_comment(modname: str, name: str) -> str | None:
    """The ``#:`` comment lines right above ``name = ...`` in a module's source, joined."""
    mod = importlib.import_module(modname)
    try:
        source = inspect.getsource(mod)
    except (OSError, TypeError):
        return None
    lines = source.splitlines()
    for node in ast.parse(source).body:
        targets = []
        if isinstance(node, ast.Assign):
            targets = [t.id for t in node.targets if isinstance(t, ast.Name)]
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            targets = [node.target.id]
        if name not in targets:
            continue
        comment = []
        i = node.lineno - 2
        while i >= 0 and lines[i].lstrip().startswith("#:"):
            comment.insert(0, lines[i].lstrip()[2:].strip())
            i -= 1
        if comment:
            return " ".join(comment)
    return None


def _doc(obj) -> str | None:
    if inspect.isclass(obj):
        doc = obj.__dict__.get("__doc__")
        return inspect.cleandoc(doc) if doc else None
    return inspect.getdoc(_func(obj))


def _signature(obj) -> str:
    """``(a, b=1, *, c=None) -> R`` without parameter annotations, stable across runs."""
    try:
        sig = inspect.signature(_func(obj))
    except (TypeError, ValueError):
        return "(...)"
    params = [p.replace(annotation=inspect.Parameter.empty) for p in sig.parameters.values()]
    if inspect.isclass(obj) and params and params[0].name == "self":
        params = params[1:]
    text = str(sig.replace(parameters=params, return_annotation=inspect.Signature.empty))
    ret = sig.return_annotation
    if ret is not inspect.Signature.empty and not inspect.isclass(obj):
        text += " -> " + (ret if isinstance(ret, str) else inspect.formatannotation(ret))
    return re.sub(r" at 0x[0-9a-fA-F]+", "", text)


def _members(cls) -> list[tuple[str, object]]:
    """Public methods and properties defined in the class body, in source order."""
    out = []
    for name, value in vars(cls).items():
        if name.startswith("_"):
            continue
        if isinstance(value, property):
            out.append((name, value))
        elif isinstance(value, (staticmethod, classmethod)):
            out.append((name, value.__func__))
        elif inspect.isfunction(value):
            out.append((name, value))
    return out


def undocumented() -> list[str]:
    """Public names without a docstring (or, for data, without a ``#:`` comment)."""
    missing = []
    for modname in public_modules():
        mod = importlib.import_module(modname)
        if not inspect.getdoc(mod):
            missing.append(f"{modname} (module docstring)")
        for name in mod.__all__:
            if name.startswith("__"):
                continue
            obj = getattr(mod, name)
            home = _home(obj, modname, name)
            if home != modname:
                continue                  # documented (and checked) at its home
            if _kind(obj) == "data":
                if not _data_comment(modname, name):
                    missing.append(f"{modname}.{name}")
            elif not _doc(obj):
                missing.append(f"{modname}.{name}")
    return missing


# --------------------------------------------------------------------------- rendering
_ROLE = re.compile(r":(?:func|class|meth|data|mod|attr|exc|obj|py:\w+):`~?([^`]+)`")


def _inline(text: str) -> str:
    text = _ROLE.sub(r"`\1`", text)
    return text.replace("``", "`")


def docstring_md(doc: str) -> str:
    """A numpydoc docstring as Markdown: section headers bold, ``name : type`` entries as a list,
    ``>>>`` examples fenced, roles and double backquotes as code spans."""
    lines = doc.splitlines()
    out: list[str] = []
    section = None
    in_code = False
    i = 0
    while i < len(lines):
        line = lines[i]
        stripped = line.strip()
        nxt = lines[i + 1].strip() if i + 1 < len(lines) else ""
        if in_code and not stripped.startswith((">>>", "...")) and (not stripped or section != "Examples"):
            out.append("```")
            in_code = False
        if stripped and nxt and set(nxt) == {"-"} and len(nxt) >= 3 and not line.startswith(" "):
            section = stripped
            out += ["", f"**{stripped}**", ""]
            i += 2
            continue
        if stripped.startswith(">>>") and not in_code:
            out.append("```python")
            in_code = True
        if in_code:
            out.append(line)
        elif (section in ENTRY_SECTIONS and stripped and not line.startswith(" ") and " : " not in stripped
              and i + 1 < len(lines) and not lines[i + 1].startswith(" ")):
            section = None                # a paragraph after the entries, not an entry
            out.append(_inline(line))
        elif section in ENTRY_SECTIONS and stripped and not line.startswith(" "):
            name, sep, typ = stripped.removesuffix(" :").partition(" : ")
            out.append(f"- `{name}`" + (f" : {_inline(typ)}" if sep else ""))
        elif section in ENTRY_SECTIONS and stripped:
            out.append("  " + _inline(stripped))
        else:
            out.append(_inline(line))
        i += 1
    if in_code:
        out.append("```")
    text = "\n".join(out).strip("\n")
    return re.sub(r"\n{3,}", "\n\n", text)


def _anchor(heading: str) -> str:
    """GitHub's anchor for a heading."""
    text = heading.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _data_value(obj) -> str:
    text = repr(obj)
    if " at 0x" in text or len(text) > 90 or "\n" in text:
        return type(obj).__name__
    return text


def render() -> str:
    """The text of ``docs/api.md``."""
    modules = public_modules()
    documented = {}                     # (home, name) -> heading
    for modname in modules:
        mod = importlib.import_module(modname)
        for name in mod.__all__:
            obj = getattr(mod, name)
            if _home(obj, modname, name) == modname:
                documented[(modname, name)] = f"{modname}.{name}"

    parts = [
        "# API reference",
        "",
        "Generated from the docstrings by `docs/gen_api.py`; do not edit by hand.  After a change",
        "to a public name or a docstring, rewrite it with",
        "",
        "```sh",
        "python docs/gen_api.py",
        "```",
        "",
        "(`tests/test_docs.py` fails while this file is out of date or a public name has no",
        "docstring).  Public names are the `__all__` of each module below; everything else,",
        "and every module whose name starts with `_`, is internal.  Guides: `docs/getting-started.md`,",
        "`docs/tutorial-cli.md`, `docs/tutorial-python.md`; the method: `docs/method.md`.",
        "",
        "## Modules",
        "",
    ]
    for modname in modules:
        mod = importlib.import_module(modname)
        first = (inspect.getdoc(mod) or "").strip().split("\n\n")[0].replace("\n", " ")
        parts.append(f"- [`{modname}`](#{_anchor(modname)}): {_inline(first)}")
    parts.append("")

    for modname in modules:
        mod = importlib.import_module(modname)
        parts += [f"## {modname}", ""]
        if inspect.getdoc(mod):
            parts += [docstring_md(inspect.getdoc(mod)), ""]
        here, elsewhere = [], []
        for name in mod.__all__:
            obj = getattr(mod, name)
            home = _home(obj, modname, name)
            if home == modname:
                here.append((name, obj))
            elif (home, name) in documented:
                elsewhere.append((name, documented[(home, name)]))
            else:
                here.append((name, obj))     # re-exported from a private module: documented here
        if elsewhere:
            parts.append("Also here: " + ", ".join(
                f"[`{name}`](#{_anchor(target)})" for name, target in elsewhere) + ".")
            parts.append("")
        for name, obj in here:
            parts += _render_name(modname, name, obj)
    return "\n".join(parts).rstrip("\n") + "\n"


def _render_name(modname: str, name: str, obj) -> list[str]:
    kind = _kind(obj)
    out = [f"### {modname}.{name}", ""]
    if name == "__version__":
        return out + [f"The package version (`{obj}`).", ""]
    if kind == "data":
        out += [f"`{name} = {_data_value(obj)}`", "",
                _inline(_data_comment(modname, name) or "*(undocumented)*"), ""]
        return out
    if kind == "class":
        bases = [b.__name__ for b in obj.__bases__ if b is not object]
        head = f"class {name}{_signature(obj)}"
        if bases and issubclass(obj, BaseException):
            head = f"class {name}({', '.join(bases)})"
        out += ["```python", head, "```", "", docstring_md(_doc(obj) or "*(undocumented)*"), ""]
        for mname, member in _members(obj):
            if isinstance(member, property):
                out += [f"#### {name}.{mname}", "", "*property*", ""]
                doc = inspect.getdoc(member.fget) if member.fget else None
            else:
                out += [f"#### {name}.{mname}", "", "```python", f"{mname}{_signature(member)}", "```", ""]
                doc = inspect.getdoc(member)
            out += [docstring_md(doc) if doc else "*(no docstring)*", ""]
        return out
    out += ["```python", f"{name}{_signature(obj)}", "```", "",
            docstring_md(_doc(obj) or "*(undocumented)*"), ""]
    return out


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    text = render()
    missing = undocumented()
    for name in missing:
        print(f"undocumented public name: {name}", file=sys.stderr)
    if "--check" in argv:
        current = API_MD.read_text(encoding="utf-8") if API_MD.exists() else ""
        if current != text:
            print(f"{API_MD} is out of date: run python docs/gen_api.py", file=sys.stderr)
            return 1
        return 1 if missing else 0
    API_MD.write_text(text, encoding="utf-8")
    print(f"wrote {API_MD} ({len(text.splitlines())} lines)")
    return 1 if missing else 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
