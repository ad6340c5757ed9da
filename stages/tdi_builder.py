"""TDI builder stage: X2, Y2, Z2 of the data and of the 24 TTL regressors, segment by segment.

Input ``ttl/<run>/telemetry/<i>`` (replayer); output ``ttl/<run>/tdi/<i>``: arrays ``data``
(3, n) and ``regressors`` (3, 24, n), channels X2, Y2, Z2, the header's t0 and fs those of
the telemetry segment, and the segment's telemetry itself (``eta``, ``dws_phi``,
``dws_eta``, ``ltt``, (6, n) each: the live fitter builds the columns of any model's effects
from the DWS readouts, and keeps them for its window); meta ``names`` (the 24 coefficient names), ``ltt_mean`` (6,), and,
passed on from the telemetry, ``segments_total``, ``segment_duration``, ``source``,
``truth``, ``dws_asd``; ``continuous`` is false when the stream restarted at this segment
(its first samples are then NaN: the nested delays reach before the data, as on the very
first segment).

The delays and interpolation reach back about 70 s: :class:`ttlcore.tdi.data.TDIStream`
keeps that tail of telemetry between segments, so the output for a day fed in segments
equals the batch TDI of the whole day, and segments stay independent messages.  Segments
are therefore processed in index order (:class:`streamer.runtime.pipeline_stage.OrderedStage`); a segment whose t0 does
not follow the previous one (files with a gap) restarts the stream, and so does a stage
restarted mid-run, from the earliest segment the replayer's cache still holds (its output
is a duplicate its consumers ignore, and it re-creates the tail the next segments need).
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

from streamer.bus.codec import Expect, encode
from streamer.bus.messages import TELEMETRY_ARRAYS, telemetry_of
from streamer.recording.recorded_inputs import recorded_copies
from streamer.recording.recording_reader import RecordedSegment, RecordingError
from streamer.runtime.pipeline_stage import OrderedStage
from streamer.runtime.stage import Output, stage_main
from streamer.runtime.stage_options import OrderedOptions, option, positive_int
from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.io.telemetry import Telemetry
from ttlcore.tdi.combinations import XYZ
from ttlcore.tdi.data import TDIStream, history_samples

#: Arrays kept in the recording: the regressors (72 channels, two thirds of a day's MCAP)
#: are rebuilt from the replayer's recorded telemetry when needed (:func:`rebuilt_copy`),
#: and the forwarded telemetry is the replayer's (recorded there).
RECORDED = ("data",)
#: Units of the output arrays.
UNITS = {
    "data": "fractional frequency",
    "regressors": "fractional frequency per m/rad",
    "eta": "fractional frequency",
    "dws_phi": "rad/s",
    "dws_eta": "rad/s",
    "ltt": "s",
}
#: Axis labelled by the channels (X2, Y2, Z2) per array: none for the forwarded telemetry (links, MOSAs).
CHANNEL_AXIS = {"data": 0, "regressors": 0, **dict.fromkeys(TELEMETRY_ARRAYS)}


@dataclass(frozen=True)
class TDIBuilderOptions(OrderedOptions):
    """The tdi_builder's options (their command-line help in :func:`add_options`)."""

    #: Lagrange interpolation order of the TDI delays (odd; None: TDIStream's default).
    order: int | None = option(None, positive_int)


class TDIBuilder(OrderedStage[TDIBuilderOptions]):
    """Builds TDI (X2, Y2, Z2) of the data and of the 24 regressors from telemetry segments."""

    name = "tdi_builder"
    options_type = TDIBuilderOptions
    inputs = ("telemetry",)
    follow = ("replayer",)
    reorders = ("telemetry",)

    def __init__(self, config):
        super().__init__(config)
        order = self.options.order
        self.stream = TDIStream() if order is None else TDIStream(order=order)

    def expect(self, topic, index):
        # NaN stretches in eta / DWS are data with a gap (the replayer flags them in meta.gaps);
        # ltt must be finite and eta finite somewhere (streamer.runtime.plan.Validator)
        return Expect(
            run=self.run_id, index=index, arrays={k: ("<f8", (6, None)) for k in TELEMETRY_ARRAYS}, allow_nonfinite=True
        )

    def handle(self, header, arrays):
        # validated here, before buffering: a segment that raises is reported as failed and
        # not marked processed, so a good copy of it is still accepted
        self.enqueue(header, telemetry_of(header, arrays))
        return ()

    def restart(self) -> None:
        self.stream.reset()

    def process(self, header, tm: Telemetry) -> Output:
        """TDI of one telemetry segment (the stream's tail makes it continuous)."""
        next_t0, tail = self.stream.next_t0, self.stream._tail  # both set by the stream's last push
        continuous = next_t0 is not None
        if next_t0 is not None and tail is not None and (abs(tm.t0 - next_t0) > 0.5 / tm.fs or tm.fs != tail.fs):
            self.event(
                "discontinuity",
                index=header.index,
                message=f"t0={tm.t0} s does not follow the previous segment (expected {next_t0} s); TDI restarts here",
            )
            self.stream.reset()
            continuous = False
        td = self.stream.push(tm)
        meta = {
            k: header.meta.get(k) for k in ("segments_total", "segment_duration", "source", "truth", "dws_asd", "gaps")
        }
        meta.update(
            names=list(td.names),
            ltt_mean=[float(x) for x in td.ltt_mean],
            continuous=continuous,
            tdi_order=self.stream.order,
        )
        if tuple(td.names) != tuple(COEFFICIENT_NAMES) or tuple(td.channels) != XYZ:
            raise ValueError(
                f"TDIStream gave channels {td.channels} and names {td.names[:2]}...; "
                f"expected {XYZ} and the 24 coefficients"
            )
        return Output(
            self.output_topic,
            {"data": td.data, "regressors": td.regressors, **{k: getattr(tm, k) for k in TELEMETRY_ARRAYS}},
            fields={"channels": list(td.channels), "channel_axis": CHANNEL_AXIS, "units": UNITS, "meta": meta},
            allow_nonfinite=True,
            record_arrays=RECORDED,
        )


