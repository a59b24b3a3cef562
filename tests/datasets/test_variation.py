"""Appearance variation of generated variants, against the sRGB standard's formulas and an
unvaried data set of the same seeds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from regnf.compositor.cameras_io import OrbitConfig
from regnf.core.executors import ExecutorConfig
from regnf.datasets.generation import GenerateConfig, generate
from regnf.datasets.variation import Appearance, apply_appearance, draw_appearance
from regnf.scene_graph import add_instance
from tests.scene_graph.helpers import make_stage, similarity

ORBIT = OrbitConfig(n=2, width=24, height=18, radius=4.5)


def test_draws_are_seeded_within_their_ranges_and_keep_the_brightness() -> None:
    draws = [draw_appearance(s, 1.5, 0.2) for s in range(200)]
    assert draws[7] == draw_appearance(7, 1.5, 0.2) and draws[7] != draws[8]
    stops = np.array([d.stops for d in draws])
    gains = np.array([d.gains for d in draws])
    assert (np.abs(stops) <= 1.5).all() and stops.min() < -1.0 and stops.max() > 1.0
    np.testing.assert_allclose(gains.mean(axis=1), 1.0, atol=1e-12)
    # A gain of 1 + w beside two of 1 - w is the farthest from 1 once divided by the mean.
    assert (np.abs(gains - 1) <= 4 * 0.2 / (3 - 0.2) + 1e-9).all()
    assert draw_appearance(3, 0.0, 0.0).identity
    for bad in ((-1.0, 0.0), (0.0, 1.0), (float("nan"), 0.0)):
        with pytest.raises(ValueError):
            draw_appearance(0, *bad)


def test_one_stop_doubles_the_linear_light_of_the_srgb_standard() -> None:
    rgb = np.array([[[0, 10, 128], [200, 255, 60]]], dtype=np.uint8)
    out = apply_appearance(rgb, Appearance(1.0, (1.0, 1.0, 1.0)))
    # IEC 61966-2-1, written out here.
    c = rgb / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4) * 2.0
    lin = np.clip(lin, 0, 1)
    enc = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
    np.testing.assert_array_equal(out, np.round(enc * 255).astype(np.uint8))
    assert out[0, 1, 1] == 255 and out[0, 0, 0] == 0  # white saturates, black stays black


def test_a_varied_data_set_is_the_unvaried_one_seen_by_the_recorded_camera(tmp_path: Path) -> None:
    stage = make_stage(tmp_path, names=("c", "dc", "t"))
    add_instance(stage, "c", similarity(0.5, (2.2, -0.5, 0.0), 1.0))
    add_instance(stage, "t", similarity(-0.3, (0.3, 2.3, 0.0), 1.0))
    runs = {}
    for name, (e, w) in {"plain": (0.0, 0.0), "varied": (1.0, 0.2)}.items():
        cfg = GenerateConfig(variants=2, cameras=ORBIT, exposure_stops=e, white_balance=w,
                             executor=ExecutorConfig(kind="local", workers=1))
        assert generate(stage, tmp_path / name, cfg, progress=False).made == [0, 1]
        runs[name] = {r["seed"]: r for r in map(json.loads, (tmp_path / name / "manifest.jsonl").read_text().splitlines())}
    for seed, row in runs["varied"].items():
        look = draw_appearance(seed, 1.0, 0.2)
        assert row["appearance"] == {"exposure_stops": look.stops, "white_balance": list(look.gains)}
        assert runs["plain"][seed]["appearance"] == {"exposure_stops": 0.0, "white_balance": [1.0, 1.0, 1.0]}
        for k in range(2):
            def read(run: str, name: str, seed: int = seed) -> np.ndarray:
                with Image.open(tmp_path / run / runs[run][seed]["variant"] / name) as im:
                    return np.asarray(im)
            plain, varied = read("plain", f"rgb_{k:04d}.png"), read("varied", f"rgb_{k:04d}.png")
            assert not np.array_equal(plain, varied)
            np.testing.assert_array_equal(varied, apply_appearance(plain, look))
            for other in (f"depth_{k:04d}.png", f"instance_{k:04d}.png", f"class_{k:04d}.png"):
                np.testing.assert_array_equal(read("plain", other), read("varied", other))
