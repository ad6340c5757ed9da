"""Model against measurement: effects the model may lack, the adequacy test against the
instrument noise model (with its fitted noise levels), the diagnosis (candidates ranked by
evidence), the profile search of effects' nonlinear parameters, the witness search, the
coefficient trends (drift and step detection) and the reprocessing of many days on Dask.

``effects`` (named effects, witness and frequency-dependent couplings, plugins), ``adequacy``
and ``noise_model`` (the reference the residual is tested against), ``diagnoser`` (fits,
candidates, the report), ``search`` (profile likelihood over nonlinear parameters),
``evidence`` (Bayes factors), ``witnesses``, ``trends``, ``reprocess``.
"""

__all__ = ['adequacy', 'diagnoser', 'effects', 'evidence', 'noise_model', 'reprocess', 'search', 'trends', 'witnesses']
