"""One grammar for every effect spec, printed as it is typed, with units (issue 35, "Effect
specs do not round-trip"; docs/cli.md, "Effect specs").

``NAME[:key=value,...]``, several effects separated by ``,`` too, in ``--effects``,
``--inject``, ``ttl refit``, ``ttl control ... model``, configs and every report.  Each
registered effect's :meth:`~ttlcore.effects.base.Effect.spec` parses back to the same
effect, alone and in a list; the former spelling (``;`` between one effect's options) still
parses; a real ``ttl diagnose`` prints nothing that cannot be pasted back; the error
messages that suggest a spelling suggest one that parses.
"""

from __future__ import annotations

import argparse
import json
import re
import shlex

import numpy as np
import pytest

from streamer.tools.parsers import register
from ttlcore.cli.main import build_parser, main
from ttlcore.conventions import (
    COEFFICIENT_NAMES,
    format_frequency,
    format_time,
    parse_duration,
    parse_frequency,
    parse_time,
)
from ttlcore.effects import (
    EFFECTS,
    EffectInput,
    Gate,
    Glitch,
    injection_from_spec,
    make_effects,
    parse_effect_spec,
    split_effects,
)
from ttlcore.effects.fd_coupling import FrequencyCoupling
from ttlcore.effects.step import Step
from ttlcore.effects.timing_offset import TimingOffset
from ttlcore.errors import ConfigError

#: Representative effects of every registered name: options given, searched options filled
#: (as the diagnosis fills them), glitches, gates, steps, witnesses, fd-couplings with
#: filters, timing offsets.
EXAMPLES = [
    "linear-ttl",
    "linear-ttl:mosas=12+13,angles=phi,sides=rx",
    "drift",
    "drift:mosas=12,t_ref=1d",
    "drift:t_ref=43200.25",
    "step:t_step=15.2h,mosas=12+13",
    "step:t_step=-10min,sides=tx",
    Step().with_options(t_step=round(259198.7573, 3)),  # a searched step time
    "cross-coupling:sides=tx",
    "cross-coupling:mosas=12+23,angles=eta",
    "timing-offset",
    "timing-offset:per=mosa,offset.12=0.35,offset.21=-1.5e-3",
    TimingOffset().with_options(**{"offset.sc1": 0.350123}),  # a searched offset, 6 digits
    "ltt-error:links=12+21,offset.12=-0.2",
    "ltt-error:offset.31=-0.36368s,offset.21=-0.360132s",
    "second-order",
    "second-order:terms=phiphi+etaeta,offset_phi=1e-5,offset_eta=-2e-6",
    "witness:source=23.phi,delay=2",
    "witness:source=12.eta,link=23,delay=1,derivative=1",
    "witness:source=12.phieta,link=21,delay=1",
    "witness:mosas=12,angles=phi,sides=rx,vary=cycle,period=7200",
    "witness:source=23.eta,link=31,vary=cycle,t_ref=0",
    "witness:source=23.eta,link=31,vary=step,t_step=3h",
    "witness:source=23.eta,link=31,vary=drift,t_ref=1800",
    "fd-coupling:source=13.eta,link=31,delay=1,filter=pole1,fc=0.0130453",
    "fd-coupling:source=12.eta,link=21,delay=1,f0=0.00896699Hz,q=43.7422",
    "fd-coupling:mosas=12,flat=keep",
    "fd-coupling:source=23.eta,vary=cycle,period=6h",
    FrequencyCoupling(source="12.phi", link="23", delay=1).with_options(f0=0.0114316, q=0.5),
    "glitch",
    "glitch:t=2.7h,tm=12,beta=35",
    "glitch:t=-480,link=23,beta=5.5",
    "glitch:span=9000-11000",
    "glitch:span=-480.0-2.5h,tm=21",
    Glitch(span="100.0-3600.0").with_options(t=9734.251, beta=31.2, tm="12"),  # searched
    "gate:start=15.2h,stop=15.8h",
    "gate:start=1800,stop=2880,taper=600",
    Gate(start=28711.0, stop=30646.0),
    Gate(start=round(28786.4), stop=round(30720.6)),
]


def _effect(example):
    return example if not isinstance(example, str) else make_effects(example)[0]


def _options(spec: str) -> list[tuple[str, str]]:
    return [tuple(o.split("=", 1)) for o in spec.partition(":")[2].split(",") if o]


