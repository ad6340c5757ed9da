"""``--json FILE|-`` for every command: the JSON report to a file (atomically) or to
standard output, where it then replaces the text report."""

from __future__ import annotations

import json
import sys

from ..io.atomic import json_default, write_json


def to_stdout(target) -> bool:
    """True when ``--json -``: the JSON goes to standard output instead of the text."""
    return target is not None and str(target) == "-"


def write_report(target, content, indent: int = 2) -> str | None:
    """Write ``content`` to ``target`` (a path, ``"-"`` for standard output, or None for
    nothing); returns the path written, or None."""
    if target is None:
        return None
    if to_stdout(target):
        sys.stdout.write(json.dumps(content, indent=indent, allow_nan=True, default=json_default) + "\n")
        sys.stdout.flush()
        return None
    return str(write_json(target, content, indent=indent))
