"""``regnf view`` against a hostile page, a hostile client and a stage that changes under it.

Clients are real: a websocket client (``websockets``, as a page's script would open one), raw
HTTP requests and the command line. A refused request gets HTTP 403 and never becomes a client
of the viewer; what a client with the session's token sends is checked before use; a stage
changed on disk by another program is noticed, and an edit it makes stale is refused with a
message in the panel, never a traceback.
"""

from __future__ import annotations

import logging
import re
import socket
import time
import types
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path

import msgspec
import numpy as np
import pytest
import viser
from websockets.exceptions import InvalidStatus
from websockets.sync.client import ClientConnection, connect

from regnf.benchmarks.viewer import free_port
from regnf.cli import commands_view
from regnf.cli.app import EXIT_OK
from regnf.core.cameras import look_at
from regnf.scene_graph import InstanceRecord, add_instance, read_stage, write_stage
from regnf.viewer import StageViewer, ViewerConfig, stage_viewer
from regnf.viewer.messages import MAX_ASPECT
from regnf.viewer.render_worker import wxyz_of
from tests.adversarial.disk import changes, snapshot
from tests.cli.cli_helpers import assert_fails, run_cli
from tests.scene_graph.helpers import make_stage, registration_json, similarity

COARSE, REFINED = 16 * 12, 24 * 18
"""The viewers' image sizes here (pixels): small, so that every render is quick."""


@pytest.fixture
def stage(tmp_path: Path) -> Path:
    path = make_stage(tmp_path / "main", ("c", "dc"))
    add_instance(path, "c", similarity(0.3, (0.8, 0.4, 0.0), 1.0), instance_id="c_1")
    return path


@pytest.fixture
def viewer(stage: Path) -> Iterator[StageViewer]:
    """A viewer of ``stage`` on a free loopback port; its timer does not check the stage (the
    edits' own checks are what is tested), unless a test asks for another viewer."""
    v = StageViewer(stage, ViewerConfig(port=0, coarse_pixels=COARSE, refined_pixels=REFINED,
                                        opening_rest_seconds=0.0, stage_poll_seconds=600.0))
    try:
        yield v
    finally:
        v.close()


