"""Model effects: named groups of extra regressors for the TTL fit, and their injections.

An *effect* is a physically motivated set of extra terms in ``eta``, linear in its
parameters, written as regressor columns (docs/diagnostics.md): the diagnosis fits them
(:mod:`ttlcore.diagnose`), the simulator injects them (:mod:`ttlcore.sim.injection`).  One
concept per module:

``columns`` (:class:`Part`, :class:`Column`, :class:`EffectInput`), ``base`` (the
:class:`Effect` base class: what an effect is, asked of it), ``filters`` (filter and
derivative numerics), ``injection`` (an effect injected into the simulator), ``column_tdi``
(TDI of columns) and ``registry`` (lookup by name, plugins, the one reader of effect specs:
``NAME[:key=value,...]``, several separated by ``,``; docs/cli.md, "Effect specs").

One effect per module, as emcee's moves: ``linear_ttl``, ``drift``, ``step``,
``cross_coupling``, ``second_order``; ``witness`` and ``fd_coupling`` on the base ``placed``
(a witness of the library placed on a link); ``timing_offset`` and ``ltt_error`` on the
base ``shifted`` (a witness read at shifted times, and its exact injection); the transients
``glitch`` and ``gate``.

::

    from ttlcore.effects import make_effects, injection_from_spec
    linear, gate = make_effects("linear-ttl,gate:start=15.2h,stop=15.8h")
    inj = injection_from_spec("drift:12.phi.rx=1e-3")
"""

from .base import Effect
from .column_tdi import columns_tdi, effect_input_from_telemetry, tdi_in_blocks
from .columns import Column, EffectInput, Part
from .gate import Gate
from .glitch import Glitch
from .injection import EffectInjection
from .registry import (
    EFFECTS,
    available_effects,
    injection_from_spec,
    load_effect_module,
    make_effects,
    parse_effect_spec,
    split_effects,
)

__all__ = [
    "EFFECTS",
    "Column",
    "Effect",
    "EffectInjection",
    "EffectInput",
    "Gate",
    "Glitch",
    "Part",
    "available_effects",
    "columns_tdi",
    "effect_input_from_telemetry",
    "injection_from_spec",
    "load_effect_module",
    "make_effects",
    "parse_effect_spec",
    "split_effects",
    "tdi_in_blocks",
]
