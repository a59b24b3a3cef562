"""Golden images: the cases, how they are rendered and stored, and how renders are compared.

Per case four PNGs in ``golden/``: ``<case>_rgb.png`` (8-bit), ``<case>_normals.png`` (world
normals as ``(n + 1) / 2`` in 8 bits, black on the background), ``<case>_depth.png`` (16-bit
millimetres) and ``<case>_instance.png`` (16-bit renderer id + 1, so that no hit (-1) and the
scene (0) stay apart; written and read here, not with regnf's instance writer, which merges them).

A render matches its golden when (thresholds below, chosen so that a few pixels flipping at
silhouettes from floating-point differences between machines still pass, while a 1 cm offset
of the surface, a flipped normal or wrong colours fail):

- RGB PSNR >= 35 dB and normals PSNR >= 30 dB (8-bit images, peak 255; one silhouette pixel
  of the 6912 going fully wrong alone gives about 38 dB);
- depth agreement >= 99 %: of the pixels where either image has a surface, the fraction
  where both have one within 2 mm of each other;
- instance agreement >= 99 % of all pixels.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from regnf.compositor import Camera, SphereTracerConfig, VolumeRendererConfig, render, render_volume
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.core.image_io import (
    depth_to_mm,
    read_rgb_png,
    rgb_to_uint8,
    write_depth_png,
    write_rgb_png,
)
from regnf.fields.field import Field

from . import golden_scenes as G

RGB_PSNR_MIN = 35.0
"""dB, RGB against the golden."""
NORMALS_PSNR_MIN = 30.0
"""dB, normal image against the golden."""
DEPTH_TOL_M = 0.002
"""Metres: two depths within this agree."""
DEPTH_AGREEMENT_MIN = 0.99
"""Fraction of surface pixels whose depths agree."""
INSTANCE_AGREEMENT_MIN = 0.99
"""Fraction of pixels with the same instance id."""
KINDS = ("rgb", "normals", "depth", "instance")
"""The images stored per case."""
VOLUME = VolumeRendererConfig(n_samples=128)
"""The volume renderer's settings for its golden (fewer samples than the default, same look)."""


class Case(NamedTuple):
    """A golden case: a field, a camera and a renderer."""

    field: Callable[[], Field]
    """Builds the field (lazily: the neural case needs the stored checkpoint)."""
    camera: Callable[[], Camera]
    """The view."""
    renderer: str = "sphere"
    """``sphere`` or ``volume``."""


SUBSTITUTE = StageCompositeConfig()
CASES: dict[str, Case] = {
    "analytic_scene": Case(lambda: G.composite("own", StageCompositeConfig(mode="scene")), G.camera),
    "analytic_substitute": Case(lambda: G.composite("own", SUBSTITUTE), G.camera),
    "analytic_replace": Case(lambda: G.composite("other", SUBSTITUTE), G.camera),
    "analytic_shell_tint": Case(
        lambda: G.composite("other", StageCompositeConfig(removal="shell", tint=True)), G.camera
    ),
    "analytic_volume": Case(lambda: G.composite("own", SUBSTITUTE), G.camera, "volume"),
    "neural_object": Case(G.neural_pouf, G.neural_camera),
    "neural_replace": Case(lambda: G.composite("neural", SUBSTITUTE), G.camera),
}


class Images(NamedTuple):
    """A render as stored: what the PNGs hold."""

    rgb: np.ndarray
    """(h, w, 3) uint8."""
    normals: np.ndarray
    """(h, w, 3) uint8, ``(n + 1) / 2``; 0 on the background."""
    depth: np.ndarray
    """(h, w) float64 metres (millimetre resolution); 0 no hit."""
    instance: np.ndarray
    """(h, w) int64 ids; -1 background."""


