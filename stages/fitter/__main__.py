"""``python -m stages.fitter``: the fitter's process (:func:`stages.fitter.fitter.main`).

``ttl stage fitter`` imports this module for its ``main`` (:func:`streamer.tools.cli.stage_program`)."""

import sys

from .fitter import main

if __name__ == "__main__":
    sys.exit(main())
