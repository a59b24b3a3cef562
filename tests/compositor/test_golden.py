"""Golden-image regression tests of the compositor (scene, substitution, replacement, neural).

The goldens are 96 x 72 PNGs in ``golden/`` (see ``golden.py`` for the thresholds and
``golden_scenes.py`` for the scenes). After an intended change of the renderer or the
scenes, regenerate them with ``python -m tests.compositor.make_goldens`` and review the
printed list of changed files (and the images) before committing.

The last tests check the check: a renderer broken on purpose (a surface offset by 1 cm,
flipped normals, swapped colour channels) must FAIL the comparison.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import pytest
import torch

from regnf.compositor import CompositeField
from regnf.fields.shading import Shaded
from regnf.render import sphere_render

from . import golden as GD


@pytest.fixture(scope="module")
def renders() -> Iterator[dict[str, GD.Images]]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the goldens were made
    try:
        yield {name: GD.render_case(name) for name in GD.CASES}
    finally:
        torch.set_num_threads(threads)


@pytest.mark.parametrize("name", list(GD.CASES))
def test_render_matches_its_golden(name: str, renders: dict[str, GD.Images]) -> None:
    result = GD.compare(renders[name], GD.read_images(name))
    assert result.ok(), (
        f"{name}: {'; '.join(result.failures())}. If the change is intended, regenerate the goldens "
        "with `python -m tests.compositor.make_goldens` and review them."
    )


def test_goldens_show_what_they_claim(renders: dict[str, GD.Images]) -> None:
    """The cases differ where they should: ids per mode, colours between substitution and replacement."""
    scene, sub, rep = renders["analytic_scene"], renders["analytic_substitute"], renders["analytic_replace"]
    assert set(scene.instance.ravel().tolist()) == {-1, 0}
    assert {1, 2} <= set(sub.instance.ravel().tolist()) and {1, 2} <= set(rep.instance.ravel().tolist())
    # Substituting each object by its own library field keeps the geometry (frames are right).
    same = GD.compare(sub._replace(instance=scene.instance, rgb=scene.rgb), scene)
    assert same.depth_agreement > 0.995 and same.normals_psnr > 35.0
    # ... while a replacement changes it.
    assert GD.compare(rep, sub).depth_agreement < 0.95
    assert math.isfinite(GD.compare(rep, sub).rgb_psnr)


def _offset_sdf(monkeypatch: pytest.MonkeyPatch, delta: float) -> None:
    evaluate = CompositeField.evaluate

    def shifted(self, x):
        s = evaluate(self, x)
        return s._replace(sdf=s.sdf + delta)

    monkeypatch.setattr(CompositeField, "evaluate", shifted)


def _flip_normals(monkeypatch: pytest.MonkeyPatch) -> None:
    shade = sphere_render.shade_hits

    def flipped(*args, **kwargs):
        s = shade(*args, **kwargs)
        return Shaded(s.rgb, -s.normals)

    monkeypatch.setattr(sphere_render, "shade_hits", flipped)


def _swap_channels(monkeypatch: pytest.MonkeyPatch) -> None:
    color = CompositeField.color
    monkeypatch.setattr(CompositeField, "color", lambda self, x, d=None: color(self, x, d).flip(-1))


@pytest.mark.parametrize("name", ["analytic_substitute", "neural_replace"])
def test_rounding_sized_differences_still_match(monkeypatch: pytest.MonkeyPatch, name: str) -> None:
    """What another machine's floating point might do (a surface moved by 16 micrometres) passes."""
    _offset_sdf(monkeypatch, 1e-5)
    result = GD.compare(GD.render_case(name), GD.read_images(name))
    assert result.ok(), result.failures()


@pytest.mark.parametrize(
    ("breakage", "fails"),
    [
        (lambda mp: _offset_sdf(mp, 0.01 / 1.6), "depth agreement"),  # 1 cm in scene metres
        (_flip_normals, "normals PSNR"),
        (_swap_channels, "RGB PSNR"),
    ],
    ids=["sdf_offset_1cm", "flipped_normals", "swapped_colours"],
)
@pytest.mark.parametrize("name", ["analytic_substitute", "neural_replace"])
def test_a_broken_renderer_fails_the_comparison(
    monkeypatch: pytest.MonkeyPatch, breakage, fails: str, name: str
) -> None:
    breakage(monkeypatch)
    result = GD.compare(GD.render_case(name), GD.read_images(name))
    assert not result.ok()
    assert any(f.startswith(fails) for f in result.failures()), result.failures()
