"""``tfi-quat`` command line: ``main(argv=None)`` dispatches to one module per subcommand.

Each subcommand module defines ``HELP`` (one line), ``add_args(parser)`` and
``run(args) -> int``.

Exit status: 0 success; 1 the command ran but its result failed a check the
user asked for or the command makes by default (``deform`` produced negative
cells, ``quality --fail-on-negative``); 2 bad input or usage: a
:class:`~tfi_quat.errors.TfiQuatError`, an ``OSError`` (missing file,
directory, no permission) or a ``MemoryError`` becomes one line on stderr;
70 an internal error (a bug: one line, please report it); 130 interrupted
(Ctrl-C), 143 terminated (SIGTERM).  ``--debug`` shows the traceback
instead of the one line.  An interrupted or terminated write leaves neither
a partial output nor its temporary file.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import signal
import sys
import threading

from ..errors import TfiQuatError

__all__ = ["main", "console_main", "GC_THRESHOLDS", "SUBCOMMANDS", "EXIT_CHECK", "EXIT_INPUT", "EXIT_INTERNAL", "EXIT_INTERRUPTED",
           "EXIT_TERMINATED"]

#: exit status: the command ran but its result failed a check (a folded grid, not written)
EXIT_CHECK = 1
#: exit status: bad input or usage (one line on stderr)
EXIT_INPUT = 2
#: exit status: an internal error (a bug; ``--debug`` shows the traceback)
EXIT_INTERNAL = 70
#: exit status: interrupted by Ctrl-C (SIGINT); temporary files removed
EXIT_INTERRUPTED = 130
#: exit status: terminated by SIGTERM; temporary files removed
EXIT_TERMINATED = 128 + signal.SIGTERM

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


#: garbage-collector thresholds of a ``tfi-quat`` process: numba's cached-kernel loads
#: allocate some 10^5 container objects, and the default (700, 10, 10) ran about 280
#: collections in a ``deform``, two of them over every object (0.2 s of CPU; 0.05 s so)
GC_THRESHOLDS = (10_000, 10, 10)


def console_main() -> None:
    """The ``tfi-quat`` process (console script and ``python -m tfi_quat.cli``): :func:`main`
    with the garbage collector set for a short run (:data:`GC_THRESHOLDS`, and the objects of
    the imports frozen, so that no later collection walks them); exits with its status.
    :func:`main` itself leaves the collector alone, as a library call should."""
    gc.set_threshold(*GC_THRESHOLDS)
    build_parser()                  # imports every subcommand module (numba with them) ...
    gc.freeze()                     # ... whose objects live as long as the process anyway
    sys.exit(main())


class Terminated(BaseException):
    """Raised in the main thread by SIGTERM while :func:`main` runs (like ``KeyboardInterrupt``
    for SIGINT), so that ``finally`` clauses (a write's temporary file) run before exiting."""


def _raise_terminated(signum, frame):
    raise Terminated()


def _message(exc: BaseException) -> str:
    """One line for an error: ``PATH: reason`` for an OSError, else the message."""
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"
    if isinstance(exc, MemoryError):
        return f"out of memory{f' ({exc})' if str(exc) else ''}"
    msg = " ".join(str(exc).split()) or type(exc).__name__   # one line, always
    if isinstance(exc, OSError) and exc.filename and str(exc.filename) not in msg:
        msg = f"{exc.filename}: {msg}"
    return msg


def main(argv=None) -> int:
    """Run the command line; returns the exit status (see the module docstring)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "_run", None) is None:
        parser.print_help(sys.stderr)
        return EXIT_INPUT
    debug = getattr(args, "debug", False)
    installed = threading.current_thread() is threading.main_thread()
    if installed:
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        return int(args._run(args) or 0)
    except (TfiQuatError, OSError, MemoryError) as exc:
        if debug:
            raise
        print(f"tfi-quat {args.command}: error: {_message(exc)}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print("tfi-quat: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Terminated:
        print("tfi-quat: terminated", file=sys.stderr)
        return EXIT_TERMINATED
    except Exception as exc:    # a bug, not bad input: still one line (--debug shows the traceback)
        if debug:
            raise
        print(f"tfi-quat {args.command}: internal error: {type(exc).__name__}: {_message(exc)} "
              "(please report it; --debug shows the traceback)", file=sys.stderr)
        return EXIT_INTERNAL
    finally:
        if installed:
            signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
