"""Helpers shared by the subcommands."""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import OverwriteError


def check_output(path, force: bool, inputs=()) -> Path:
    """Refuse an existing output file unless ``force``; never silently replace an input."""
    out = Path(os.fspath(path))
    if out.exists() and not force:
        for p in inputs:
            if p is not None and Path(p).exists() and os.path.samefile(out, p):
                raise OverwriteError(f"{out}: is an input of this command; refusing to overwrite it "
                                     "(use --force)")
        raise OverwriteError(f"{out}: exists; refusing to overwrite it (use --force)")
    return out
