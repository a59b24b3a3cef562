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

import dataclasses
import math
import secrets
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from regnf.compositor.from_stage import StageComposite, composite_from_scene
from regnf.compositor.render_folder import MAX_PIXELS
from regnf.compositor.replace import pick_replacements, swapped
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.core.cameras import look_at
from regnf.core.image_io import rgb_to_uint8
from regnf.neural_fields.camera import Camera
from regnf.neural_fields.distance_grid import DistanceGrid
from regnf.neural_fields.sphere_render import render
from regnf.neural_fields.sphere_tracer import SphereTracerConfig
from regnf.scene_graph import (
    SCENE_PRIM,
    ComposedScene,
    add_instance_from_registration,
    discovery_line,
    load_record_field,
    original_selections,
    read_stage,
    replacement_base,
)
from regnf.viewer import messages
from regnf.viewer.editing import (
    DEFAULT_BOX_SIZE,
    MIN_BOX_SIZE,
    EditState,
    SampleSets,
    gone,
    instance_samples,
    refine_from_pose,
    register_box,
    write_refined,
)
from regnf.viewer.messages import MAX_ASPECT, one_line_errors, one_line_logs, quiet, render_size
from regnf.viewer.stage_watch import StageWatcher, stamp
from regnf.viewer.trust import check_host, free_port, guarded_server, page_url, uninstall

VIEWS = ("proxies", "scene field", "substitution", "replacement")
"""What the viewport shows: the stage's proxy meshes, or a field render of one composite."""
CHANNELS = ("rgb", "depth", "instance id")
"""Which image of a field render is shown."""

_MODE_OF_VIEW = {"scene field": "scene", "substitution": "substitute", "replacement": "substitute"}
SCENE_SAMPLES_RGB = (40, 110, 255)
"""Colour of a selected registration's scene samples (the benchmark's pictures use blue too)."""
LIBRARY_SAMPLES_RGB = (255, 140, 0)
"""Colour of its library samples (orange)."""
OPENING_GRACE_S = 3.0
"""Seconds after a browser connects during which its camera reports count only once they show
the opening view (see ``StageViewer._on_connect``)."""


