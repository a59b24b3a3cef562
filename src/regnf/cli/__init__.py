"""The command line: ``regnf`` and its commands (:func:`main`).

Names load their module on first use (:mod:`regnf.core.lazy_exports`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from regnf.core.lazy_exports import lazy_exports

_EXPORTS = {
    "main": "app",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static analysers see the real names
    from .app import main
