"""The live diagnosis' schedule (stages/fitter/schedule.py) and the live model's transients
leaving it (stages/fitter/live_model.py): parts of the fitter with no bus in them."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from stages.fitter.live_model import LiveModel
from stages.fitter.model import FitterModel
from stages.fitter.schedule import SUSTAINED_OUTLIERS, DiagnosisSchedule
from ttlcore.diagnose.diagnosis import Coefficients, Recommendation
from ttlcore.effects.gate import GATE_TAPER
from ttlcore.effects.glitch import GLITCH_DAMPING_SPAN, TDI_REACH


def test_a_one_day_file_is_diagnosed_at_half_a_day_and_at_its_end():
    # default cadence 24 (1-h segments): the first diagnosis at 12 h, so that a model adopted
    # then is fitted for the rest of the day, then at the end of every day, and the run's
    # last segment wherever it falls
    s = DiagnosisSchedule(24)
    due = [i for i in range(24) if s.due(i, last=i == 23, new_model=False)]
    assert due == [11, 23]
    week = [i for i in range(124) if s.due(i, last=i == 123, new_model=False)]
    assert week == [11, 23, 47, 71, 95, 119, 123]
    assert s.due(5, last=False, new_model=True)
    # a short cadence is its own first diagnosis: 3 segments, not one
    assert [i for i in range(9) if DiagnosisSchedule(3).due(i, last=False, new_model=False)] == [2, 5, 8]
    assert not any(DiagnosisSchedule(0).due(i, last=True, new_model=True) for i in range(30))
    # the last segment only when half a cadence has passed since the last diagnosis: a run of
    # 124 h diagnosed at 119 h is not diagnosed again at 123 h; a 4-segment run not at its end
    s.done(119)
    assert not s.due(123, last=True, new_model=False) and s.due(131, last=True, new_model=False)
    assert not DiagnosisSchedule(24).due(3, last=True, new_model=False)


def _slots(s: DiagnosisSchedule, segments, last: int) -> list[int]:
    """The segments diagnosed of ``segments`` (in hand one by one, each asked twice as the
    fitter does: for the window refit and for the diagnosis)."""
    out = []
    for i in segments:
        s.arrive(i)
        if s.due(i, last=i == last, new_model=False) and s.due(i, last=i == last, new_model=False):
            out.append(i)
            s.done(i)
    return out


def test_a_slot_inside_a_gap_falls_on_the_first_segment_after_it():
    # the mission week's planned 7-h gap covered segments 118-123: the daily slot 119 never
    # came, and the window 96..119 was diagnosed at no slot; now at segment 124
    week = [i for i in range(168) if not 118 <= i <= 123]
    assert _slots(DiagnosisSchedule(24), week, 167) == [11, 23, 47, 71, 95, 124, 143, 167]
    # the first diagnosis at half a day, in a gap of hours 9-14: at hour 15
    assert _slots(DiagnosisSchedule(24), [*range(9), *range(15, 30)], 29) == [15, 23]
    # a gap that holds no slot moves none; segments in order keep the cadence
    assert _slots(DiagnosisSchedule(24), [*range(30), *range(40, 48)], 47) == [11, 23, 47]
    assert _slots(DiagnosisSchedule(24), range(48), 47) == [11, 23, 47]


def test_the_segments_a_late_diagnosis_no_longer_holds_are_named():
    # the blind week: the slot 119 fell in the gap 118-123 and was taken at 124, whose one-day
    # window (101..124, the gap held as NaN) starts after segments 96-100: those were in no
    # diagnosed window (a 4.8e-11 m/s glitch at 98.8 h among them), and done() names them;
    # a diagnosis on time names none, and neither do the gap's segments (never in hand)
    s, missed = DiagnosisSchedule(24), {}
    for i in (i for i in range(168) if not 118 <= i <= 123):
        s.arrive(i)
        if s.due(i, last=i == 167, new_model=False):
            missed[i] = s.done(i, first=max(0, i - 23))
    assert missed == {11: [], 23: [], 47: [], 71: [], 95: [], 124: [96, 97, 98, 99, 100], 143: [], 167: []}
    # a gap right after a diagnosis leaves nothing undiagnosed but the gap itself
    s = DiagnosisSchedule(24)
    for i in [*range(24), *range(40, 48)]:
        s.arrive(i)
        if s.due(i, last=False, new_model=False):
            assert s.done(i, first=max(0, i - 23)) == [], i
    # without a cadence nothing is counted
    s = DiagnosisSchedule(0)
    s.arrive(3)
    assert s.since_done == set() and s.done(3, first=10) == []


def test_the_fitter_warns_of_the_segments_no_diagnosis_saw(tmp_path):
    """FitterModel.diagnosis_done on a stand-in for the stage (the schedule above, a window
    from 101): one ``undiagnosed`` warning naming 96-100 and the ``ttl refit`` that looks at
    them; none when nothing was missed."""
    s = DiagnosisSchedule(24)
    for i in range(96, 118):
        s.arrive(i)
    s.arrive(124)
    warnings = []
    stage = SimpleNamespace(
        schedule=s,
        window_tm=SimpleNamespace(first=101),
        config=SimpleNamespace(recordings=tmp_path),
        run_id="week",
        model=SimpleNamespace(effects=["linear-ttl", "fd-coupling:source=23.phi,link=13"]),
        warn=lambda kind, message, **details: warnings.append((kind, message, details)),
    )
    FitterModel.diagnosis_done(stage, 124)
    [(kind, message, details)] = warnings
    assert kind == "undiagnosed" and details == {"index": 124, "segments": [[96, 100]]}
    assert "segment(s) 96-100 in no diagnosed window" in message
    assert (
        f"ttl refit {tmp_path / 'week'} --segments 96:100 --effects linear-ttl,fd-coupling:source=23.phi,link=13"
        in message
    )
    FitterModel.diagnosis_done(stage, 143)
    assert len(warnings) == 1


def test_a_sustained_excess_brings_the_diagnosis_forward_once():
    s = DiagnosisSchedule(24)
    outlier = {"t_start": 0.0, "t_stop": 3600.0, "chi2_dof": 1.5, "reference": 1.0, "z": 40.0}
    gate = {"t_start": 0.0, "t_stop": 3600.0, "gate": [0.0, 10.0]}
    assert not s.outlier(outlier) and not s.outlier(outlier)
    assert not s.outlier(gate)  # a gate ends the run: not an outlier of the data
    fired = [s.outlier(outlier) for _ in range(2 * SUSTAINED_OUTLIERS)]
    assert fired == [k == SUSTAINED_OUTLIERS - 1 for k in range(2 * SUSTAINED_OUTLIERS)]
    assert not s.outlier(None) and s.outlier_run == 0


def test_transients_leave_the_model_once_their_span_has_left_the_window():
    glitch = "glitch:t=36000.0,tm=12,beta=30.0"
    gate = "gate:start=50000.0,stop=52000.0"
    model = LiveModel(["linear-ttl", "witness:source=12.phi,link=31,delay=2", glitch, gate])
    glitch_end = 36000.0 + GLITCH_DAMPING_SPAN * 30.0 + TDI_REACH
    assert model.expired(36000.0) == []
    assert model.expired(glitch_end + 1.0) == [model.effects[2]]
    # the gate with its tapers (GATE_TAPER); the coupling never leaves
    assert model.expired(52000.0 + GATE_TAPER - 1.0) == [model.effects[2]]
    assert model.expired(52000.0 + GATE_TAPER + 1.0) == model.effects[2:]
    assert model.expired(1e9) == model.effects[2:]
    # a glitch whose time is still to be searched has no span yet
    assert LiveModel(["linear-ttl", "glitch:tm=12"]).expired(1e9) == []


@pytest.mark.parametrize("diagnose", [True, False])
def test_a_change_that_only_drops_transients_is_not_diagnosed_again(diagnose):
    model = LiveModel(["linear-ttl", "gate:start=0,stop=10"])
    model.change(["linear-ttl"], 5, diagnose=diagnose)
    assert model.change_due == {
        "before": ["linear-ttl", "gate:start=0s,stop=10s"],
        "after": ["linear-ttl"],
        "from_index": 5,
    }
    assert model.diagnose_due is diagnose


def test_an_effect_whose_evidence_is_gone_is_proposed_for_removal():
    # the window's fit of the model: the witness at 0.4 sigma (a coupling that switched off),
    # the fd-coupling's two parameters far from zero; p of chi^2 = 0.16 with 1 dof is 0.69
    # (scipy's chi2.sf, checked against the normal tail: 2 * (1 - Phi(0.4)) = 0.689)
    from stages.fitter.live_diagnosis import stale_effects

    witness = "witness:source=12.eta,link=23,delay=2"
    fd = "fd-coupling:source=12.eta,delay=1,filter=pole1,fc=0.02"
    report = {
        "model": {
            "coefficients": {
                "values": {"witness.12.eta>23+2L": 0.4e-3, "fd.12.eta>12+1L.b0": 5e-3, "fd.12.eta>12+1L.b1": 1e-3},
                "sigma": {"witness.12.eta>23+2L": 1e-3, "fd.12.eta>12+1L.b0": 1e-4, "fd.12.eta>12+1L.b1": 1e-4},
            }
        }
    }
    fitted = Coefficients.from_json(report["model"]["coefficients"])
    (stale,) = stale_effects(fitted, ["linear-ttl", witness, fd, "gate:start=0.0,stop=10.0"], ())
    assert stale["spec"] == witness and stale["dof"] == 1
    assert stale["chi2"] == pytest.approx(0.16) and stale["p"] == pytest.approx(0.6892, abs=1e-4)


def test_an_adopted_offset_keeps_its_evidence():
    """A shifted effect's ``.d1`` column is the offset beyond its expansion point, ~0 once
    the point is right: its evidence is the whole offset.  (Right after the live loop adopted
    ``timing-offset:offset.sc1=0.099483s``, log B 2.5e4, the next diagnosis proposed to
    remove it, p = 0.013, from the ``.d1`` columns alone.)"""
    from stages.fitter.live_diagnosis import stale_effects

    spec = "timing-offset:offset.sc1=0.099483s"
    names = [f"timing-offset.sc{k}.d{o}" for k in (1, 2, 3) for o in (1, 2)]
    values = dict.fromkeys(names, 0.0)
    sigma = dict.fromkeys(names, 1e-3)
    values["timing-offset.sc1.d1"] = 1e-4  # 0.1 sigma beyond the expansion point
    report = {
        "model": {
            "coefficients": {
                "values": values,
                "sigma": sigma,
                "offsets": {"timing-offset.sc1": {"value": 0.0995, "sigma": 1e-3, "unit": "s"}},
            }
        }
    }
    assert stale_effects(Coefficients.from_json(report["model"]["coefficients"]), ["linear-ttl", spec], ()) == []
    del report["model"]["coefficients"]["offsets"]  # the .d1 columns alone: wrongly stale
    stale = stale_effects(Coefficients.from_json(report["model"]["coefficients"]), ["linear-ttl", spec], ())
    assert [s["spec"] for s in stale] == [spec]


def test_a_model_that_only_gained_transients_is_diagnosed_a_little_later():
    # an excess going on to the window's end (a coupling switched on an hour ago) was gated
    # again at every segment, each time by a diagnosis of minutes: a change that only adds
    # gates or glitches puts the diagnosis off by TRANSIENT_SPACING segments; one that adds a
    # coupling is diagnosed on its first segment, as before
    from stages.fitter.schedule import TRANSIENT_SPACING

    model = LiveModel(["linear-ttl", "step:t_step=259198.757"])
    assert model.only_transients_added(["linear-ttl", "step:t_step=259198.757", "gate:start=1,stop=2"])
    assert model.only_transients_added(["linear-ttl", "glitch:t=5.0,tm=12,beta=3.0", "step:t_step=259198.757"])
    assert not model.only_transients_added(
        ["linear-ttl", "step:t_step=259198.757", "witness:source=12.eta,link=23,delay=2"]
    )
    assert not model.only_transients_added(["linear-ttl"])  # a coupling removed
    s = DiagnosisSchedule(24)
    s.later(74 + TRANSIENT_SPACING)
    due = [i for i in range(72, 96) if s.due(i, last=False, new_model=False)]
    assert due[0] == 74 + TRANSIENT_SPACING
    s.done(77)
    assert [i for i in range(78, 96) if s.due(i, last=False, new_model=False)] == [95]


def test_a_time_inside_a_gap_is_not_adopted():
    # the mission week's planned gap (127.2-134.2 h): its edge was adopted as a step at 132.1 h,
    # inside it, and every coefficient after the gap came out 0
    from stages.fitter.live_diagnosis import outside_gaps

    gap = [[457890.0, 483224.0]]

    def advice(spec, actions=()):
        return Recommendation.from_json({"spec": spec, "actions": list(actions)})

    ok, why = outside_gaps(advice("step:t_step=475424.5"), gap, "explains")
    assert not ok and "t_step=475424.5s lies in a gap" in why
    actions = [{"spec": "glitch:t=460000.0,tm=12,beta=3.0"}, {"spec": "gate:start=1,stop=2"}]
    assert not outside_gaps(advice("x", actions), gap, "")[0]
    assert outside_gaps(advice("step:t_step=400000"), gap, "explains") == (True, "explains")
    assert outside_gaps(advice("witness:source=12.eta,link=23,delay=1"), gap, "x") == (True, "x")


@pytest.mark.parametrize("diagnose_every, adopt, ranked", [(24, "ask", False), (24, "never", True), (0, "ask", True)])
def test_a_change_is_ranked_by_the_window_refit_only_without_the_live_diagnosis(
    tmp_path, monkeypatch, diagnose_every, adopt, ranked
):
    """The window refit of a model change compares both models; the candidates not in the
    model are ranked there only when no live diagnosis will rank them (its first segment's
    diagnosis, or the next slot): a whole candidate phase per change otherwise (55-65 s of a
    day's window; 14 changes in the mission week)."""
    from types import SimpleNamespace

    import stages.fitter.fitter as fitter_module
    from streamer.runtime.stage import StageConfig

    options = {"diagnose_every": diagnose_every, "adopt": adopt, "adequacy_every": 0}
    fitter = fitter_module.Fitter(StageConfig(run="u", recordings=tmp_path, options=options))
    seen = {}
    monkeypatch.setattr(fitter, "window_whitened", lambda header, keep: (None, None))
    monkeypatch.setattr(fitter_module, "window_refit", lambda *a, **kw: "refit")
    monkeypatch.setattr(fitter_module, "window_refit_meta", lambda r, **kw: seen.update(kw) or {})
    monkeypatch.setattr(fitter.window_tm, "segments", [(3, SimpleNamespace(size=10))])
    fitter.model.change_due = {"before": ["linear-ttl"], "after": ["linear-ttl", "drift"], "from_index": 3}
    header = SimpleNamespace(index=3, t0=0.0, meta={"segment_duration": 3600.0})
    assert fitter.window_fit(header) == {}
    assert seen["change"] is not None and seen["ranked"] is ranked


@pytest.mark.parametrize("t_glitch_h, later", [(12.5, False), (21.2, True), (20.5, False)])
def test_transients_adopted_inside_the_window_wait_for_the_next_slot(tmp_path, monkeypatch, t_glitch_h, later):
    """A glitch adopted from a diagnosis of the window 0-24 h is diagnosed again 3 segments
    later only when its span reaches the window's last TRANSIENT_SPACING (3) hours (an
    excess that may go on past the end); one half a day back waits for the next slot.  The
    glitch at 20.5 h with beta = 10 s ends 20.5 h + GLITCH_DAMPING_SPAN * 10 s + TDI_REACH,
    before 21 h; the one at 21.2 h ends after it."""
    from types import SimpleNamespace

    import stages.fitter.fitter as fitter_module
    from stages.fitter.schedule import TRANSIENT_SPACING
    from streamer.runtime.stage import StageConfig

    assert 20.5 * 3600 + GLITCH_DAMPING_SPAN * 10.0 + TDI_REACH < 21 * 3600
    options = {"diagnose_every": 24, "adopt": "auto", "adequacy_every": 0}
    fitter = fitter_module.Fitter(StageConfig(run="u", recordings=tmp_path, options=options))
    segments = [(i, SimpleNamespace(t0=i * 3600.0, size=14400, fs=4.0)) for i in range(24)]
    monkeypatch.setattr(fitter.window_tm, "segments", segments)
    monkeypatch.setattr(fitter, "event", lambda *a, **kw: None)
    fitter.queue.next = 24
    fitter.change_model(["linear-ttl", f"glitch:t={t_glitch_h * 3600}s,tm=12,beta=10s"], by="adopt auto")
    assert fitter.schedule.pending_from == (24 + TRANSIENT_SPACING if later else None)
    assert not fitter.model.pending[-1]["diagnose"]