def test_every_registered_effect_has_an_example():
    assert {_effect(x).name for x in EXAMPLES} == set(EFFECTS)


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda x: x if isinstance(x, str) else f"{x.name}-filled")
def test_the_spec_parses_back_to_the_same_effect(example):
    effect = _effect(example)
    spec = effect.spec()
    (back,) = make_effects(spec)
    assert back.describe() == effect.describe(), spec
    assert back.column_names() == effect.column_names(), spec
    assert back.spec() == spec and effect.cli_spec() == spec and ";" not in spec
    # the old spelling: ';' between one effect's options
    old = spec.replace(",", ";")
    assert make_effects(old)[0].describe() == effect.describe(), old
    assert make_effects(f"linear-ttl,{old}")[1].describe() == effect.describe(), old
    # a time carries its unit, a frequency its hertz
    for key, value in _options(spec):
        unit = effect.option_unit(key)
        if unit == "s":
            assert re.fullmatch(r"-?[0-9.e+-]+(s|h|d)", value), (key, value)
            assert parse_time(value) == effect.options[key]
        elif unit == "Hz":
            assert value.endswith("Hz") and parse_frequency(value) == effect.options[key]
        elif key == "span":
            assert all(re.search(r"(s|h|d)$", t) for t in re.split(r"(?<=[a-z])-", value)), value


def test_a_list_of_specs_parses_back_to_the_same_list():
    effects = [_effect(x) for x in EXAMPLES]
    text = ",".join(e.spec() for e in effects)
    back = make_effects(text)
    assert [e.describe() for e in back] == [e.describe() for e in effects]
    assert split_effects(text) == [e.spec() for e in effects]
    # the old spelling of the same list, and a list given as a list of strings
    old = ",".join(e.spec().replace(",", ";") for e in effects)
    assert [e.describe() for e in make_effects(old)] == [e.describe() for e in effects]
    assert [e.spec() for e in make_effects([e.spec() for e in effects])] == split_effects(text)


def test_the_grammar_splits_on_names_not_on_options():
    text = "linear-ttl,gate:start=15.2h,stop=15.8h,drift:mosas=12+13,12.phi.rx=0.05,all=1e-3,timing-offset"
    assert split_effects(text) == [
        "linear-ttl",
        "gate:start=15.2h,stop=15.8h",
        "drift:mosas=12+13,12.phi.rx=0.05,all=1e-3",
        "timing-offset",
    ]
    # the command lines: the one spelling and the former one
    assert split_effects("linear-ttl,gate:start=15.2h;stop=15.8h") == ["linear-ttl", "gate:start=15.2h,stop=15.8h"]
    eff, values = parse_effect_spec("drift:mosas=12+13,12.phi.rx=0.05")
    assert eff.mosas == ("12", "13") and values == {"drift.12.phi.rx": 0.05}
    for bad, match in (
        ("mosas=12", "before any effect"),
        ("drift,mosas=12", "write drift:mosas=12"),
        ("linear-ttl:mosas=12,13", "joined by '\\+'"),
    ):
        with pytest.raises(ConfigError, match=match):
            make_effects(bad)
    with pytest.raises(ConfigError, match="expected one effect, got 2"):
        parse_effect_spec("drift,timing-offset")
    # --inject: the same grammar, several effects in one option
    from ttlcore.cli.simulation import _effect_injections

    two = "glitch:t=3h,tm=12,beta=35s,all=1e-9,glitch:t=5h;tm=21;beta=20s;all=2e-9"
    first, second = _effect_injections(argparse.Namespace(inject=[two], effect_module=[]))
    assert first.values == {"glitch.tm12@10800.0": 1e-9} and second.values == {"glitch.tm21@18000.0": 2e-9}
    assert (first.name, second.name) == ("glitch", "glitch-2")


def test_times_and_frequencies_print_exactly():
    rng = np.random.default_rng(35)
    values = [0.0, 1800.0, 54720.0, 86400.0, 129600.0, 9734.25, -480.0, 1e-3, 0.350123, 7e5 + 1 / 3]
    values += list(rng.uniform(-1e6, 1e6, 200)) + list(np.round(rng.uniform(0, 1e6, 200), 1))
    for v in values:
        text = format_time(v)
        assert parse_time(text) == v and text[-1] in "shd", (v, text)
        if v > 0:
            assert parse_duration(text) == v
    assert [format_time(v) for v in (1800.0, 54720.0, 86400.0, 7200.0, 300.0)] == ["1800s", "15.2h", "1d", "2h", "300s"]
    for f in (0.0718, 0.00896699, 1.0, 2.5e-3, *rng.uniform(1e-3, 2, 50)):
        assert parse_frequency(format_frequency(f)) == f
    assert parse_frequency("71.8mHz") == pytest.approx(0.0718)


