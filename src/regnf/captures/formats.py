"""The one seam between capture formats and the rest: detect a folder's format, read it.

Each format is a module with ``detect(folder) -> bool`` and ``read(path) -> Capture`` (see
:class:`CaptureFormat`); :data:`FORMATS` lists them. A new format is one small module plus one
line here (docs/design.md, extension points).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from regnf.captures import nerfstudio, scannet, sdfstudio
from regnf.captures.model import META_NAME, Capture, CaptureError


@dataclass(frozen=True)
class CaptureFormat:
    """One capture layout regnf reads."""

    name: str
    """Name on the command line (``--capture-format``) and in messages."""
    meta_name: str
    """The metadata file that marks a folder of this format."""
    detect: Callable[[Path], bool]
    """Whether a folder holds a capture of this format."""
    read: Callable[[Path], Capture]
    """Read and check a capture folder (or its metadata file)."""


FORMATS: tuple[CaptureFormat, ...] = (
    CaptureFormat("sdfstudio", META_NAME, sdfstudio.detect, sdfstudio.load_capture),
    CaptureFormat("nerfstudio", nerfstudio.TRANSFORMS_NAME, nerfstudio.detect, nerfstudio.read),
    CaptureFormat("scannet", scannet.INTRINSIC_DEPTH, scannet.detect, scannet.read),
)
"""Every format, in the order detection reports them."""

FORMAT_NAMES = tuple(f.name for f in FORMATS)
"""Names accepted by :func:`read_capture`'s ``format`` (besides ``auto``)."""


def detect_format(path: str | Path) -> CaptureFormat:
    """The format of a capture folder, or of a metadata file named by its path.

    A ``.json`` file is read as the format whose metadata file has its name, else as sdfstudio
    (whose loader takes any name).

    Raises
    ------
    CaptureError
        No format or several formats match; the message names the folder and the files looked for.
    """
    path = Path(os.path.abspath(path))
    if path.suffix == ".json" and not path.is_dir():
        return next((f for f in FORMATS if f.meta_name == path.name), FORMATS[0])
    found = [f for f in FORMATS if f.detect(path)]
    if len(found) == 1:
        return found[0]
    expected = ", ".join(f"{f.meta_name} ({f.name})" for f in FORMATS)
    if not found:
        what = "no such folder" if not path.exists() else "not a capture folder"
        raise CaptureError(f"{path}: {what}: expected one of {expected}")
    both = " and ".join(f"{f.meta_name} ({f.name})" for f in found)
    raise CaptureError(f"{path}: holds {both}; choose one with --capture-format")


def read_capture(path: str | Path, format: str = "auto") -> tuple[Capture, str]:
    """Read a capture folder of any format in :data:`FORMATS`.

    Parameters
    ----------
    path : str or Path
        The capture folder, or its metadata file.
    format : str
        ``auto`` (detect from the folder) or one of :data:`FORMAT_NAMES`.

    Returns
    -------
    Capture
        The capture (normalised frame, ``worldtogt`` to its own metric world).
    str
        The name of the format read.

    Raises
    ------
    CaptureError
        An unknown format name, detection failing (:func:`detect_format`), or the format's
        reader refusing the capture.
    """
    if format == "auto":
        chosen = detect_format(path)
    else:
        chosen = next((f for f in FORMATS if f.name == format), None)
        if chosen is None:
            raise CaptureError(f"unknown capture format {format!r}; expected auto or one of {', '.join(FORMAT_NAMES)}")
    return chosen.read(Path(path)), chosen.name
