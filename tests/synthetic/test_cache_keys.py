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


@dataclasses.dataclass(frozen=True)
class _WithNewSetting(type(NOISE_LEVELS["sensor"])):  # type: ignore[misc]
    new_setting: float = 1.0


def test_a_new_noise_setting_at_its_default_makes_the_noisy_captures_anew(tmp_path: Path) -> None:
    """A setting added to the noise model changes what a level makes even at its default value."""
    cache = Cache(tmp_path, progress=False)
    config = RoomCaptureConfig(coverage="low", noise="sensor")
    before = cache.room_capture_folder("ac-room", config)
    sensor = NOISE_LEVELS["sensor"]
    extended = _WithNewSetting(**{f.name: getattr(sensor, f.name) for f in dataclasses.fields(sensor)})
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(cache_module, "NOISE_LEVELS", dict(NOISE_LEVELS, sensor=extended))
        after = cache.room_capture_folder("ac-room", config)
    assert after != before
