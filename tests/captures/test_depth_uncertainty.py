"""The depth noise model against hand-computed values of Nguyen et al.'s closed form, its weights,
a capture's model and its override, and the depth confidence reader."""

from __future__ import annotations

import json
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from regnf.captures.depth_io import read_confidence
from regnf.captures.depth_uncertainty import (
    MAX_THETA,
    DepthNoiseModel,
    axial_sigma,
    parse_depth_noise,
)
from regnf.captures.model import CaptureError
from regnf.captures.sdfstudio import load_capture, write_capture
from regnf.synthetic import sensor_noise

# (z metres, theta radians, sigma metres) worked by hand from
# 0.0012 + 0.0019 (z - 0.4)^2 + 0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2.
HAND = [
    (0.4, 0.0, 0.0012),  # the quadratic term vanishes at 0.4 m
    (1.0, 0.0, 0.0012 + 0.0019 * 0.36),  # 0.001884
    (2.0, math.pi / 4, 0.0012 + 0.0019 * 2.56 + 0.0001 / math.sqrt(2.0)),  # theta = pi/2 - theta
    (4.0, math.pi / 3, 0.0012 + 0.0019 * 12.96 + 0.0001 / 2.0 * 4.0),  # (pi/3 / (pi/6))^2 = 4: 0.026024
]


@pytest.mark.parametrize(("z", "theta", "sigma"), HAND)
def test_sigma_is_nguyens_closed_form(z: float, theta: float, sigma: float) -> None:
    assert DepthNoiseModel().sigma(z, theta) == pytest.approx(sigma, rel=1e-12)
    assert axial_sigma(np.array([z]), np.array([theta]))[0] == pytest.approx(sigma, rel=1e-12)


def test_the_synthetic_sensor_and_training_share_one_sigma() -> None:
    assert sensor_noise.axial_sigma is axial_sigma
    assert sensor_noise.MAX_THETA == MAX_THETA


def test_sigma_on_arrays_and_at_grazing_angles() -> None:
    z = np.array([[0.5, 1.0, 3.0], [0.5, 1.0, 3.0]])
    theta = np.array([0.0, 1.0])[:, None]
    got = DepthNoiseModel().sigma(z, theta)
    assert got.shape == (2, 3) and got.dtype == np.float64
    # Clamped at 89.9 degrees: finite at and beyond 90.
    assert DepthNoiseModel().sigma(1.0, math.pi / 2) == DepthNoiseModel().sigma(1.0, MAX_THETA)
    assert np.isfinite(DepthNoiseModel().sigma(1.0, 2.0))
    # Another sensor's constants.
    other = DepthNoiseModel(constant_m=0.003, quadratic_per_m=0.0, angular_m15=0.0)
    assert other.sigma(7.0, 1.2) == pytest.approx(0.003, rel=1e-15)


def test_weights_fall_with_depth_and_incidence_within_their_bounds() -> None:
    model = DepthNoiseModel()
    z = np.linspace(0.4, 8.0, 200)
    theta = np.radians(np.linspace(0.0, 80.0, 100))
    w = model.weight(model.sigma(z[:, None], theta[None, :]))
    assert ((w >= 0.1) & (w <= 1.0)).all()
    assert (np.diff(w, axis=1) <= 0).all()  # monotone in theta at every depth
    assert (np.diff(w[:, 0]) <= 0).all()  # and in z at normal incidence
    # The angular term falls as 1 / sqrt(z) (Nguyen et al.'s fit), so at grazing angles sigma
    # falls with z close to the sensor; from 1.5 m on it rises with z up to 80 degrees.
    far = z >= 1.5
    assert (np.diff(w[far], axis=0) <= 0).all()
    assert (np.diff(model.sigma(z[far][:, None], theta[None, :]), axis=0) > 0).all()
    assert w[0, 0] == 1.0 and w[-1, -1] == 0.1
    # (2 mm / sigma)^2 between the clips, by hand.
    assert model.weight(0.004) == pytest.approx(0.25, rel=1e-12)
    assert model.weight(0.001) == 1.0 and model.weight(0.1) == 0.1


def test_parse_depth_noise() -> None:
    assert parse_depth_noise("none") is None
    assert parse_depth_noise({}) == DepthNoiseModel()
    assert parse_depth_noise({"constant_m": 0.002, "min_weight": 0.5}) == DepthNoiseModel(constant_m=0.002, min_weight=0.5)
    cases = [
        ("exact", r"regnf.depth_noise must be 'none' or an object of model fields, got 'exact'"),
        ({"sigma": 1.0}, r"regnf.depth_noise has unknown field\(s\) 'sigma'; known: constant_m, "),
        ({"constant_m": 0.0}, r"regnf.depth_noise: constant_m must be > 0"),
        ({"min_weight": 0.0}, r"regnf.depth_noise: min_weight must be in \(0, 1\], got 0"),
        ({"reference_m": "2mm"}, r"regnf.depth_noise: reference_m must be a finite number, got '2mm'"),
        ({"angular_m15": float("nan")}, r"regnf.depth_noise: angular_m15 must be a finite number, got nan"),
    ]
    for value, match in cases:
        with pytest.raises(ValueError, match=match):
            parse_depth_noise(value)


