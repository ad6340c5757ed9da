"""The monitor's segments gone from the publishers' caches, read back from the recordings.

A monitor restarted while the fitter and the subtractor went on may need segments that no
cache holds any more (:meth:`stages.monitor_settling.Settling.evicted`): they would never
come, and it would wait for them as long as their producers live (the chaos test's run
never ended).  Every :data:`RECOVER_EVERY` seconds the monitor asks its settling which
those are and reads them from their producers' recordings
(:func:`streamer.recorded_inputs.recorded_copies`), drawing each as if it had arrived; a
``recovered`` event says how many.  One that no recording holds (a producer on another
host) is given up: its segment fails with the reason, as a lost sample's would.
"""

from __future__ import annotations

import time
from pathlib import Path

from streamer.recorded_inputs import recorded_copies

from .monitor_settling import RECORDED

__all__ = ["RECOVER_EVERY", "recover_evicted"]

#: Seconds between two looks for segments gone from the caches.
RECOVER_EVERY = 10.0


def recover_evicted(monitor, now: float | None = None) -> int:
    """Read back and draw the segments ``monitor`` needs that left the caches (module
    docstring); returns how many were drawn.  Rate-limited to one look every
    :data:`RECOVER_EVERY` seconds (``monitor._recovered_at``)."""
    now = time.monotonic() if now is None else now
    if now - getattr(monitor, "_recovered_at", -RECOVER_EVERY) < RECOVER_EVERY:
        return 0
    monitor._recovered_at = now
    board = monitor.board.snapshot()
    gone = monitor.settling.evicted(
        board, monitor.done | monitor.failed, monitor.config.cache, board.get(monitor.stage_name)
    )
    run_dir = Path(monitor.config.recordings) / monitor.run_id
    drawn = 0
    for topic, indices in gone.items():
        copies = recorded_copies(run_dir, RECORDED[topic], topic, indices)
        for i in sorted(indices):
            seg = copies.get(i)
            if seg is None:
                monitor.settling.unhandled[topic].add(i)  # not waited for: the segment fails
                monitor.report_error(
                    "failed",
                    f"segment {i}: its {topic} left the publisher's cache before this monitor "
                    f"process could take it, and no recording in {run_dir} holds it",
                    index=i,
                    details={"waiting_for": topic},
                )
                continue
            try:
                monitor.handle(seg.header, seg.arrays)
                drawn += 1
            except Exception as exc:  # noqa: BLE001 - recorded and settled as any input that fails
                monitor.report_error("failed", f"segment {i}: its recorded {topic} could not be drawn: {exc}", index=i)
        if copies:
            monitor.event(
                "recovered",
                message=f"{len(copies)} {topic} segment(s) read back from {RECORDED[topic]}'s recordings "
                "(gone from its cache while this monitor process was not there)",
                topic=topic,
                indices=sorted(copies),
            )
    return drawn
