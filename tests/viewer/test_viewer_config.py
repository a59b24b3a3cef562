"""The viewer's settings: angles in degrees, as every angle a user sets."""

from __future__ import annotations

import pytest

from regnf.viewer.viewer_config import ViewerConfig


def test_the_opening_field_of_view_is_in_degrees() -> None:
    assert ViewerConfig(opening_fov=90.0).opening_fov == 90.0
    with pytest.raises(ValueError, match=r"opening_fov must be in \(3, 170\) degrees, got 1.1"):
        ViewerConfig(opening_fov=1.1)  # radians by mistake: refused, not a one-degree view
