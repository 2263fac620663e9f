"""``python -m tfi_quat.cli``: the same as the ``tfi-quat`` command."""

from . import console_main

console_main()
