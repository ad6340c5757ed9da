"""The live model's checks (``stages/fitter/live_model.py``): a state object with no bus in it."""

from __future__ import annotations

import numpy as np
import pytest

from stages.fitter.live_model import MAX_COLUMNS, MAX_EFFECTS, MAX_GATES, LiveModel, header_bytes
from ttlcore.conventions import DAY
from ttlcore.effects.glitch import GLITCH_DAMPING_SPAN, TDI_REACH
from ttlcore.io.telemetry import Telemetry


def model() -> LiveModel:
    return LiveModel(["linear-ttl"], ())


def telemetry(n: int = 4 * 600) -> Telemetry:
    """Ten minutes of telemetry at 4 Hz (noise readouts, constant light travel times)."""
    rng = np.random.default_rng(1)
    return Telemetry(
        t0=0.0,
        fs=4.0,
        eta=rng.normal(size=(6, n)) * 1e-12,
        dws_phi=rng.normal(size=(6, n)) * 1e-9,
        dws_eta=rng.normal(size=(6, n)) * 1e-9,
        ltt=np.full((6, n), 8.3),
        source="test",
    )


def test_a_model_is_checked_and_spelled_as_the_effects_spell_it():
    assert model().check(["linear-ttl", "drift"]) == ["linear-ttl", "drift"]


@pytest.mark.parametrize(
    "specs, needle",
    [
        (["linear-ttl", "step:t_step=abc"], "bad duration 'abc'"),
        (["linear-ttl", "witness:source=foo"], "unknown 'foo'"),
        (["drift"], "must include linear-ttl"),
        (["linear-ttl", "no-such-effect"], "unknown effect"),
        ("", "expected a list"),
    ],
)
def test_a_model_that_cannot_be_fitted_is_refused_with_the_option_at_fault(specs, needle):
    with pytest.raises(ValueError, match=needle):
        model().check(specs)


def test_the_size_of_a_model_is_bounded():
    """100,000 effects (900 kB) grew the fitter to 6 GB; they are refused before any is built
    (the count comes first); columns are counted too: ten drifts of 24 and the 24 linear
    ones are 264 > 256."""
    with pytest.raises(ValueError, match=f"100001 effects, at most {MAX_EFFECTS}"):
        model().check(["linear-ttl"] + [f"gate:start={k + 1}s,stop={k + 2}s" for k in range(100_000)])
    assert MAX_COLUMNS < 24 * 11
    with pytest.raises(ValueError, match=f"264 columns, at most {MAX_COLUMNS}"):
        model().check(["linear-ttl"] + ["drift"] * 10)
    assert len(model().check(["linear-ttl"] + ["drift"] * 9)) == 10


def test_gates_are_bounded_in_number_and_span():
    """10,000 gates made the fitter's own fit header exceed 1 MiB; a gate over the whole day
    left the window without data (every later fit a copy of the last): both refused, with the
    limit named.  A gate from the data's start (0 s) is a gate like any other."""
    m = model()
    with pytest.raises(ValueError, match=f"{MAX_GATES + 1} gates, at most {MAX_GATES}"):
        m.check(["linear-ttl"] + [f"gate:start={k + 1}h,stop={k + 1}.1h" for k in range(MAX_GATES + 1)])
    with pytest.raises(ValueError, match="the gates span 24 h in total, at most 12 h"):
        m.check(["linear-ttl", "gate:start=0s,stop=1d"])
    # the union of the spans: overlapping gates are not counted twice
    assert m.check(["linear-ttl", "gate:start=0s,stop=6h", "gate:start=2h,stop=8h"])[1] == "gate:start=0s,stop=6h"
    with pytest.raises(ValueError, match="span 13 h"):
        m.check(["linear-ttl", "gate:start=0s,stop=6h", "gate:start=7h,stop=14h"])
    assert LiveModel(["linear-ttl"], (), window_duration=7 * DAY).check(["linear-ttl", "gate:start=0s,stop=1d"])