def _write(root: Path, meta: dict | None) -> Path:
    depth = np.full((4, 5), 1.5)
    write_capture(root, [np.zeros((4, 5, 3), np.uint8)], [depth], np.eye(4)[None],
                  np.array([[5.0, 0, 2.5], [0, 5.0, 2.0], [0, 0, 1]]), np.eye(4), meta=meta)
    return root


def test_a_captures_depth_noise_follows_the_capture(tmp_path: Path) -> None:
    cases = {
        "ideal": ({"generator": "regnf.synthetic/2"}, None),
        "zeros-empty": ({"zero_depth": "empty"}, None),
        "real": (None, DepthNoiseModel()),
        "noisy": ({"generator": "regnf.synthetic/2", "noise": {"level": "sensor", "seed": 0}}, DepthNoiseModel()),
        "exact": ({"depth_noise": "none"}, None),
        "own": ({"generator": "regnf.synthetic/2", "depth_noise": {"constant_m": 0.004}}, DepthNoiseModel(constant_m=0.004)),
    }
    for name, (meta, model) in cases.items():
        assert load_capture(_write(tmp_path / name, meta)).depth_noise == model, name


def test_a_bad_depth_noise_is_refused_naming_the_metadata_file(tmp_path: Path) -> None:
    root = _write(tmp_path, {"depth_noise": {"constant_m": -1.0}})
    with pytest.raises(CaptureError, match=r"meta_data.json: regnf.depth_noise: constant_m must be > 0"):
        load_capture(root)
    # The property says the same where the metadata changed after loading.
    capture = load_capture(_write(tmp_path / "ok", None))
    capture.meta["depth_noise"] = "exact"
    with pytest.raises(CaptureError, match=r"ok/meta_data.json: regnf.depth_noise must be 'none' or an object"):
        _ = capture.depth_noise
    assert json.loads((root / "meta_data.json").read_text())["regnf"]["depth_noise"] == {"constant_m": -1.0}


def test_read_confidence(tmp_path: Path) -> None:
    conf = np.array([[0, 1, 2], [2, 2, 1]], np.uint8)
    iio.imwrite(tmp_path / "c.png", conf)
    np.testing.assert_array_equal(read_confidence(tmp_path / "c.png", 2, 3), conf)
    np.save(tmp_path / "c.npy", conf)
    np.testing.assert_array_equal(read_confidence(tmp_path / "c.npy", 2, 3), conf)
    bad = {
        "size.png": (np.zeros((3, 3), np.uint8), r"depth confidence shape \(3, 3\) does not match the depth's 2x3"),
        "wide.png": (np.zeros((2, 3), np.uint16), r"depth confidence has dtype uint16, expected uint8"),
        "high.png": (conf * 100, r"depth confidence has values up to 200; expected 0 \(low\), 1 \(medium\) or 2 \(high\)"),
        "rgb.png": (np.zeros((2, 3, 3), np.uint8), r"depth confidence shape \(2, 3, 3\) does not match"),
    }
    for name, (img, match) in bad.items():
        iio.imwrite(tmp_path / name, img)
        with pytest.raises(ValueError, match=match):
            read_confidence(tmp_path / name, 2, 3)
    (tmp_path / "junk.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match=r"cannot read depth confidence"):
        read_confidence(tmp_path / "junk.png", 2, 3)


def test_nerfstudio_frames_name_their_confidence(tmp_path: Path) -> None:
    from regnf.captures.formats import read_capture
    from tests.captures.ns_helpers import H, W, write_nerfstudio

    data = write_nerfstudio(tmp_path)
    (tmp_path / "confidence").mkdir()
    iio.imwrite(tmp_path / "confidence" / "0.png", np.full((H, W), 2, np.uint8))
    data["frames"][0]["confidence_path"] = "confidence/0.png"
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    capture, _ = read_capture(tmp_path)
    assert capture.frames[0].confidence_path == tmp_path / "confidence" / "0.png"
    assert all(f.confidence_path is None for f in capture.frames[1:])
    assert capture.depth_noise == DepthNoiseModel()  # a sensor's capture
    data["frames"][1]["confidence_path"] = "confidence/1.png"
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(CaptureError, match=r"transforms.json: frames\[1\].confidence_path: file .*confidence/1.png not found"):
        read_capture(tmp_path)
