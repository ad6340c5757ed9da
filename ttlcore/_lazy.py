"""A package face whose names are imported on first use (PEP 562).

The faces of :mod:`ttlcore`, :mod:`ttlcore.io` and :mod:`ttlcore.tdi` name what a notebook
calls without importing it: ``import ttlcore.io.atomic`` (the stages' atomic writes) or
``ttl --help`` must not pull in h5py, scipy and the TDI engine.
"""

import importlib
from collections.abc import Callable, Mapping

__all__ = ["lazy_face"]


def lazy_face(package: str, exports: Mapping[str, str], namespace: dict) -> tuple[Callable, Callable]:
    """The ``__getattr__`` and ``__dir__`` of a package whose names live in its modules.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    exports : mapping
        Name -> module relative to the package (``"read_telemetry": "reader"``); a name that is
        itself a sub-module or sub-package maps to itself (``"diagnose": "diagnose"``).
    namespace : dict
        The package's ``globals()``: a name, once imported, is bound there, so later look-ups
        do not come back to ``__getattr__``.
    """

    def __getattr__(name: str):
        try:
            module = importlib.import_module(f".{exports[name]}", package)
        except KeyError:
            raise AttributeError(f"module {package!r} has no attribute {name!r}") from None
        value = module if exports[name] == name else getattr(module, name)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(exports))

    return __getattr__, __dir__
