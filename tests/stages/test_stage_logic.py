"""The stages' bookkeeping without a bus: ranges, ordering, which fit applies, replay sources."""

import json
import time
from types import SimpleNamespace

import numpy as np
import pytest

from stages.replayer import FileSource, Replayer, make_source
from stages.subtractor import Subtractor
from streamer.bus.keys import from_ranges, to_ranges
from streamer.bus.residual_record import SCHEMA as RESIDUAL_SCHEMA
from streamer.bus.residual_record import ResidualMessage
from streamer.runtime.pipeline_stage import InOrder
from streamer.runtime.progress import Progress
from streamer.runtime.rangeset import RangeSet
from streamer.runtime.stage import StageConfig
from ttlcore.cli.simulation import simulation_config
from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.errors import ConfigError, TelemetryError
from ttlcore.io.telemetry import Telemetry, write_telemetry
from ttlcore.io.truth import truth_path
from ttlcore.sim.simulator import Simulator
from ttlcore.tdi.data import TDIData


def sample(msg: dict):
    return SimpleNamespace(payload=json.dumps(msg).encode(), key_expr=f"ttl/u/control/progress/{msg['stage']}")


def test_ranges_round_trip():
    assert to_ranges([5, 0, 1, 2, 2]) == [[0, 2], [5, 5]]
    assert from_ranges([[0, 2], [5, 5]]) == {0, 1, 2, 5}
    assert to_ranges([]) == [] and from_ranges(None) == set() and from_ranges([["x"]]) == set()
    p = Progress("fitter")
    p.update({"done": [[0, 3]], "failed": [[5, 5]], "segments_total": 7, "fits_ranges": [[1, 3]]})
    p.update({"done": [[4, 4], [6, 6]], "pid": 2})  # a restarted process: union of both
    assert p.handled == set(range(7)) and p.covers() and p.highest == 6 and p.extra["fits"] == {1, 2, 3}


def test_in_order_settles_reorders_and_skips():
    q = InOrder(settle=0.2, gap_timeout=0.3)
    q.add(5, "e")
    q.add(3, "c")
    assert list(q.ready()) == []  # still collecting history
    time.sleep(0.25)
    q.add(4, "d")
    assert list(q.ready()) == [(3, "c"), (4, "d"), (5, "e")]
    assert not q.add(2, "late")  # behind the stream: stale
    q.add(7, "g")
    assert list(q.ready()) == []  # 6 missing, 7 waits
    assert list(q.ready(skip=lambda i: i == 6)) == [(6, None), (7, "g")]
    q.add(9, "i")
    assert list(q.ready()) == []
    time.sleep(0.35)
    assert list(q.ready()) == [(8, None), (9, "i")]  # gap timeout
    q2 = InOrder(settle=10)
    q2.add(0, "a")
    assert list(q2.ready()) == [(0, "a")]  # index 0 needs no settling
    # conflicting copies: a buffered or future index is withdrawn and skipped in its turn
    q2.add(2, "c")
    assert q2.withdraw(2, "conflict") and q2.withdraw(3, "conflict") and not q2.withdraw(0, "conflict")
    q2.add(1, "b")
    q2.add(4, "e")
    out = []
    for i, item in q2.ready():
        out.append((i, item, q2.skipped_reason if item is None else ""))
    assert out == [(1, "b", ""), (2, None, "conflict"), (3, None, "conflict"), (4, "e", "")]
    q3 = InOrder(settle=0)
    q3.withdraw(0, "conflict")
    q3.add(1, "b")
    assert list(q3.ready()) == [(0, None), (1, "b")]  # a withdrawn first index is still accounted for
    q4 = InOrder(settle=10)
    q4.withdraw(1, "failed here")  # nothing buffered, every index withdrawn: the queue still starts
    assert list(q4.ready()) == []  # 0 may still come: settling
    q4.withdraw(0, "failed here")
    assert [(i, q4.skipped_reason) for i, _ in q4.ready()] == [(0, "failed here"), (1, "failed here")]


