"""The simulator injection of an effect (:mod:`ttlcore.sim.injection` protocol).

The columns of an effect, evaluated on the *true* angular velocities of a simulated chunk,
give its injection: the simulator adds ``sum_e theta_e col_e`` to ``eta`` (Tx parts through
the simulator's own delays, :attr:`ttlcore.sim.injection.ChunkContext.delayed_onto_links`),
and the diagnosis sees the same columns built from the noisy DWS readouts - exactly as for
the linear TTL itself.  Effects whose exact form is nonlinear in their parameter carry
their own exact injection (:class:`ttlcore.effects.shifted.ShiftInjection`).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from ..errors import ConfigError
from ..sim.injection import ChunkContext
from .columns import EffectInput


class InjectedEffect(Protocol):
    """What an injection reads of its effect: :class:`ttlcore.effects.base.Effect` is one.

    Named by its shape rather than imported: :mod:`ttlcore.effects.base` imports this module
    (``Effect.injection``), so an import of it here, even for the type checker only, would
    close a circle (tests/test_import_graph.py).
    """

    @property
    def name(self) -> str: ...

    @property
    def options(self) -> dict: ...

    @property
    def integrates_angles(self) -> bool: ...

    def column_names(self) -> list[str]: ...

    def describe(self) -> dict: ...

    def signal(self, data: EffectInput, values: dict, delayed_onto_links, history: int) -> np.ndarray: ...


class EffectInjection:
    """Injection of an effect into the simulator (:mod:`ttlcore.sim.injection` protocol).

    ``values`` maps column names to the true parameter values (column units).
    """

    def __init__(self, effect: InjectedEffect, values: dict, name: str | None = None):
        self.effect = effect
        self.values = {k: float(v) for k, v in values.items()}
        unknown = set(self.values) - set(effect.column_names())
        if unknown:
            raise ConfigError(f"injection of {effect.name!r}: unknown columns {sorted(unknown)[:5]}")
        self.name = name or effect.name
        self._angle: np.ndarray | None = (
            None  # running angle integral (phi, eta) at the last sample of the previous chunk
        )
        self._next_n0 = 0

    def describe(self) -> dict:
        return {"kind": "effect", "name": self.name, **self.effect.describe(), "values": dict(self.values)}

    def _input(self, ctx: ChunkContext) -> EffectInput:
        angle0 = np.zeros((2, 6))
        if self.effect.integrates_angles:
            # angles need the running integral: chunks must come in order (Simulator.chunks)
            if ctx.n0 == 0:
                self._angle = np.zeros((2, 6))
            elif self._angle is None or ctx.n0 != self._next_n0:
                raise ConfigError(
                    f"injection {self.name!r}: second-order terms need the chunks in order from "
                    f"the start (got sample {ctx.n0}, expected {self._next_n0})"
                )
            # angle just before the first history sample: subtract the history's integral
            hist = np.stack([ctx.phi_dot[:, : ctx.h].sum(axis=1), ctx.eta_dot[:, : ctx.h].sum(axis=1)]) / ctx.fs
            angle0 = self._angle - hist
        t_ref = self.effect.options.get("t_ref")
        data = EffectInput(
            t=ctx.t_ext,
            fs=ctx.fs,
            phi_dot=ctx.phi_dot,
            eta_dot=ctx.eta_dot,
            ltt=np.pad(ctx.ltt, ((0, 0), (ctx.h, 0)), mode="edge"),
            coefficients=ctx.coefficients,
            angle0=angle0,
            t_ref=0.0 if t_ref is None else float(t_ref),
        )
        return data

    def link_signal(self, ctx: ChunkContext) -> np.ndarray:
        data = self._input(ctx)
        out = self.effect.signal(data, self.values, ctx.delayed_onto_links, ctx.h)
        if self.effect.integrates_angles:
            phi, eta = data.angles
            self._angle = np.stack([phi[:, -1], eta[:, -1]])
            self._next_n0 = ctx.n0 + ctx.n
        return out
