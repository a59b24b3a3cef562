"""The web viewer of a stage (``regnf view``): proxies, instances, progressive compositor renders,
pose correction and new instances (:func:`serve`, :class:`StageViewer`, :class:`ViewerConfig`).

Names load their module on first use (:mod:`regnf.core.lazy_exports`), so that the command line
does not load viser until a viewer starts.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from regnf.core.lazy_exports import lazy_exports

_EXPORTS = {
    "serve": "stage_viewer",
    "StageViewer": "stage_viewer",
    "ViewerConfig": "viewer_config",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static analysers see the real names
    from .stage_viewer import StageViewer, serve
    from .viewer_config import ViewerConfig
