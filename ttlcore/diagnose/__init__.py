"""Model against measurement: effects the model may lack, the adequacy test against the
instrument noise model (with its fitted noise levels), the diagnosis (candidates ranked by
evidence), the profile search of effects' nonlinear parameters, the witness search, the
coefficient trends (drift and step detection) and the reprocessing of many days on Dask.

``effects`` (named effects, witness and frequency-dependent couplings, plugins), ``adequacy``
and ``noise_model`` (the reference the residual is tested against), ``settings``,
``whitened`` (the whitened data, an immutable value), ``columns`` (an effect's whitened
columns), ``model_fit`` (the GLS fit with errors in variables), ``fitting`` (a model of
effects fitted), ``evidence`` (Bayes factors), ``search`` (profile likelihood over nonlinear
parameters: step time, offsets, poles, periods), ``glitches`` (the glitch and gate effects, gated data), ``candidates``, ``report``, ``diagnoser``
(``diagnose``, ``refit``), ``witnesses``, ``trends``, ``reprocess``.
"""

from .effects import EFFECTS
from .glitches import Gate, Glitch

# the transient effects live with their search and gating (glitches imports effects)
EFFECTS.update({Glitch.name: Glitch, Gate.name: Gate})

__all__ = [
    "adequacy",
    "candidates",
    "columns",
    "diagnoser",
    "effects",
    "evidence",
    "fitting",
    "glitches",
    "model_fit",
    "noise_model",
    "report",
    "reprocess",
    "search",
    "settings",
    "trends",
    "whitened",
    "witnesses",
]
