"""Reading a monitor's Rerun recording (``monitor.rrd``) back in the tests, with Rerun's own
reader and ``rerun rrd verify`` (tests of the monitor, the pipeline, the live loop)."""

from __future__ import annotations

import subprocess
from pathlib import Path

from rerun.chunk import RrdReader

from streamer.tools.viewer import rerun_binary


def rrd_entities(path: Path) -> dict:
    """Entity path -> list of (timeline values, {component: value}) rows of the recording store."""
    reader = RrdReader(path)
    out: dict = {}
    for chunk in reader.stream():
        rb = chunk.to_record_batch()
        cols = [n for n in rb.schema.names if ":" in n]
        for r in range(rb.num_rows):
            times = {t: rb.column(t)[r].as_py() for t in ("mission_time", "segment") if t in rb.schema.names}
            out.setdefault(chunk.entity_path, []).append((times, {c: rb.column(c)[r].as_py() for c in cols}))
    return out


def blueprint_views(path: Path) -> list[tuple[str, str]]:
    reader = RrdReader(path)
    views = []
    for chunk in reader.stream(store=reader.blueprints()[0]):
        rb = chunk.to_record_batch()
        if "ViewBlueprint:class_identifier" in rb.schema.names:
            cls = rb.column("ViewBlueprint:class_identifier").to_pylist()[0]
            origin = rb.column("ViewBlueprint:space_origin").to_pylist()[0]
            views.append((cls[0] if isinstance(cls, list) else cls, origin[0] if isinstance(origin, list) else origin))
    return views


def rrd_chunks(path: Path) -> int:
    return sum(1 for _ in RrdReader(path).stream())


def rrd_footer(path: Path) -> bool:
    """Whether the file ends with an RRD footer (``rerun rrd verify`` says "Missing RRD footer" if not)."""
    done = subprocess.run([rerun_binary(), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=60)
    return done.returncode == 0 and "footer" not in (done.stdout + done.stderr).lower()
