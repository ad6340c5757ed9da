"""The segment a model change applies from (stages.fitter.model.FitterModel.change_model): the
next one to be processed, never before a change already queued (the order asked is the order
in force) and never a segment an earlier process already published (a restarted fitter
replaying it).  The chaos run of seed 825968289 recorded a change from 82, then one from 79
made by a restarted fitter replaying 79-81: the first would have overridden the second at 82.
A real Fitter, not run (no session): its queue, board and live model are set as a run sets them."""

from ttl_testutil import local_stage_config

from stages.fitter.fitter import Fitter
from streamer.runtime.progress import Progress
from streamer.runtime.rangeset import RangeSet

DRIFT = ["linear-ttl", "drift"]
LINEAR = ["linear-ttl"]


def fitter(tmp_path) -> Fitter:
    return Fitter(local_stage_config("change-start", 1, tmp_path))


def test_a_change_applies_from_the_next_segment(tmp_path):
    f = fitter(tmp_path)
    f.queue.next = 12  # segment 11 in hand
    f.change_model(DRIFT, by="control")
    assert [(c["effects"], c["from_index"]) for c in f.model.pending] == [(DRIFT, 12)]


def test_a_restarted_fitter_replaying_published_segments_applies_a_change_after_them(tmp_path):
    f = fitter(tmp_path)
    f.board.stages["fitter"] = Progress("fitter", done=RangeSet.from_ranges([[0, 81]]))  # its predecessor's
    f.queue.next = 80  # replaying 79, whose fit is out
    f.change_model(DRIFT, by="control")
    assert [c["from_index"] for c in f.model.pending] == [82]


def test_a_change_never_applies_before_one_already_queued(tmp_path):
    f = fitter(tmp_path)
    f.model.request(DRIFT, 82)  # restored from the predecessor's recording
    f.queue.next = 80
    f.change_model(LINEAR, by="control")
    assert [(c["effects"], c["from_index"]) for c in f.model.pending] == [(DRIFT, 82), (LINEAR, 82)]
    applied = f.model.apply(82)  # both at 82, in the order asked: the last is in force
    assert [c["effects"] for c in applied] == [DRIFT, LINEAR] and f.model.effects == LINEAR


def test_a_change_applies_after_segments_an_earlier_process_recorded_the_fits_of(tmp_path):
    # the chaos run of seed 825968289: a fitter published and recorded fits 136-139 and went
    # with its launcher before the board learned of 138-139; its successor, started at 138
    # and told of a change there, made it from 139 - a second fit 139 with another model
    f = fitter(tmp_path)
    f.board.stages["fitter"] = Progress("fitter", done=RangeSet.from_ranges([[0, 137]]))
    f.recorded_fits = set(range(136, 140))  # the predecessor's recording (restore_model reads it)
    f.queue.next = 139  # 138 in hand again
    f.change_model(DRIFT, by="control")
    assert [c["from_index"] for c in f.model.pending] == [140]
