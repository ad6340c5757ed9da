"""Model against measurement: the adequacy test against the instrument noise model (with
its fitted noise levels), the diagnosis (candidates ranked by evidence), the profile search
of effects' nonlinear parameters, the glitch search and gated data, the witness search, the
coefficient trends (drift and step detection) and the reprocessing of many days on Dask.

The effects the diagnosis fits are defined below it, in :mod:`ttlcore.effects`.  Modules:
``adequacy`` and ``noise_model`` (the reference the residual is tested against),
``settings``, ``whitened`` (the whitened data, an immutable value), ``columns`` (an effect's
whitened columns), ``model_fit`` (the GLS fit with errors in variables), ``fitting`` (a
model of effects fitted), ``evidence`` (Bayes factors), ``search`` (profile likelihood over
nonlinear parameters: step time, offsets, poles, periods), ``glitches`` (the glitch
search), ``gating`` (gated data), ``transients`` (the time-frequency map, its events), ``excess`` (their class, the quiet tiles, the report), ``candidates``, ``report``, ``diagnoser``
(``diagnose``, ``refit``), ``diagnosis`` (what they return: ``Diagnosis``, ``Refit``), ``witnesses``, ``trends``, ``prediction``.

::

    from ttlcore.diagnose import DiagnoseSettings, diagnose, text_report

    d = diagnose(tm)  # a Diagnosis: d.adequacy.fails, d.recommendation, d.fit, d.to_json()
    print(d.text())  # the one-minute report; text_report(report) of a JSON report read back
"""

from .diagnoser import diagnose, refit, text_report
from .diagnosis import Diagnosis, Refit
from .settings import DiagnoseSettings

__all__ = ["DiagnoseSettings", "Diagnosis", "Refit", "diagnose", "refit", "text_report"]
