"""``tfi-quat`` command line: ``main(argv=None)`` dispatches to one module per subcommand.

Each subcommand module defines ``HELP`` (one line), ``add_args(parser)`` and
``run(args) -> int``.  A :class:`~tfi_quat.errors.TfiQuatError` (or an
``OSError``: missing file, permission) becomes one line on stderr and exit
status 2; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from ..errors import TfiQuatError

__all__ = ["main", "SUBCOMMANDS"]

#: subcommand name -> module (relative to this package)
SUBCOMMANDS = {
    "info": "._info",
    "convert": "._convert",
    "connect": "._connect",
    "generate": "._generate",
    "deform": "._deform",
    "demo": "._demo",
    "quality": "._quality",
    "plot": "._plot",
}


def _version() -> str:
    from .. import __version__
    return __version__


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tfi-quat",
        description="Multiblock structured grids: I/O, connectivity, quaternion TFI deformation.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    parser.add_argument("--debug", action="store_true", help="show the full traceback on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, modname in SUBCOMMANDS.items():
        mod = importlib.import_module(modname, __name__)
        p = sub.add_parser(name, help=mod.HELP, description=getattr(mod, "DESCRIPTION", mod.HELP))
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                       help="show the full traceback on errors")
        mod.add_args(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv=None) -> int:
    """Run the command line; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "_run", None) is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args._run(args) or 0)
    except (TfiQuatError, OSError) as exc:
        if getattr(args, "debug", False):
            raise
        msg = " ".join(str(exc).split()) or type(exc).__name__   # one line, always
        if isinstance(exc, OSError) and exc.filename and str(exc.filename) not in msg:
            msg = f"{exc.filename}: {msg}"
        print(f"tfi-quat {args.command}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("tfi-quat: interrupted", file=sys.stderr)
        return 130
