"""The monitor stage (``python -m stages.monitor``, ``ttl stage monitor``) and its parts.

Modules
-------
monitor
    The program: :class:`~stages.monitor.monitor.Monitor`, ASDs, coefficient trends, model
    adequacy and alerts drawn in Rerun, and its ``main``.
options
    Its options (:class:`~stages.monitor.options.MonitorOptions`) and command line.
settling
    When the monitor is done with a segment: waiting for alive producers, and giving up.
status
    Its output ``ttl/<run>/monitor/<i>``: the trend state and the alerts raised since.
epochs
    The model epochs drawn: where the fitter's model changed between two fits.
noise
    The noise view: the ASDs of X2 of each segment.
timeline
    The model timeline drawn beside the coefficient trends.
truth
    The truth drawn beside the fits: the true coefficients averaged over each window.
views
    What is drawn in Rerun, and how the views are laid out (the blueprint).

Nothing is imported here.
"""
