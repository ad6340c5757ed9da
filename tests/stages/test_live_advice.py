"""The live diagnosis advises as the offline one does (issue: live advice recommended
effects that explain nothing, with the command to add them)."""

from __future__ import annotations

from stages.live_diagnosis import recommendation_meta
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
