"""Atomic, non-destructive writes, and bounded reads of small text files.

A writer opens :func:`atomic_output`, writes into the temporary file it
yields, and the file is renamed over the target only when the writer
finished without error.  A failure (an exception, Ctrl-C, or SIGTERM under
the command line, which turns it into an exception) leaves the target
untouched and removes the temporary file.  Only ``kill -9`` (or a power
cut) can leave the hidden temporary file ``.TARGET.XXXXXXXX.tmp`` in the
target's folder; the target itself is never half-written.

:func:`read_text` reads the small text inputs (connectivity maps, case
files): OS conditions raise the standard ``OSError`` subclasses naming the
path; a file larger than the limit or not valid UTF-8 raises the caller's
error class naming the file.
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from pathlib import Path

from ..errors import OverwriteError

__all__ = ["atomic_output", "check_target", "new_temp", "install", "read_text", "TEXT_LIMIT"]

#: largest text input read by :func:`read_text` (bytes)
TEXT_LIMIT = 64 << 20


def check_target(path, *, overwrite: bool, protect=(), replace_existing: bool = True) -> Path:
    """Refuse to write over a protected (input) file unless ``overwrite``.

    ``protect`` lists paths that are inputs of the operation (e.g. the grid's
    ``source_path``).  With ``replace_existing=False`` every existing file is
    refused unless ``overwrite``.  Returns the target as a :class:`~pathlib.Path`.
    """
    target = Path(os.fspath(path))
    if target.is_dir():
        raise OverwriteError(f"{target}: is a directory")
    if not overwrite and not replace_existing and target.exists():
        raise OverwriteError(f"{target}: exists (pass overwrite=True, or --force on the command line)")
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


def new_temp(path) -> tuple[int, str]:
    """Create the hidden temporary file ``.TARGET.XXXXXXXX.tmp`` in the target's folder.

    Returns its open descriptor and path.  FileNotFoundError when the folder
    does not exist.
    """
    target = Path(os.fspath(path))
    folder = target.parent if str(target.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"{target}: folder {folder} does not exist")
    return tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=folder)


def install(tmp, path) -> None:
    """Give a complete, synced temporary file the usual permissions and rename it over ``path``."""
    # keep the usual permissions of a new file (mkstemp makes it 0600)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    os.replace(tmp, os.fspath(path))


@contextlib.contextmanager
def atomic_output(path, mode: str = "wb"):
    """Yield a temporary file object in the target's folder; rename into place on success.

    ``mode`` is ``"wb"`` or ``"w"`` (text); the special mode ``"path"`` yields the
    temporary *path* instead (for libraries such as h5py that open files themselves).
    """
    target = Path(os.fspath(path))
    fd, tmp = new_temp(target)
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
        install(tmp, target)
        ok = True
    finally:
        if not ok:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def read_text(path, error, *, limit: int = TEXT_LIMIT) -> str:
    """The UTF-8 text of a small input file, read with a size bound.

    Parameters
    ----------
    path : str or path-like
    error : type
        The :class:`~tfi_quat.errors.TfiQuatError` subclass raised for a file
        that is too large or not UTF-8 (``ConnectivityError``, ``CaseError``).
    limit : int
        Most bytes read; a larger file (or an endless one such as
        ``/dev/zero``) is refused after reading ``limit + 1`` bytes.

    Raises
    ------
    FileNotFoundError, IsADirectoryError, PermissionError
        With the path (``exc.filename``) and the reason.
    error
        Larger than ``limit``, or not UTF-8 (with the byte offset).
    """
    p = Path(os.fspath(path))
    if p.is_dir():          # some platforms open folders for reading; none reads them
        raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(p))
    too_big = error(f"{p}: larger than {limit:,} bytes; not a file this reader expects")
    with open(p, "rb") as fh:
        if os.fstat(fh.fileno()).st_size > limit:
            raise too_big
        chunks, total = [], 0
        while total <= limit:       # in pieces: read(n) would allocate n bytes up front
            chunk = fh.read(min(1 << 20, limit + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
    if total > limit:
        raise too_big
    raw = b"".join(chunks)
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise error(f"{p}:{line}: not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start})") from None
