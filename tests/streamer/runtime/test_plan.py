"""The run's plan and the message validator (streamer.runtime.plan): each rule against a crafted message."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from streamer.bus.codec import Expect, decode, encode
from streamer.bus.keys import from_ranges
from streamer.runtime.plan import Holdback, Plan, RangeSet, Rejected, Validator

FS = 4.0
N = 2400  # 10 min segments
PLAN = Plan(segments_total=30, fs=FS, t0=100.0, samples=N, samples_total=29 * N + 600)


def tdi(index, producer="tdi_builder", n=None, t0=None, fs=FS, data=None):
    n = (PLAN.segment(index)[1] if index < PLAN.segments_total else N) if n is None else n
    rng = np.random.default_rng(index)
    arrays = {
        "data": rng.standard_normal((3, n)) if data is None else data,
        "regressors": rng.standard_normal((3, 2, n)),
    }
    t0 = (PLAN.segment(index)[0] if index < PLAN.segments_total else 0.0) if t0 is None else t0
    fields = {"run": "r", "index": index, "t0": t0, "fs": fs, "channels": ["X2", "Y2", "Z2"], "producer": producer}
    payload, attachment = encode(arrays, fields, allow_nonfinite=True)
    return decode(payload, attachment, Expect(allow_nonfinite=True), key=f"ttl/r/tdi/{index}")


def check(v, msg):
    return v.check("tdi", *msg)


def accept(v, msg):
    assert check(v, msg) == "new"
    v.accepted("tdi", msg[0])


def test_range_set_keeps_ranges_not_indices():
    s = RangeSet()
    for i in (5, 3, 4, 10, 2**40, 11, 0):
        s.add(i)
    assert s.ranges() == [[0, 0], [3, 5], [10, 11], [2**40, 2**40]]
    assert 4 in s and 6 not in s and 2**40 in s and len(s) == 7
    s.add_range(1, 9)
    assert s.ranges() == [[0, 11], [2**40, 2**40]]
    s.discard(5)
    assert s.ranges() == [[0, 4], [6, 11], [2**40, 2**40]]
    assert s.missing(0, 14) == [[5, 5], [12, 14]] and s.covers(6, 11) and not s.covers(0, 6)
    tracemalloc.start()
    big = RangeSet.from_ranges([[0, 2**40], [2**41, 2**62]])
    assert tracemalloc.get_traced_memory()[1] < 100_000 and big.n_ranges == 2
    tracemalloc.stop()
    # the set-valued inverse of to_ranges clips hostile ranges to the plan
    assert from_ranges([[0, 2**40]], limit=30) == set(range(30)) and from_ranges([[-5, 2]]) == {0, 1, 2}


def test_range_set_operations_as_sets():
    """The set operations the progress bookkeeping uses give what plain sets give."""
    rng = np.random.default_rng(3)
    for _ in range(50):
        a, b = (set(rng.integers(0, 40, rng.integers(0, 30)).tolist()) for _ in range(2))
        ra, rb = RangeSet(a), RangeSet(b)
        assert ra | rb == a | b and (ra | b) == a | b and (a | rb) == a | b
        assert ra - rb == a - b and ra - b == a - b and (a - rb) == a - b and isinstance(a - rb, set)
        assert ra.issuperset(b) == a.issuperset(b) and ra.issuperset(rb) == a.issuperset(b)
        assert ra.issuperset(range(5, 12)) == a.issuperset(range(5, 12))
        c = ra.copy()
        c |= rb
        assert c == a | b and ra == a and (ra == RangeSet(a)) and ra.max() == max(a, default=-1)
    assert RangeSet([1, 2]) != {1, 2, 3} and RangeSet().issuperset(range(0))


def test_remembered_copies_bounded_by_the_window():
    """The validator remembers the copies it accepted within the index window only; an older
    copy, identical or not, is refused as too late (nothing of it compared or kept)."""
    plan = Plan(segments_total=1000, fs=FS, t0=100.0, samples=N, samples_total=1000 * N, window=4)
    v = Validator(plan)
    msgs = {}
    for i in range(1000):
        t0, _ = plan.segment(i)
        msgs[i] = m = tdi(i, t0=t0, n=N)
        assert v.check("tdi", *m) == "new"
        v.accepted("tdi", m[0])
        assert len(v.digests) <= 2 * (plan.window + 1)
    assert v.check("tdi", *msgs[999 - 4]) == "duplicate"  # inside the window: compared
    for late in (msgs[999 - 5], tdi(10, t0=plan.segment(10)[0], n=N, data=np.zeros((3, N)))):
        with pytest.raises(Rejected, match="behind the highest accepted segment 999: too late") as err:
            v.check("tdi", *late)
        assert (err.value.kind, err.value.field) == ("rejected", "index")


def test_plan_segments_regular_and_table():
    assert PLAN.segment(0) == (100.0, N) and PLAN.segment(29) == (100.0 + 29 * N / FS, 600)
    p = Plan.from_dict({**PLAN.to_dict(), "segments_total": 2, "table": [[0.0, 10], [50.0, 7]]})
    assert p.segment(1) == (50.0, 7)
    with pytest.raises(ValueError, match="table has 2 rows for 3"):
        Plan.from_dict({**p.to_dict(), "segments_total": 3})
    with pytest.raises(ValueError, match="segments_total"):
        Plan.from_dict({**PLAN.to_dict(), "segments_total": 0})


@pytest.mark.parametrize(
    "change, kind, field",
    [
        ({"producer": "intruder"}, "forged", "producer"),
        ({"index": 30}, "rejected", "index"),  # beyond the run
        ({"fs": 1e6}, "rejected", "fs"),
        ({"t0": 0.0}, "rejected", "t0"),
        ({"n": 10}, "rejected", "arrays[data].shape"),  # a 10-sample segment
        ({"data": np.full((3, N), np.nan)}, "rejected", "arrays[data]"),  # all NaN
    ],
)
def test_each_rule_rejects_and_names_the_field(change, kind, field):
    v = Validator(PLAN)
    index = change.pop("index", 1)
    with pytest.raises(Rejected) as err:
        check(v, tdi(index, **change))
    assert (err.value.kind, err.value.field) == (kind, field), err.value


def test_nan_stretch_is_data_and_window_bounds_the_index():
    v = Validator(Plan.from_dict({**PLAN.to_dict(), "window": 4}))
    data = np.random.default_rng(0).standard_normal((3, N))
    data[:, 100:700] = np.nan  # 150 s with no data: a gap, still a message
    accept(v, tdi(2, data=data))
    assert check(v, tdi(6)) == "new"
    with pytest.raises(Rejected, match="more than 4 ahead"):
        check(v, tdi(7))


def test_duplicates_resolved_by_content():
    v = Validator(PLAN)
    accept(v, tdi(3))
    assert check(v, tdi(3)) == "duplicate"  # identical copy: ignored
    other = tdi(3, data=np.zeros((3, N)))
    with pytest.raises(Rejected) as err:
        check(v, other)
    assert err.value.kind == "conflict"
    with pytest.raises(Rejected, match="conflicting copies"):  # from then on no copy gets in
        check(v, tdi(3))


def test_conflicting_copies_keep_both_out_while_held():
    """A different copy within the hold withdraws the first; after the hold the first was used."""
    v, held = Validator(PLAN), Holdback(1.0)
    first = tdi(3)
    assert check(v, first) == "new"
    v.accepted("tdi", first[0])
    assert held.put("tdi", 3, first, now=10.0) and held.due(now=10.5) == []
    with pytest.raises(Rejected) as err:
        check(v, tdi(3, data=np.zeros((3, N))))
    assert (err.value.kind, err.value.field) == ("conflict", "payload") and "both copies refused" in str(err.value)
    assert held.withdraw("tdi", 3) and held.due(now=20.0) == []  # the first copy never reaches the stage
    with pytest.raises(Rejected, match="conflicting copies"):
        check(v, first)  # nor does any later copy
    # no contender within the hold: the copy comes out, a later different copy cannot withdraw it
    second = tdi(4)
    assert check(v, second) == "new"
    v.accepted("tdi", second[0])
    held.put("tdi", 4, second, now=30.0)
    assert held.due(now=30.99) == [] and held.due(now=31.0) == [second] and len(held) == 0
    with pytest.raises(Rejected, match="both copies refused"):
        check(v, tdi(4, data=np.ones((3, N))))
    assert not held.withdraw("tdi", 4)  # used already: the stage is told so
    assert not Holdback(0).put("tdi", 5, tdi(5), now=0.0)  # no hold: used at once
    with pytest.raises(ValueError, match="hold"):
        Holdback(-1)


def test_without_a_plan_the_first_message_fixes_producer_rate_and_length():
    v = Validator(None)
    accept(v, tdi(0))
    with pytest.raises(Rejected, match="producer"):
        check(v, tdi(1, producer="intruder"))
    with pytest.raises(Rejected, match="fs"):
        check(v, tdi(1, fs=2.0, t0=0.0))
    with pytest.raises(Rejected, match="samples"):
        check(v, tdi(1, n=10))
    with pytest.raises(Rejected, match="ahead"):
        check(v, tdi(2**40 - 1, t0=0.0))
