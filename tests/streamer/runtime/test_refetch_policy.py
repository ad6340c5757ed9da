"""Which damaged copies are asked for again, and how many refusals are recorded (issue 33),
without a bus: :mod:`streamer.runtime.refetch_policy` and :class:`streamer.runtime.ingest.Ingest`."""

from __future__ import annotations

import json
import logging
import time

import numpy as np

from streamer.bus.codec import Expect, encode
from streamer.runtime.ingest import Ingest
from streamer.runtime.plan import Holdback, Plan, Validator
from streamer.runtime.rangeset import RangeSet
from streamer.runtime.refetch_policy import (
    MAX_REFETCHES,
    OTHER_SENDER,
    REFETCH_BURST,
    RefetchBudget,
    ReportLimiter,
    refetch_refusal,
    sender,
)

RUN = "u"


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_refetch_refusal_checks_the_plan_the_window_the_producer_and_what_was_done():
    ok = {"total": 6, "floor": -64, "ceiling": 64, "done": False}
    assert refetch_refusal(3, "tdi_builder", "tdi_builder", **ok) is None
    assert "not the topic's" in refetch_refusal(3, "intruder", "tdi_builder", **ok)
    assert "plan" in refetch_refusal(6, "tdi_builder", "tdi_builder", **ok)
    assert "plan" in refetch_refusal(-1, "tdi_builder", "tdi_builder", **ok)
    assert "plan" in refetch_refusal(2**40, "tdi_builder", "tdi_builder", **{**ok, "total": 10_000_000})
    assert "window" in refetch_refusal(70, "tdi_builder", "tdi_builder", **{**ok, "total": None})
    assert "window" in refetch_refusal(3, "tdi_builder", "tdi_builder", **{**ok, "floor": 4})
    assert "processed" in refetch_refusal(3, "tdi_builder", "tdi_builder", **{**ok, "done": True})


def test_the_budget_is_per_segment_and_per_producer_and_does_not_forget():
    clock = Clock()
    b = RefetchBudget(clock=clock)
    assert [b.take("s", 0, "p", 0) for _ in range(MAX_REFETCHES + 1)] == [*range(1, MAX_REFETCHES + 1), 0]
    # ever new indices: the producer's budget, not the count per index, stops them
    asked = [b.take("s", i, "p", 0) for i in range(1, 1000)]
    assert sum(1 for a in asked if a) == REFETCH_BURST - MAX_REFETCHES
    assert b.refused["p"] == 999 - (REFETCH_BURST - MAX_REFETCHES)
    assert b.take("s", 2000, "q", 0) == 1  # another producer has its own
    clock.t += b.period  # one grows back per period
    assert b.take("s", 3000, "p", 0) == 1 and b.take("s", 3001, "p", 0) == 0
    # segment 0's attempts are used up however long it has been, while 0 is in the window
    clock.t += 1e6
    assert b.take("s", 0, "p", 0) == 0
    # over a day at the full rate: the queries are bounded by the rate, the counts by the window
    b2 = RefetchBudget(clock=clock)
    n = 0
    for k in range(20_000):
        clock.t += 0.01
        n += bool(b2.take("s", k, "p", k - 64))
    assert n <= REFETCH_BURST + 200 / b2.period + 1
    assert len(b2.asked) <= 4 * REFETCH_BURST + 1


def test_the_report_limiter_counts_past_the_limit_per_cause_and_producer():
    clock = Clock()
    lim = ReportLimiter(limit=3, every=10.0, clock=clock)
    assert [lim.admit("fitter", "rejected", "payload") for _ in range(5)] == [True] * 3 + [False] * 2
    assert lim.admit("fitter", "rejected", "checksum")  # another cause
    assert lim.due() == []  # not yet
    clock.t += 10
    assert lim.due() == [("fitter", "rejected", "payload", 2)]
    assert lim.due() == []
    lim.admit("fitter", "rejected", "payload")
    assert lim.due(final=True) == [("fitter", "rejected", "payload", 1)]
    # a sender that writes a new producer name in every message makes no new cause
    assert sender("fitter", "fitter") == "fitter" and sender("p" * 5000, "fitter") == OTHER_SENDER
    assert sender(None, "fitter") == OTHER_SENDER


def _tdi(index: int, producer: str = "tdi_builder") -> tuple[bytes, bytes]:
    arrays = {"data": np.ones((3, 8)), "regressors": np.ones((24, 3, 8))}
    return encode(arrays, {"run": RUN, "index": index, "t0": 2.0 * index, "fs": 4.0, "producer": producer})


