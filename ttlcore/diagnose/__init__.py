"""Model against measurement: effects the model may lack, the adequacy test against the
instrument noise model, the diagnosis (candidates ranked by evidence), the witness search
and the coefficient trends (drift and step detection).
"""

__all__ = ['adequacy', 'diagnoser', 'effects', 'evidence', 'noise_model', 'reprocess', 'search', 'trends', 'witnesses']