def test_subtractor_applies_the_latest_fit_covering_each_segment(tmp_path):
    s = Subtractor(StageConfig(run="u", recordings=tmp_path))
    fit = {"coefficients": {}, "t_start": 0.0, "t_stop": 1.0}
    assert s.choose(0) == ("wait", None)  # the fitter has not passed segment 0
    s.board.feed(sample({"stage": "fitter", "done": [[0, 1]], "fits_ranges": []}))
    assert s.choose(0) == ("apply", None)  # passed, no fit yet: published unchanged
    s.board.feed(sample({"stage": "fitter", "done": [[0, 3]], "fits_ranges": [[2, 3]]}))
    assert s.choose(2) == ("wait", None)  # fit 2 announced, not received yet
    s.fits[2] = fit
    assert s.choose(2) == ("apply", 2)
    assert s.choose(3) == ("wait", None)
    s.fits[3] = fit
    assert s.choose(3) == ("apply", 3)
    s.board.feed(sample({"stage": "fitter", "done": [[0, 5]], "fits_ranges": [[2, 3]]}))
    assert s.choose(5) == ("apply", 3)  # no refit at 4, 5: the latest earlier fit
    assert s.choose(6) == ("wait", None)
    s.fits[7] = fit
    assert s.choose(6) == ("wait", None)  # a later fit is no proof that the fitter passed 6 (issue 33)
    s.board.feed(sample({"stage": "fitter", "done": [[0, 6]], "fits_ranges": [[2, 3]]}))
    assert s.choose(6) == ("apply", 3)  # the fitter's progress is


def test_a_fit_forged_ahead_releases_no_segment_before_it(tmp_path):
    """Issue 33: a fit for segment 9 while the fitter is at 1 released segments 2-8 with fit
    1 (residual 2 with fit 0 and so on), silently.  Each segment waits for the fitter's
    progress on its own index; one the fitter handled without a fit (a no-fit, a gap) gets
    the latest earlier fit, as before."""
    s = Subtractor(StageConfig(run="u", recordings=tmp_path))
    fit = {"coefficients": {}, "t_start": 0.0, "t_stop": 1.0}
    s.fits[0] = s.fits[1] = fit
    s.board.feed(sample({"stage": "fitter", "done": [[0, 1]], "fits_ranges": [[0, 1]]}))
    s.fits[9] = fit  # forged with the fitter's key
    assert [s.choose(i) for i in range(2, 10)] == [("wait", None)] * 7 + [("wait", None)]
    # the fitter reaches 4: segment 2 fitted, 3 a no-fit, 4 failed (a gap)
    s.fits[2] = fit
    s.board.feed(sample({"stage": "fitter", "done": [[0, 3]], "failed": [[4, 4]], "fits_ranges": [[0, 2]]}))
    assert [s.choose(i) for i in range(2, 6)] == [("apply", 2), ("apply", 2), ("apply", 2), ("wait", None)]
    # a fit forged for segment 3, which the fitter handled without one: never applied, reported
    reports = []
    s.report_error = lambda kind, message, **k: reports.append((kind, k.get("index")))
    s.fits[3] = fit
    assert s.choose(3) == ("apply", 2) and s.choose(4) == ("apply", 2) and reports == [("forged", 3)]


def test_a_waiting_subtractor_asks_the_fitters_progress_again_when_it_hears_none(tmp_path):
    """A late joiner's history query can be lost under load; a fitter that has finished
    publishes no more progress, and a fit of a later segment is no proof any more: after
    FIT_FETCH_AFTER seconds without the fitter's progress, its cache is asked again, at most
    that often."""
    from stages.subtractor import FIT_FETCH_AFTER

    s = Subtractor(StageConfig(run="u", recordings=tmp_path))
    asked = []
    s.refresh_progress = asked.append
    assert s.choose(0) == ("wait", None) and asked == []  # just started
    s._started -= FIT_FETCH_AFTER + 1
    assert s.choose(0) == ("wait", None) and asked == ["fitter"]
    assert s.choose(1) == ("wait", None) and asked == ["fitter"]  # not again at once
    s._board_asked -= FIT_FETCH_AFTER + 1
    s.choose(0)
    assert asked == ["fitter", "fitter"]
    s.board.feed(sample({"stage": "fitter", "done": [[0, 0]], "fits_ranges": []}))  # heard now
    s._board_asked -= FIT_FETCH_AFTER + 1
    assert s.choose(1) == ("wait", None) and asked == ["fitter", "fitter"]


