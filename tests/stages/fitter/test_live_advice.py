"""The live diagnosis advises as the offline one does (issue: live advice recommended
effects that explain nothing, with the command to add them)."""

from __future__ import annotations

from stages.fitter.live_diagnosis import recommendation_meta
from ttlcore.diagnose.diagnosis import Candidate, Recommendation


def _report(option: str, explains: bool) -> tuple[Recommendation, list[Candidate]]:
    spec = "second-order"
    return (
        Recommendation.from_json(
            {
                "effect": spec,
                "spec": spec,
                "cli_spec": spec,
                "option": option,
                "explains": explains,
                "explained_fraction": 0.12 if not explains else 0.9,
                "message": "no candidate explains the excess (the best, second-order, explains 12 %)",
            }
        ),
        [Candidate.from_json({"spec": spec, "log_bayes_factor": 40.0})],
    )


def command(effects):
    return "ttl control ... fitter model " + ",".join(effects)


def test_a_candidate_that_explains_nothing_gets_no_command():
    rec = recommendation_meta(*_report("", False), ["linear-ttl"], (), command)
    assert "command" not in rec and "effects" not in rec
    assert rec["message"].startswith("no candidate explains the excess")


def test_an_advised_candidate_gets_its_model_and_command():
    rec = recommendation_meta(*_report("--effects linear-ttl,second-order", True), ["linear-ttl"], (), command)
    assert rec["effects"] == ["linear-ttl", "second-order"]
    assert rec["command"] == "ttl control ... fitter model linear-ttl,second-order"
    assert rec["log_bayes_factor"] == 40.0


def test_a_reshaped_coupling_takes_the_place_of_the_one_it_replaces():
    # the live model holds the first-order path at the corner adopted from the first hours
    # after its onset; the diagnosis searched the corner again on the window
    old = "fd-coupling:source=23.phi,link=13,filter=pole1,fc=0.0714692Hz"
    new = "fd-coupling:source=23.phi,link=13,filter=pole1,fc=0.0769062Hz"
    effects = ["linear-ttl", old, "glitch:t=222327.41s,tm=12,beta=89.54s"]
    advice = Recommendation.from_json(
        {"effect": "fd-coupling", "spec": new, "cli_spec": new, "option": "--effects ...", "explains": True}
        | {"replaces": old, "explained_fraction": 1.0}
    )
    rec = recommendation_meta(advice, [Candidate.from_json({"spec": new, "replaces": old})], effects, (), command)
    assert rec["effects"] == ["linear-ttl", new, "glitch:t=222327.41s,tm=12,beta=89.54s"]
    assert advice.replaces == old
    # spelled otherwise (the corner in Hz without its unit), still the model's effect
    advice = Recommendation.from_json(advice.to_json() | {"replaces": old.replace("Hz", "")})
    rec = recommendation_meta(advice, [], effects, (), command)
    assert rec["effects"] == ["linear-ttl", new, "glitch:t=222327.41s,tm=12,beta=89.54s"]
    # one the model does not hold: no model, no command (it must not be added beside)
    advice = Recommendation.from_json(advice.to_json() | {"replaces": old.replace("link=13", "link=12")})
    rec = recommendation_meta(advice, [], effects, (), command)
    assert "effects" not in rec and "command" not in rec
