"""A contact sheet of a capture: evenly spaced frames, colour above depth, each labelled with its index.

Depth is coloured with viridis from the capture's 1st to 99th depth percentile (near dark blue,
far yellow); a pixel without depth is :data:`UNKNOWN_COLOUR`, a colour viridis never gives.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from regnf.captures.model import Capture
from regnf.captures.selection import evenly_spaced
from regnf.core.image_io import write_rgb_png

SHEET_FRAMES = 24
"""Frames on a contact sheet at most."""

SHEET_COLUMNS = 6
"""Frames per row of the sheet."""

THUMB_WIDTH = 160
"""Width of each thumbnail, pixels."""

LABEL_HEIGHT = 14
"""Height of the strip above each frame that holds its index, pixels."""

GAP = 4
"""Space between frames, pixels."""

UNKNOWN_COLOUR = (255, 0, 255)
"""Colour of a pixel without depth (magenta)."""

BACKGROUND = (32, 32, 32)
"""Colour of the sheet between the frames."""


def sheet_frames(capture: Capture, limit: int = SHEET_FRAMES) -> list[int]:
    """At most ``limit`` frame indices, evenly spaced over the capture, first and last included."""
    return [int(i) for i in evenly_spaced(len(capture.frames), limit)]


def colour_depth(depth_m: np.ndarray | None, near: float, far: float, shape: tuple[int, int]) -> np.ndarray:
    """(h, w, 3) uint8 viridis of ``depth_m`` (metres) between ``near`` and ``far``; :data:`UNKNOWN_COLOUR` where 0.

    ``depth_m`` None (a frame without depth) is all unknown, of ``shape``.
    """
    from matplotlib import colormaps

    if depth_m is None:
        return np.broadcast_to(np.array(UNKNOWN_COLOUR, np.uint8), (*shape, 3)).copy()
    t = np.clip((depth_m - near) / max(far - near, 1e-9), 0.0, 1.0)
    rgb = (colormaps["viridis"](t)[..., :3] * 255.0).round().astype(np.uint8)
    rgb[~(depth_m > 0)] = UNKNOWN_COLOUR
    return rgb


def write_contact_sheet(capture: Capture, path: str | os.PathLike, near: float, far: float,
                        frames: Sequence[int] | None = None) -> Path:
    """Write the contact sheet of ``capture`` to ``path`` (PNG, atomically; its folder is made).

    Parameters
    ----------
    capture : Capture
    path : str or PathLike
    near, far : float
        Depth (metres) at the two ends of the colour scale.
    frames : sequence of int, optional
        Frames to show, in order; default :func:`sheet_frames`.

    Raises
    ------
    CaptureError
        An unreadable or invalid image or depth file.
    """
    frames = sheet_frames(capture) if frames is None else list(frames)
    tw = THUMB_WIDTH
    th = max(1, round(tw * capture.height / capture.width))
    cols = min(SHEET_COLUMNS, max(1, len(frames)))
    rows = math.ceil(len(frames) / cols)
    cell_w, cell_h = tw + GAP, LABEL_HEIGHT + 2 * th + GAP
    sheet = Image.new("RGB", (cols * cell_w + GAP, rows * cell_h + GAP), BACKGROUND)
    draw = ImageDraw.Draw(sheet)
    for k, i in enumerate(frames):
        x, y = GAP + (k % cols) * cell_w, GAP + (k // cols) * cell_h
        colour = (capture.rgb(i) * 255.0).round().astype(np.uint8)
        depth = capture.depth(i)
        depth_m = None if depth is None else depth * np.float32(capture.scale)
        shaded = colour_depth(depth_m, near, far, (capture.height, capture.width))
        draw.text((x + 2, y + 1), f"frame {i} ({capture.frames[i].split})", fill=(230, 230, 230))
        sheet.paste(Image.fromarray(colour).resize((tw, th), Image.Resampling.BILINEAR), (x, y + LABEL_HEIGHT))
        # Nearest: a pixel without depth keeps its own colour, never blended into a depth colour.
        sheet.paste(Image.fromarray(shaded).resize((tw, th), Image.Resampling.NEAREST), (x, y + LABEL_HEIGHT + th))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_rgb_png(path, np.asarray(sheet))