def test_fit_for_by_index():
    from stages.subtractor import fit_for

    upto = lambda n: set(range(n + 1))  # noqa: E731 - the fitter handled 0..n
    assert fit_for(5, upto(1), {0, 1}, {0, 1, 9}) == ("wait", None)  # fits ahead prove nothing
    assert fit_for(5, upto(5), set(), set()) == ("apply", None)
    assert fit_for(5, upto(9), {0, 3}, {0, 3, 9}) == ("apply", 3)  # no fit at 4, 5: the latest earlier
    assert fit_for(5, upto(5), {0, 3, 5}, {0, 3}) == ("await", 5)  # announced, on its way
    assert fit_for(5, upto(5), {0, 3, 5}, {0, 3, 5}) == ("apply", 5)
    # a fit received for a segment the fitter handled without one (a no-fit): not the fitter's
    assert fit_for(5, upto(5), {0, 3}, {0, 3, 4}) == ("apply", 3)


def test_subtractor_asks_the_fitter_cache_for_an_announced_fit_that_does_not_come(tmp_path):
    """A late joiner's history query can be lost on a loaded machine: fits 0-4, announced by
    the fitter's progress, never came, and segments 0-4 got no fit after 30 s each.  After
    FIT_FETCH_AFTER seconds the fit is asked of the fitter's cache, once."""
    from stages.subtractor import FIT_FETCH_AFTER

    s = Subtractor(StageConfig(run="u", recordings=tmp_path))
    asked = []
    s.fetch = lambda topic, index: asked.append((topic, index))
    s.board.feed(sample({"stage": "fitter", "done": [[0, 3]], "fits_ranges": [[0, 3]]}))
    assert s.choose(2) == ("wait", None) and asked == []  # just announced: on its way
    s._waiting_since[2] -= FIT_FETCH_AFTER + 1.0
    assert s.choose(2) == ("wait", None) and asked == [("fit", 2)]
    assert s.choose(2) == ("wait", None) and asked == [("fit", 2)]  # asked once
    s.fits[2] = {"coefficients": {}, "t_start": 0.0, "t_stop": 1.0}
    assert s.choose(2) == ("apply", 2)


def test_an_announced_input_that_never_comes_is_asked_of_the_producers_cache(tmp_path):
    """CI, 2026-11-28: a subtractor started half-way through the replay never received tdi
    segments 0-5 (its history query was lost under load) and the run timed out waiting for
    them.  A segment the tdi_builder's progress says it published, not received here after
    ANNOUNCED_FETCH_AFTER seconds, is asked of its cache, once; received, handled, or below
    the validator's floor, it is not."""
    from streamer.runtime.pipeline_stage import ANNOUNCED_FETCH_AFTER

    s = Subtractor(StageConfig(run="u", recordings=tmp_path))
    asked = []
    s.fetch = lambda topic, index: asked.append((topic, index)) or True
    s.board.feed(sample({"stage": "tdi_builder", "done": [[0, 7]]}))
    s.ingest.done["tdi"] = RangeSet([6])  # received and used
    s.validator.digests[("tdi", 7)] = ()  # received, held
    s.mark_done(1)
    t0 = time.monotonic()
    assert s.fetch_announced(t0) == [] and asked == []  # just announced: on its way
    assert s.fetch_announced(t0 + ANNOUNCED_FETCH_AFTER / 2) == []
    assert s.fetch_announced(t0 + ANNOUNCED_FETCH_AFTER) == [("tdi", i) for i in (0, 2, 3, 4, 5)]
    assert asked == [("tdi", i) for i in (0, 2, 3, 4, 5)]
    assert s.fetch_announced(t0 + 3 * ANNOUNCED_FETCH_AFTER) == []  # once
    s.board.feed(sample({"stage": "tdi_builder", "done": [[0, 8]]}))  # a new one: its own clock
    assert s.fetch_announced(t0 + 3 * ANNOUNCED_FETCH_AFTER) == []
    assert s.fetch_announced(t0 + 4 * ANNOUNCED_FETCH_AFTER) == [("tdi", 8)]


