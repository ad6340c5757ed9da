"""The shape of the pipeline, written once: its stages in order, what each publishes, whom each follows.

==============  ==============  ==================================================
stage           output topic    upstream (whose segments it handles)
==============  ==============  ==================================================
``replayer``    ``telemetry``   (the source: files or a simulation)
``tdi_builder`` ``tdi``         ``replayer``
``fitter``      ``fit``         ``tdi_builder``
``subtractor``  ``residual``    ``tdi_builder`` (and the fitter's fits)
``monitor``     ``monitor``     ``tdi_builder`` (and whatever else it receives)
==============  ==============  ==================================================

Every other list of stages or topics is derived from :data:`PIPELINE`: the launcher's,
``ttl stage``'s choices, the topics of :mod:`streamer.bus.keys`, the producers of
:mod:`streamer.runtime.plan`, the identities of :mod:`streamer.bus.security` and the order of
``ttl inspect``.  Each stage runs as ``python -m stages.<name>`` (:func:`stage_module`).
Adding a stage: a row here and the program ``stages/<name>.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Package holding the stage programs (``stages.<name>``).
STAGE_PACKAGE = "stages"


@dataclass(frozen=True)
class StageSpec:
    """One stage of the pipeline.

    Attributes
    ----------
    name : str
        Stage name: its module ``stages.<name>``, liveliness token, recording and identity.
    output : str
        The segment topic it publishes (``ttl/<run>/<output>/<i>``); no other stage does.
    upstream : str or None
        The stage whose segments it handles: its progress bounds what this stage may claim
        to have handled, and its gaps are this stage's gaps.  None for the source.
    """

    name: str
    output: str
    upstream: str | None


#: The stages of a run, in pipeline order.
PIPELINE = (
    StageSpec("replayer", "telemetry", None),
    StageSpec("tdi_builder", "tdi", "replayer"),
    StageSpec("fitter", "fit", "tdi_builder"),
    StageSpec("subtractor", "residual", "tdi_builder"),
    StageSpec("monitor", "monitor", "tdi_builder"),
)

#: Stage names, in pipeline order.
STAGES: tuple[str, ...] = tuple(s.name for s in PIPELINE)
#: Output topic of each stage.
OUTPUT_TOPIC: dict[str, str] = {s.name: s.output for s in PIPELINE}
#: The stage that owns (publishes) each segment topic: the inverse of :data:`OUTPUT_TOPIC`.
PRODUCERS: dict[str, str] = {s.output: s.name for s in PIPELINE}
#: The stage whose segments each stage handles (the source has none).
UPSTREAM: dict[str, str] = {s.name: s.upstream for s in PIPELINE if s.upstream is not None}


def stage_module(name: str) -> str:
    """``stages.<name>``: the module a stage runs as (``python -m stages.<name>``)."""
    return f"{STAGE_PACKAGE}.{name}"
