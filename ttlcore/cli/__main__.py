"""``python -m ttlcore.cli``: the ``ttl`` command line."""

import sys

from .main import main

sys.exit(main())