def rebuilt_copy(run_dir: Path, seg: RecordedSegment) -> tuple[bytes, bytes]:
    """The published ``(payload, attachment)`` of tdi segment ``seg``, recorded with its
    ``data`` only (:data:`RECORDED`), rebuilt from the replayer's recorded telemetry.

    The TDI stream is pushed again, as the TDI builder pushed it: the segment alone when its
    stream restarted there (``meta.continuous`` false), else from the recorded segments
    before it that reach back over the stream's tail (:func:`ttlcore.tdi.data.history_samples`,
    back to a break in time).  The copy is bit-identical or refused: its payload checksum
    must be the published one (``meta.recorded.published_checksum``).

    Raises
    ------
    RecordingError
        If the telemetry is not in the replayer's recordings, or the rebuilt payload is not
        the published one (the message names the segment and why).
    """
    header, data = seg.header, seg.data or {}
    meta = dict(header.meta or {})
    recorded = meta.pop("recorded", None)
    index, fs = header.index, header.fs
    if not isinstance(recorded, dict) or not isinstance(recorded.get("published_checksum"), str):
        raise RecordingError(f"tdi segment {index}: not a partly recorded copy (no meta.recorded)")
    # the segments before it that the stream's tail can reach (twice the tail, to be safe)
    before = 0
    if meta.get("continuous"):
        reach_s = history_samples(fs, 2 * max(8.6, *(meta.get("ltt_mean") or [0.0]))) / fs
        before = math.ceil(reach_s / float(meta.get("segment_duration") or reach_s)) + 1
    copies = recorded_copies(run_dir, "replayer", "telemetry", range(index - before, index + 1))
    if index not in copies:
        raise RecordingError(f"tdi segment {index}: its telemetry is not in the replayer's recordings in {run_dir}")
    telemetry = {i: telemetry_of(m.header, m.arrays) for i, m in copies.items()}
    start = index
    while (
        start - 1 in telemetry
        and abs(telemetry[start - 1].t0 + telemetry[start - 1].duration - telemetry[start].t0) < 0.5 / fs
    ):
        start -= 1
    order = meta.get("tdi_order")
    stream = TDIStream() if order is None else TDIStream(order=int(order))
    for i in range(start, index + 1):
        td = stream.push(telemetry[i])
    tm = telemetry[index]
    arrays = {"data": td.data, "regressors": td.regressors, **{k: getattr(tm, k) for k in TELEMETRY_ARRAYS}}
    fields = {k: data[k] for k in ("run", "index", "t0", "fs", "channels", "producer") if k in data}
    fields.update(units=UNITS, channel_axis=CHANNEL_AXIS, meta=meta)
    published, names = recorded["published_checksum"], recorded.get("published_arrays", list(arrays))
    if not set(names) <= arrays.keys():
        raise RecordingError(f"tdi segment {index}: published arrays {names}, the TDI builder's are {list(arrays)}")
    payload, attachment = encode(
        {k: arrays[k] for k in names},
        fields,
        checksum=published.partition(":")[0],
        allow_nonfinite=True,
    )
    checksum = json.loads(attachment)["checksum"]
    if checksum != published:
        raise RecordingError(
            f"tdi segment {index}: rebuilt from the replayer's telemetry (segments {start}..{index}), its "
            f"checksum {checksum} is not the published {published}"
        )
    return payload, attachment


def add_options(p) -> None:
    p.add_argument("--order", type=int, help="Lagrange interpolation order of the TDI delays (odd, default 31)")
    p.add_argument("--settle", type=float, help="seconds to collect cached history before choosing the first segment")
    p.add_argument("--gap-timeout", type=float, help="seconds to wait for a missing segment before skipping it")


def options(args) -> dict:
    return {"order": args.order, "settle": args.settle, "gap_timeout": args.gap_timeout}


def main(argv=None) -> int:
    return stage_main(TDIBuilder, argv, add_options, options)


if __name__ == "__main__":
    sys.exit(main())