def test_a_model_whose_fit_header_would_be_too_large_is_refused(monkeypatch):
    """The specs are spelled back by the effects (a 20,000-digit time is one number), so the
    limits on effects and columns keep the model's part of the fit header small (the largest
    model allowed: ~20 kB of the 1 MiB); the size is checked all the same, against a budget
    here lowered to show it."""
    import stages.fitter.live_model as live_model

    largest = ["linear-ttl"] + ["drift"] * 9 + [f"gate:start={k}h,stop={k}.01h" for k in range(MAX_GATES)]
    assert len(model().check(largest)) == 42
    assert header_bytes(largest, [f"drift.{k}" for k in range(MAX_COLUMNS)], MAX_GATES) < 40_000
    monkeypatch.setattr(live_model, "MAX_MODEL_HEADER_BYTES", 2000)
    with pytest.raises(ValueError, match="bytes of the fit header, at most 2000"):
        model().check(largest)


def test_a_model_is_checked_on_the_window():
    """The columns are built on the newest telemetry when it is given; an effect whose
    parameters are searched (``step``, ``glitch`` without them) or whose columns need the
    fitted coefficients (``timing-offset``) is left to the window refit, not refused."""
    tm = telemetry()
    for spec in (
        "drift",
        "step",
        "step:t_step=0.1h",
        "glitch",
        "glitch:t=300s,tm=12,beta=10s",
        "witness:source=12.eta,link=23,delay=2",
        "fd-coupling:source=12.eta,link=23,delay=2",
        "timing-offset",
        "ltt-error",
        "cross-coupling",
        "second-order",
    ):
        assert len(model().check(["linear-ttl", spec], window=tm)) == 2, spec


def test_changes_are_queued_and_applied_at_segment_boundaries():
    """A change asked for while segment 4 is next takes effect when 4 is processed, not
    before; several changes for one segment make one change (from the model before the
    first to the model after the last); the model planned already changes nothing."""
    m = model()
    assert m.request(["linear-ttl", "drift"], 4)
    assert not m.request(["linear-ttl", "drift"], 4)
    assert m.request(["linear-ttl"], 4) and m.request(["linear-ttl", "drift", "gate:start=1h,stop=2h"], 4)
    assert m.effects == ["linear-ttl"] and m.planned == ["linear-ttl", "drift", "gate:start=1h,stop=2h"]
    assert m.apply(3) == [] and m.effects == ["linear-ttl"] and m.change_due is None
    assert len(m.apply(4)) == 3
    assert m.effects == ["linear-ttl", "drift", "gate:start=1h,stop=2h"] and not m.pending
    assert m.change_due == {"before": ["linear-ttl"], "after": m.effects, "from_index": 4} and m.diagnose_due
    # back to the model before within one segment: no change to report
    m.change_due = None
    m.request(["linear-ttl"], 6)
    m.request(["linear-ttl", "drift", "gate:start=1h,stop=2h"], 6)
    m.apply(6)
    assert m.change_due is None


def test_a_restart_queues_the_recorded_changes_at_their_segments():
    """The changes of earlier processes take effect at their own segments while the window
    is rebuilt: a segment before a change is fitted with the model before it; a change whose
    segment has a recorded fit is not reported again, the last one (no fit from it) is."""
    m = model()
    events = [
        {"details": {"effects": ["linear-ttl", "drift"], "before": ["linear-ttl"], "from_index": 3}},
        {"details": {"effects": ["linear-ttl"], "before": ["linear-ttl", "drift"], "from_index": 7}},
    ]
    assert m.restore(events, fits=set(range(6))) == (7, True)
    assert m.effects == ["linear-ttl"] and m.planned == ["linear-ttl"]
    for i in range(3):
        m.apply(i)
    assert m.effects == ["linear-ttl"]
    m.apply(3)
    assert m.effects == ["linear-ttl", "drift"] and m.change_due is None  # reported by the earlier process
    m.apply(7)
    assert m.effects == ["linear-ttl"] and m.change_due == {
        "before": ["linear-ttl", "drift"],
        "after": ["linear-ttl"],
        "from_index": 7,
    }


