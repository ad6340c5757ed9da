"""The model epochs the monitor draws: where the fitter's model changed between two fits.

A fit message's meta ``model`` lists the effects its coefficients were estimated under.  When
it changes, the fitter has rebuilt its window under another model and the estimates jump by
what the old model got wrong, not by anything the coefficients did.  The trend tests
(:class:`ttlcore.diagnose.trends.TrendMonitor`) then start a new series (a change of the
couplings: a new *model epoch*) or leave the one difference across the change out (a change
of the transients ``glitch`` and ``gate`` only; the reasons are in
:mod:`ttlcore.diagnose.trends`, "Model epochs").  :class:`ModelEpochs` follows the same rule
over the fits as they are drawn, so that the monitor draws what the tests do:

* the coefficient lines are broken between the last fit under the old model and the first
  under the new one (an ``rr.Clear`` of the 24 coefficient entities: a time series plot
  draws a clear as a hole), and a new epoch's fits are drawn in the epoch's colour
  (:func:`stages.monitor.views.epoch_style`);
* a line of the model log says what changed and what the trends do about it;
* the run summary lists the epochs and the changes of transients (:attr:`ModelEpochs.lines`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from streamer.bus.fit_record import FitMessage
from streamer.tools.model_timeline import model_delta
from ttlcore.diagnose.trends import model_key

from .views import days


@dataclass(frozen=True)
class Change:
    """A change of the model between two fits as drawn.

    ``new_epoch``: the couplings changed (a new series); else the transients only.
    ``number``: the model epoch from this fit on.  ``t_break``: mission time [s] between the
    centres of the two fits' windows, where the coefficient lines are broken; None for the
    first model of the run (nothing to break: only its line of the model log, when it is
    not the plain ``linear-ttl``).
    """

    index: int
    new_epoch: bool
    number: int
    t_break: float | None
    message: str


class ModelEpochs:
    """The model of the fits drawn so far and its epochs (in the order the fits are drawn; a
    fit that comes late, its window's centre before the latest drawn, changes nothing)."""

    def __init__(self):
        self.model: list | None = None
        self.number = 0
        self.centre: float | None = None
        self.lines: list[str] = []  # for the run summary: every epoch and change of transients

    def fit(self, index: int, model, centre: float, t_stop: float) -> Change | None:
        """The fit ``index`` (meta ``model``, its window's centre and end [s]) is about to be
        drawn: the change of model it brings, if any."""
        key = model_key(model)
        if self.centre is not None and centre <= self.centre:
            return None  # a fit that came late
        if key is None:  # no model in the meta: the one before holds
            self.centre = centre
            return None
        before, before_key, last = self.model, model_key(self.model), self.centre
        self.model, self.centre = list(model), centre
        if before is None or before_key is None:  # the first model seen (model_key(None) is None)
            self.lines.append(f"epoch 0 from fit {index}: {', '.join(model)}")
            if list(model) == ["linear-ttl"]:
                return None
            return Change(index, False, 0, None, f"fit {index}: model {','.join(model)}")
        if key == before_key:
            return None
        added, removed, couplings = model_delta(before, model)
        what = "; ".join(
            [f"added {', '.join(added)}"] * bool(added) + [f"removed {', '.join(removed)}"] * bool(removed)
        )
        head = f"fit {index}: model {','.join(before)} -> {','.join(model)}"
        if couplings:
            self.number += 1
            self.lines.append(f"epoch {self.number} from fit {index} (window end {days(t_stop)}): {', '.join(model)}")
            message = (
                f"{head}: couplings changed ({what}): the coefficient trends start a new series "
                f"(model epoch {self.number}); the step and drift tests start again"
            )
        else:
            self.lines.append(f"transients changed at fit {index} ({what}): the series goes on")
            message = (
                f"{head}: transients changed ({what}): the coefficient trends go on; the difference "
                "across the change is not tested"
            )
        t_break = centre if last is None else 0.5 * (last + centre)
        return Change(index, couplings, self.number, t_break, message)


def trend_estimate(meta: FitMessage, coefficients: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The coefficients and sigmas [m/rad] the trend tests follow for a fit: the rolling fit's
    (meta ``rolling``, :func:`stages.fitter.message.rolling_estimate`) when the published fit is a
    window refit that replaced it, so that the series holds one estimator (the daily switch
    between the two read as a step); the published ones otherwise."""
    rolling = meta.rolling
    if rolling is not None:
        c = np.asarray(rolling.coefficients, dtype=float)
        s = np.asarray(rolling.sigma, dtype=float)
        if c.shape == coefficients.shape and s.shape == sigma.shape:
            return c, s
    return coefficients, sigma