def test_subtractor_keeps_only_the_fits_segments_to_come_can_get(tmp_path):
    """Memory flat in a long run: fits older than the latest one before the segments still to
    come (less the message window, for late arrivals) are forgotten; choices are unchanged."""
    s = Subtractor(StageConfig(run="u", recordings=tmp_path))
    fit = {"coefficients": {}, "t_start": 0.0, "t_stop": 1.0}
    window = s.validator.window
    for i in range(0, 1000, 10):  # a fit every 10th segment
        s.fits[i] = fit
    s.board.feed(sample({"stage": "fitter", "done": [[0, 999]], "fits_ranges": [[i, i] for i in range(0, 1000, 10)]}))
    before = {i: s.choose(i) for i in range(600, 1000)}
    for i in range(600):
        if i != 580:
            s.mark_done(i)
    s.tdi[580] = None  # a segment still waiting holds its fit (and the window before it)
    s._prune_fits()
    assert min(s.fits) == 510
    del s.tdi[580]
    s.mark_done(580)
    s._prune_fits()
    assert min(s.fits) == 530 and len(s.fits) == 47  # the latest fit at or before 600 - 64, and the later ones
    assert {i: s.choose(i) for i in range(600 - window, 1000)} == {
        **{i: ("apply", i - i % 10) for i in range(600 - window, 600)},
        **before,
    }


def _file(path, t0, n, seed=0):
    rng = np.random.default_rng(seed)
    tm = Telemetry(
        t0=t0,
        fs=4.0,
        eta=rng.standard_normal((6, n)),
        dws_phi=rng.standard_normal((6, n)),
        dws_eta=rng.standard_normal((6, n)),
        ltt=np.full((6, n), 8.3),
        config={"noises": {"dws": False}},
    )
    write_telemetry(path, tm)
    return tm


def test_file_source_orders_files_and_cuts_segments(tmp_path):
    a = _file(tmp_path / "a.h5", 0.0, 100)
    b = _file(tmp_path / "b.h5", 25.0, 60, seed=1)
    truth_path(tmp_path / "b.h5").write_bytes(b"")  # a truth file beside b
    src = FileSource([tmp_path / "b.h5", tmp_path / "a.h5"], segment_duration=10.0)
    assert src.segments_total == 3 + 2  # 100 = 40 + 40 + 20 samples, 60 = 40 + 20
    tm, meta = src.segment(2)
    np.testing.assert_array_equal(tm.eta, a.eta[:, 80:])
    assert tm.t0 == 20.0 and meta["source"].endswith("a.h5") and meta["truth"] is None and meta["dws_asd"] == 0.0
    tm, meta = src.segment(3)
    np.testing.assert_array_equal(tm.eta, b.eta[:, :40])
    assert tm.t0 == 25.0 and meta["truth"].endswith("b.truth.h5")
    with pytest.raises(TelemetryError, match="overlapping"):
        _file(tmp_path / "c.h5", 20.0, 10)
        FileSource([tmp_path / "a.h5", tmp_path / "c.h5"], 10.0)
    with pytest.raises(TelemetryError, match="missing.h5"):
        FileSource([tmp_path / "missing.h5"], 10.0)


