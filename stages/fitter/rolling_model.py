"""The rolling model: an extended model fitted by the rolling fit, the work of one segment.

Under ``--model-update rolling`` an extended model whose parameters are all given and whose
columns come from the telemetry is fitted between the window refits by the rolling fit
(:class:`ttlcore.estimate.rolling.RollingFit`): the model's columns of each new segment are
computed from its telemetry with :data:`COLUMN_HISTORY` before it
(:func:`ttlcore.diagnose.prediction.column_regressors`) and appended to its 24 TDI
regressors (:meth:`RollingModel.with_columns`).  A fit of them gives the 24 coefficients,
the other parameters and each effect's contribution to X2, Y2, Z2 on the new segment
(:func:`rolling_outputs`).  The model's gates leave their hours out of the rolling fit.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from streamer.bus.messages import concatenate_telemetry
from streamer.tools.refit import refit_settings
from ttlcore.diagnose.prediction import column_regressors
from ttlcore.effects import effect_input_from_telemetry, make_effects
from ttlcore.effects.gate import split_gates
from ttlcore.estimate.fit import FitSettings, with_extra_regressors
from ttlcore.estimate.rolling import RollingFit
from ttlcore.io.telemetry import Telemetry
from ttlcore.tdi.data import TDIData, TDIStream

#: Telemetry [s] before a segment from which the rolling model's columns of that segment are
#: computed: the TDI delays (~70 s), a witness' delay of a few light travel times and the
#: ring-in of a column's filter (an fd-coupling pole at 1 mHz decays in 160 s: 1e-5 of it
#: is left after 1800 s).
COLUMN_HISTORY = 1800.0


class RollingModel:
    """The columns the rolling fit carries for the model in force.

    Parameters
    ----------
    update : str
        ``--model-update``: ``rolling`` (the rolling fit carries the columns of a model that
        allows it) or ``refit`` (never: every segment of an extended model is a window refit).
    band : tuple of float or None
        The fit band [Hz] (None: the default), for the columns' filter orders.
    effect_modules : sequence of str
        Plugin modules defining effects (the stage's configuration).

    Attributes
    ----------
    effects : list or None
        The column effects of the model last asked about (:meth:`column_effects`; None: not
        rollable).
    gates : list
        The spans [s] of that model's gates.
    eiv : dict
        The DWS readouts each column of the latest :meth:`with_columns` carries the noise of
        (a new dict every call: a rolling fit keeps the one it was built with).
    """

    def __init__(self, update: str, band: tuple | None, effect_modules: Sequence[str] = ()):
        self.update = update
        self.band = band
        self.effect_modules = tuple(effect_modules)
        self._key: tuple | None = None
        self.effects: list | None = None
        self.gates: list = []
        self.eiv: dict = {}
        #: column name -> prior scale (:attr:`ttlcore.effects.Column.prior_scale`): a column the
        #: window does not determine better than that is set apart (a glitch whose FFT segments
        #: are left out as outliers; :func:`ttlcore.estimate.gls.set_apart`)
        self.priors: dict = {}

    def column_effects(self, model: list[str]) -> list | None:
        """The effects of ``model`` beyond ``linear-ttl`` whose columns the rolling fit
        carries, or None when it carries the 24 regressors alone: under ``rolling``, an
        extended model whose parameters are all given and whose columns come from the
        telemetry (not the linearised shifts of ``timing-offset`` and ``ltt-error``).  Other
        extended models are refitted on the window every segment."""
        if self.update != "rolling":
            return None
        if model == ["linear-ttl"]:
            # back to the 24 alone (the transients left the window, or a control message):
            # no column of the model before may be rebuilt into the new rolling fit
            self._key, self.effects, self.gates = tuple(model), None, []
            return None
        key = tuple(model)
        if self._key != key:
            gates, effects = split_gates(make_effects(list(model), self.effect_modules))
            ok = all(not e.needs_coefficients and not e.unresolved() for e in effects)
            self.effects = [e for e in effects if not e.is_linear_ttl] if ok else None
            self.gates = [g.span for g in gates]
            self._key = key
        return self.effects

    def with_columns(self, td: TDIData, history: list[Telemetry], tm: Telemetry) -> tuple[TDIData, dict, np.ndarray]:
        """``td`` with the rolling model's columns appended to its 24 regressors.

        The columns' X2, Y2, Z2 (:func:`ttlcore.diagnose.prediction.column_regressors`) are
        computed on ``tm`` with up to :data:`COLUMN_HISTORY` of the contiguous telemetry
        before it (``history``, oldest first), and kept on ``tm``'s samples.  Returns the
        extended TDI, effect spec -> its column names, and the columns (3, k, n)."""
        parts, have = [tm], 0.0
        for prev in reversed(history):
            if have >= COLUMN_HISTORY:
                break
            parts.insert(0, prev)
            have += prev.duration
        tail = concatenate_telemetry(parts) if len(parts) > 1 else tm
        s = refit_settings(None, self.band)
        owners: dict[str, tuple] = {}
        columns = []
        self.eiv = {}  # the DWS readouts each column carries the noise of
        for effect in self.effects or ():
            names, xyz, eiv = column_regressors(tail, effect, order=s.order, delay_order=s.delay_order)
            owners[effect.spec()] = names
            columns.append(xyz[:, :, -tm.size :])
            self.eiv.update(eiv)
            if not all(n in self.priors for n in names):
                self.priors.update({c.name: c.prior_scale for c in effect.columns(effect_input_from_telemetry(tail))})
        xyz = np.concatenate(columns, axis=1)
        names = tuple(n for ns in owners.values() for n in ns)
        extra = TDIData(
            t0=td.t0, fs=td.fs, channels=td.channels, data=td.data, regressors=xyz, names=names, ltt_mean=td.ltt_mean
        )
        return with_extra_regressors(td, extra), owners, xyz

    def new_fit(self, settings: FitSettings, window_duration: float, names: tuple) -> RollingFit:
        """An empty rolling fit for the regressors ``names``: the 24, and the columns of the
        rolling model when it has some (their readout noise and prior scales)."""
        extended = bool(self.effects)
        return RollingFit(
            settings,
            window_duration=window_duration,
            names=names,
            eiv_extra=self.eiv if extended else None,
            prior_scale=self.priors if extended else None,
        )

    def rebuilt(
        self, settings: FitSettings, window_duration: float, names: tuple, window: list[Telemetry]
    ) -> RollingFit:
        """A new rolling fit for the regressors ``names``, the window pushed into it again from
        the window's telemetry (TDI from a new stream, the model's columns with their history):
        when the rolling model's columns change (a model change)."""
        rolling = self.new_fit(settings, window_duration, names)
        stream = TDIStream()
        for j, tm in enumerate(window):
            td = stream.push(tm)
            if self.effects:
                td = self.with_columns(td, window[:j], tm)[0]
            rolling.push(td)
        return rolling


