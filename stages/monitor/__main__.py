"""``python -m stages.monitor``: the monitor's process (:func:`stages.monitor.monitor.main`).

``ttl stage monitor`` imports this module for its ``main`` (:func:`streamer.tools.cli.stage_program`)."""

import sys

from .monitor import main

if __name__ == "__main__":
    sys.exit(main())
