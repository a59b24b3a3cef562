"""``regnf view``: a local web viewer of a stage (viser), with field renders from the compositor.

What it shows (all in room metres, +Z up):

- the stage's proxies: the scene's mesh and each instance's library proxy placed by its
  ``object_to_scene``; a side panel lists every instance with its class, library object,
  confidence and how its transform was found, and draws the selected instance's proposal box
  and, on request ("show sample sets"), the two point sets its registration compares: the
  scene's surface samples inside the box and the library object's, placed by its pose;
- a render of the viewer's own camera, from the project's compositor: the scene field alone, the
  substitution (every instance replaced by its library field) or a random replacement (seed
  chosen in the panel), as RGB, depth or instance ids. Progressive: a coarse image as soon as
  the camera moves, the full-size one once it rests (``ViewerConfig.rest_seconds``);
- editing: "move selected" puts a transform gizmo (with the library proxy) on the selected
  instance; "refine" runs the registration's refinement from the dragged pose
  (:func:`regnf.registration.register` with ``initial``); "accept" writes the refined pose to
  the stage (:func:`regnf.scene_graph.set_instance`: locked, atomic), its provenance saying it
  was refined from a pose set by hand; "reject" leaves the stage untouched;
- a new instance: "draw box" puts a proposal box (size in the panel) on the floor to be dragged
  around an object; "register box" registers the library object chosen in the list inside it
  (the whole pipeline); "add instance" writes the result to the stage.

Rendering runs on one worker thread, never on viser's event loop or in a GUI callback: a busy
render delays only the next image, not the panel. A newer camera supersedes a queued request;
an image whose camera moved while it rendered is dropped.

The stage is read (and refused with the same one-line error as ``regnf stage show``) before
any server starts, and the port is checked free (:mod:`regnf.viewer.trust`).

Only the viewer's own page edits: requests must name the viewer's address and carry the
session's token (:attr:`StageViewer.url`; :mod:`regnf.viewer.trust`), and what a page sends is
checked before use (:mod:`regnf.viewer.messages`). A stage changed on disk by another program
is reloaded, on a timer and before each edit (:mod:`regnf.viewer.stage_watch`); a write it
makes stale is refused with a message in the panel.
"""

from __future__ import annotations

import math
import secrets
import threading
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from regnf.core.cameras import look_at
from regnf.scene_graph import (
    SCENE_PRIM,
    discovery_line,
    read_stage,
    replacement_base,
)
from regnf.viewer import messages
from regnf.viewer.edit_panel import EditPanel, instance_table
from regnf.viewer.editing import (
    EditState,
    SampleSets,
    instance_samples,
)
from regnf.viewer.messages import one_line_errors, one_line_logs, quiet
from regnf.viewer.render_worker import (
    Composites,
    RenderWorker,
    ViewRequest,
    client_pose,
    instance_palette,
    opening_view,
    render_request,
    same_camera,
    wxyz_of,
)
from regnf.viewer.stage_watch import StageWatcher, stamp
from regnf.viewer.trust import free_port, guarded_server, page_url, uninstall
from regnf.viewer.viewer_config import (
    CHANNELS,
    LIBRARY_SAMPLES_RGB,
    OPENING_GRACE_S,
    SCENE_SAMPLES_RGB,
    VIEWS,
    ViewerConfig,
)


