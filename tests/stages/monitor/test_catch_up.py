"""An input segment announced by its producer that does not come (streamer.runtime.catch_up): the
cache, then the producer's recordings, then given up; never waited for forever.  No bus: the
stages are driven by hand, their recordings are real MCAP files read back."""

from __future__ import annotations

import json
import time
from types import SimpleNamespace

import numpy as np
import pytest

from stages.monitor.monitor import Monitor
from streamer.bus.codec import encode
from streamer.recording.recorder import Recorder, read_recording
from streamer.runtime.catch_up import ANNOUNCED_FETCH_AFTER, CACHE_ANSWER_WITHIN, CatchUp
from streamer.runtime.rangeset import RangeSet
from streamer.runtime.stage import StageConfig

RUN = "u"


def sample(msg: dict):
    return SimpleNamespace(payload=json.dumps(msg).encode(), key_expr=f"ttl/{RUN}/control/progress/{msg['stage']}")


@pytest.mark.parametrize("t0", [100.0, 1015.0100000000112])
def test_the_rule_cache_then_recordings_once_each(t0):
    """``t0`` 1015.01...: a monotonic clock where ``(t0 + 10) - t0`` rounds to less than 10 s
    (the rule compared differences, and a fresh CI machine's uptime made the catch-up test
    flaky: nothing was asked at the deadline)."""
    assert (t0 + ANNOUNCED_FETCH_AFTER) - t0 < ANNOUNCED_FETCH_AFTER or t0 == 100.0
    c = CatchUp()
    assert c.step({"fit": {3, 4, 5, 6}}, t0) == ([], {})  # just announced: on its way
    ask, read = c.step({"fit": {3, 4, 5, 6}}, t0 + ANNOUNCED_FETCH_AFTER)
    assert ask == [("fit", 3), ("fit", 4), ("fit", 5), ("fit", 6)] and read == {}
    c.asked("fit", 3, True, t0 + ANNOUNCED_FETCH_AFTER)
    c.asked("fit", 4, True, t0 + ANNOUNCED_FETCH_AFTER)
    c.asked("fit", 5, False, t0 + ANNOUNCED_FETCH_AFTER)  # the re-fetch budget said no
    c.asked("fit", 6, True, t0 + ANNOUNCED_FETCH_AFTER)
    c.answered("fit", 3, 0)  # no cache holds it
    c.answered("fit", 4, 1)  # one came: it is on its way in
    # 3 (no copy) and 5 (not asked) go to the recordings at once; 4 and 6 wait for their copy
    assert c.step({"fit": {3, 4, 5, 6}}, t0 + ANNOUNCED_FETCH_AFTER + 0.1) == ([], {"fit": {3, 5}})
    assert c.step({"fit": {3, 4, 5, 6}}, t0 + ANNOUNCED_FETCH_AFTER + 1) == ([], {})  # once
    # the cache's copy of 4 came; 6's query never ended: the recordings, CACHE_ANSWER_WITHIN after
    assert c.step({"fit": {3, 5, 6}}, t0 + ANNOUNCED_FETCH_AFTER + CACHE_ANSWER_WITHIN) == ([], {"fit": {6}})
    assert c.waiting() == 0
    # a segment no longer missing is forgotten; missing again later, it starts afresh
    assert c.step({}, t0 + 200) == ([], {})
    assert c.step({"fit": {3}}, t0 + 300) == ([], {})
    assert c.step({"fit": {3}}, t0 + 300 + ANNOUNCED_FETCH_AFTER) == ([("fit", 3)], {})


