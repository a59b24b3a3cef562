"""What a browser of ``regnf view`` asks to see, and the one thread that renders it: its camera,
the composites the views show (made once per view and seed), and the requests a newer camera
supersedes (:mod:`regnf.viewer.stage_viewer`)."""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from regnf.compositor.from_stage import StageComposite, composite_from_scene
from regnf.compositor.replace import pick_replacements, swapped
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.core.image_io import rgb_to_uint8
from regnf.fields.distance_grid import DistanceGrid
from regnf.render.camera import Camera
from regnf.render.sphere_render import render
from regnf.scene_graph import (
    ComposedScene,
    load_record_field,
    original_selections,
)
from regnf.viewer.messages import render_size
from regnf.viewer.viewer_config import _MODE_OF_VIEW, ViewerConfig


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