class StageViewer(EditPanel):
    """A running viewer of one stage: the viser server, its panel and the render worker."""

    def __init__(self, stage: str | Path, config: ViewerConfig = ViewerConfig()) -> None:
        self.stage = Path(stage)
        # Read (and refuse) the stage before any socket is opened.
        before = stamp(self.stage)
        self.scene = read_stage(self.stage, allow_outside=config.allow_outside)
        base = replacement_base(self.stage, allow_outside=config.allow_outside)
        self.config = config
        # A port in use is refused before the fields load and the first image renders.
        port = free_port(config.host, config.port)
        self.composites = Composites(self.stage, self.scene, config)
        # The first view's composite (fields loaded, empty-space grid built) is made before the
        # server starts, so that a browser's first image needs only a render
        # (docs/decisions/rendering-speed.md).
        # So is the coarse image of the camera a browser opens with: the browser needs seconds
        # to start its page, and a render then would compete with it for the CPU.
        eye, target = opening_view(self.scene, self.composites.field(SCENE_PRIM, self.scene.scene))
        opening = None
        if self.scene.instances:
            self.composites.get("substitution", 0)
            first = ViewRequest(look_at(eye, target), math.radians(config.opening_fov), config.opening_aspect,
                                "substitution", "rgb", 0)
            wide = round(config.coarse_pixels * config.opening_aspect * 0.75)  # a 4:3 coarse image's height
            opening = (first, render_request(self.composites, first, wide, config))
        self.token = secrets.token_urlsafe(24)
        """The session's token: the page's URL carries it (:attr:`url`)."""
        self.server, self._guard = guarded_server(config.host, port, self.token)
        one_line_errors(self.server._websock_server._background_event_loop)  # viser has no public handle
        one_line_logs()
        # An image finished after its page closed has nowhere to go: not worth a warning.
        warnings.filterwarnings("ignore", message="Queued a .* on a closed connection", category=UserWarning)
        self.server.scene.set_up_direction("+z")
        camera = self.server.initial_camera
        camera.position, camera.look_at, camera.up, camera.fov = eye, target, (0.0, 0.0, 1.0), math.radians(config.opening_fov)
        self._meshes: list[Any] = []
        self._box = None
        self.edit: EditState | None = None
        self._edit_lock = threading.Lock()
        # One registration job (refine, register box, sampling) at a time: they share the
        # fields and set torch's process-wide thread count (regnf.core.threads).
        self._job_lock = threading.Lock()
        self._sample_clouds: list[Any] = []
        self._samples_for: tuple[str, bytes] | None = None
        self._samples_cache: dict[tuple[str, bytes], SampleSets] = {}
        self.shown_at: dict[str, float] = {}
        """``time.monotonic()`` when the first ``coarse`` and ``refined`` images were sent."""
        self._add_panel()
        self._add_editing()
        self.worker = RenderWorker(self.composites, config, self._show, opening)
        self.server.on_client_connect(self._quiet(self._on_connect, "a new page"))
        self.server.on_client_disconnect(lambda client: self.worker.forget(client.client_id))
        self.watch = StageWatcher(self.stage, base, tuple(sorted(before + stamp(base) if base else before)),
                                  self._reload_from_disk, config.stage_poll_seconds)
        self.watch.start()

    @property
    def port(self) -> int:
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        """The page's URL, with the session's token (what ``regnf view`` prints)."""
        return page_url(self.config.host, self.port, self.token)

    def _quiet(self, callback: Any, what: str, status: Any = None) -> Any:
        """``callback`` for viser, whose error is one logged line (and shown in ``status``)."""
        def report(line: str) -> None:
            if status is not None:
                status.content = line

        return quiet(callback, what, report)

    # -- the stage ---------------------------------------------------------------------------
    def _add_proxies(self) -> None:
        proxy = self.scene.scene.proxy
        self._meshes.append(self.server.scene.add_mesh_simple(
            "/stage/scene", proxy.points, proxy.faces, color=(180, 180, 180), side="double"))
        for iid, inst in self.scene.instances.items():
            rec = self.scene.library.get(inst.library_name)
            if rec is None:
                continue
            M = inst.object_to_scene
            pts = rec.proxy.points.astype(np.float64) @ M[:3, :3].T + M[:3, 3]
            colour = tuple(int(c) for c in (instance_palette(np.array([[len(self._meshes)]]))[0, 0]))
            self._meshes.append(self.server.scene.add_mesh_simple(
                f"/stage/instances/{iid}", pts.astype(np.float32), rec.proxy.faces, color=colour))

    def _add_panel(self) -> None:
        gui = self.server.gui
        with gui.add_folder("View"):
            self.view = gui.add_dropdown("show", VIEWS, initial_value="substitution")
            self.channel = gui.add_dropdown("channel", CHANNELS, initial_value="rgb")
            self.seed = gui.add_number("replacement seed", initial_value=0, min=0, step=1)
            self.status = gui.add_markdown("")
        with gui.add_folder("Instances"):
            self.table = gui.add_markdown(instance_table(self.scene))
            self.stage_status = gui.add_markdown("")
            ids = list(self.scene.instances) or ["(none)"]
            self.selected = gui.add_dropdown("selected", ids, initial_value=ids[0])
            self.show_samples = gui.add_checkbox("show sample sets", initial_value=False)
            self.details = gui.add_markdown("")
            self.samples_status = gui.add_markdown("")
        for handle, what in ((self.view, "show"), (self.channel, "channel"), (self.seed, "replacement seed")):
            handle.on_update(self._quiet(lambda event: self._view_changed(event.target), what, self.status))
        self.selected.on_update(self._quiet(lambda _: self._select(), "select", self.details))
        self.show_samples.on_update(self._quiet(lambda _: self.update_samples(), "show sample sets",
                                                self.samples_status))
        self._select()
        self._show_proxies()

    def _view_changed(self, handle: Any) -> None:
        """A choice of the View panel changed: an unknown one (logged) is put back, else the
        proxies and every client's image follow."""
        if handle is self.seed:
            if messages.seed(handle.value) is None:
                handle.value = 0  # its own update follows
                return
        else:
            names, fallback, what = ((VIEWS, "substitution", "view") if handle is self.view
                                     else (CHANNELS, "rgb", "channel"))
            if messages.known(handle.value, names, what) is None:
                handle.value = fallback  # its own update follows
                return
        if handle is self.view:
            self._show_proxies()
        self._request_all()

    def _show_proxies(self) -> None:
        visible = self.view.value == "proxies"
        if visible and not self._meshes:
            # Sent when first shown, not with the page: a page that opens on a render starts
            # faster without them (docs/decisions/rendering-speed.md).
            self._add_proxies()
        for mesh in self._meshes:
            mesh.visible = visible
        if visible:
            for client in self.server.get_clients().values():
                client.scene.set_background_image(None)

    def _select(self) -> None:
        inst = self.scene.instances.get(self.selected.value)
        if self._box is not None:
            self._box.remove()
            self._box = None
        if inst is None:
            if self.selected.value != "(none)":
                messages.ignored("an unknown instance", self.selected.value)
            self.details.content = ""
            return
        reg = inst.registration
        lines = [f"**{inst.id}**: `{inst.library_name}`"]
        if reg is not None:
            lines.append(f"method {reg.method}, confidence {reg.confidence:.3f}, "
                         f"{'accepted' if reg.accepted else 'not accepted'}"
                         f"{' (forced)' if reg.forced else ''}")
            lines += [f"{k}: {v:.4g}" for k, v in sorted(reg.timings.items())]
            if reg.discovery is not None:
                lines.append(discovery_line(reg.discovery))
            if reg.proposal_center is not None and reg.proposal_half_extents is not None:
                S = self.scene.scene.to_world
                s = float(np.cbrt(abs(np.linalg.det(S[:3, :3]))))
                R_box = np.eye(3) if reg.proposal_rotation is None else reg.proposal_rotation
                R = (S[:3, :3] / s) @ R_box
                centre = S[:3, :3] @ reg.proposal_center + S[:3, 3]
                self._box = self.server.scene.add_box(
                    "/selection/proposal", color=(255, 200, 0),
                    dimensions=tuple(2.0 * s * reg.proposal_half_extents), wireframe=True,
                    position=tuple(centre), wxyz=wxyz_of(R))
        else:
            lines.append("placed by hand")
        self.details.content = "\n\n".join(lines)
        self.update_samples()

    def update_samples(self) -> threading.Thread | None:
        """Show the selected instance's two sample sets (computed on a thread: about a second
        or two of sampling), or hide them when "show sample sets" is off."""
        for handle in self._sample_clouds:
            handle.remove()
        self._sample_clouds = []
        self._samples_for = None
        iid = self.selected.value
        if not self.show_samples.value or iid not in self.scene.instances:
            self.samples_status.content = ""
            return None
        self._samples_for = key = (iid, self.scene.instances[iid].object_to_scene.tobytes())
        self.samples_status.content = f"sampling **{iid}** ..."
        scene = self.scene

        def job() -> None:
            try:
                with self._job_lock:
                    sets = self._samples_cache.get(key) or instance_samples(scene, self.composites, iid)
                self._samples_cache[key] = sets
            except Exception as exc:  # noqa: BLE001 (reported in the panel; the viewer keeps running)
                self.samples_status.content = f"sampling failed: {type(exc).__name__}: {exc}"
                return
            if self._samples_for != key:
                return  # another instance was selected, or the samples were hidden, meanwhile
            size = 0.004 * float(np.linalg.norm(np.ptp(sets.library, axis=0)))
            self._sample_clouds = [
                self.server.scene.add_point_cloud(f"/selection/samples/{side}", pts.astype(np.float32),
                                                  colors=colour, point_size=size, precision="float32")
                for side, pts, colour in (("scene", sets.scene, SCENE_SAMPLES_RGB),
                                          ("library", sets.library, LIBRARY_SAMPLES_RGB))]
            self.samples_status.content = (f"sample sets of **{iid}**: {len(sets.scene)} scene samples (blue), "
                                           f"{len(sets.library)} library samples at its pose (orange)")

        thread = threading.Thread(target=job, name="regnf-view-samples", daemon=True)
        thread.start()
        return thread

    # -- clients and renders -----------------------------------------------------------------
    def _on_connect(self, client: Any) -> None:
        # A browser opens at the initial camera, but first reports the camera its page starts
        # with (viser 1.1: 5 m along -x), 0.5-1 s before; rendering that would keep the worker
        # busy when the real one arrives. So ask at once for the opening view (its coarse image
        # is ready), and ignore the client's cameras until it reports that one, or for
        # OPENING_GRACE_S at most.
        connected = time.monotonic()
        settled = [False]

        def camera_moved(_: Any) -> None:
            if not settled[0]:
                cam = messages.camera(client.camera.position, client.camera.wxyz, client.camera.fov)
                if cam is None:
                    return
                reported = ViewRequest(client_pose(cam[0], cam[1]), cam[2], 1.0, "", "", 0)
                opening = ViewRequest(look_at(self.server.initial_camera.position, self.server.initial_camera.look_at),
                                      float(self.server.initial_camera.fov), 1.0, "", "", 0)
                settled[0] = same_camera(reported, opening) or time.monotonic() - connected > OPENING_GRACE_S
                if not settled[0]:
                    return
            self._request(client)

        client.camera.on_update(self._quiet(camera_moved, "a camera update", self.status))
        self._request(client, opening=True)

    def _request_all(self) -> None:
        for client in self.server.get_clients().values():
            self._request(client)

    def _request(self, client: Any, opening: bool = False) -> None:
        """Ask the worker for ``client``'s view: its camera (or the opening one) and the panel's
        choices, each checked (:mod:`regnf.viewer.messages`); one that is not usable (logged)
        asks for nothing."""
        cam = client.camera
        aspect = messages.viewport_aspect(cam.image_width, cam.image_height)
        if opening:
            initial = self.server.initial_camera
            pose, fov = look_at(initial.position, initial.look_at), float(initial.fov)
        else:
            got = messages.camera(cam.position, cam.wxyz, cam.fov)
            if got is None:
                return
            pose, fov = client_pose(got[0], got[1]), got[2]
        view = messages.known(self.view.value, VIEWS, "view")
        channel = messages.known(self.channel.value, CHANNELS, "channel")
        seed = messages.seed(self.seed.value)
        if view is None or channel is None or seed is None:
            return
        req = ViewRequest(pose, fov, aspect, view, channel, seed)
        self.worker.request(client.client_id, req, self.config.opening_rest_seconds if opening else None)

    def _show(self, client_id: int, image: np.ndarray, level: str) -> None:
        client = self.server.get_clients().get(client_id)
        if client is None or self.view.value == "proxies":
            return
        client.scene.set_background_image(image, format="png")
        self.shown_at.setdefault(level, time.monotonic())
        self.status.content = f"{level} render {image.shape[1]} x {image.shape[0]}"
        if self.worker.errors:
            self.status.content += f"\n\nlast error: {self.worker.errors[-1]}"

    def close(self) -> None:
        """Stop the stage's watcher, the render worker and the server."""
        self.watch.stop()
        self.worker.stop()
        self.server.stop()
        uninstall(self._guard)


def serve(stage: str | Path, config: ViewerConfig = ViewerConfig()) -> StageViewer:
    """Start a viewer of ``stage`` (returns at once; :meth:`StageViewer.close` stops it; its page
    is :attr:`StageViewer.url`).

    Raises :class:`~regnf.scene_graph.StageError` (naming the stage) before any server starts if
    the stage cannot be read, and :class:`~regnf.viewer.trust.TrustError` if the port is in use.
    """
    return StageViewer(stage, config)