# ------------------------------------------------------------------ a real `ttl diagnose`


@pytest.fixture(scope="module")
def diagnosed(tmp_path_factory):
    """Two hours with a test-mass glitch and a DWS timing offset, diagnosed with a model typed
    partly in the former spelling (the issue's), with a gate, a searched step, searched
    offsets and a witness: the report prints every kind of spec (effects, searched ones,
    candidates, witnesses, the glitch's action, the advice's option)."""
    tmp = tmp_path_factory.mktemp("spec")
    data = tmp / "d.h5"
    argv = ["simulate", "--duration", "2h", "--orbit", "keplerian", "--seed", "3", "--telemetry", str(data)]
    argv += ["--inject", "glitch:t=3000s,tm=12,beta=30s,all=3e-10", "--inject", "timing-offset:sc1.d1=0.3"]
    assert main([*argv, "--quiet"]) == 0
    effects = "linear-ttl,gate:start=1.5h;stop=1.6h;taper=300s,step:mosas=12,witness:source=23.phi;delay=2"
    out = tmp / "r.json"
    return data, tmp, effects, out, ["diagnose", str(data), "--effects", effects, "--json", str(out), "--quiet"]


def _printed_specs(report: dict) -> tuple[list[str], list[str], list[str]]:
    """(specs of one effect, comma-separated lists of effects, ``--effects`` options) of a
    JSON report: every ``spec``/``cli_spec``, every element of ``effects``/``added``/
    ``removed``, the keys of ``searched``, every ``cli_effects`` and ``option``."""
    found: tuple[list[str], list[str], list[str]] = ([], [], [])
    _walk(report, None, found)
    return found


def _walk(x, key, found: tuple) -> None:
    """The specs printed in ``x`` (under ``key``) into ``found`` (:func:`_printed_specs`)."""
    if isinstance(x, dict):
        if key == "searched":
            found[0].extend(k for k in x if k.split(":")[0] in EFFECTS)
        for k, v in x.items():
            _walk(v, k, found)
    elif isinstance(x, list):
        if key in ("effects", "added", "removed") and all(isinstance(v, str) for v in x):
            found[0].extend(x)
        else:
            for v in x:
                _walk(v, key, found)
    elif isinstance(x, str) and x:
        _take_string(x, key, found)


def _take_string(x: str, key, found: tuple) -> None:
    """A string under ``key``: a spec (``spec``, ``cli_spec``), a list of effects
    (``cli_effects``) or an ``--effects`` option (``option``); anything else is not a spec."""
    one, many, options = found
    if key in ("spec", "cli_spec"):
        one.append(x)
    elif key == "cli_effects":
        many.append(x)
    elif key == "option":
        options.append(x)


def test_a_real_diagnosis_prints_only_specs_that_paste_back(diagnosed, capsys):
    data, tmp, effects, out, argv = diagnosed
    capsys.readouterr()
    assert main(argv[:-1]) == 0  # the text report on standard output, the JSON in a file
    text = capsys.readouterr().out
    report = json.loads(out.read_text())
    one, many, options = _printed_specs(report)
    kinds = {s.split(":")[0] for s in one}
    assert {"linear-ttl", "gate", "step", "timing-offset", "ltt-error", "witness", "glitch"} <= kinds, kinds
    assert any(re.search(r"offset\.\w+=-?[0-9.e-]+s\b", x) for x in one), one  # searched offsets, in s
    assert any(s.startswith("step:") and "t_step=" in s for s in report["model"]["effects"])  # searched, filled
    assert options and many
    for spec in one:
        (effect,) = make_effects(spec)
        assert effect.spec() == spec, spec  # printed exactly as it parses (units and all)
    for value in many:
        assert ",".join(e.spec() for e in make_effects(value)) == value
    for option in options:
        flag, value = shlex.split(option)
        assert flag == "--effects" and ",".join(e.spec() for e in make_effects(value)) == value
    # the model as typed: the one spelling of the former, printed as typed in the new one
    assert "gate:start=1.5h,stop=1.6h,taper=300s" in report["model"]["effects"]
    assert "witness:source=23.phi,delay=2" in report["model"]["effects"]
    assert [e.spec() for e in make_effects(report["model"]["cli_effects"])] == report["model"]["effects"]

    # the text report: the model, the change, the candidates and the next step
    head = re.match(r".*?: model (.*) \(\d+ parameters\)", text.splitlines()[0]).group(1)
    assert [e.spec() for e in make_effects(head)] == head.split(", ")
    change = re.search(r"before -> after \((.*)\):", text).group(1)
    assert [e.spec() for e in make_effects(change)] == change.split(", ")
    labels = re.findall(r"^    [* ] (\S+)\s+-?[0-9.]+ / ", text, flags=re.M)
    assert labels and all(make_effects(x)[0].spec() == x for x in labels), labels
    assert "offsets sc1 +0.3" in text and " s" in text  # the searched offsets with their unit
    step_line = next(x for x in text.splitlines() if "best next step" in x)
    cmd = shlex.split(step_line.split(":  ", 1)[1])
    assert cmd[:3] == ["ttl", "diagnose", str(data)] and cmd[3] == "--effects"
    # run as printed: the model it fits is the one the option spells (a searched option, as
    # the step's time, filled in by the search)
    again = tmp / "again.json"
    assert main([*cmd[1:], "--json", str(again), "--no-witnesses", "--candidates", "drift", "--quiet"]) == 0
    fitted = make_effects(json.loads(again.read_text())["model"]["effects"])
    asked = make_effects(cmd[4])
    assert sorted(e.name for e in fitted) == sorted(e.name for e in asked)
    for e in asked:
        unset = [f.with_options(**dict.fromkeys(e.unresolved())).spec() for f in fitted if f.name == e.name]
        assert e.spec() in unset, (e.spec(), unset)


