"""The science commands of ``ttl``: simulate, info, analyze, diagnose, scenarios.

One module per command (``simulate``, ``info``, ``analyze``, ``diagnose``, ``scenarios``:
each a ``run(args)``, named by the parser in ``main``), ``simulation_options`` and
``simulation`` (``ttl simulate``'s options and the configuration they describe),
``progress`` and ``report``.  The work itself is :mod:`ttlcore.app`'s and the science's.
Commands are called from the shell (``ttl ...``, :func:`ttlcore.cli.main.main`); this
package exports no names, so that the parser is built without importing the science.
"""

__all__: list[str] = []