def render_case(name: str) -> Images:
    """Render case ``name`` and quantise it exactly as the PNGs store it."""
    case = CASES[name]
    field, cam = case.field(), case.camera()
    r = render_volume(field, cam, VOLUME) if case.renderer == "volume" else render(field, cam, SphereTracerConfig())
    normals = torch.where(r.mask[..., None], (r.normals + 1.0) / 2.0, 0.0)
    return Images(rgb_to_uint8(r.rgb), rgb_to_uint8(normals), depth_to_mm(r.depth, r.mask) / 1000.0,
                  r.instance_id.detach().cpu().numpy().astype(np.int64))


def paths(name: str, folder: Path = G.GOLDEN_DIR) -> dict[str, Path]:
    return {k: folder / f"{name}_{k}.png" for k in KINDS}


def write_images(images: Images, name: str, kinds: tuple[str, ...] = KINDS, folder: Path = G.GOLDEN_DIR) -> None:
    """Write the ``kinds`` of ``images`` into ``folder``."""
    p = paths(name, folder)
    if "rgb" in kinds:
        write_rgb_png(p["rgb"], images.rgb)
    if "normals" in kinds:
        write_rgb_png(p["normals"], images.normals)
    if "depth" in kinds:
        write_depth_png(p["depth"], images.depth)
    if "instance" in kinds:
        from PIL import Image

        with Image.fromarray((images.instance + 1).astype(np.uint16)) as im:
            im.save(p["instance"])


def read_images(name: str, folder: Path = G.GOLDEN_DIR) -> Images:
    """The stored golden of case ``name``."""
    from PIL import Image

    p = paths(name, folder)
    with Image.open(p["depth"]) as im:
        depth = np.asarray(im).astype(np.float64) / 1000.0
    with Image.open(p["instance"]) as im:
        ids = np.asarray(im).astype(np.int64) - 1
    return Images(read_rgb_png(p["rgb"]), read_rgb_png(p["normals"]), depth, ids)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two uint8 images (peak 255); inf when identical."""
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(255.0**2 / mse)


class Comparison(NamedTuple):
    """How a render compares with its golden."""

    rgb_psnr: float
    """dB."""
    normals_psnr: float
    """dB."""
    depth_agreement: float
    """Fraction of surface pixels (in either) with both depths within ``DEPTH_TOL_M``."""
    instance_agreement: float
    """Fraction of pixels with equal ids."""

    def failures(self) -> list[str]:
        """What is below its threshold, in words (empty: the render matches)."""
        out = []
        if not self.rgb_psnr >= RGB_PSNR_MIN:
            out.append(f"RGB PSNR {self.rgb_psnr:.2f} dB < {RGB_PSNR_MIN}")
        if not self.normals_psnr >= NORMALS_PSNR_MIN:
            out.append(f"normals PSNR {self.normals_psnr:.2f} dB < {NORMALS_PSNR_MIN}")
        if not self.depth_agreement >= DEPTH_AGREEMENT_MIN:
            out.append(f"depth agreement {self.depth_agreement:.4f} < {DEPTH_AGREEMENT_MIN}")
        if not self.instance_agreement >= INSTANCE_AGREEMENT_MIN:
            out.append(f"instance agreement {self.instance_agreement:.4f} < {INSTANCE_AGREEMENT_MIN}")
        return out

    def ok(self) -> bool:
        return not self.failures()

    def summary(self) -> str:
        return (f"RGB {self.rgb_psnr:.1f} dB, normals {self.normals_psnr:.1f} dB, depth {self.depth_agreement:.4f}, "
                f"ids {self.instance_agreement:.4f}")


def compare(got: Images, golden: Images) -> Comparison:
    """Compare a render with its golden (see the module for the measures)."""
    if got.rgb.shape != golden.rgb.shape:
        raise ValueError(f"render {got.rgb.shape} and golden {golden.rgb.shape} differ in size")
    hit_a, hit_b = got.depth > 0, golden.depth > 0
    either = hit_a | hit_b
    agree = hit_a & hit_b & (np.abs(got.depth - golden.depth) <= DEPTH_TOL_M + 1e-9)
    depth = float(agree.sum() / either.sum()) if either.any() else 1.0
    return Comparison(psnr(got.rgb, golden.rgb), psnr(got.normals, golden.normals), depth,
                      float(np.mean(got.instance == golden.instance)))