def test_source_options_name_the_problem():
    with pytest.raises(ConfigError, match="--bogus"):
        simulation_config("--duration 1h --bogus 3")
    with pytest.raises(ConfigError, match="--duration"):
        simulation_config("--duration soon")
    with pytest.raises(ConfigError, match="no telemetry source"):
        make_source({})
    with pytest.raises(ConfigError, match="--segment"):
        make_source({"simulate": "--duration 1h", "segment": "later"})
    cfg = simulation_config("--duration 2h --seed 7 --orbit equal --noises all,-laser")
    assert cfg.duration == 7200 and cfg.seed == 7 and not cfg.noises.laser


def test_replayer_stays_within_window_of_the_slowest_stage(tmp_path):
    _file(tmp_path / "a.h5", 0.0, 400)
    r = Replayer(
        StageConfig(
            run="u",
            recordings=tmp_path,
            options={
                "telemetry": [str(tmp_path / "a.h5")],
                "segment": "10",
                "window": 2,
                "pace_on": ["tdi_builder", "fitter"],
            },
        )
    )
    assert r.segments_total == 10
    assert r.lagging(1) == [] and r.lagging(2) == ["fitter", "tdi_builder"]
    r.board.feed(sample({"stage": "tdi_builder", "done": [[0, 4]]}))
    r.board.feed(sample({"stage": "fitter", "done": [[0, 1]]}))
    assert r.lagging(3) == [] and r.lagging(4) == ["fitter"]
    r.board.feed(sample({"stage": "subtractor", "done": []}))  # a late joiner registers: followed too
    assert r.lagging(2) == ["subtractor"]
    assert r._resume_index() == 0


def test_replayer_paces_at_a_multiple_of_real_time(tmp_path, monkeypatch):
    _file(tmp_path / "a.h5", 0.0, 400)
    r = Replayer(
        StageConfig(
            run="u", recordings=tmp_path, options={"telemetry": [str(tmp_path / "a.h5")], "segment": "10", "pace": 100}
        )
    )  # 10 s segments: one per 0.1 s
    published = []
    monkeypatch.setattr(r, "publish", lambda out, source=None: published.append((time.monotonic(), out)))
    deadline = time.monotonic() + 5
    while len(published) < 5 and time.monotonic() < deadline:
        r.tick()
        time.sleep(0.005)
    times = np.array([t for t, _ in published])
    assert [o.index for _, o in published] == [0, 1, 2, 3, 4] and r.done == {0, 1, 2, 3, 4}
    # segment k is due 0.1 k s after the start: never published ahead of its time (a late
    # one, on a loaded machine, is followed by a shorter interval that catches up)
    assert np.all(times - r._t_start >= 0.1 * np.arange(5)), times - r._t_start
    assert 0.09 < np.mean(np.diff(times)) < 0.2, np.diff(times)
    out = published[1][1]
    assert out.topic == "telemetry" and out.fields["t0"] == 10.0 and out.arrays["eta"].shape == (6, 40)
    assert out.fields["meta"]["segments_total"] == 10 and out.fields["meta"]["segment_duration"] == 10.0


def test_run_options_merge_config_file_and_command_line(tmp_path):
    from pathlib import Path

    from streamer.tools.cli import register, run_options
    from ttlcore.cli.main import build_parser

    (tmp_path / "run.toml").write_text(
        'run_id = "from-file"\nsimulate = "--duration 6h"\nsegment = "30min"\n'
        'window = 3\nskip = ["monitor"]\nfit_window = "6h"\n'
        '[stages.monitor]\nlive = "serve"\n'
    )
    args = build_parser(register).parse_args(
        [
            "run",
            "--config",
            str(tmp_path / "run.toml"),
            "--segment",
            "1h",
            "--band",
            "0.004",
            "0.5",
            "--external",
            "subtractor,fitter",
            "--diagnosis-workers",
            "2",
        ]
    )
    o = run_options(args)
    assert (o.run_id, o.simulate, o.segment, o.window, o.skip) == ("from-file", "--duration 6h", "1h", 3, ("monitor",))
    assert o.external == ("subtractor", "fitter") and o.recordings == Path("recordings")
    fitter = {"window_duration": "6h", "band": [0.004, 0.5], "diagnosis_workers": 2}
    assert o.stage_options == {"monitor": {"live": "serve"}, "fitter": fitter}
    (tmp_path / "bad.json").write_text('{"run_id": "x", "colour": "red"}')
    with pytest.raises(Exception, match="colour"):
        run_options(build_parser(register).parse_args(["run", "--config", str(tmp_path / "bad.json")]))
    with pytest.raises(Exception, match="--run-id"):
        run_options(build_parser(register).parse_args(["run", "--simulate", "--duration 1h"]))