def test_a_segment_that_came_and_failed_here_is_given_up_once_published_and_no_good_copy_follows():
    c = CatchUp()
    t0 = 100.0
    c.failed_here("tdi", 2, "ValueError: bad", t0)
    c.failed_here("tdi", 3, "ValueError: bad", t0)
    c.failed_here("tdi", 9, "ValueError: forged", t0)  # ahead of the producer: a forged copy
    c.failed_here("fit", 4, "ValueError: bad", t0)
    published = {"tdi": RangeSet(range(4))}
    assert c.unusable(published, {}, t0 + ANNOUNCED_FETCH_AFTER - 1) == []  # a good copy may follow
    c.failed_here("tdi", 2, "ValueError: worse", t0 + 5)  # failed again: the clock runs from the first
    got = c.unusable(published, {"tdi": RangeSet([3])}, t0 + ANNOUNCED_FETCH_AFTER)  # a good 3 came
    # 2 given up with its last reason; "fit" has no producer known here: on time alone; 9 waits
    assert got == [("fit", 4, "ValueError: bad"), ("tdi", 2, "ValueError: worse")]
    assert c.unusable(published, {}, t0 + 100) == []  # each once; 9 not published yet
    assert c.unusable({"tdi": RangeSet(range(10))}, {}, t0 + 100) == [("tdi", 9, "ValueError: forged")]


def _write_fits(path, indices, stage: str = "fitter", bad=()) -> None:
    """A fitter process's recording with the fits of ``indices`` (as it records them; those
    in ``bad`` with NaN coefficients, which no stage accepts)."""
    rec = Recorder(path, metadata={"run": RUN, "stage": stage, "class": "Fitter", "config": "{}"})
    for i in indices:
        payload, attachment = encode(
            {
                "coefficients": np.full(24, np.nan if i in bad else 1e-3 * (i + 1)),
                "sigma": np.full(24, 1e-5),
                "covariance": np.eye(24) * 1e-10,
            },
            {
                "run": RUN,
                "index": i,
                "t0": 600.0 * i,
                "fs": 4.0,
                "producer": "fitter",
                "meta": {"t_start": 600.0 * (i - 2), "t_stop": 600.0 * (i + 1), "model": ["linear-ttl"]},
            },
            allow_nonfinite=i in bad,
        )
        rec.write_segment("fit", json.loads(attachment), payload)
    rec.close()


