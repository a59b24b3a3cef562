"""Package exports that load their module on first use.

A package's ``__init__`` names its few entry points without importing the modules behind them,
so that importing one light module of a package (``regnf.registration.metrics``) does not load
Open3D, pyrender or the whole package. Usage, in a package's ``__init__``::

    _EXPORTS = {"register": "register", "RegistrationConfig": "register"}  # name -> module
    __all__ = list(_EXPORTS)
    __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any


def lazy_exports(package: str, exports: Mapping[str, str]
                 ) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module-level ``__getattr__`` and ``__dir__`` of ``package``.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    exports : mapping of str to str
        Exported name -> the package's module (relative name) that defines it, or an absolute
        module name (``regnf.``...) for a name a lower package defines and this one re-exports.
    """

    def __getattr__(name: str) -> Any:
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module = exports[name]
        absolute = module.startswith("regnf.")
        value = getattr(importlib.import_module(module if absolute else f"{package}.{module}"), name)
        vars(sys.modules[package])[name] = value  # later look-ups skip __getattr__
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(exports))

    return __getattr__, __dir__