def test_a_fit_that_took_in_no_data_is_flagged_stale(tmp_path):
    """The fitter (real, fed synthetic segments): a fit whose newest FFT segment was gated is
    the last fit again, flagged ``stale`` with the segment of the fit it repeats; once the
    gates leave the window without any FFT segment, ``no_data`` and a ``no-data`` warning
    naming the segment.  (Before, such fits went out as fresh: a gate over the whole day
    made fits 3-11 bit-identical copies of fit 2.)"""
    from ttl_testutil import noise_tdi_segment

    from stages.fitter.fitter import Fitter
    from streamer.runtime.stage import StageConfig

    fitter = Fitter(StageConfig(run="u", recordings=tmp_path, options={"adequacy_every": 0, "diagnose_every": 0}))
    warned = []
    fitter.warn = lambda kind, message, **kw: warned.append((kind, kw.get("index"), message))
    fitter.event = lambda *a, **kw: None
    rng = np.random.default_rng(1)
    fs, n = 4.0, 2400
    metas = {}
    for i in range(5):
        if i == 2:  # gates over the first 2 segments and the next 2: the window holds nothing to fit
            fitter.model.change(["linear-ttl", "gate:start=0s,stop=2400s,taper=1s"], 2)
        if i == 3:
            fitter.model.change(["linear-ttl"], 3)
        header, td = noise_tdi_segment(rng, i, n, fs)
        tm = telemetry(n)
        tm.t0 = header.t0
        out = fitter.process(header, (td, tm))
        metas[i] = out.fields["meta"] if out is not None else None
    assert "stale" not in metas[0] and "stale" not in metas[1]
    assert metas[2]["stale"] == {"since": 1, "no_data": True}
    assert [i for k, i, _ in warned if k == "no-data"] == [2], warned
    assert "stale" not in metas[3] and "stale" not in metas[4]  # the gate left: fresh fits again


def test_a_coupling_switched_on_before_the_window_settles_into_the_plain_coupling():
    """``witness:...,vary=step,t_step=T`` (an onset's advice) is the plain witness on data that
    start an hour or more after ``T``: the live model puts the plain spec in its place then,
    and only then.  Checked on the columns themselves: built on ten minutes of telemetry
    after the switch, the switched-on column equals the plain one (the same series times 1)."""
    from ttlcore.effects import effect_input_from_telemetry, make_effects

    switched = "witness:source=12.eta,link=23,delay=1,vary=step,t_step=30600s"
    resonance = "fd-coupling:source=32.phi,link=23,f0=0.048Hz,q=3.8,vary=step,t_step=43174.2s"
    live = LiveModel(["linear-ttl", switched, resonance], ())
    switched, resonance = live.effects[1:]  # as the model spells them
    assert live.settled(30600.0 + 1800.0) == {}  # the switch inside the columns' history
    assert live.settled(30600.0 + 3601.0) == {switched: "witness:source=12.eta,link=23,delay=1"}
    assert live.settled(43174.2 + 3601.0) == {
        switched: "witness:source=12.eta,link=23,delay=1",
        resonance: make_effects(["fd-coupling:source=32.phi,link=23,f0=0.048Hz,q=3.8"])[0].spec(),
    }
    data = effect_input_from_telemetry(telemetry())  # t0 = 0: long after a switch at -2 h
    on, plain = make_effects(
        ["witness:source=12.eta,link=23,delay=1,vary=step,t_step=-7200s", "witness:source=12.eta,link=23,delay=1"]
    )
    (a,), (b,) = on.columns(data), plain.columns(data)
    assert [(p.link, p.delayed, p.channel) for p in a.parts] == [(p.link, p.delayed, p.channel) for p in b.parts]
    for pa, pb in zip(a.parts, b.parts, strict=True):
        np.testing.assert_array_equal(pa.series, pb.series)  # the witness times H(t + 2 h) = 1


