"""The fitter stage (``python -m stages.fitter``, ``ttl stage fitter``) and its parts.

Modules
-------
fitter
    The program: :class:`~stages.fitter.fitter.Fitter`, rolling one-day fit refit on every
    segment, and its ``main``.
options
    Its options (:class:`~stages.fitter.options.FitterOptions`) and command line.
message
    The fit message's meta, its recorded summary, and what it warns about.
window
    The window of telemetry the model's refits read.
live_model
    The model in force: its effects, its changes, what a restarted fitter restores.
model
    Model changes and restarts: what may change the model, when, and the catch-up.
recordings
    What a restarted fitter reads from the run's recordings.
rolling_model
    An extended model fitted by the rolling fit, the work of one segment.
window_refit
    The window's telemetry refitted with the model, as ``ttl refit`` does.
live_diagnosis
    The window diagnosed as ``ttl diagnose`` would, and its adoption.
schedule
    When the window is diagnosed.

Only :mod:`~stages.fitter.fitter` and :mod:`~stages.fitter.model` touch the bus; the other
parts are values and functions with no bus in them.  Nothing is imported here.
"""