def test_a_restarted_monitor_takes_the_fits_no_cache_holds_from_the_fitters_recordings(tmp_path):
    """Issue 33, the chaos run with model changes that never ended.  The fitter was restarted
    at segment 20: its earlier process published fits 0-18 (recorded in ``fitter.1.mcap``),
    the live one 20-21 (fit 19 is in no recording: say a fitter on another host).  The
    monitor, restarted after segment 14, drew TDI 15-21 and fits 20-21 from the caches; no
    cache holds fits 15-19 (a publisher's cache holds its own process's segments), and the
    monitor waited for them as long as the fitter lived (its earlier rule thought the last 8
    fits cached).  Now: asked of the fitter's cache after ANNOUNCED_FETCH_AFTER, then read
    from its recordings and drawn as if they had come; fit 19 is given up with an
    ``input-lost`` warning and segment 19 fails (``ttl run`` exits 1), so the monitor ends;
    so does 18, whose recorded copy the checks refuse."""
    run_dir = tmp_path / RUN
    run_dir.mkdir()
    _write_fits(run_dir / "fitter.1.mcap", range(19), bad={18})  # 18 damaged on disk
    _write_fits(run_dir / "fitter.mcap", [20, 21])
    _write_fits(run_dir / "subtractor.mcap", range(22), stage="subtractor")  # another stage's file: not read

    m = Monitor(StageConfig(run=RUN, recordings=tmp_path, stage="monitor"))
    m.recorder = Recorder(run_dir / "monitor.mcap", metadata={"run": RUN, "stage": "monitor", "class": "Monitor"})
    m.rrd = run_dir / "monitor.rrd"
    m.open_recording()
    m.board.feed(sample({"stage": "fitter", "done": [[0, 21]], "fits_ranges": [[0, 21]]}))
    m.board.feed(sample({"stage": "monitor", "done": [[0, 14]]}))  # the earlier monitor process
    m.settling.drawn["tdi"] |= set(range(15, 22))
    m.settling.drawn["fit"] |= {20, 21}
    m.ingest.done["fit"] = RangeSet([20, 21])
    asked: list = []
    m.fetch = lambda topic, index: asked.append((topic, index)) or True  # the caches: none holds them
    published: list = []
    m.publish = lambda out, source=None: published.append(out.index) or ""  # monitor/<i>

    t0 = time.monotonic()
    assert m.fetch_announced(t0) == []  # just announced: on its way
    want = [("fit", i) for i in range(15, 20)]
    assert m.fetch_announced(t0 + ANNOUNCED_FETCH_AFTER) == want and asked == want
    for _, i in want:
        m.fetched("fit", i, 0)  # each cache query over, no copy
    m.fetch_announced(t0 + ANNOUNCED_FETCH_AFTER + 0.1)
    assert m.settling.drawn["fit"] == {20, 21}  # in the hold-back, as any copy from the bus
    time.sleep(m.config.hold + 0.1)
    m._release_held()

    assert m.settling.drawn["fit"] == {15, 16, 17, 20, 21}  # read back and drawn
    m._settle()
    # settled: 15-17 and 20-21 done (their monitor message out), 18 and 19 failed (ttl run exits 1)
    assert sorted(published) == [15, 16, 17, 20, 21]
    assert set(m.done) == {15, 16, 17, 20, 21} and set(m.failed) == {18, 19}
    assert m.fetch_announced(t0 + 10 * CACHE_ANSWER_WITHIN) == []  # nothing asked twice
    m.recorder.close()

    rec = read_recording(run_dir / "monitor.mcap")
    events = [e for e in rec.json("events") if e.get("kind") == "recovered"]
    assert len(events) == 1 and events[0]["details"] == {"topic": "fit", "indices": [[15, 18]]}
    lost = {w["index"]: w["message"] for w in rec.json("warnings") if w.get("kind") == "input-lost"}
    assert sorted(lost) == [18, 19], lost
    assert f"ttl/{RUN}/fit/19 given up" in lost[19] and "no recording" in lost[19]
    assert "recorded copy was refused" in lost[18]
    assert [(e["kind"], e["index"]) for e in rec.json("errors") if e["kind"] == "rejected"] == [("rejected", 18)]
    # each read-back fit is recorded as an input like one that came on the bus
    assert sorted(s.header.index for s in rec.segments("fit")) == [15, 16, 17]


def test_an_ordered_stage_skips_a_lost_input_in_its_turn(tmp_path):
    """A TDI builder whose telemetry segment 2 is in no cache and no recording (the replayer
    said it published 0-3; 0, 1 and 3 came): 2 is skipped when its turn comes (failed,
    reported), not waited for, and the state carried between segments sees the skip in
    order."""
    from stages.tdi_builder import TDIBuilder

    s = TDIBuilder(StageConfig(run=RUN, recordings=tmp_path, stage="tdi_builder"))
    handled: list = []
    s.process = lambda header, item: handled.append(header.index)  # no TDI computed here
    s.board.feed(sample({"stage": "replayer", "done": [[0, 3]]}))
    for i in (0, 1, 3):
        s.queue.add(i, (SimpleNamespace(index=i, key=None, meta={}), None))
        s.ingest.done.setdefault("telemetry", RangeSet()).add(i)
    s.drain(limit=10)
    assert handled == [0, 1] and s.queue.next == 2  # 3 waits for 2
    asked: list = []
    s.fetch = lambda topic, index: asked.append((topic, index)) or True
    t0 = time.monotonic()
    assert s.fetch_announced(t0) == []
    assert s.fetch_announced(t0 + ANNOUNCED_FETCH_AFTER) == [("telemetry", 2)]
    s.fetched("telemetry", 2, 0)
    s.fetch_announced(t0 + ANNOUNCED_FETCH_AFTER + 0.1)  # no replayer recording: lost
    s.drain(limit=10)
    assert handled == [0, 1, 3] and set(s.failed) == {2} and set(s.done) == {0, 1, 3}


