"""Settings of a diagnosis (:func:`ttlcore.diagnose.diagnoser.diagnose`, ``ttl diagnose``)."""

from __future__ import annotations

import os
from dataclasses import dataclass

from ..errors import ConfigError
from ..tdi.combinations import DEFAULT_DELAY_ORDER
from ..tdi.interpolation import DEFAULT_ORDER
from .adequacy import DEFAULT_ALPHA, DEFAULT_TOLERANCE, DIAGNOSIS_BAND

#: at most this many candidate-scoring threads by default: each holds one candidate's
#: temporaries (a search's products, a segment's spectra), and beyond a few the
#: candidates' lengths, not the threads, set the time (the step-time search alone is a
#: fifth of the total)
MAX_WORKERS = 4


@dataclass(frozen=True)
class DiagnoseSettings:
    """Settings of a diagnosis: a value, built once (``dataclasses.replace`` for another).

    Attributes
    ----------
    band : tuple
        Frequency band [Hz] (default :data:`ttlcore.diagnose.adequacy.DIAGNOSIS_BAND`).
    segment_duration : float or None
        FFT segment length [s]; None: 6 h, or a quarter of shorter data (shortened by a
        few samples to a length whose prime factors are 2, 3, 5 and 7: fast transforms).
    n_bands : int
        Log-spaced bands for the per-band tests.
    time_segment : float
        Length [s] of the time slices of the per-time adequacy (Hann-windowed residual).
    tolerance, alpha : float
        Noise-model tolerance and significance level (:mod:`ttlcore.diagnose.adequacy`).
    noise_model : str
        ``"fitted"``: the secondary-noise levels are fitted with the model
        (:mod:`ttlcore.diagnose.noise_model`, default); ``"fixed"``: the paper's levels (then a
        tolerance of 0.05 is advisable, see docs/diagnostics.md).
    log_bf_threshold : float
        A candidate is significant when its log Bayes factor exceeds this (2.3: odds 10:1)
        *and* its delta chi^2 has p < alpha.
    step_grid, step_refine : float
        Coarse and fine spacing [s] of the step-time search.
    expansion_passes, shift_span : int, float
        Gauss-Newton passes of the shifted-witness effects (``timing-offset``,
        ``ltt-error``), and the half-width [s] of the offset search that starts them.
    witnesses : bool
        Run the witness search.
    dws_asd : float or None
        DWS readout noise [rad/sqrt(Hz)]; None: from the telemetry's configuration.
    workers : int or None
        Threads scoring the candidates side by side
        (:class:`ttlcore.diagnose.candidates.CandidatePool`; the report does not depend on
        it); None: one per core, at most :data:`MAX_WORKERS`.
    """

    band: tuple = DIAGNOSIS_BAND
    segment_duration: float | None = None
    window: str = "tukey:0.1"
    n_bands: int = 8
    time_segment: float = 3600.0
    tolerance: float = DEFAULT_TOLERANCE
    alpha: float = DEFAULT_ALPHA
    noise_model: str = "fitted"
    log_bf_threshold: float = 2.3
    step_grid: float = 3600.0
    step_refine: float = 900.0
    witnesses: bool = True
    top_witnesses: int = 5
    #: distinct top witnesses turned into candidates (witness effect; for DWS witnesses
    #: also fd-coupling with a searched pole pair and with a searched real pole)
    witness_candidates: int = 3
    #: Gauss-Newton passes of the linearised effects in a model (0: Taylor at zero only)
    expansion_passes: int = 3
    #: half-width [s] of the profile search of the offsets of ``timing-offset`` and
    #: ``ltt-error`` (:func:`ttlcore.diagnose.offset_search.offset_search`) that starts those passes
    shift_span: float = 5.0
    #: bands with fewer degrees of freedom are merged with their neighbour, so that the
    #: statistical scatter of chi2/dof in a band (sqrt(2 kappa / dof) = 0.032 at 2000) stays
    #: well inside the +-10 % a correct model must meet
    min_band_dof: int = 2000
    dws_asd: float | None = None
    order: int = DEFAULT_ORDER
    delay_order: int = DEFAULT_DELAY_ORDER
    workers: int | None = None

    def n_workers(self) -> int:
        """The number of candidate-scoring threads: :attr:`workers`, or one per core (at
        most :data:`MAX_WORKERS`)."""
        if self.workers is not None:
            if int(self.workers) < 1:
                raise ConfigError(f"workers must be at least 1, not {self.workers}")
            return int(self.workers)
        return max(1, min(os.cpu_count() or 1, MAX_WORKERS))