def test_a_flood_of_damaged_headers_asks_a_few_refetches_and_records_a_bounded_count():
    """Issue 33: 3000 headers with empty payloads caused 9000 cache queries (3 per header per
    consumer) and as many records with a 2000-character preview each.  Now: only indices of
    the plan not processed yet, within the producer's budget; the records stop at the limit
    and one ``suppressed`` count stands for the rest."""
    asked, reports = [], []
    ing = Ingest(
        RUN,
        Validator(Plan(segments_total=6, fs=4.0, t0=0.0, samples=8, samples_total=48)),
        Holdback(0.0),
        expect=lambda topic, index: Expect(run=RUN, index=index),
        withdraw=lambda *a: True,
        report=lambda kind, what, **k: reports.append((kind, k.get("field"), k.get("details", {}))),
        event=lambda *a, **k: None,
        use=lambda key, header, arrays, payload: ing.done.setdefault("tdi", RangeSet()).add(header.index),
        log=logging.getLogger("test"),
        refetch=lambda stream, index, header, sn: asked.append(index),
    )
    ing.limiter.limit = 100
    payload, attachment = _tdi(0, producer="tdi_builder")
    ing.take(f"ttl/{RUN}/tdi", payload, attachment)  # segment 0 intact: used
    for k in range(3000):
        _, att = _tdi(k, producer="tdi_builder" if k % 2 else "intruder")
        ing.take(f"ttl/{RUN}/tdi", b"", att)  # an empty payload: damaged
    # segment 0 is done, 6.. are not in the plan, the intruder is not the producer: 1..5
    # asked for once each (the producer's budget allows 8 at once)
    assert asked == [1, 3, 5], asked
    assert len(reports) == 200  # 100 per producer (the intruder's under one name)
    assert all(len(json.dumps(d)) < 3000 for _, _, d in reports)
    assert sorted(ing.suppressed(final=True)) == [
        (OTHER_SENDER, "rejected", "payload", 1400),
        ("tdi_builder", "rejected", "payload", 1400),
    ]


def test_a_refetch_asks_one_index_and_passes_the_access_control(tmp_path):
    """Through a router with the run's credentials (the access control on): a re-fetch that
    names the damaged copy's sequence number is answered by the fitter's cache with that
    sample only (without it, every cached segment comes back: 11.4 MB each for TDI), and a
    number no longer cached with nothing."""
    import threading

    from proc_testutil import output, wait_for
    from ttl_testutil import Procs

    from streamer.bus import security
    from streamer.bus.codec import parse_header
    from streamer.bus.segment_stream import refetch_segment
    from streamer.bus.session import Bus, SessionSettings, free_port

    creds = security.ensure_credentials(tmp_path / "creds")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    procs = Procs(tmp_path)

    def session(identity):
        return Bus.open(SessionSettings(mode="client", connect=(endpoint,), credentials=creds, identity=identity))

    try:
        router = procs.ttl("router", "--credentials", str(creds), "--listen", endpoint, name="router")
        wait_for(lambda: "listening on" in output(router) or router.poll() is not None, 60, "the router")
        with session("fitter") as fitter, session("subtractor") as reader:
            pub = fitter.segment_publisher(RUN, "fit", cache=4)
            for i in range(8):  # the cache keeps 4..7
                pub.put(
                    i,
                    *encode(
                        np.full(24, float(i)), {"run": RUN, "index": i, "t0": 0.0, "fs": 4.0, "producer": "fitter"}
                    ),
                )
            time.sleep(0.5)

            def ask(index, sn):
                """(indices handed on, replies that came over the wire for that query)."""
                import zenoh

                got, replies, done = [], [], threading.Event()
                refetch_segment(
                    reader.session,
                    f"ttl/{RUN}/fit",
                    index,
                    None,
                    lambda s: got.append(parse_header(s.attachment, "fit").index),
                    on_done=lambda n: done.set(),
                    timeout=5.0,
                    sn=sn,
                )
                assert done.wait(10)
                wire = threading.Event()
                selector = f"ttl/{RUN}/fit/@adv/pub/**" + (f"?_sn={sn}..{sn}" if sn is not None else "")
                reader.session.get(  # the very query refetch_segment asks, every reply counted
                    selector,
                    zenoh.handlers.Callback(lambda r: replies.append(r.ok is not None), wire.set),
                    target=zenoh.QueryTarget.ALL,
                    consolidation=zenoh.ConsolidationMode.NONE,
                    accept_replies=zenoh.ReplyKeyExpr.ANY,
                    timeout=5.0,
                )
                assert wire.wait(10)
                return got, len(replies)

            # the publisher's sequence numbers are 0..7 (one put per segment)
            assert ask(6, 6) == ([6], 1)  # one reply: segment 6, not the four cached
            assert ask(2, 2) == ([], 0)  # no longer cached: nothing
            assert ask(6, None) == ([6], 4)  # without the number: the whole cache, filtered here
    finally:
        procs.close()
