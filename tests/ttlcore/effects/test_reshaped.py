"""Effect.reshaped: which effects of a model have a shape the diagnosis can search again."""

from __future__ import annotations

from ttlcore.effects import make_effects


def _reshaped(spec: str):
    (effect,) = make_effects([spec])
    new = effect.reshaped()
    return None if new is None else new.spec()


def test_a_coupling_with_given_poles_is_searched_again_with_its_placement_kept():
    assert _reshaped("fd-coupling:source=23.phi,link=13,filter=pole1,fc=0.0714692Hz") == (
        "fd-coupling:source=23.phi,link=13,filter=pole1"
    )
    assert _reshaped("fd-coupling:source=21.phi,link=13,f0=0.0726Hz,q=0.5") == "fd-coupling:source=21.phi,link=13"
    # a coupling switched on keeps its switch time (an onset, searched by its own search)
    assert _reshaped("fd-coupling:source=23.phi,link=13,filter=pole1,fc=0.07Hz,vary=step,t_step=178736.8s") == (
        "fd-coupling:source=23.phi,link=13,filter=pole1,vary=step,t_step=178736.8s"
    )
    # a step of the coefficients: its time
    assert _reshaped("step:t_step=50400s") == "step"


def test_effects_without_a_shape_to_search_again():
    for spec in (
        "linear-ttl",  # nothing searched
        "witness:source=23.phi,link=13",
        "fd-coupling:source=23.phi,link=13,filter=pole1",  # not yet searched
        "glitch:t=222327.41s,tm=12,beta=89.54s",  # a transient: searched where it is found
        "gate:start=10h,stop=11h",
        "timing-offset:offset.sc1=0.35s",  # its offsets are searched again at every fit
    ):
        assert _reshaped(spec) is None, spec
