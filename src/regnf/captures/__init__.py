"""Reading and writing captures: posed RGB-D frames in a capture's own metric world.

One small module per format (:mod:`~regnf.captures.sdfstudio`, :mod:`~regnf.captures.nerfstudio`,
:mod:`~regnf.captures.scannet`)
behind one seam, :func:`read_capture` (:mod:`regnf.captures.formats`); all produce the same
in-memory :class:`Capture` (:mod:`regnf.captures.model`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from regnf.core.lazy_exports import lazy_exports

_EXPORTS: dict[str, str] = {
    "FORMATS": "formats",
    "detect_format": "formats",
    "read_capture": "formats",
    "Instance": "instance",
    "Capture": "model",
    "CaptureError": "model",
    "CaptureFrame": "model",
    "load_capture": "sdfstudio",
    "write_capture": "sdfstudio",
}

__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)


if TYPE_CHECKING:  # static analysers see the real names
    from regnf.captures.formats import FORMATS, detect_format, read_capture
    from regnf.captures.instance import Instance
    from regnf.captures.model import Capture, CaptureError, CaptureFrame
    from regnf.captures.sdfstudio import load_capture, write_capture