def rolling_outputs(res, td: TDIData, owners: dict, xyz: np.ndarray) -> tuple[dict, dict]:
    """Arrays and meta of a fit of the rolling model: the 24 coefficients (and their
    covariance), ``extra_parameters`` and, for this segment, each effect's contribution
    ``sum_k theta_k TDI(col_k)`` (``model_parts``; zero where a column is not computable)."""
    k = [res.names.index(n) for n in td.names]
    arrays = {
        "coefficients": res.coefficients[k],
        "sigma": res.sigma[k],
        "covariance": res.covariance[np.ix_(k, k)],
    }
    theta = dict(zip(res.names, map(float, res.coefficients)))
    extra = {n: [float(v), float(s)] for n, v, s in zip(res.names, res.coefficients, res.sigma) if n not in td.names}
    col = {n: j for j, n in enumerate(n for ns in owners.values() for n in ns)}
    parts = [
        np.nan_to_num(sum(theta[n] * xyz[:, col[n]] for n in names), nan=0.0, posinf=0.0, neginf=0.0)
        for names in owners.values()
    ]
    arrays["model_parts"] = np.stack(parts)
    return arrays, {"extra_parameters": extra, "model_parts": list(owners), "model_update": "rolling"}


def dropped_columns(old: dict, new: dict, rolling_names: tuple, names: tuple) -> list[str]:
    """The columns a model change only removes from the rolling fit, or none when it adds or
    alters one.

    ``old`` and ``new`` map each column effect's spec to its columns' names (the rolling
    fit's, the new model's); ``rolling_names`` are the rolling fit's regressors, ``names``
    the new model's.  The columns of the effects gone are returned when every effect left
    has the same columns and ``names`` are ``rolling_names`` without them
    (:meth:`ttlcore.estimate.rolling.RollingFit.drop` then keeps the window)."""
    if any(old.get(spec) != cols for spec, cols in new.items()):
        return []
    gone = [n for spec, cols in old.items() if spec not in new for n in cols]
    return gone if tuple(n for n in rolling_names if n not in gone) == tuple(names) else []