def test_restarted_fitter_recovers_the_model_in_force(tmp_path):
    """A model changed by a control message survives a restart: taken from the earlier
    process's recording, queued from its segment, its model_change still due when no fit
    followed it."""
    from stages.fitter.fitter import Fitter
    from streamer.recording.recorder import Recorder

    run_dir = tmp_path / "u"
    first = Fitter(StageConfig(run="u", recordings=tmp_path))
    first.queue.next = 5  # segments 0..4 handled
    with Recorder(run_dir / "fitter.1.mcap") as rec:
        first.recorder = rec
        for i in range(5):
            rec.write_json("fit/summary", {"index": i})
        first.control("model", b'{"effects": ["linear-ttl", "drift"]}')
    first.recorder = None
    # queued: in force from segment 5, not within segment 4
    assert first.effects == ["linear-ttl"] and len(first.model.planned) == 2
    first.model.apply(5)
    assert len(first.effects) == 2 and first.effects[1].startswith("drift")

    second = Fitter(StageConfig(run="u", recordings=tmp_path, options={"effects": ["linear-ttl"]}))
    second.restore_model()
    assert second.model.planned == first.effects and second.effects == ["linear-ttl"]
    second.model.apply(4)
    assert second.effects == ["linear-ttl"]  # segment 4 is refitted with the model before the change
    second.model.apply(5)
    assert second.effects == first.effects
    assert second.model.change_due == {"before": ["linear-ttl"], "after": first.effects, "from_index": 5}

    # killed again after fit 5 was out: the model holds, its change was reported already
    with Recorder(run_dir / "fitter.2.mcap") as rec:
        rec.write_json("fit/summary", {"index": 5})
    third = Fitter(StageConfig(run="u", recordings=tmp_path))
    third.restore_model()
    third.model.apply(6)
    assert third.effects == first.effects and third.model.change_due is None

    # no model event in the earlier recordings: the configured model stays
    (run_dir / "fitter.1.mcap").unlink()
    (run_dir / "fitter.2.mcap").unlink()
    with Recorder(run_dir / "fitter.1.mcap") as rec:
        rec.write_json("fit/summary", {"index": 0})
    fourth = Fitter(StageConfig(run="u", recordings=tmp_path, options={"effects": ["linear-ttl", "step"]}))
    fourth.restore_model()
    assert fourth.effects == Fitter(StageConfig(run="u", options={"effects": ["linear-ttl", "step"]})).effects


def test_simulation_source_keeps_one_noise_block_and_equals_the_simulator():
    """The replayer reads in order: its noise cache holds one block per stream, so its memory
    does not step up when the second block (~36 h in) comes; the segments are the simulator's."""
    src = make_source({"simulate": "--duration 2d --fs 2 --noises all,-laser --seed 3", "segment": "4h"})
    ref = Simulator(src.config)  # default caching
    cached = []
    for i in range(src.segments_total):
        tm, _ = src.segment(i)
        expected, _ = ref.chunk(i * src.n, min(src.n, src.sim.size - i * src.n))
        np.testing.assert_array_equal(tm.eta, expected.eta)
        np.testing.assert_array_equal(tm.dws_phi, expected.dws_phi)
        cached.append(sum(s.cache_nbytes for s in src.sim.streams.values() if s is not None))
    blocks = {s.block_length for s in src.sim.streams.values() if s is not None}
    assert src.segments_total * src.n > 1.1 * max(blocks)  # the run crosses a block boundary
    assert max(cached) == cached[0], cached