# ------------------------------------------------------------------ suggested spellings


def _suggestions(message: str) -> list[str]:
    """The spellings a message suggests after ``e.g.`` (``X`` or ``X or Y``; a quoted one as
    a shell reads it)."""
    m = re.search(r"e\.g\. (?:--inject )?('[^']+'|[^ ;)]+)(?: or ([^ ;)]+))?", message)
    assert m, message
    return [shlex.split(s)[0] for s in m.groups() if s]


def _error(call) -> str:
    with pytest.raises(ConfigError) as exc:
        call()
    return str(exc.value)


def test_the_spellings_error_messages_suggest_parse():
    data = EffectInput(
        t=np.arange(64.0),
        fs=1.0,
        phi_dot=np.zeros((6, 64)),
        eta_dot=np.zeros((6, 64)),
        ltt=np.full((6, 64), 8.3),
        coefficients=np.zeros(len(COEFFICIENT_NAMES)),
    )
    for message in (
        _error(lambda: make_effects("gate:start=1h")),
        _error(lambda: Step().columns(data)),
        _error(lambda: make_effects("glitch:span=soon")),
    ):
        for spec in _suggestions(message):
            assert make_effects(spec), message
    # --inject without a value: the suggestion is an injection that parses
    for spec in ("drift", "glitch:t=3h,tm=12,beta=35", "fd-coupling:source=12.phi,link=23,f0=0.05,q=3"):
        message = _error(lambda spec=spec: injection_from_spec(spec))
        (suggested,) = _suggestions(message)
        assert injection_from_spec(suggested).values, message
    # a bad offset: the values suggested read as offsets
    message = _error(lambda: make_effects("timing-offset:offset.sc1=late"))
    for value in re.findall(r"'([^']+)'", message.split("e.g.", 1)[1]):
        assert make_effects(f"timing-offset:offset.sc1={value}")[0].fixed_offsets()
    # options after an effect without ':', and a list value split by ','
    for bad in ("drift,mosas=12", "linear-ttl:mosas=12,13"):
        message = _error(lambda bad=bad: make_effects(bad))
        fix = re.search(r"write (\S+)\)|'\+': (\S+)\)", message)
        assert fix, message
        assert make_effects(fix.group(1) or "linear-ttl:" + fix.group(2))


def _help_examples(parser: argparse.ArgumentParser) -> list[str]:
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                out += _help_examples(sub)
        elif {"--effects", "--inject"} & set(action.option_strings) and "e.g." in (action.help or ""):
            out += _suggestions(action.help)
    return out


def test_the_help_examples_of_effect_options_parse():
    from stages.fitter.options import add_options

    fitter = argparse.ArgumentParser()
    add_options(fitter)
    examples = _help_examples(build_parser(register)) + _help_examples(fitter)
    assert len(examples) >= 4, examples
    for spec in examples:
        effects, values = [], []
        for one in split_effects(spec):
            effect, v = parse_effect_spec(one)
            effects.append(effect)
            values.append(v)
        assert effects, spec
