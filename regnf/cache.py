"""The cache directory: captures and trained fields are made once, keyed by their inputs.

Layout (default root ``~/.cache/regnf``, or ``$REGNF_CACHE``)::

    captures/object-<name>-<key>/meta_data.json ...
    captures/room-<name>-<coverage>-<key>/meta_data.json ...
    fields/<name>-<source>-<key>.safetensors

``key`` hashes everything the result depends on (generator version, configs, and for a
field the SHA-256 of its training data), so a changed input never reuses a stale result.
Every entry is written atomically: a half-made capture has no meta_data.json, a half-written
checkpoint never replaces a good one.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path

import trimesh

from neural_fields.checkpoint import save_field
from neural_fields.distill import DistillConfig, distill_mesh
from neural_fields.field import FieldInfo, Symmetry
from neural_fields.presets import object_mesh_preset, object_rgbd_preset, scene_rgbd_preset
from neural_fields.training import RGBDTrainConfig, capture_fingerprint, train_rgbd
from synthetic.capture import ObjectCaptureConfig, RoomCaptureConfig, capture_object, capture_room
from synthetic.library import make_library_object
from synthetic.sdfstudio_format import Capture, load_capture
from synthetic.shading import shaded_copy

CACHE_VERSION = 2
"""Bump when the meaning of cached data changes (including a changed default setting)."""


def default_cache_dir() -> Path:
    """``$REGNF_CACHE`` if set, else ``~/.cache/regnf``."""
    return Path(os.environ.get("REGNF_CACHE", "~/.cache/regnf")).expanduser()


def non_default(config: object) -> object:
    """The fields of a (nested) dataclass that differ from their defaults.

    Keying the cache on these only means that adding an option whose default keeps the old
    behaviour does not invalidate every trained field; changing a default's meaning must
    bump :data:`CACHE_VERSION` instead.
    """
    if not dataclasses.is_dataclass(config):
        return config
    out = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
            default = f.default_factory()  # type: ignore[misc]
        else:
            default = dataclasses.MISSING
        if dataclasses.is_dataclass(value):
            nested = non_default(value)
            if nested:
                out[f.name] = nested
        elif default is dataclasses.MISSING or value != default:
            out[f.name] = value
    return out


def config_key(*parts: object) -> str:
    """A short stable hash of JSON-serialisable parts (dataclasses: their non-default fields)."""
    text = json.dumps([CACHE_VERSION, *[non_default(p) for p in parts]], sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def _without_progress(config: object) -> object:
    # Whether a progress bar was shown does not change what was made.
    return dataclasses.replace(config, progress=True)


def capture_info(capture: Capture) -> FieldInfo:
    """Label, name and symmetry of the captured thing, from the capture's ``regnf`` block."""
    meta = capture.meta or {}
    kind = meta.get("kind", "scene")
    return FieldInfo(
        label="scene" if kind == "scene" else str(meta.get("label", "object")),
        name=str(meta.get("name", capture.root.name)),
        symmetry=Symmetry.from_json(meta.get("symmetry")),
    )


def capture_files(capture: Capture) -> list[str]:
    """Paths (relative to the capture root) of every image and depth file it references."""
    rel = []
    for f in capture.frames:
        for p in (f.rgb_path, f.depth_path):
            if p is not None:
                rel.append(str(Path(p).relative_to(capture.root)) if Path(p).is_absolute() else str(p))
    return rel


@dataclasses.dataclass
class Cache:
    """Get-or-make access to captures and trained fields under ``root``."""

    root: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory."""
    progress: bool = True
    """Show progress bars while making things."""

    def object_capture(self, name: str, config: ObjectCaptureConfig | None = None) -> Capture:
        """The capture of library object ``name`` (made if missing)."""
        cfg = config or ObjectCaptureConfig()
        folder = self.root / "captures" / f"object-{name}-{config_key('object', name, _without_progress(cfg))}"
        if (folder / "meta_data.json").is_file():
            return load_capture(folder)
        return capture_object(name, folder, dataclasses.replace(cfg, progress=self.progress))

    def room_capture(self, name: str, config: RoomCaptureConfig | None = None) -> Capture:
        """The capture of room ``name`` (made if missing)."""
        cfg = config or RoomCaptureConfig()
        key = config_key("room", name, _without_progress(cfg))
        folder = self.root / "captures" / f"room-{name}-{cfg.coverage}-{key}"
        if (folder / "meta_data.json").is_file():
            return load_capture(folder)
        return capture_room(name, folder, dataclasses.replace(cfg, progress=self.progress))

    def rgbd_field(self, capture: Capture, config: RGBDTrainConfig) -> Path:
        """Checkpoint of a field trained on ``capture`` with ``config`` (trained if missing)."""
        info = capture_info(capture)
        fingerprint = capture_fingerprint(capture.root, capture_files(capture))
        path = self.root / "fields" / f"{info.name}-rgbd-{config_key(config, fingerprint)}.safetensors"
        if path.is_file():
            return path
        info.provenance = {"source": "rgbd", "capture": str(capture.root), "data_sha256": fingerprint}
        field, _ = train_rgbd(capture, config, info=info, progress=self.progress)
        return save_field(field, path)

    def object_field(self, name: str, source: str = "rgbd", device: str = "cpu") -> Path:
        """Checkpoint of library object ``name`` trained from RGB-D or distilled from its mesh."""
        if source == "rgbd":
            return self.rgbd_field(self.object_capture(name), object_rgbd_preset(device))
        if source == "mesh":
            return self.mesh_field(name, object_mesh_preset(device))
        raise ValueError(f"unknown source {source!r} (expected 'rgbd' or 'mesh')")

    def mesh_field(self, name: str, config: DistillConfig) -> Path:
        """Checkpoint of library object ``name`` distilled from its procedural mesh."""
        obj = make_library_object(name)
        # Distil the mesh as the captures show it (the same baked Lambertian shading), so that
        # a field from either source has the colours a capture of the object has.
        info = FieldInfo(label=obj.label, name=name, symmetry=Symmetry(obj.symmetry_order))
        return self.distilled_field(shaded_copy(obj.mesh), info, config)

    def distilled_field(self, mesh: trimesh.Trimesh, info: FieldInfo, config: DistillConfig) -> Path:
        """Checkpoint of a field distilled from ``mesh`` (distilled if missing)."""
        colors = mesh.visual.face_colors.tobytes() if mesh.visual.kind == "face" else b""
        mesh_sha = hashlib.sha256(mesh.vertices.tobytes() + mesh.faces.tobytes() + colors).hexdigest()
        key = config_key(config, mesh_sha, info.label, info.name, info.symmetry.order)
        path = self.root / "fields" / f"{info.name or 'mesh'}-mesh-{key}.safetensors"
        if path.is_file():
            return path
        info.provenance = {**info.provenance, "source": "mesh", "mesh_sha256": mesh_sha}
        field, _ = distill_mesh(mesh, config, info=info, progress=self.progress)
        return save_field(field, path)

    def scene_field(self, name: str, coverage: str = "full", device: str = "cpu") -> Path:
        """Checkpoint of room ``name`` trained from its ``coverage`` capture."""
        capture = self.room_capture(name, RoomCaptureConfig(coverage=coverage))
        return self.rgbd_field(capture, scene_rgbd_preset(device))