def test_a_restored_change_published_again_is_reported_again():
    """A restarted fitter that publishes again the first segment of a change an earlier
    process reported (the board had not learned that segment was out: the chaos test, seed
    825968289, fit 140) computes it whole, its window refit and ``model_change`` included,
    as the earlier process did; a segment only replayed to rebuild the state reports nothing."""
    events = [
        {"details": {"effects": ["linear-ttl", "drift"], "before": ["linear-ttl"], "from_index": 3}},
        {"details": {"effects": ["linear-ttl"], "before": ["linear-ttl", "drift"], "from_index": 5}},
    ]
    for recomputed, reported in ((True, True), (False, False)):
        m = model()
        assert m.restore(events, fits=set(range(6))) == (5, False)
        for i in range(3):
            m.apply(i, recomputed=recomputed)
            assert m.change_due is None
        m.apply(3, recomputed=recomputed)
        want = {"before": ["linear-ttl"], "after": ["linear-ttl", "drift"], "from_index": 3}
        assert m.effects == ["linear-ttl", "drift"] and m.change_due == (want if reported else None)
    # a change asked for live is reported whatever the segment
    m = model()
    m.request(["linear-ttl", "drift"], 2)
    m.apply(2, recomputed=False)
    assert m.change_due is not None


def test_a_transient_leaving_the_window_is_not_reported_and_a_restart_keeps_it_so():
    """A transient's expiry (``report`` False: both models are the same on the window) makes no
    window refit, before a restart or after it; a restart diagnoses a change's first segment
    only when the earlier process did (``diagnose`` in its event)."""
    glitch = "glitch:t=900s,tm=12,beta=10s"
    m = LiveModel(["linear-ttl", glitch])
    assert m.request(["linear-ttl"], 4, diagnose=False, report=False)
    m.apply(4)
    assert m.effects == ["linear-ttl"] and m.change_due is None and not m.diagnose_due
    # a reported change queued with an expiry behind it in one segment is still reported
    m = LiveModel(["linear-ttl", glitch])
    m.request(["linear-ttl", glitch, "drift"], 4)
    m.request(["linear-ttl", "drift"], 4, diagnose=False, report=False)
    m.apply(4)
    assert m.change_due == {"before": ["linear-ttl", glitch], "after": ["linear-ttl", "drift"], "from_index": 4}
    events = [
        {"details": {"effects": ["linear-ttl", glitch, "drift"], "from_index": 3, "diagnose": True, "report": True}},
        {"details": {"effects": ["linear-ttl", "drift"], "from_index": 5, "diagnose": False, "report": False}},
    ]
    for recomputed in (True, False):
        m = LiveModel(["linear-ttl"])
        assert m.restore(events, fits=set(range(3))) == (5, False)  # the last change: never reported
        m.apply(3, recomputed=recomputed)
        assert m.change_due is not None and m.diagnose_due
        m.change_due, m.diagnose_due = None, False  # reported and diagnosed at segment 3
        m.apply(5, recomputed=recomputed)
        assert m.effects == ["linear-ttl", "drift"] and m.change_due is None and not m.diagnose_due


def test_the_span_of_the_transients_a_model_adds():
    m = LiveModel(["linear-ttl", "drift"])
    gate, glitch = "gate:start=1000s,stop=2000s,taper=100s", "glitch:t=5000s,tm=12,beta=10s"
    # the gate with its taper; the glitch to its damping span and the TDI's reach after it
    assert m.transients_added_until(["linear-ttl", "drift", gate]) == pytest.approx(2100.0)
    until = m.transients_added_until(["linear-ttl", "drift", gate, glitch])
    assert until == pytest.approx(5000.0 + GLITCH_DAMPING_SPAN * 10.0 + TDI_REACH)
    assert m.transients_added_until(["linear-ttl", "drift", "witness:source=12.eta,link=23,delay=1"]) is None
    assert m.transients_added_until(["linear-ttl", gate]) is None  # a coupling removed
    assert m.transients_added_until(["linear-ttl", "drift"]) is None