def test_fitter_window_keeps_one_window_of_telemetry(tmp_path):
    """The fitter's telemetry window (for the refits of extended models and the live
    diagnosis) holds the segments of one window and joins them as ``ttl refit`` would."""
    from ttl_testutil import noise_tdi_segment

    from stages.fitter.fitter import Fitter
    from streamer.bus.messages import concatenate_telemetry
    from ttlcore.io.telemetry import Telemetry

    fitter = Fitter(
        StageConfig(
            run="u", recordings=tmp_path, options={"window_duration": "1800", "adequacy_every": 0, "diagnose_every": 0}
        )
    )
    rng = np.random.default_rng(1)
    fs, n = 4.0, 2400
    segments = []
    for i in range(6):
        header, td = noise_tdi_segment(rng, i, n, fs)
        tm = Telemetry(
            t0=header.t0,
            fs=fs,
            eta=rng.standard_normal((6, n)),
            dws_phi=rng.standard_normal((6, n)),
            dws_eta=rng.standard_normal((6, n)),
            ltt=np.full((6, n), 8.3),
        )
        segments.append(tm)
        fitter.process(header, (td, tm))
        assert [j for j, _ in fitter.window_tm] == list(range(max(0, i - 2), i + 1))  # 1800 s: three segments
    joined = fitter.window_telemetry()
    expected = concatenate_telemetry(segments[3:])
    assert joined.t0 == expected.t0 == 3 * n / fs
    np.testing.assert_array_equal(joined.dws_eta, expected.dws_eta)
    np.testing.assert_array_equal(joined.dws_eta[:, -n:], segments[-1].dws_eta)


def test_adoption_needs_a_recommendation_that_explains_the_excess():
    """--adopt auto takes only what the diagnosis recommends, says explains the excess, with
    decisive evidence."""
    from stages.fitter.live_diagnosis import adoptable

    rec = {
        "option": "--effects linear-ttl,drift",
        "spec": "drift",
        "explains": True,
        "explained_fraction": 0.93,
        "log_bayes_factor": 40.0,
    }
    assert adoptable(rec)[0]
    assert not adoptable(None)[0] and not adoptable({"effect": None, "explains": False})[0]
    assert not adoptable({**rec, "option": ""})[0]  # nothing recommended (the option left empty)
    no, why = adoptable({**rec, "explains": False, "explained_fraction": 0.2})
    assert not no and "20 %" in why
    assert not adoptable({**rec, "log_bayes_factor": 1.0})[0]
    assert adoptable(rec)[1] == "explains 93 % of the excess, log Bayes factor 40.0"
    # glitches and gates: the share of their transients' excess, not of the whole (read 0 %)
    glitch = {"kind": "glitch", "explained_fraction": 1.0}
    transients = {**rec, "explained_fraction": 0.003, "actions": [glitch, {**glitch, "explained_fraction": 0.8}]}
    assert adoptable(transients)[1] == "models 2 transient(s), 80 % or more of each one's excess, log Bayes factor 40.0"


def test_an_effect_waits_while_the_models_gates_hide_most_of_the_window():
    """An effect is adopted only from a window whose gates leave half of it (a 16-h window with
    11 h gated once adopted second-order from noise levels fitted on the 5 h left); counted on
    the gates merged and clipped to the window."""
    from stages.fitter.live_diagnosis import enough_ungated
    from ttlcore.diagnose.diagnosis import TimeSlice

    report = [TimeSlice(t_start=3600.0 * h, t_stop=3600.0 * (h + 1), chi2_dof=1.0, fails=False) for h in range(16)]
    ok, why = enough_ungated(report, ["linear-ttl", "gate:start=14400,stop=54000"], (), "explains")
    assert not ok and "5.0 h of the window's 16.0 h" in why
    # two touching gates (0-2 h, 2-6 h) and one reaching beyond the window (2 h of it): 8 h left of 16
    gates = ["gate:start=0,stop=7200", "gate:start=7200,stop=21600", "gate:start=50400,stop=1e6"]
    assert enough_ungated(report, ["linear-ttl", *gates], (), "x") == (True, "x")
    assert not enough_ungated(report, ["linear-ttl", *gates[:2], "gate:start=46800,stop=1e6"], (), "x")[0]
    assert enough_ungated(report, ["linear-ttl", "drift"], (), "explains") == (True, "explains")