def test_an_ordered_stage_whose_every_input_failed_upstream_settles_them():
    """A fitter to which nothing ever comes, because the tdi_builder gave up segments 0-2 (its
    handle failed on each): its queue starts on those losses and fails 0-2 in order, instead
    of waiting for a first segment until the run's timeout.  A segment still on its way (3,
    done upstream) is not skipped for it."""
    from stages.tdi_builder import TDIBuilder

    s = TDIBuilder(StageConfig(run=RUN, recordings="/nonexistent", stage="tdi_builder"))
    s.process = lambda header, item: None
    s.board.feed(sample({"stage": "replayer", "failed": [[0, 2]], "done": [[3, 3]]}))
    s.drain(limit=10)
    assert set(s.failed) == {0, 1, 2} and not s.done and s.queue.next == 3  # 3 is waited for


def test_a_restarted_subtractor_takes_fits_no_cache_holds_from_the_fitters_recordings(tmp_path):
    """The subtractor waits for the fit of each segment by its index; fits 2-3 of a fitter
    process killed since are in no cache.  Before, segments 2-3 got fit 1 after
    ``fit_timeout`` (a ``missing-fit``: residuals unlike the clean run's); now the fits are
    read from ``fitter.1.mcap`` and applied."""
    from stages.subtractor import Subtractor

    run_dir = tmp_path / RUN
    run_dir.mkdir()
    _write_fits(run_dir / "fitter.1.mcap", range(4))
    s = Subtractor(StageConfig(run=RUN, recordings=tmp_path, stage="subtractor", hold=0.0))
    s.recorder = Recorder(run_dir / "subtractor.mcap", metadata={"run": RUN, "stage": "subtractor", "class": "S"})
    s.board.feed(sample({"stage": "fitter", "done": [[0, 3]], "fits_ranges": [[0, 3]]}))
    s.board.feed(sample({"stage": "subtractor", "done": [[0, 1]]}))  # the earlier process
    s.fetch = lambda topic, index: True
    t0 = time.monotonic()
    assert s.fetch_announced(t0) == []
    assert s.fetch_announced(t0 + ANNOUNCED_FETCH_AFTER) == [("fit", 2), ("fit", 3)]
    s.fetched("fit", 2, 0)
    s.fetched("fit", 3, 0)
    s.fetch_announced(t0 + ANNOUNCED_FETCH_AFTER + 0.1)
    assert sorted(s.fits) == [2, 3]
    assert s.choose(2) == ("apply", 2) and s.choose(3) == ("apply", 3)
    s.recorder.close()


def test_a_restarted_ordered_stage_starts_where_its_earlier_process_stopped(tmp_path):
    """A fitter killed after segment 3 and restarted after the tdi_builder was restarted too:
    TDI 4-5 (the tdi_builder's earlier process) are in no cache, the caches give 6-9.  The
    queue used to start at 6, the lowest received: 4 and 5 were never handled by any
    process and the run could not end.  It starts at 4, the first segment the earlier
    process did not handle, and takes 4 and 5 when they come (from the recordings)."""
    from stages.tdi_builder import TDIBuilder

    s = TDIBuilder(StageConfig(run=RUN, recordings=tmp_path, stage="tdi_builder", options={"settle": 0.0}))
    handled: list = []
    s.process = lambda header, item: handled.append(header.index)
    s.board.feed(sample({"stage": "tdi_builder", "done": [[0, 3]]}))  # the earlier process
    for i in (6, 7, 8, 9):
        s.queue.add(i, (SimpleNamespace(index=i, key=None, meta={}), None))
    s.drain(limit=10)
    assert handled == [] and s.queue.next == 4
    for i in (5, 4):
        s.queue.add(i, (SimpleNamespace(index=i, key=None, meta={}), None))
    s.drain(limit=10)
    assert handled == [4, 5, 6, 7, 8, 9]
