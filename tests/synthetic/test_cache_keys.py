"""Which settings a cached room capture's folder depends on."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from regnf.synthetic import cache as cache_module
from regnf.synthetic.cache import Cache
from regnf.synthetic.capture import RoomCaptureConfig
from regnf.synthetic.sensor_noise import NOISE_LEVELS


def test_a_changed_noise_model_makes_the_noisy_captures_anew_and_keeps_the_ideal_ones(tmp_path: Path) -> None:
    cache = Cache(tmp_path, progress=False)
    configs = {lv: RoomCaptureConfig(coverage="low", noise=lv) for lv in ("ideal", "sensor", "slam")}
    before = {lv: cache.room_capture_folder("ac-room", cfg) for lv, cfg in configs.items()}
    assert len(set(before.values())) == 3
    changed = dict(NOISE_LEVELS, sensor=dataclasses.replace(NOISE_LEVELS["sensor"], lateral_scale=0.5))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(cache_module, "NOISE_LEVELS", changed)
        after = {lv: cache.room_capture_folder("ac-room", cfg) for lv, cfg in configs.items()}
    assert after["sensor"] != before["sensor"]
    assert after["ideal"] == before["ideal"] and after["slam"] == before["slam"]
    # The ideal capture's key is the one it always had: no noise settings in it.
    assert before["ideal"].name.startswith("room-ac-room-low-") and "ideal" not in before["ideal"].name
