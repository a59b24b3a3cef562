"""The checks of what a page sends the viewer, and of who may send it, without a server."""

from __future__ import annotations

import math

import numpy as np
import pytest
from websockets.datastructures import Headers

from regnf.compositor.render_folder import MAX_PIXELS
from regnf.viewer import messages
from regnf.viewer.messages import FOV_RANGE, MAX_ASPECT, render_size
from regnf.viewer.trust import Guard, TrustError, check_host, own_hosts, page_url


@pytest.mark.parametrize("aspect", [1e-12, 1e-3, 0.2, 0.75, 1.0, 4 / 3, 2.4, 5.0, 1e3, 1e9, math.inf, math.nan])
@pytest.mark.parametrize("pixels", [1, 192, 320 * 240, MAX_PIXELS, 10**12])
def test_a_render_stays_within_the_limits(pixels: int, aspect: float) -> None:
    w, h = render_size(pixels, aspect)
    assert w >= 1 and h >= 1
    assert w * h <= MAX_PIXELS
    assert w * h <= max(1.05 * min(pixels, MAX_PIXELS), 2 * MAX_ASPECT + 2)  # about the pixels asked
    assert max(w / h, h / w) <= MAX_ASPECT + 1  # rounding a 1-pixel side
    if 0.25 <= aspect <= 4 and pixels >= 192:
        assert abs(w / h - aspect) / aspect < 0.2  # an ordinary window keeps its shape


def test_a_viewport_aspect_is_bounded() -> None:
    assert messages.viewport_aspect(10**9, 1) == MAX_ASPECT
    assert messages.viewport_aspect(1, 10**9) == 1 / MAX_ASPECT
    assert messages.viewport_aspect(800, 600) == pytest.approx(4 / 3)
    for bad in ((0, 600), (800, 0), (-1, 5), (math.nan, 600), ("wide", 600), (None, None)):
        assert messages.viewport_aspect(*bad) == messages.DEFAULT_ASPECT


def test_a_camera_with_a_number_that_is_not_finite_is_ignored(caplog: pytest.LogCaptureFixture) -> None:
    good = ([1.0, 2.0, 1.5], [1.0, 0.0, 0.0, 0.0], 1.0)
    p, q, f = messages.camera(*good)
    np.testing.assert_array_equal(q, good[1])
    np.testing.assert_array_equal(p, good[0])
    assert f == 1.0
    assert messages.camera([1.0, 2.0, 1.5], [2.0, 0.0, 0.0, 0.0], 10.0)[2] == FOV_RANGE[1]  # clamped
    np.testing.assert_allclose(messages.camera([0, 0, 0], [2.0, 0.0, 0.0, 0.0], 1.0)[1], [1, 0, 0, 0])
    np.testing.assert_allclose(messages.camera([0, 0, 0], [1e300, 0.0, 0.0, 1e300], 1.0)[1], [0.5**0.5, 0, 0, 0.5**0.5])
    bad = [([math.nan, 0, 0], good[1], 1.0), (good[0], [1, math.inf, 0, 0], 1.0), (good[0], good[1], math.nan),
           (good[0], [0, 0, 0, 0], 1.0), ([1e9, 0, 0], good[1], 1.0), (good[0][:2], good[1], 1.0),
           ("here", good[1], 1.0), (good[0], good[1], True)]
    for args in bad:
        assert messages.camera(*args) is None, args
    assert caplog.text.count("regnf view: ignored") == len(bad)


def test_names_and_numbers_from_the_panel() -> None:
    assert messages.known("rgb", ("rgb", "depth"), "channel") == "rgb"
    assert messages.known("rgbx", ("rgb", "depth"), "channel") is None
    assert messages.known(["rgb"], ("rgb", "depth"), "channel") is None
    assert messages.seed(3) == 3 and messages.seed(3.0) == 3
    for bad in (-1, 2**31, 0.5, math.nan, "3"):
        assert messages.seed(bad) is None
    np.testing.assert_array_equal(messages.box_size((0.0, 100.0, 1.0), 0.05, 6.0), [0.05, 6.0, 1.0])
    assert messages.box_size((math.inf, 1.0, 1.0), 0.05, 6.0) is None


def test_a_failing_callback_is_one_line(caplog: pytest.LogCaptureFixture) -> None:
    shown: list[str] = []
    run = messages.quiet(lambda: {}["missing"], "accept", shown.append)
    assert run() is None
    assert shown == ["accept failed: KeyError: 'missing'"]
    assert "Traceback" not in caplog.text and "accept failed: KeyError" in caplog.text


def test_the_guard_lets_through_only_the_viewers_own_page() -> None:
    port, token = 8123, "t0ken-Of-the-session_0123456789abcdef"
    guard = Guard(port, own_hosts("127.0.0.1", port), token)
    own = [("Host", f"127.0.0.1:{port}"), ("Origin", f"http://127.0.0.1:{port}")]

    def why(path: str, headers: list[tuple[str, str]]) -> str | None:
        return guard.refusal(path, Headers(headers))

    assert why(f"/?token={token}", own) is None
    assert why(f"/?token={token}", [("Host", f"localhost:{port}")]) is None  # no Origin: not a browser's script
    assert why("/", own + [("Cookie", f"a=b; regnf-view-{port}={token}")]) is None
    assert "Host" in why(f"/?token={token}", [("Host", f"evil.example:{port}")])
    assert "Host" in why(f"/?token={token}", [("Host", "127.0.0.1:80")])
    assert "Host" in why(f"/?token={token}", [])
    assert "Host" in why(f"/?token={token}", own + [("Host", f"127.0.0.1:{port}")])  # two of them
    assert "Origin" in why(f"/?token={token}", [own[0], ("Origin", "http://evil.example")])
    assert "Origin" in why(f"/?token={token}", [own[0], ("Origin", "null")])
    assert "Origin" in why(f"/?token={token}", [own[0], ("Origin", f"https://127.0.0.1:{port}")])
    for path, extra in (("/", []), ("/?token=", []), (f"/?token={token[:-1]}", []), ("/?token=é", []),
                        ("/", [("Cookie", f"regnf-view-{port + 1}={token}")]), ("/", [("Cookie", f'regnf-view-{port}="{token}')])):
        assert "token" in why(path, own + extra), (path, extra)


def test_a_host_beyond_this_machine_needs_the_acknowledgement() -> None:
    for host in ("127.0.0.1", "localhost", "::1", "127.0.0.2"):
        check_host(host, False)
    for host in ("0.0.0.0", "::", "192.0.2.7", "example.org"):
        with pytest.raises(TrustError, match="--allow-remote-edits"):
            check_host(host, False)
        check_host(host, True)
    assert page_url("localhost", 8080, "abc") == "http://127.0.0.1:8080/?token=abc"
    assert page_url("::1", 8080, "abc") == "http://[::1]:8080/?token=abc"
    assert "0.0.0.0" not in page_url("0.0.0.0", 8080, "abc")
    assert {"127.0.0.1:8080", "localhost:8080", "[::1]:8080"} <= own_hosts("0.0.0.0", 8080)
