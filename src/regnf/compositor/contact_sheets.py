"""A contact sheet: many RGB views tiled on one image."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from PIL import Image

from regnf.core.errors import RegnfError


def contact_sheet(
    images: Sequence[np.ndarray],
    columns: int = 0,
    tile_width: int = 192,
    gap: int = 2,
    background: tuple[int, int, int] = (32, 32, 32),
) -> np.ndarray:
    """Tile ``images`` row by row into one (H, W, 3) uint8 image.

    Parameters
    ----------
    images : sequence of (h, w, 3) uint8
        At least one; each is resized (aspect kept) to ``tile_width`` pixels wide if wider.
    columns : int
        Tiles per row; 0 picks ``ceil(sqrt(n))``.
    tile_width : int
        Largest tile width in pixels, >= 1.
    gap : int
        Pixels between tiles and around the sheet, >= 0.
    background : (3,) int
        Colour of the gaps.
    """
    if len(images) == 0:
        raise RegnfError("a contact sheet needs at least one image")
    if tile_width < 1 or gap < 0 or columns < 0:
        raise RegnfError(f"need tile_width >= 1, gap >= 0, columns >= 0; got {tile_width}, {gap}, {columns}")
    tiles = []
    for k, img in enumerate(images):  # a loop over views (resizing is per image)
        a = np.asarray(img)
        if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
            raise RegnfError(f"images[{k}] must be (h, w, 3) uint8, got {a.shape} {a.dtype}")
        if a.shape[1] > tile_width:
            h = max(1, round(a.shape[0] * tile_width / a.shape[1]))
            a = np.asarray(Image.fromarray(a).resize((tile_width, h), Image.Resampling.BILINEAR))
        tiles.append(a)
    cols = columns or math.ceil(math.sqrt(len(tiles)))
    rows = math.ceil(len(tiles) / cols)
    th = max(t.shape[0] for t in tiles)
    tw = max(t.shape[1] for t in tiles)
    sheet = np.empty((gap + rows * (th + gap), gap + cols * (tw + gap), 3), dtype=np.uint8)
    sheet[:] = np.asarray(background, dtype=np.uint8)
    for k, t in enumerate(tiles):
        r, c = divmod(k, cols)
        y, x = gap + r * (th + gap), gap + c * (tw + gap)
        sheet[y : y + t.shape[0], x : x + t.shape[1]] = t
    return sheet
