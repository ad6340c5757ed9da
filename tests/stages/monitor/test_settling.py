"""Unit tests of :mod:`stages.monitor.settling`: when the monitor is done with a segment (no bus in it)."""

from stages.monitor.settling import Settling
from streamer.runtime.progress import Progress
from streamer.runtime.rangeset import RangeSet

INPUTS = ("tdi", "fit", "residual")


def progress(stage, done=(), fits=None, complete=False) -> Progress:
    extra = {"fits": RangeSet(fits)} if fits is not None else {}
    return Progress(stage=stage, done=RangeSet(done), extra=extra, complete=complete)


def test_nothing_is_waited_for_from_a_stage_that_is_neither_alive_nor_reporting():
    s = Settling(INPUTS)
    s.drawn["tdi"].update({0, 1})
    assert list(s.ready({}, set(), set(), None, now=0.0)) == [(0, "done", None, None), (1, "done", None, None)]


def test_an_alive_stage_that_has_not_reported_is_waited_for():
    s = Settling(INPUTS)
    s.drawn["tdi"].add(0)
    assert s.waiting_for(0, {}, {"fitter"}) == "fit"
    assert list(s.ready({}, set(), {"fitter"}, None, now=0.0)) == []
    s.refused["fit"].add(0)  # conflicting copies of the fit: not waited for
    assert s.waiting_for(0, {}, {"fitter"}) is None


def test_what_a_producer_published_is_waited_for_until_drawn():
    s = Settling(INPUTS, settle_timeout=60.0)
    s.drawn["tdi"].update({0, 1, 2})
    board = {"fitter": progress("fitter", done={0, 1, 2}, fits={0, 2}), "subtractor": progress("subtractor", {0, 1, 2})}
    alive = {"fitter", "subtractor"}
    # segment 1 made no fit: it waits only for its residual
    assert s.waiting_for(1, board, alive) == "residual"
    s.drawn["residual"].update({0, 1, 2})
    assert s.waiting_for(1, board, alive) is None
    assert s.waiting_for(0, board, alive) == "fit"
    s.drawn["fit"].add(0)
    s.unhandled["fit"].add(2)  # its drawing raised: failed, not waited for
    assert list(s.ready(board, RangeSet(), alive, None, now=0.0)) == [
        (0, "done", None, None),
        (1, "done", None, None),
        (2, "unhandled", None, None),
    ]
    assert list(s.ready(board, RangeSet({0, 1}), alive, None, now=0.0)) == [(2, "unhandled", None, None)]
    assert s.pending(RangeSet({0})) == 2
    s.forget(2)
    assert 2 not in s.unhandled["fit"]


def test_a_producer_not_past_the_segment_is_waited_for():
    s = Settling(INPUTS)
    s.drawn["tdi"].add(5)
    board = {"subtractor": progress("subtractor", done={0, 1})}
    assert s.waiting_for(5, board, set()) == "residual"
    board = {"subtractor": progress("subtractor", done={0, 1}, complete=True)}
    assert s.waiting_for(5, board, set()) is None


def test_giving_up_only_on_a_gone_producer_or_a_loss_after_the_timeout():
    s = Settling(INPUTS, settle_timeout=60.0)
    s.drawn["tdi"].add(0)
    board = {"subtractor": progress("subtractor", done={0})}
    # the subtractor alive, nothing lost: the wait starts again, however long
    assert list(s.ready(board, RangeSet(), {"subtractor"}, None, now=0.0)) == []
    assert list(s.ready(board, RangeSet(), {"subtractor"}, None, now=1000.0)) == []
    assert s.since[0] == 1000.0
    # gone: waited for settle_timeout from the last time it was seen waiting
    assert list(s.ready(board, RangeSet(), set(), None, now=1030.0)) == []
    assert list(s.ready(board, RangeSet(), set(), None, now=1061.0)) == [
        (0, "gone", "residual", "subtractor gone for 60 s")
    ]
    # alive but a sample lost beyond recovery
    assert s.give_up("residual", since=0.0, now=59.0, alive={"subtractor"}, last_miss=1.0) is None
    assert s.give_up("residual", since=0.0, now=61.0, alive={"subtractor"}, last_miss=1.0).startswith("lost beyond")
    assert s.give_up("residual", since=100.0, now=200.0, alive={"subtractor"}, last_miss=10.0) is None


def test_announced_and_needed():
    s = Settling(INPUTS)
    board = {
        "tdi_builder": progress("tdi_builder", done={0, 1, 2}),
        "fitter": progress("fitter", done={0, 1, 2}, fits={2}),
    }
    announced = s.announced(board)
    assert set(announced) == {"tdi", "fit"}
    assert announced["fit"][0] == "fitter" and list(announced["fit"][1]) == [2]
    assert list(announced["tdi"][1]) == [0, 1, 2]
    assert s.needed("fit", 2)
    s.drawn["fit"].add(2)
    assert not s.needed("fit", 2)