@pytest.fixture
def no_grace(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every camera a client reports counts at once (a browser's first ones are skipped for a
    while: see ``StageViewer._on_connect``)."""
    monkeypatch.setattr(stage_viewer, "OPENING_GRACE_S", 0.0)


def wait_for(predicate: Callable[[], bool], timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def open_socket(viewer: StageViewer, query: str = "", origin: str | None = None) -> ClientConnection:
    """A websocket to the viewer, as viser's page opens it (its protocol), at ``/`` + ``query``."""
    headers = {} if origin is None else {"Origin": origin}
    return connect(f"ws://127.0.0.1:{viewer.port}/{query}", additional_headers=headers, max_queue=None,
                   subprotocols=[f"viser-v{viser.__version__}"], open_timeout=10)


def send(ws: ClientConnection, kind: str, **fields: object) -> None:
    """One message of viser's protocol (msgpack of the fields and the message's type)."""
    ws.send(msgspec.msgpack.encode({"type": kind, **fields}))


def camera(position: object, wxyz: object, fov: object = 1.0, width: object = 800, height: object = 600) -> dict:
    """The fields of the camera message a page sends when its camera or window changes."""
    return {"wxyz": wxyz, "position": position, "fov": fov, "near": 0.01, "far": 100.0,
            "image_height": height, "image_width": width, "look_at": [0.0, 0.0, 0.0],
            "up_direction": [0.0, 0.0, 1.0]}


def opening_camera(viewer: StageViewer, **size: object) -> dict:
    """The camera message of a page at the viewer's opening view."""
    initial = viewer.server.initial_camera
    pose = look_at(np.asarray(initial.position), np.asarray(initial.look_at))
    return camera(list(map(float, pose[:3, 3])), list(wxyz_of(pose[:3, :3])), float(initial.fov), **size)


def page(viewer: StageViewer, query: str = "", headers: dict | None = None) -> int:
    """HTTP status of a request for the viewer's page."""
    request = urllib.request.Request(f"http://127.0.0.1:{viewer.port}/{query}", headers=headers or {})
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.status
    except urllib.error.HTTPError as exc:
        return exc.code


def raw_upgrade(viewer: StageViewer, host: str, query: str) -> str:
    """The status line answering a websocket handshake sent with ``Host: host`` (a site whose
    name was rebound to 127.0.0.1 sends its own name)."""
    request = (f"GET /{query} HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
               "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
               f"Sec-WebSocket-Protocol: viser-v{viser.__version__}\r\n\r\n")
    with socket.create_connection(("127.0.0.1", viewer.port), timeout=10) as s:
        s.sendall(request.encode())
        return s.recv(4096).decode(errors="replace").splitlines()[0]


def assert_refused(viewer: StageViewer, query: str, origin: str | None, why: str) -> None:
    with pytest.raises(InvalidStatus) as refused:
        open_socket(viewer, query, origin)
    assert refused.value.response.status_code == 403
    assert why in refused.value.response.body.decode()
    time.sleep(0.2)
    assert not viewer.server.get_clients()


# -- who may connect --------------------------------------------------------------------------
def test_a_foreign_origin_is_refused(viewer: StageViewer, caplog: pytest.LogCaptureFixture) -> None:
    token = f"?token={viewer.token}"
    assert_refused(viewer, token, "http://evil.example", "Origin http://evil.example is not this viewer's page")
    assert_refused(viewer, token, "null", "Origin null")
    assert page(viewer, token, {"Origin": "http://evil.example"}) == 403
    assert "refused a websocket for /: Origin http://evil.example" in caplog.text
    assert viewer.token not in caplog.text  # the log never shows the token


def test_a_foreign_host_is_refused(viewer: StageViewer) -> None:
    token = f"?token={viewer.token}"
    assert raw_upgrade(viewer, f"evil.example:{viewer.port}", token) == "HTTP/1.1 403 Forbidden"
    assert raw_upgrade(viewer, "127.0.0.1:1", token) == "HTTP/1.1 403 Forbidden"  # another port
    assert page(viewer, token, {"Host": f"evil.example:{viewer.port}"}) == 403
    # The same request naming the viewer's own address is let through (a truth for the above).
    assert raw_upgrade(viewer, f"localhost:{viewer.port}", token) == "HTTP/1.1 101 Switching Protocols"


def test_a_missing_or_wrong_token_is_refused(viewer: StageViewer) -> None:
    own = f"http://127.0.0.1:{viewer.port}"
    assert_refused(viewer, "", own, "no valid session token")
    assert_refused(viewer, "?token=" + "x" * len(viewer.token), own, "no valid session token")
    assert_refused(viewer, f"?token={viewer.token}&token=x", own, "no valid session token")
    assert page(viewer) == 403
    assert page(viewer, "?token=wrong") == 403
    assert page(viewer, "", {"Cookie": f"regnf-view-{viewer.port}=wrong"}) == 403


def test_the_right_token_from_the_viewers_page_is_accepted(viewer: StageViewer) -> None:
    assert viewer.url == f"http://127.0.0.1:{viewer.port}/?token={viewer.token}"
    assert len(viewer.token) >= 32
    # The page asked with the token sets the cookie its websocket then sends.
    with urllib.request.urlopen(viewer.url, timeout=10) as response:
        assert response.status == 200
        cookie = response.headers["Set-Cookie"]
    assert cookie.startswith(f"regnf-view-{viewer.port}={viewer.token};") and "HttpOnly" in cookie
    assert page(viewer, "", {"Cookie": cookie.split(";")[0]}) == 200
    for origin in (f"http://127.0.0.1:{viewer.port}", f"http://localhost:{viewer.port}", None):
        with open_socket(viewer, f"?token={viewer.token}", origin) as ws:
            send(ws, "ViewerCameraMessage", **opening_camera(viewer))
            wait_for(lambda: len(viewer.server.get_clients()) == 1, 10, "the client")
        wait_for(lambda: not viewer.server.get_clients(), 10, "the client to leave")


# -- what a client sends ----------------------------------------------------------------------
def test_an_oversized_viewport_is_clamped(viewer: StageViewer, no_grace: None) -> None:
    sizes: list[tuple[int, int]] = []
    show = viewer.worker.show
    viewer.worker.show = lambda cid, image, level: (sizes.append(image.shape[:2]), show(cid, image, level))
    with open_socket(viewer, f"?token={viewer.token}") as ws:
        # One camera message 1e9 pixels wide and 1 high (what made an 8,763,561 x 1 render), then
        # its transpose from another place.
        send(ws, "ViewerCameraMessage", **opening_camera(viewer, width=10**9, height=1))
        wait_for(lambda: len(sizes) >= 2, 30, "the coarse and refined images")
        moved = opening_camera(viewer, width=1, height=10**9)
        moved["position"] = [p + 0.3 for p in moved["position"]]
        send(ws, "ViewerCameraMessage", **moved)
        wait_for(lambda: len(sizes) >= 4, 30, "the second view's images")
    for h, w in sizes:
        assert w * h <= 1.1 * REFINED, f"a {w} x {h} render"
        assert max(w / h, h / w) <= MAX_ASPECT * 1.2, f"a {w} x {h} render"
    assert any(w > h for h, w in sizes) and any(h > w for h, w in sizes)


def test_non_finite_numbers_are_ignored(viewer: StageViewer, caplog: pytest.LogCaptureFixture,
                                        capfd: pytest.CaptureFixture[str], no_grace: None) -> None:
    caplog.set_level(logging.WARNING, logger="regnf.viewer")
    with open_socket(viewer, f"?token={viewer.token}") as ws:
        send(ws, "ViewerCameraMessage", **opening_camera(viewer))
        wait_for(lambda: len(viewer.server.get_clients()) == 1, 10, "the client")
        cid = next(iter(viewer.server.get_clients()))
        moved = opening_camera(viewer)
        moved["position"] = [p + 0.3 for p in moved["position"]]
        send(ws, "ViewerCameraMessage", **moved)  # a camera that moved is rendered (a truth)
        wait_for(lambda: viewer.worker.current(cid) == 2, 10, "the moved camera's request")
        bad = [{"position": [float("nan"), 0.0, 1.0]}, {"wxyz": [1.0, float("inf"), 0.0, 0.0]},
               {"wxyz": [0.0, 0.0, 0.0, 0.0]}, {"fov": float("nan")}, {"position": [1e300, 0.0, 0.0]}]
        for fields in bad:  # one at a time: a camera callback reads the client's latest camera
            logged = caplog.text.count("ignored")
            send(ws, "ViewerCameraMessage", **{**opening_camera(viewer), **fields})
            wait_for(lambda n=logged: caplog.text.count("ignored") > n, 10, f"a logged line for {fields}")
        # A GUI value that is not a number at all fails in viser's own handler: one line too.
        send(ws, "GuiUpdateMessage", uuid=viewer.seed._impl.uuid, updates={"value": float("nan")})
        wait_for(lambda: "was not handled" in caplog.text, 10, "the malformed message's line")
        time.sleep(0.3)
        assert viewer.worker.current(cid) == 2  # none of them asked for a render
        # A message viser cannot decode ends that client's connection: one line too.
        send(ws, "ViewerCameraMessage", **{**opening_camera(viewer), "fov": "wide"})
        wait_for(lambda: "connection handler failed: ValueError" in caplog.text, 10, "the undecodable message's line")
    assert "ignored a camera's position" in caplog.text and "of zero length" in caplog.text
    assert "Traceback" not in capfd.readouterr().err


def test_names_are_checked_against_the_current_lists(viewer: StageViewer, caplog: pytest.LogCaptureFixture) -> None:
    with open_socket(viewer, f"?token={viewer.token}") as ws:
        send(ws, "ViewerCameraMessage", **opening_camera(viewer))
        wait_for(lambda: len(viewer.server.get_clients()) == 1, 10, "the client")
        send(ws, "GuiUpdateMessage", uuid=viewer.view._impl.uuid, updates={"value": "../../etc"})
        wait_for(lambda: viewer.view.value == "substitution", 10, "the view put back")
        send(ws, "GuiUpdateMessage", uuid=viewer.seed._impl.uuid, updates={"value": 2**40})
        wait_for(lambda: viewer.seed.value == 0, 10, "the seed put back")
        send(ws, "GuiUpdateMessage", uuid=viewer.selected._impl.uuid, updates={"value": "no_such"})
        send(ws, "GuiUpdateMessage", uuid=viewer.move_button._impl.uuid, updates={"value": True})
        wait_for(lambda: "no instance **no_such**" in viewer.edit_status.content, 10, "the panel's message")
        assert viewer.edit is None
        viewer.draw_box()
        send(ws, "GuiUpdateMessage", uuid=viewer.new_object._impl.uuid, updates={"value": "no_such"})
        send(ws, "GuiUpdateMessage", uuid=viewer.register_button._impl.uuid, updates={"value": True})
        wait_for(lambda: "no library object **no_such**" in viewer.new_status.content, 10, "the panel's message")
    assert "ignored an unknown view from a client: '../../etc'" in caplog.text


# -- the command line -------------------------------------------------------------------------
def test_host_beyond_this_machine_needs_the_acknowledgement(stage: Path, capsys: pytest.CaptureFixture[str],
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    def never(*args: object, **kwargs: object) -> None:
        raise AssertionError("the stage was read before the host was checked")

    monkeypatch.setattr(stage_viewer, "read_stage", never)
    before = snapshot(stage.parent)
    for host in ("0.0.0.0", "::", "192.0.2.7"):
        line = assert_fails(capsys, ["view", str(stage), "--host", host, "--port", "0"], r"--allow-remote-edits")
        assert line.startswith(f"regnf view: --host {host}: others on the network could open the viewer")
    assert changes(before, snapshot(stage.parent)) == []


def test_an_acknowledged_remote_host_warns_and_prints_a_reachable_url(
        stage: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    def stop(_: float) -> None:
        raise KeyboardInterrupt  # what Ctrl-C does to the command's wait

    monkeypatch.setattr(commands_view, "time", types.SimpleNamespace(sleep=stop))
    code, err = run_cli(capsys, ["view", str(stage), "--host", "0.0.0.0", "--port", "0", "--allow-remote-edits",
                                 "--coarse-pixels", str(COARSE), "--refined-pixels", str(REFINED)])
    assert code == EXIT_OK, err
    lines = err.splitlines()
    assert any(re.match(r"warning: the viewer listens on 0\.0\.0\.0: anyone on the network", ln) for ln in lines), err
    url = next(ln for ln in lines if "open http://" in ln)
    assert "0.0.0.0" not in url and "on this machine" not in url
    assert re.search(r"open http://[^/\s]+:\d+/\?token=[\w-]{32,} in a browser", url), url


def test_a_port_in_use_is_one_line(stage: Path, capsys: pytest.CaptureFixture[str]) -> None:
    port = free_port()
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", port))
        holder.listen()
        line = assert_fails(capsys, ["view", str(stage), "--port", str(port)], "is in use")
    assert line == (f"regnf view: 127.0.0.1:{port} is in use by another program; choose another --port "
                    "(--port 0 picks a free one)")


# -- the stage changed on disk ----------------------------------------------------------------
def _rename(stage: Path, old: str, new: str) -> None:
    """Rename instance ``old`` as another program would (the stage written anew)."""
    scene = read_stage(stage)
    scene.instances = {(new if k == old else k): (InstanceRecord(new, v.library_name, v.object_to_scene,
                                                                 v.registration) if k == old else v)
                       for k, v in scene.instances.items()}
    write_stage(scene, stage)


def _refined(viewer: StageViewer, stage: Path) -> np.ndarray:
    """Start an edit of c_1 with a refined result ready to accept (what refine leaves); its pose."""
    viewer.start_edit("c_1")
    M = similarity(0.5, (0.7, 0.5, 0.0), 1.0)
    viewer.edit.payload = registration_json("c", stage.parent / "fields" / "c.safetensors", M)
    return M


def test_accept_on_an_instance_renamed_on_disk_is_a_message(viewer: StageViewer, stage: Path,
                                                           capfd: pytest.CaptureFixture[str]) -> None:
    _refined(viewer, stage)
    _rename(stage, "c_1", "c_9")
    before = snapshot(stage.parent)
    with open_socket(viewer, f"?token={viewer.token}") as ws:  # the browser's accept button
        send(ws, "ViewerCameraMessage", **opening_camera(viewer))
        wait_for(lambda: len(viewer.server.get_clients()) == 1, 10, "the client")
        send(ws, "GuiUpdateMessage", uuid=viewer.accept_button._impl.uuid, updates={"value": True})
        wait_for(lambda: "no longer in the stage" in viewer.edit_status.content, 10, "the panel's message")
    assert viewer.edit is None
    assert list(viewer.scene.instances) == ["c_9"] and "c_9" in viewer.table.content
    assert "changed on disk" in viewer.stage_status.content
    assert changes(before, snapshot(stage.parent)) == []
    assert "Traceback" not in capfd.readouterr().err


def test_an_edit_after_a_change_on_disk_is_confirmed_first(viewer: StageViewer, stage: Path) -> None:
    M = _refined(viewer, stage)
    add_instance(stage, "dc", similarity(-1.1, (-0.9, 0.2, 0.0), 1.0), instance_id="dc_1")
    before = snapshot(stage.parent)
    viewer.accept()  # the stage changed since the viewer read it: reloaded, not written
    assert "press accept again" in viewer.edit_status.content
    assert changes(before, snapshot(stage.parent)) == []
    assert list(viewer.scene.instances) == ["c_1", "dc_1"]
    viewer.accept()  # the user saw the new stage: written
    assert "written to" in viewer.edit_status.content
    on_disk = read_stage(stage)
    assert list(on_disk.instances) == ["c_1", "dc_1"]
    np.testing.assert_allclose(on_disk.instances["c_1"].object_to_scene, M, atol=1e-9)


def test_the_stage_is_watched_and_an_unreadable_one_holds_the_edits(stage: Path,
                                                                    capfd: pytest.CaptureFixture[str]) -> None:
    v = StageViewer(stage, ViewerConfig(port=0, coarse_pixels=COARSE, refined_pixels=REFINED,
                                        stage_poll_seconds=0.1))
    try:
        add_instance(stage, "dc", similarity(-1.1, (-0.9, 0.2, 0.0), 1.0), instance_id="dc_1")
        wait_for(lambda: "changed on disk by another program" in v.stage_status.content, 10, "the reload")
        assert v.selected.options == ("c_1", "dc_1") and "dc_1" in v.table.content
        text = stage.read_text()
        before = snapshot(stage.parent)
        stage.write_text("#usda 1.0\n(\n  garbage\n")  # a hand edit, half done
        wait_for(lambda: "cannot be read now" in v.stage_status.content, 10, "the panel's message")
        v.start_edit("c_1")
        assert v.edit is None and "move selected refused" in v.edit_status.content
        assert list(v.scene.instances) == ["c_1", "dc_1"]  # shown as it was
        stage.write_text(text)  # the edit finished
        wait_for(lambda: "cannot be read" not in v.stage_status.content, 10, "the stage read again")
        v.start_edit("c_1")
        assert v.edit is not None
        assert changes(before, snapshot(stage.parent)) == []
    finally:
        v.close()
    assert "Traceback" not in capfd.readouterr().err


def test_a_browser_opens_at_the_configured_field_of_view_in_degrees(viewer: StageViewer) -> None:
    import math

    assert math.isclose(viewer.server.initial_camera.fov, math.radians(ViewerConfig().opening_fov), rel_tol=1e-6)
