"""``python -m tfi_quat.cli``: the same as the ``tfi-quat`` command."""

import sys

from . import main

sys.exit(main())
