"""Atomic, non-destructive writes.

A writer opens :func:`atomic_output`, writes into the temporary file it
yields, and the file is renamed over the target only when the writer
finished without error.  A failure leaves the target untouched and removes
the temporary file.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from ..errors import OverwriteError

__all__ = ["atomic_output", "check_target"]


def check_target(path, *, overwrite: bool, protect=()) -> Path:
    """Refuse to write over a protected (input) file unless ``overwrite``.

    ``protect`` lists paths that are inputs of the operation (e.g. the grid's
    ``source_path``).  Returns the target as a :class:`~pathlib.Path`.
    """
    target = Path(os.fspath(path))
    if target.is_dir():
        raise OverwriteError(f"{target}: is a directory")
    if not overwrite and target.exists():
        for p in protect:
            if p is None:
                continue
            try:
                same = os.path.samefile(target, os.fspath(p))
            except OSError:
                same = False
            if same:
                raise OverwriteError(f"{target}: refusing to overwrite the input file "
                                     "(pass overwrite=True, or --force on the command line)")
    return target


@contextlib.contextmanager
def atomic_output(path, mode: str = "wb"):
    """Yield a temporary file object in the target's folder; rename into place on success.

    ``mode`` is ``"wb"`` or ``"w"`` (text); the special mode ``"path"`` yields the
    temporary *path* instead (for libraries such as h5py that open files themselves).
    """
    target = Path(os.fspath(path))
    folder = target.parent if str(target.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"{target}: folder {folder} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=folder)
    ok = False
    try:
        if mode == "path":
            os.close(fd)
            yield tmp
            # the library that wrote the file has closed it: make it durable too
            sync = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(sync)
            finally:
                os.close(sync)
        else:
            kw = {} if "b" in mode else {"encoding": "ascii", "newline": "\n"}
            with os.fdopen(fd, mode, **kw) as fh:
                yield fh
                fh.flush()
                os.fsync(fh.fileno())
        # keep the usual permissions of a new file (mkstemp makes it 0600)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, target)
        ok = True
    finally:
        if not ok:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
