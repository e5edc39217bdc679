"""``python -m hybridloc.cli``: the ``hybridloc`` command."""

import sys

from . import main

sys.exit(main())