@dataclass(frozen=True)
class ViewerConfig:
    """Settings of :func:`serve`."""

    port: int = 8080
    """TCP port of the viewer's web page (0: any free one); a port in use is refused."""
    host: str = "127.0.0.1"
    """Interface to listen on; the default serves this machine only (others need allow_remote_edits)."""
    allow_remote_edits: bool = False
    """Accept a non-loopback ``host``: whoever has the printed URL can then edit the stage."""
    device: str = "cpu"
    """Where the fields are loaded and rendered (``cpu`` or ``cuda``)."""
    coarse_pixels: int = 64 * 48
    """Pixels of the image rendered as soon as the camera moves: a fraction of a second on 2 CPU
    cores (docs/decisions/rendering-speed.md)."""
    refined_pixels: int = 320 * 240
    """Pixels of the image rendered once the camera rests (docs/decisions/rendering-speed.md)."""
    rest_seconds: float = 0.4
    """The camera counts as resting when it has not moved for this long."""
    opening_rest_seconds: float = 3.0
    """Seconds a newly opened page's first view waits before it is refined: the browser is still
    building the page, and a render then takes the CPU from it
    (docs/decisions/rendering-speed.md)."""
    opening_fov: float = 1.1
    """Vertical field of view (radians) of the camera a browser opens with (viser's default
    is 1.31: wider than a room needs)."""
    opening_aspect: float = 2.4
    """The opening view's coarse image is rendered before the server starts, this wide (width
    over height), and cropped to each browser's aspect: any window up to this wide gets its
    first image without waiting for a render."""
    sphere: SphereTracerConfig = field(default_factory=lambda: SphereTracerConfig(footprint_fraction=0.05))
    """The sphere tracer's settings (``regnf render``'s defaults: stop at 5 % of a pixel's
    footprint)."""
    allow_outside: bool = False
    """Open asset paths of the stage that lie outside its folder (refused by default, as in
    ``regnf stage show``)."""
    stage_poll_seconds: float = 1.0
    """Seconds between two checks of the stage's files for changes made by another program."""

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port must be in [0, 65535], got {self.port}")
        check_host(self.host, self.allow_remote_edits)
        if self.coarse_pixels < 1 or self.refined_pixels < self.coarse_pixels:
            raise ValueError("need 1 <= coarse_pixels <= refined_pixels, got "
                             f"{self.coarse_pixels} and {self.refined_pixels}")
        if self.refined_pixels > MAX_PIXELS:
            raise ValueError(f"refined_pixels must be at most {MAX_PIXELS:,}, got {self.refined_pixels:,}")
        if not (math.isfinite(self.stage_poll_seconds) and self.stage_poll_seconds > 0):
            raise ValueError(f"stage_poll_seconds must be finite and > 0, got {self.stage_poll_seconds}")
        for name in ("rest_seconds", "opening_rest_seconds"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {getattr(self, name)}")
        if not 0.05 < self.opening_fov < 3.0:
            raise ValueError(f"opening_fov must be in (0.05, 3) radians, got {self.opening_fov}")
        if not (math.isfinite(self.opening_aspect) and 1.0 <= self.opening_aspect <= MAX_ASPECT):
            raise ValueError(f"opening_aspect must be in [1, {MAX_ASPECT:g}], got {self.opening_aspect}")


class ViewRequest(NamedTuple):
    """What one client wants to see: a camera and the panel's choices."""

    camera_to_world: np.ndarray
    """(4, 4) float64 OpenCV camera -> room metres."""
    fov_y: float
    """Vertical field of view, radians."""
    aspect: float
    """Width over height of the client's viewport."""
    view: str
    """One of :data:`VIEWS`."""
    channel: str
    """One of :data:`CHANNELS`."""
    seed: int
    """The replacement's seed (``view == "replacement"``)."""


def viewer_camera(request: ViewRequest, pixels: int) -> Camera:
    """The pinhole camera of ``request`` with about ``pixels`` square pixels, centred (its size
    bounded by :func:`regnf.viewer.messages.render_size`)."""
    w, h = render_size(pixels, request.aspect)
    f = 0.5 * h / math.tan(0.5 * request.fov_y)
    K = np.array([[f, 0.0, 0.5 * w], [0.0, f, 0.5 * h], [0.0, 0.0, 1.0]])
    return Camera(K, w, h, request.camera_to_world)


def opening_view(scene: ComposedScene, scene_field: Any) -> tuple[np.ndarray, np.ndarray]:
    """(eye, target), (3,) room metres, of the camera a browser opens with.

    It looks at the middle of the instances (of the room, when it has none) from the first of
    a ring of places around it (2.5-1.2 m away, 30-45 degrees up, every 45 degrees about the
    vertical, the side facing the room's centre first) that stands in free space the scene's
    views observed, with free space all the way to the target: a room captured from a few
    places holds a made-up fill where no view looked, and a camera there sees only that (the
    demo's stage, from a fixed corner: a grey image). Without any such place, the first of the
    ring inside the room.
    """
    lo, hi = scene.scene.proxy.extent.astype(np.float64)
    if scene.instances:
        target = np.mean([inst.object_to_scene[:3, 3] for inst in scene.instances.values()], axis=0)
    else:
        target = 0.5 * (lo + hi)
    centre = 0.5 * (lo + hi)
    towards_centre = math.atan2(centre[1] - target[1], centre[0] - target[0]) if np.linalg.norm(
        (centre - target)[:2]) > 1e-6 else -math.pi / 4
    azimuths = towards_centre + np.radians([0, 45, -45, 90, -90, 135, -135, 180])
    elevations, distances = np.radians([35.0, 45.0, 30.0]), np.array([2.5, 2.0, 1.6, 1.2])
    az, el, dist = (g.reshape(-1) for g in np.meshgrid(azimuths, elevations, distances, indexing="ij"))
    eyes = target + dist[:, None] * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    inside = np.all((eyes[:, :2] > lo[:2]) & (eyes[:, :2] < hi[:2]), axis=1)  # within the walls
    # 12 points on each sight line, from the eye to 80 % of the way to the target.
    f = np.linspace(0.0, 0.8, 12)
    line = eyes[:, None, :] + f[None, :, None] * (target - eyes)[:, None, :]  # (m, 12, 3)
    W = scene_field.to_world.detach().cpu().double().numpy()
    local = (line.reshape(-1, 3) - W[:3, 3]) @ np.linalg.inv(W[:3, :3]).T
    x = torch.as_tensor(local, dtype=torch.float32, device=scene_field.device)
    with torch.no_grad():
        free = (scene_field.sdf(x) * scene_field.world_scale > 0.05).reshape(len(eyes), -1).all(dim=1)
        if scene_field.visibility is not None:
            seen = scene_field.visibility.observed(x).reshape(len(eyes), -1).min(dim=1).values >= 0.5
            free = free & seen
    good = np.flatnonzero(free.cpu().numpy() & inside)
    pick = good[0] if len(good) else (np.flatnonzero(inside)[0] if inside.any() else 0)
    return eyes[pick], target


def same_camera(a: ViewRequest, b: ViewRequest, tol: float = 1e-4) -> bool:
    """Whether two requests look from the same camera (pose and field of view within ``tol``:
    metres and radians; a browser reports back the pose it was given in float32)."""
    return (abs(a.fov_y - b.fov_y) < tol
            and bool(np.abs(a.camera_to_world - b.camera_to_world).max() < tol))


def same_view(a: ViewRequest, b: ViewRequest) -> bool:
    """Whether two requests show the same image: the same camera, aspect and panel choices."""
    return (same_camera(a, b) and abs(a.aspect - b.aspect) < 1e-6
            and (a.view, a.channel, a.seed) == (b.view, b.channel, b.seed))


def crop_to_aspect(image: Any, aspect: float) -> Any | None:
    """The centre columns (or rows) of a render that a camera of the same focal length and
    ``aspect`` (width over height) sees, or None if it is wider than the render."""
    h, w = image.rgb.shape[:2]
    cw = max(1, round(h * aspect))
    cw -= (w - cw) % 2  # an even margin: the crop's centre is the render's, to the pixel
    if cw < 1 or cw > w:
        return None
    x0 = (w - cw) // 2
    return type(image)(*(None if t is None else t[:, x0:x0 + cw] for t in image))


def client_pose(position: np.ndarray, wxyz: np.ndarray) -> np.ndarray:
    """(4, 4) camera -> world of a viser camera (OpenCV axes: +Z forward, +Y down)."""
    q = np.asarray(wxyz, dtype=np.float64)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()  # scipy: x, y, z, w
    pose[:3, 3] = np.asarray(position, dtype=np.float64)
    return pose


def wxyz_of(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """viser's (w, x, y, z) quaternion of a rotation matrix (3, 3): the inverse of
    :func:`client_pose`'s rotation."""
    return tuple(float(v) for v in np.roll(Rotation.from_matrix(rotation).as_quat(), 1))  # scipy: x, y, z, w


def colourise(image: Any, channel: str) -> np.ndarray:
    """(h, w, 3) uint8 picture of one channel of a :class:`~regnf.core.render_result.Render`."""
    if channel == "rgb":
        return rgb_to_uint8(image.rgb)
    if channel == "depth":
        d = image.depth.detach().cpu().double().numpy()
        hit = image.mask.detach().cpu().numpy()
        lo, hi = (float(d[hit].min()), float(d[hit].max())) if hit.any() else (0.0, 1.0)
        v = np.where(hit, 1.0 - (d - lo) / max(hi - lo, 1e-9), 0.0)  # near is bright
        return rgb_to_uint8(np.repeat(v[..., None], 3, axis=-1))
    ids = image.instance_id.detach().cpu().numpy()
    return instance_palette(ids)


def instance_palette(ids: np.ndarray) -> np.ndarray:
    """(h, w, 3) uint8 colours of instance ids (h, w): black background, grey scene, hues."""
    golden = (np.maximum(ids, 0) * 0.618034) % 1.0
    hue = np.stack([golden, (golden + 1 / 3) % 1.0, (golden + 2 / 3) % 1.0], axis=-1)
    rgb = 0.35 + 0.6 * np.abs(np.sin(np.pi * hue))
    rgb = np.where((ids == 0)[..., None], 0.5, rgb)
    rgb = np.where((ids < 0)[..., None], 0.0, rgb)
    return rgb_to_uint8(rgb)


class Composites:
    """The composites of one stage, built on first use and kept (fields loaded once)."""

    def __init__(self, stage: Path, scene: ComposedScene, config: ViewerConfig) -> None:
        self.stage, self.scene, self.config = stage, scene, config
        self._loaded: dict[str, Any] = {}
        self._built: dict[tuple[str, int], tuple[StageComposite, DistanceGrid | None]] = {}
        self._originals: dict[str, str] | None = None

    def reset(self, scene: ComposedScene) -> None:
        """The stage changed (an accepted edit): composites are rebuilt on next use."""
        self.scene, self._built, self._originals = scene, {}, None

    def field(self, prim: str, record: Any) -> Any:
        """A field of the stage, loaded once."""
        return load_record_field(self.stage, prim, record, self.config.device, self._loaded)

    def get(self, view: str, seed: int) -> tuple[StageComposite, DistanceGrid | None]:
        """The composite (and its empty-space grid) shown by ``view``."""
        key = (view, seed if view == "replacement" else 0)
        if key not in self._built:
            mode = StageCompositeConfig(mode=_MODE_OF_VIEW[view])
            scene = self.scene
            if view == "replacement":
                # Every instance swapped for a random object of its class; the one it shows
                # now is what is removed.
                originals = {iid: inst.library_name for iid, inst in scene.instances.items()}
                scene = swapped(scene, pick_replacements(scene, seed))
            elif view == "substitution":
                if self._originals is None:
                    self._originals = original_selections(self.stage, self.scene,
                                                          allow_outside=self.config.allow_outside)
                originals = self._originals
            else:
                originals = {}
            comp = composite_from_scene(scene, originals, self.stage, mode, self.config.device,
                                        loaded=self._loaded)
            sphere = self.config.sphere
            grid = (DistanceGrid.build(comp.field, sphere.grid_resolution, sphere.grid_lipschitz)
                    if sphere.grid_resolution > 0 else None)
            self._built[key] = (comp, grid)
        return self._built[key]


def render_request(composites: Composites, req: ViewRequest, pixels: int, config: ViewerConfig) -> Any:
    """The :class:`~regnf.core.render_result.Render` of ``req`` with about ``pixels`` pixels."""
    comp, grid = composites.get(req.view, req.seed)
    # A viewer camera may sit inside an object (flying through a room): show what it sees.
    sphere = dataclasses.replace(config.sphere, check_camera=False)
    with torch.no_grad():
        return render(comp.field, viewer_camera(req, pixels), sphere, grid=grid)


class RenderWorker:
    """One thread that renders the newest request of every client, coarse then refined.

    ``show(client_id, image)`` is called from the worker thread with a (h, w, 3) uint8 picture.
    """

    def __init__(self, composites: Composites, config: ViewerConfig, show,
                 opening: tuple[ViewRequest, Any] | None = None) -> None:
        self.composites, self.config, self.show = composites, config, show
        self.opening = opening
        """The opening view's request and its wide coarse render (cropped per client)."""
        self._lock = threading.Condition()
        self._requests: dict[int, tuple[int, float, ViewRequest, float]] = {}  # id -> (version, time, req, rest)
        self._done: dict[int, tuple[int, str]] = {}  # id -> (version, "coarse" | "refined")
        self._stop = False
        self.errors: list[str] = []
        self._thread = threading.Thread(target=self._loop, name="regnf-view-render", daemon=True)
        self._thread.start()

    def request(self, client_id: int, req: ViewRequest, rest: float | None = None) -> None:
        """Ask for ``req`` (a newer request of the same client supersedes it; one that shows
        the same as the current one changes nothing). Its refined image is rendered once it
        has been current for ``rest`` seconds (``config.rest_seconds`` by default)."""
        with self._lock:
            version, _, current, _ = self._requests.get(client_id, (0, 0.0, None, 0.0))
            if current is not None and same_view(current, req):
                return
            version += 1
            wait = self.config.rest_seconds if rest is None else rest
            self._requests[client_id] = (version, time.monotonic(), req, wait)
            self._lock.notify()

    def forget(self, client_id: int) -> None:
        with self._lock:
            self._requests.pop(client_id, None)
            self._done.pop(client_id, None)

    def stop(self) -> None:
        with self._lock:
            self._stop = True
            self._lock.notify()
        self._thread.join(timeout=30.0)

    def current(self, client_id: int) -> int:
        with self._lock:
            return self._requests.get(client_id, (0,))[0]

    def _next(self) -> tuple[int, int, ViewRequest, str] | None:
        """The next job (client, version, request, level), or None (caller waits)."""
        now = time.monotonic()
        for cid, (version, since, req, rest) in self._requests.items():
            if req.view == "proxies":
                continue
            done = self._done.get(cid)
            if done is None or done[0] != version:
                return cid, version, req, "coarse"
            if done[1] == "coarse" and now - since >= rest:
                return cid, version, req, "refined"
        return None

    def _loop(self) -> None:
        while True:
            with self._lock:
                job = None
                while not self._stop and (job := self._next()) is None:
                    self._lock.wait(timeout=0.05)
                if self._stop:
                    return
            cid, version, req, level = job
            try:
                image = self._render(req, level)
            except Exception as exc:  # noqa: BLE001 (shown in the panel; the viewer keeps running)
                self.errors.append(f"{type(exc).__name__}: {exc}")
                image = None
            with self._lock:
                if self._requests.get(cid, (None,))[0] != version:
                    continue  # the camera or the panel moved on while this rendered
                self._done[cid] = (version, level)
            if image is not None:
                self.show(cid, image, level)

    def _render(self, req: ViewRequest, level: str) -> np.ndarray:
        if level == "coarse" and self.opening is not None:
            first, image = self.opening
            if (req.view, req.seed) == (first.view, first.seed) and same_camera(req, first):
                crop = crop_to_aspect(image, req.aspect)
                if crop is not None:
                    return colourise(crop, req.channel)
        pixels = self.config.coarse_pixels if level == "coarse" else self.config.refined_pixels
        return colourise(render_request(self.composites, req, pixels, self.config), req.channel)


def instance_table(scene: ComposedScene) -> str:
    """Markdown table of the stage's instances: id, class, library object, confidence, source."""
    rows = ["| instance | class | object | confidence | found by |", "|---|---|---|---|---|"]
    for iid, inst in scene.instances.items():
        label = scene.library[inst.library_name].label if inst.library_name in scene.library else "?"
        reg = inst.registration
        if reg is None:
            conf, how = "-", "placed by hand"
        else:
            conf = f"{reg.confidence:.3f}"
            how = "discovery" if reg.discovery is not None else reg.method
            if not reg.accepted:
                how += ", forced" if reg.forced else ", rejected"
        rows.append(f"| {iid} | {label} | {inst.library_name} | {conf} | {how} |")
    if not scene.instances:
        rows.append("| (no instances) | | | | |")
    return "\n".join(rows)


class StageViewer:
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
        # The first view's composite (fields loaded, empty-space grid built: 3.6 s for the demo
        # room) is made before the server starts, so that a browser's first image needs only
        # a render.
        # So is the coarse image of the camera a browser opens with: the browser needs seconds
        # to start its page, and a render then would compete with it for the CPU.
        eye, target = opening_view(self.scene, self.composites.field(SCENE_PRIM, self.scene.scene))
        opening = None
        if self.scene.instances:
            self.composites.get("substitution", 0)
            first = ViewRequest(look_at(eye, target), config.opening_fov, config.opening_aspect,
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
        camera.position, camera.look_at, camera.up, camera.fov = eye, target, (0.0, 0.0, 1.0), config.opening_fov
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
            # faster without them (measured: 0.3-0.4 s of the demo stage's 6 s, 2 cores).
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

    # -- editing ------------------------------------------------------------------------------
    def _add_editing(self) -> None:
        gui = self.server.gui
        # Folded until opened: a page builds folded controls later, and opens faster (measured:
        # 0.4-0.5 s of the demo stage's 6 s on 2 cores).
        with gui.add_folder("Edit", expand_by_default=False):
            self.move_button = gui.add_button("move selected")
            self.refine_button = gui.add_button("refine", disabled=True)
            self.accept_button = gui.add_button("accept", disabled=True)
            self.reject_button = gui.add_button("reject", disabled=True)
            self.edit_status = gui.add_markdown("")
        with gui.add_folder("New instance", expand_by_default=False):
            names = sorted(self.scene.library) or ["(empty library)"]
            self.new_object = gui.add_dropdown("library object", names, initial_value=names[0])
            self.new_size = gui.add_vector3("box size (m)", initial_value=DEFAULT_BOX_SIZE,
                                            min=(MIN_BOX_SIZE,) * 3, step=0.05)
            self.draw_button = gui.add_button("draw box")
            self.register_button = gui.add_button("register box", disabled=True)
            self.add_button = gui.add_button("add instance", disabled=True)
            self.new_status = gui.add_markdown("")
        self.new_box: dict[str, Any] = {}
        for handle, action, what, status in (
                (self.draw_button, lambda: self.draw_box(), "draw box", self.new_status),
                (self.register_button, lambda: self.register_box_async(), "register box", self.new_status),
                (self.add_button, lambda: self.add_new_instance(), "add instance", self.new_status),
                (self.move_button, lambda: self.start_edit(self.selected.value), "move selected", self.edit_status),
                (self.refine_button, lambda: self.refine_async(), "refine", self.edit_status),
                (self.accept_button, lambda: self.accept(), "accept", self.edit_status),
                (self.reject_button, lambda: self.reject(), "reject", self.edit_status)):
            handle.on_click(self._quiet(lambda _, act=action: act(), what, status))
        self.new_size.on_update(self._quiet(lambda _: self._size_box(), "box size", self.new_status))

    def _stage_ready(self, status: Any, action: str, write: bool = False) -> bool:
        """Whether ``action`` may go on. The stage is reloaded first if another program changed
        it; the action is refused (``status`` says why) while the stage on disk cannot be read
        and, for a write, when it has just changed (the user sees the new stage first)."""
        changed = self.watch.sync()
        if self.watch.error is not None:
            status.content = f"{action} refused: the stage on disk cannot be read now ({self.watch.error})"
            return False
        if changed and write:
            status.content = (f"{self.stage.name} was changed on disk by another program and is reloaded: "
                              f"check it, then press {action} again")
            return False
        return True

    def start_edit(self, iid: str) -> None:
        """Put a transform gizmo, with the library proxy, on instance ``iid``."""
        if not self._stage_ready(self.edit_status, "move selected"):
            return
        inst = self.scene.instances.get(iid)
        if inst is None or inst.library_name not in self.scene.library:
            messages.ignored("an unknown instance", iid)
            self.edit_status.content = f"no instance **{iid}** in the stage: choose one in the list"
            return
        self.reject()
        M = inst.object_to_scene
        s = float(np.cbrt(np.linalg.det(M[:3, :3])))
        gizmo = self.server.scene.add_transform_controls(
            "/edit/gizmo", scale=max(0.3, s), position=tuple(M[:3, 3]),
            wxyz=wxyz_of(M[:3, :3] / s))
        rec = self.scene.library[inst.library_name]
        self.server.scene.add_mesh_simple("/edit/gizmo/proxy", rec.proxy.points * s, rec.proxy.faces,
                                          color=(255, 90, 60), opacity=0.6)
        self.edit = EditState(iid, s, gizmo)
        self.refine_button.disabled = False
        self.reject_button.disabled = False
        self.accept_button.disabled = True
        self.edit_status.content = f"drag **{iid}** near its place, then press refine"

    def gizmo_pose(self) -> np.ndarray | None:
        """(4, 4) object -> scene metres of the gizmo, at the edited instance's scale (None,
        logged, when what the client sent is not a pose)."""
        assert self.edit is not None
        g = self.edit.gizmo
        placed = messages.pose(g.position, g.wxyz, "the gizmo")
        return None if placed is None else client_pose(*placed) @ np.diag([self.edit.scale] * 3 + [1.0])

    def refine_async(self) -> threading.Thread | None:
        """Start :meth:`refine` on its own thread (never in a GUI callback's)."""
        if self.edit is None or not self._stage_ready(self.edit_status, "refine"):
            return None
        edit = self.edit
        if edit is None:
            return None  # its instance left the stage: the reload said so
        start = self.gizmo_pose()
        if start is None:
            self.edit_status.content = f"the pose of **{edit.instance_id}**'s gizmo is not a pose: move it again"
            return None
        self.refine_button.disabled = True
        self.edit_status.content = f"refining **{edit.instance_id}** ..."
        thread = threading.Thread(target=self._refine_job, args=(edit, start), daemon=True)
        thread.start()
        return thread

    def _refine_job(self, edit: EditState, start: np.ndarray) -> None:
        try:
            with self._job_lock:
                payload = refine_from_pose(self.stage, self.scene, self.composites, edit.instance_id, start)
        except Exception as exc:  # noqa: BLE001 (reported in the panel; the viewer keeps running)
            self.edit_status.content = f"refine failed: {type(exc).__name__}: {exc}"
            self.refine_button.disabled = False
            return
        with self._edit_lock:
            if self.edit is not edit:
                return  # rejected (or another edit started) meanwhile
            edit.payload = payload
            O = np.asarray(payload["object_to_scene_metres"])
            s = float(np.cbrt(np.linalg.det(O[:3, :3])))
            edit.gizmo.position = tuple(O[:3, 3])
            edit.gizmo.wxyz = wxyz_of(O[:3, :3] / s)
        verdict = "accepted" if payload["accepted"] else "below the acceptance threshold"
        self.edit_status.content = (f"refined **{edit.instance_id}**: confidence {payload['confidence']:.3f} "
                                    f"({verdict}); accept writes it to the stage")
        self.refine_button.disabled = False
        self.accept_button.disabled = False

    def accept(self) -> None:
        """Write the refined pose of the edited instance to the stage."""
        edit = self.edit
        if edit is None or edit.payload is None:
            return
        with self.watch.lock:  # no reload between the check and the write
            ready = self._stage_ready(self.edit_status, "accept", write=True)
            if self.edit is not edit:
                self.edit_status.content = gone(edit.instance_id)
                return
            if not ready:
                return
            try:
                with self.watch.writing():
                    write_refined(self.stage, edit.instance_id, edit.payload, self.config.allow_outside)
            except Exception as exc:  # noqa: BLE001 (reported in the panel; the stage is unchanged)
                self.edit_status.content = f"accept failed: {' '.join(str(exc).split())}"
                return
        self._end_edit(edit, f"**{edit.instance_id}** written to {self.stage.name}")

    def _end_edit(self, edit: EditState, message: str) -> None:
        """Remove the gizmo of ``edit`` (if still the current one) and say ``message``."""
        with self._edit_lock:
            if self.edit is not edit:
                return
            self.edit = None
        self.server.scene.remove_by_name("/edit/gizmo")
        for button in (self.refine_button, self.accept_button, self.reject_button):
            button.disabled = True
        self.edit_status.content = message

    def draw_box(self) -> None:
        """A proposal box standing on the floor below the scene's centre, with a gizmo."""
        if not self._stage_ready(self.new_status, "draw box"):
            return
        lo, hi = self.scene.scene.proxy.extent.astype(np.float64)
        half = 0.5 * self._box_size()
        centre = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), max(lo[2], 0.0) + half[2]])
        gizmo = self.server.scene.add_transform_controls("/new/gizmo", scale=float(max(half.max(), 0.3)),
                                                          position=tuple(centre))
        self.new_box = {"gizmo": gizmo, "payload": None}
        self._size_box()
        self.register_button.disabled = False
        self.add_button.disabled = True
        self.new_status.content = "drag the box around an object, choose the object, press register box"

    def _box_size(self) -> np.ndarray:
        """(3,) size in metres of the panel's box, within [MIN_BOX_SIZE, the room's largest side];
        a size that is not finite (logged) is put back to the default."""
        lo, hi = self.scene.scene.proxy.extent.astype(np.float64)
        size = messages.box_size(self.new_size.value, MIN_BOX_SIZE, max(float((hi - lo).max()), MIN_BOX_SIZE))
        size = np.asarray(DEFAULT_BOX_SIZE) if size is None else size
        if tuple(size) != tuple(self.new_size.value):
            self.new_size.value = tuple(float(v) for v in size)  # its own update redraws the box
        return size

    def _size_box(self) -> None:
        if self.new_box:
            self.server.scene.add_box("/new/gizmo/box", color=(60, 200, 255),
                                      dimensions=tuple(float(v) for v in self._box_size()), wireframe=True)

    def new_box_pose(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(4, 4) rigid pose in scene metres and (3,) half extents of the drawn box (None, logged,
        when what the client sent is not a pose)."""
        g = self.new_box["gizmo"]
        placed = messages.pose(g.position, g.wxyz, "the box")
        return None if placed is None else (client_pose(*placed), 0.5 * self._box_size())

    def register_box_async(self) -> threading.Thread | None:
        """Start the registration inside the drawn box on its own thread."""
        if not self.new_box or not self._stage_ready(self.new_status, "register box"):
            return None
        placed = self.new_box_pose()
        name = messages.known(self.new_object.value, self.scene.library, "library object")
        if placed is None or name is None:
            self.new_status.content = ("the box's pose is not a pose: move it again" if placed is None else
                                       f"no library object **{self.new_object.value}** in the stage: choose one")
            return None
        pose, half = placed
        self.register_button.disabled = True
        self.new_status.content = f"registering **{name}** ..."
        box = self.new_box

        def job() -> None:
            try:
                with self._job_lock:
                    payload = register_box(self.scene, self.composites, name, pose, half)
            except Exception as exc:  # noqa: BLE001 (reported in the panel)
                self.new_status.content = f"registration failed: {type(exc).__name__}: {exc}"
                self.register_button.disabled = False
                return
            if self.new_box is not box:
                return
            box["payload"] = payload
            verdict = "accepted" if payload["accepted"] else "below the acceptance threshold"
            self.new_status.content = (f"**{name}**: confidence {payload['confidence']:.3f} ({verdict}); "
                                       "add instance writes it to the stage")
            self.register_button.disabled = False
            self.add_button.disabled = False

        thread = threading.Thread(target=job, daemon=True)
        thread.start()
        return thread

    def add_new_instance(self) -> str | None:
        """Write the registration of the drawn box as a new instance; returns its id."""
        payload = self.new_box.get("payload") if self.new_box else None
        if payload is None:
            return None
        with self.watch.lock:  # no reload between the check and the write
            if not self._stage_ready(self.new_status, "add instance", write=True):
                return None
            try:
                with self.watch.writing():
                    iid = add_instance_from_registration(self.stage, payload, force=not payload["accepted"],
                                                         allow_outside=self.config.allow_outside)
            except Exception as exc:  # noqa: BLE001 (reported in the panel; the stage is unchanged)
                self.new_status.content = f"add instance failed: {' '.join(str(exc).split())}"
                return None
        self.server.scene.remove_by_name("/new/gizmo")
        self.new_box = {}
        self.register_button.disabled = True
        self.add_button.disabled = True
        self.new_status.content = f"**{iid}** added to {self.stage.name}"
        return iid

    def _reload_from_disk(self, other: bool) -> None:
        """:meth:`_reload` for the stage's watcher (``other``: another program changed it)."""
        try:
            self._reload()
        except (ValueError, OSError) as exc:
            self.stage_status.content = (f"{self.stage.name} changed on disk and cannot be read now; shown as it "
                                         f"was, edits wait: {' '.join(str(exc).split())}")
            raise
        self.stage_status.content = (f"{self.stage.name} was changed on disk by another program: reloaded"
                                     if other else "")

    def _reload(self) -> None:
        """Re-read the stage after an edit or a change on disk: proxies, table, lists,
        composites, renders; an edit whose instance left the stage is dropped."""
        self.scene = read_stage(self.stage, allow_outside=self.config.allow_outside)
        self.composites.reset(self.scene)
        for mesh in self._meshes:
            mesh.remove()
        self._meshes = []
        self._show_proxies()
        self.table.content = instance_table(self.scene)
        ids = list(self.scene.instances) or ["(none)"]
        self.selected.options = ids
        self.new_object.options = sorted(self.scene.library) or ["(empty library)"]
        self._select()
        edit = self.edit
        if edit is not None and edit.instance_id not in self.scene.instances:
            self._end_edit(edit, gone(edit.instance_id))
        self._request_all()

    def reject(self) -> None:
        """Drop the edit: the stage is left untouched."""
        edit = self.edit
        if edit is not None:
            self._end_edit(edit, "edit dropped; the stage is unchanged")

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