def test_monitor_waits_for_an_alive_fitter_that_has_not_reported_yet(tmp_path):
    """A fitter still on its first segment (alive, no progress yet) is waited for; one that is
    not running blocks nothing; one that reported is waited for until it passed the segment."""
    from stages.monitor.monitor import Monitor

    m = Monitor(StageConfig(run="u", recordings=tmp_path))
    assert m.settling.waiting_for(0, {}, m.alive_peers) is None  # neither fitter nor subtractor running
    m.alive_peers = {"fitter", "subtractor"}
    assert m.settling.waiting_for(0, {}, m.alive_peers) == "fit"  # started, not reported yet
    fitter = Progress("fitter", done={0}, extra={"fits": {0}})
    assert m.settling.waiting_for(0, {"fitter": fitter}, m.alive_peers) == "fit"  # fit 0 announced, not drawn
    m.settling.drawn["fit"].add(0)
    assert m.settling.waiting_for(0, {"fitter": fitter}, m.alive_peers) == "residual"
    m.alive_peers = {"fitter"}  # no subtractor after all
    assert m.settling.waiting_for(0, {"fitter": fitter}, m.alive_peers) is None


def test_subtractor_publishes_the_residual_message_value(tmp_path):
    """The residual's meta is a :class:`streamer.bus.residual_record.ResidualMessage` header: the
    fields the subtractor wrote before (same order) and ``schema``; read back by attribute."""
    s = Subtractor(StageConfig(run="u", recordings=tmp_path))
    s.segments_total = 12
    n, p = 64, len(COEFFICIENT_NAMES)
    rng = np.random.default_rng(1)
    td = TDIData(
        t0=0.0,
        fs=1.0,
        channels=("X2", "Y2", "Z2"),
        data=rng.normal(size=(3, n)),
        regressors=rng.normal(size=(3, p, n)),
        names=COEFFICIENT_NAMES,
        ltt_mean=np.full(6, 8.3),
    )
    header = SimpleNamespace(index=5)
    coefficients = dict.fromkeys(COEFFICIENT_NAMES, 1e-3)
    # fit 4's parts are for segment 4: not subtracted from segment 5; fit 4 is stale
    s.fits[4] = {
        "coefficients": coefficients,
        "t_start": 0.0,
        "t_stop": 18000.0,
        "parts": {"drift": np.zeros((3, n))},
        "stale": {"since": 3},
    }
    meta = s.subtract(header, td, 4).fields["meta"]
    assert json.dumps(meta) == json.dumps(
        {
            "fit_index": 4,
            "coefficients_t_start": 0.0,
            "coefficients_t_stop": 18000.0,
            "segments_total": 12,
            "effects": [],
            "model_parts_missing": ["drift"],
            "fit_stale": {"since": 3},
            "schema": RESIDUAL_SCHEMA,
        }
    )
    m = ResidualMessage.from_header(meta, "residual 5")
    assert m.fit_index == 4 and m.model_parts_missing == ("drift",) and m.fit_stale == {"since": 3}
    # fit 5's parts are segment 5's: subtracted, named in ``effects``; no fit: nulls
    s.fits[5] = {**s.fits[4], "stale": None}
    meta = s.subtract(header, td, 5).fields["meta"]
    assert ResidualMessage.from_header(meta).effects == ("drift",) and "model_parts_missing" not in meta
    assert s.subtract(header, td, None).fields["meta"] == {
        "fit_index": None,
        "coefficients_t_start": None,
        "coefficients_t_stop": None,
        "segments_total": 12,
        "effects": [],
        "schema": RESIDUAL_SCHEMA,
    }
