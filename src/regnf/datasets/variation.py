"""Appearance variation of generated variants: exposure and white balance, drawn from the seed.

A variant's views are rendered as the fields show the room; a camera's exposure and white
balance then vary per variant: every pixel's linear colour (sRGB decoded) is multiplied by
``2 ** stops`` and a gain per channel, and encoded again. ``stops`` is drawn uniformly from
``[-exposure_stops, exposure_stops]`` and each channel's gain from ``[1 - white_balance,
1 + white_balance]``, the three gains then divided by their mean (white balance moves the
colour, not the brightness), from a random stream of the variant's seed of its own (the
replacements a seed picks do not change). What was drawn is recorded in the manifest row.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
from PIL import Image

from regnf.core.atomic_io import atomic_path
from regnf.core.errors import RegnfError
from regnf.core.srgb import linear_to_srgb, srgb_to_linear

STREAM = 7
"""Second seed word of the appearance's random stream (``default_rng([seed, STREAM])``)."""


class Appearance(NamedTuple):
    """One variant's camera appearance."""

    stops: float
    """Exposure change, stops (a factor ``2 ** stops`` on linear colour)."""
    gains: tuple[float, float, float]
    """White-balance gain of each channel (mean 1)."""

    @property
    def identity(self) -> bool:
        """Nothing changes."""
        return self.stops == 0.0 and self.gains == (1.0, 1.0, 1.0)


def check_ranges(exposure_stops: float, white_balance: float) -> None:
    """Refuse (``ValueError``) ranges that are negative, not finite, or white balance of 1 or more."""
    if not (math.isfinite(exposure_stops) and 0.0 <= exposure_stops <= 4.0):
        raise RegnfError(f"exposure_stops must be between 0 and 4 stops, got {exposure_stops}")
    if not (math.isfinite(white_balance) and 0.0 <= white_balance < 1.0):
        raise RegnfError(f"white_balance must be at least 0 and below 1, got {white_balance}")


def draw_appearance(seed: int, exposure_stops: float, white_balance: float) -> Appearance:
    """The appearance of variant ``seed`` (see the module); the identity when both ranges are 0."""
    check_ranges(exposure_stops, white_balance)
    if exposure_stops == 0.0 and white_balance == 0.0:
        return Appearance(0.0, (1.0, 1.0, 1.0))
    rng = np.random.default_rng([int(seed), STREAM])
    stops = float(rng.uniform(-exposure_stops, exposure_stops))
    g = rng.uniform(1.0 - white_balance, 1.0 + white_balance, size=3)
    g = g / g.mean()
    return Appearance(stops, (float(g[0]), float(g[1]), float(g[2])))


def apply_appearance(rgb: np.ndarray, appearance: Appearance) -> np.ndarray:
    """``rgb`` (h, w, 3) uint8 as the camera of ``appearance`` would record it (uint8)."""
    if appearance.identity:
        return rgb
    linear = srgb_to_linear(rgb.astype(np.float64) / 255.0)
    linear = linear * (2.0 ** appearance.stops) * np.asarray(appearance.gains)
    return np.round(255.0 * linear_to_srgb(np.clip(linear, 0.0, 1.0))).astype(np.uint8)


def vary_views(folder: Path, views: int, appearance: Appearance, sheet_columns: int = 0,
               sheet_tile_width: int = 192) -> None:
    """Apply ``appearance`` to ``rgb_k.png`` for ``k < views`` in ``folder``, in place (each
    written to a temporary file, then renamed), and tile ``contact_sheet.png`` again from them."""
    from regnf.compositor.contact_sheets import contact_sheet

    if appearance.identity:
        return
    varied = []
    for k in range(views):  # a loop over views
        path = folder / f"rgb_{k:04d}.png"
        with Image.open(path) as im:
            varied.append(apply_appearance(np.asarray(im.convert("RGB")), appearance))
        with atomic_path(path) as tmp:
            Image.fromarray(varied[-1]).save(tmp, format="PNG")
    with atomic_path(folder / "contact_sheet.png") as tmp:
        Image.fromarray(contact_sheet(varied, sheet_columns, sheet_tile_width)).save(tmp, format="PNG")
