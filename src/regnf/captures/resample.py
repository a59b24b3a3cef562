"""An image taken with one pinhole ``K`` resampled onto the pixel grid of another, same camera.

A sensor whose colour and depth cameras share a centre and axes but not a pixel grid (ScanNet:
1296x968 colour, 640x480 depth) gives each depth pixel its colour here: the depth pixel's centre
``(u + 0.5, v + 0.5)`` is taken through ``K_src K_dst^-1`` into the colour image and read
bilinearly (colour pixel ``j`` has its centre at ``j + 0.5``). Points beyond the colour image take
the nearest edge pixel.
"""

from __future__ import annotations

import numpy as np


def resample_to_grid(image: np.ndarray, K_src: np.ndarray, K_dst: np.ndarray, height: int,
                     width: int) -> np.ndarray:
    """Bilinear resampling of ``image`` (pinhole ``K_src``) onto a ``height x width`` grid of ``K_dst``.

    Parameters
    ----------
    image : (h, w, C) float32
        The source image.
    K_src, K_dst : (3, 3) float
        Pinhole intrinsics of the source image and of the wanted grid (same camera centre and
        axes); pixel centres at ``(u + 0.5, v + 0.5)``.
    height, width : int
        Size of the wanted grid, pixels.

    Returns
    -------
    (height, width, C) float32
    """
    h, w = image.shape[:2]
    M = np.asarray(K_src, dtype=np.float64) @ np.linalg.inv(np.asarray(K_dst, dtype=np.float64))
    v, u = np.mgrid[0:height, 0:width] + 0.5
    # Both K have the last row [0, 0, 1], so M maps pixels affinely (no division).
    x = np.clip(M[0, 0] * u + M[0, 1] * v + M[0, 2] - 0.5, 0.0, w - 1.0)
    y = np.clip(M[1, 0] * u + M[1, 1] * v + M[1, 2] - 0.5, 0.0, h - 1.0)
    x0, y0 = np.floor(x).astype(np.intp), np.floor(y).astype(np.intp)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    ax = (x - x0).astype(np.float32)[..., None]
    ay = (y - y0).astype(np.float32)[..., None]
    top = image[y0, x0] * (1 - ax) + image[y0, x1] * ax
    bottom = image[y1, x0] * (1 - ax) + image[y1, x1] * ax
    return (top * (1 - ay) + bottom * ay).astype(np.float32)
