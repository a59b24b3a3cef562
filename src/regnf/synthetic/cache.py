"""The cache directory: captures and trained fields are made once, keyed by their inputs.

Layout (default root ``~/.cache/regnf``, or ``$REGNF_CACHE``)::

    captures/object-<name>-<key>/meta_data.json ...
    captures/room-<name>-<coverage>[-<noise>]-<key>/meta_data.json ...   (<noise>: not at ideal)
    fields/<name>-<source>-<key>.safetensors
    fields/<name>-mesh-<key>.source-mesh.safetensors  the mesh a distilled field was made from (regnf.meshes.source_mesh)
    fields/.<name>-mesh-<key>.safetensors.lock        held while a mesh is distilled into that entry
    baked/<room>-<coverage>-<source>/index.json ...   grids ``regnf demo`` bakes from its stage (regnf.datasets.data_set_grids)

``key`` hashes everything the result depends on (generator version, configs, and for a
field the SHA-256 of the bytes of its training data, whatever the spelling of the capture's
path), so a changed input never reuses a stale result. Every entry is written atomically: a
half-made capture has no meta_data.json, a half-written checkpoint never replaces a good one.

A cached field is verified before it is reused (:func:`regnf.io.checkpoint.verify_checkpoint`:
its content digest, and the provenance naming the data it was made from); one that fails
(truncated, flipped bits, an older checkpoint format, another field under its name) is ours,
so it is remade and replaced atomically.

A cached RGB-D field saved before fields recorded where their training views observed space
(no visibility grid, see :mod:`regnf.observations.visibility`) is kept: :meth:`Cache.rgbd_field`
builds the grid from the entry's capture (the one its key and provenance name), attaches it
and re-saves the entry atomically, without retraining. Only the header's ``visibility`` block,
the counts tensor and the digest change; the provenance stays, so the entry is reused.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import re
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Literal, TypeVar

import numpy as np
import trimesh

from regnf.captures.model import Capture
from regnf.captures.sdfstudio import load_capture
from regnf.core.errors import RegnfError
from regnf.core.file_lock import LockUnavailable, file_lock
from regnf.core.preflight import check_output_dir
from regnf.fields.field import FieldInfo, Symmetry
from regnf.io.checkpoint import (
    VISIBILITY_KEY,
    CheckpointError,
    attach_visibility,
    read_header,
    save_field,
    verify_checkpoint,
)
from regnf.meshes.source_mesh import SourceMeshError, keep_source_mesh, read_source_mesh
from regnf.observations.capture_fingerprint import capture_fingerprint
from regnf.synthetic.capture import (
    GENERATOR,
    ObjectCaptureConfig,
    RoomCaptureConfig,
    capture_object,
    capture_room,
)
from regnf.synthetic.library import make_library_object
from regnf.synthetic.sensor_noise import NOISE_LEVELS, NOISE_MODEL_VERSION
from regnf.synthetic.shading import shaded_copy
from regnf.training.distill import (
    DISTILL_VERSION,
    DistillConfig,
    distill_mesh,
    distillation_targets,
    mesh_source,
)
from regnf.training.pose_refinement import PoseRefineConfig
from regnf.training.presets import object_mesh_preset, object_rgbd_preset, scene_rgbd_preset
from regnf.training.training import (
    NOISY_DEPTH_VERSION,
    TRAIN_VERSION,
    RGBDTrainConfig,
    train_rgbd,
)

CACHE_VERSION = 3
"""Bump when the meaning of cached data changes (including a changed default setting).
3: checkpoint format 2 (content digest) and path-independent capture fingerprints."""

log = logging.getLogger(__name__)

TINY_STEPS = 100
"""Training steps of every field at ``Cache.size == "tiny"``."""

CaptureConfig = TypeVar("CaptureConfig", ObjectCaptureConfig, RoomCaptureConfig)
TrainConfig = TypeVar("TrainConfig", RGBDTrainConfig, DistillConfig)


def default_cache_dir() -> Path:
    """``$REGNF_CACHE`` if set, else ``~/.cache/regnf``."""
    return Path(os.environ.get("REGNF_CACHE", "~/.cache/regnf")).expanduser()


def non_default(config: object) -> object:
    """The fields of a (nested) dataclass that differ from their defaults.

    Keying the cache on these only means that adding an option whose default keeps the old
    behaviour does not invalidate every trained field; changing a default's meaning must
    bump a version instead: :data:`~regnf.training.training.TRAIN_VERSION` for what
    training makes, :data:`~regnf.training.distill.DISTILL_VERSION` for distillation,
    :data:`CACHE_VERSION` for everything the cache keeps (captures included).
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


def capture_info(capture: Capture, room: bool = True) -> FieldInfo:
    """Label, name and symmetry of the captured thing, from the capture's ``regnf`` block.

    ``room`` says what a capture without that block (a user's own) holds: a room (label
    ``scene``) or a library object (label ``object``), as the training preset assumes.
    """
    meta = capture.meta or {}
    kind = meta.get("kind", "scene" if room else "object")
    return FieldInfo(
        label="scene" if kind == "scene" else str(meta.get("label", "object")),
        # The folder's real name: a symlink or "." must not change the field's name (or its
        # cache file).
        name=str(meta.get("name", Path(os.path.realpath(capture.root)).name)),
        symmetry=Symmetry.from_json(meta.get("symmetry")),
    )


def capture_files(capture: Capture) -> list[Path]:
    """Every image, depth and depth confidence file the capture's frames name (absolute paths,
    frame order), then every other file its reader read
    (:attr:`~regnf.captures.model.Capture.read_files`: poses, intrinsics), so that a change to
    any input changes the fingerprint."""
    return [
        Path(p) for f in capture.frames for p in (f.rgb_path, f.depth_path, f.confidence_path) if p is not None
    ] + [Path(p) for p in capture.read_files]


def selected_frames(capture: Capture, indices: Sequence[int] | None) -> list[int] | None:
    """``indices`` as a list of ints, or None when they are None or every training frame in order."""
    if indices is None:
        return None
    frames = [int(i) for i in indices]
    return None if frames == capture.train_indices() else frames


def rounded_up(up: Sequence[float]) -> list[float]:
    """An up direction as recorded in a field's provenance and key: 3 floats rounded to 1e-6."""
    return [round(float(v), 6) + 0.0 for v in up]  # + 0.0: no -0.0 in the JSON


def entry_stem(name: str, fallback: str) -> str:
    """``name`` made safe as the start of a cache file name (it comes from a capture's metadata).

    Anything but letters, digits, ``.``, ``_`` and ``-`` becomes ``_`` and leading dots go, so
    that a name such as ``../../x`` cannot place the entry outside the cache.
    """
    stem = re.sub(r"[^A-Za-z0-9._-]", "_", name).lstrip(".")
    return stem[:64] or fallback


def check_entry_writable(entry: Path) -> None:
    """Refuse, before an entry is made (a capture taken, a field trained), a cache that cannot take it.

    Raises
    ------
    regnf.core.preflight.PreflightError
        The entry's folder (or the nearest existing folder above it) is not writable, or is a file.
    """
    check_output_dir(entry.parent, "--cache-dir")


def mesh_digest(mesh: trimesh.Trimesh) -> str:
    """SHA-256 of what a field distilled from ``mesh`` depends on: its vertices, its faces and
    the face colours distillation reads (:func:`regnf.training.distill.face_colors`), which
    a mesh with vertex colours has too. Texture colours are not read, so not hashed."""
    colors = mesh.visual.face_colors.tobytes() if mesh.visual.kind in ("face", "vertex") else b""
    return hashlib.sha256(mesh.vertices.tobytes() + mesh.faces.tobytes() + colors).hexdigest()


@contextlib.contextmanager
def entry_lock(path: Path) -> Iterator[None]:
    """Hold the lock of cache entry ``path`` (``.<name>.lock`` beside it), waiting for another
    process that holds it. Where the file system cannot lock, go on without it: two processes
    then both make the entry, and the atomic writes keep it whole."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as stack:
        try:
            stack.enter_context(file_lock(path.parent / f".{path.name}.lock", "the cache entry", timeout=float("inf")))
        except LockUnavailable as exc:
            log.info("making %s without a lock: %s", path, exc)
        yield


def reusable(path: Path, provenance: dict) -> bool:
    """Whether the cached checkpoint ``path`` exists, is intact and was made from ``provenance``.

    Parameters
    ----------
    path : Path
        A cache entry.
    provenance : dict
        Items its header's provenance must hold (the data hash it was made from).

    Returns
    -------
    bool
        False when there is nothing to reuse; a damaged entry is logged (it will be remade).
    """
    if not path.is_file():
        return False
    try:
        header = verify_checkpoint(path)
    except CheckpointError as exc:
        log.warning("remaking a damaged cache entry: %s", exc)
        return False
    made_from = header.get("provenance", {})
    if any(made_from.get(k) != v for k, v in provenance.items()):
        log.warning("remaking cache entry %s: it was made from other data", path)
        return False
    return True


@dataclasses.dataclass
class Cache:
    """Get-or-make access to captures and trained fields under ``root``."""

    root: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory."""
    progress: bool = True
    """Show progress bars while making things."""
    size: Literal["full", "tiny"] = "full"
    """``full``: the measured captures and training presets. ``tiny``: a smoke-test size (every
    capture with a fifth of the frames at a quarter of the image size, every field a 2-level
    grid trained for :data:`TINY_STEPS` steps) that runs the same code in minutes, for the tests
    of the benchmarks and ``regnf bench gpu-check --size tiny``; its fields are not accurate. Its entries have keys
    of their own (the configs differ), so both sizes share a cache directory."""

    def _capture_config(self, config: CaptureConfig) -> CaptureConfig:
        if self.size == "full":
            return config
        views = config.frame_count() if isinstance(config, RoomCaptureConfig) else config.n_views
        return dataclasses.replace(config, width=config.width // 4, height=config.height // 4,
                                   n_views=max(10, views // 5), heldout_every=5)

    def _train_config(self, config: TrainConfig) -> TrainConfig:
        if self.size == "full":
            return config
        tiny = dataclasses.replace(config.architecture, levels=2,
                                   finest_resolution=2 * config.architecture.base_resolution)
        extra = {"pool_surface": 20_000} if isinstance(config, DistillConfig) else {}
        return dataclasses.replace(config, steps=TINY_STEPS, architecture=tiny, **extra)

    def object_capture(self, name: str, config: ObjectCaptureConfig | None = None) -> Capture:
        """The capture of library object ``name`` (made if missing)."""
        cfg = self._capture_config(config or ObjectCaptureConfig())
        folder = self.root / "captures" / f"object-{name}-{config_key('object', name, _without_progress(cfg), GENERATOR)}"
        if (folder / "meta_data.json").is_file():
            return load_capture(folder)
        check_entry_writable(folder)
        return capture_object(name, folder, dataclasses.replace(cfg, progress=self.progress))

    def room_capture_folder(self, name: str, config: RoomCaptureConfig | None = None) -> Path:
        """Where the capture of room ``name`` is kept (whether or not it is made yet)."""
        cfg = self._capture_config(config or RoomCaptureConfig())
        # A noisy capture's key holds all of its level's settings, defaults included, and the
        # noise model's version: a changed noise model, or a new setting, makes it anew.
        level = (() if cfg.noise == "ideal"
                 else (dataclasses.asdict(NOISE_LEVELS[cfg.noise]), NOISE_MODEL_VERSION))
        key = config_key("room", name, _without_progress(cfg), GENERATOR, *level)
        # The key holds the noise level and seed; the level also shows in the folder's name.
        noise = "" if cfg.noise == "ideal" else f"-{cfg.noise}"
        return self.root / "captures" / f"room-{name}-{cfg.coverage}{noise}-{key}"

    def room_capture(self, name: str, config: RoomCaptureConfig | None = None) -> Capture:
        """The capture of room ``name`` (made if missing)."""
        cfg = self._capture_config(config or RoomCaptureConfig())
        folder = self.room_capture_folder(name, config)
        if (folder / "meta_data.json").is_file():
            return load_capture(folder)
        check_entry_writable(folder)
        return capture_room(name, folder, dataclasses.replace(cfg, progress=self.progress))

    def rgbd_entry(self, capture: Capture, config: RGBDTrainConfig, indices: Sequence[int] | None = None,
                   up: Sequence[float] | None = None) -> tuple[Path, str]:
        """The cache file of the field trained on ``capture`` with ``config``, and the data hash.

        The key hashes the bytes of the capture's metadata file and of every image and depth (see
        :func:`regnf.observations.capture_fingerprint.capture_fingerprint`), so it is the same for any
        spelling of the capture's path and differs as soon as one input file does. It holds the
        training frames ``indices`` unless they are every training frame, and the ``up``
        recorded in the field's provenance unless it is the format's own (``Capture.up``), so
        that the fields of every training frame of regnf's captures keep their keys. The pose
        refinement settings count only where refinement is on for this capture
        (``config.pose_refine``): a capture with exact poses keeps its key.
        """
        fingerprint = capture_fingerprint(capture.root, capture_files(capture), capture.meta_name)
        stem = entry_stem(capture_info(capture).name, "capture")
        # A capture whose zero depth is unknown trains differently from one whose zeros were
        # once taken as empty: its key says so (an ideal capture's key stays as it was).
        # The pose refinement settings count only where they apply ("auto" and "on" then key alike);
        # where it is off the key is the one of a config without them.
        refine = config.pose_refine.enabled(capture.poses_estimated)
        keyed = dataclasses.replace(config, pose_refine=PoseRefineConfig())
        parts = (keyed, fingerprint, TRAIN_VERSION) + (() if capture.zero_depth_is_empty else ("zero-depth-unknown",))
        if refine:
            parts += ({"pose_refine": dataclasses.asdict(dataclasses.replace(config.pose_refine, mode="on"))},)
        # Depth weighted by a noise model trains differently from exact depth (same rule).
        noise = capture.depth_noise
        parts += () if noise is None else ({"depth_noise": dataclasses.asdict(noise), "version": NOISY_DEPTH_VERSION},)
        frames = selected_frames(capture, indices)
        if frames is not None:
            parts += ({"train_indices": frames},)
        if up is not None and not (capture.up is not None and np.allclose(up, capture.up, rtol=0.0, atol=1e-9)):
            parts += ({"up": rounded_up(up)},)
        return self.root / "fields" / f"{stem}-rgbd-{config_key(*parts)}.safetensors", fingerprint

    def rgbd_field(self, capture: Capture, config: RGBDTrainConfig, indices: Sequence[int] | None = None,
                   up: Sequence[float] | None = None) -> Path:
        """Checkpoint of a field trained on ``capture`` with ``config`` (trained if missing or damaged).

        An intact entry without the visibility grid that ``config`` asks for (trained before
        fields recorded one) gets it from ``capture`` and is re-saved, not retrained.

        Parameters
        ----------
        capture : Capture
        config : RGBDTrainConfig
        indices : sequence of int, optional
            Training frames (:func:`regnf.captures.selection.select_frames`); None: every
            training frame. A subset is recorded in the provenance as ``train_indices``.
        up : (3,) float, optional
            The capture's up in its metric world (:mod:`regnf.captures.up_axis`), recorded in
            the provenance as ``up``; it does not change what is trained.
        """
        path, fingerprint = self.rgbd_entry(capture, config, indices, up)
        frames = selected_frames(capture, indices)
        if reusable(path, {"data_sha256": fingerprint}):
            if config.visibility_resolution > 0 and read_header(path).get(VISIBILITY_KEY) is None:
                log.info("adding the visibility grid to cached field %s", path)
                check_entry_writable(path)
                # The key hashed this capture's bytes, so it is the data the field was trained
                # on: the grid is the one training would have attached.
                attach_visibility(
                    path, capture, resolution=config.visibility_resolution,
                    margin=config.visibility_margin, device=config.device, indices=indices,
                )
            return path
        check_entry_writable(path)
        info = capture_info(capture, room=config.architecture.inside_out)
        info.provenance = {"source": "rgbd", "capture": str(capture.root), "data_sha256": fingerprint}
        if frames is not None:
            info.provenance["train_indices"] = frames
        if up is not None:
            info.provenance["up"] = rounded_up(up)
        field, _ = train_rgbd(capture, config, info=info, indices=indices, progress=self.progress)
        return save_field(field, path)

    def object_field(self, name: str, source: str = "rgbd", device: str = "cpu") -> Path:
        """Checkpoint of library object ``name`` trained from RGB-D or distilled from its mesh."""
        if source == "rgbd":
            return self.rgbd_field(self.object_capture(name), self._train_config(object_rgbd_preset(device)))
        if source == "mesh":
            return self.mesh_field(name, self._train_config(object_mesh_preset(device)))
        raise RegnfError(f"unknown source {source!r} (expected 'rgbd' or 'mesh')")

    def mesh_field(self, name: str, config: DistillConfig) -> Path:
        """Checkpoint of library object ``name`` distilled from its procedural mesh."""
        obj = make_library_object(name)
        # Distil the mesh as the captures show it (the same baked Lambertian shading), so that
        # a field from either source has the colours a capture of the object has.
        info = FieldInfo(label=obj.label, name=name, symmetry=Symmetry(obj.symmetry_order))
        return self.distilled_field(shaded_copy(obj.mesh), info, config, source=obj.mesh)

    def distilled_entry(self, mesh: trimesh.Trimesh, info: FieldInfo, config: DistillConfig) -> tuple[Path, str]:
        """The cache file of the field distilled from ``mesh`` with ``config``, and the mesh's
        digest (:func:`mesh_digest`)."""
        mesh_sha = mesh_digest(mesh)
        key = config_key(config, mesh_sha, info.label, info.name, info.symmetry.order, DISTILL_VERSION)
        return self.root / "fields" / f"{entry_stem(info.name, 'mesh')}-mesh-{key}.safetensors", mesh_sha

    def distilled_field(self, mesh: trimesh.Trimesh, info: FieldInfo, config: DistillConfig,
                        source: trimesh.Trimesh | None = None) -> Path:
        """Checkpoint of a field distilled from ``mesh`` (distilled if missing), with its source
        mesh kept beside it (:mod:`regnf.meshes.source_mesh`).

        The mesh is checked and its targets prepared before anything is written; then the
        entry's lock (:func:`entry_lock`) is taken, so that of two processes distilling the
        same mesh with the same settings the second waits and reuses the first's field.
        ``source`` is the mesh as other tools should render it, when it differs from ``mesh``
        (a mesh with baked shading distilled, its plain colours kept).
        """
        path, mesh_sha = self.distilled_entry(mesh, info, config)
        if reusable(path, {"mesh_sha256": mesh_sha}):
            self._keep_source(source if source is not None else mesh, path, config)
            return path
        check_entry_writable(path)
        targets = distillation_targets(mesh, config, mesh_source(info))
        with entry_lock(path):
            if not reusable(path, {"mesh_sha256": mesh_sha}):  # else made by another process meanwhile
                info.provenance = {**info.provenance, "source": "mesh", "mesh_sha256": mesh_sha}
                field, _ = distill_mesh(mesh, config, info=info, progress=self.progress, targets=targets)
                save_field(field, path)
            self._keep_source(source if source is not None else mesh, path, config)
        return path

    @staticmethod
    def _keep_source(mesh: trimesh.Trimesh, path: Path, config: DistillConfig) -> None:
        """Write the source mesh of the entry ``path`` unless an intact one is there."""
        try:
            if read_source_mesh(path) is not None:
                return
        except SourceMeshError as exc:
            log.warning("remaking a damaged source mesh: %s", exc)
        keep_source_mesh(mesh, path, config.scale, config.up)

    def scene_field(self, name: str, coverage: str = "full", device: str = "cpu", noise: str = "ideal",
                    noise_seed: int = 0, pose_refine: str = "auto") -> Path:
        """Checkpoint of room ``name`` trained from its ``coverage`` capture made at sensor and
        pose noise level ``noise`` with seed ``noise_seed`` (:class:`RoomCaptureConfig`), its
        poses refined as ``pose_refine`` says (:class:`~regnf.training.pose_refinement.PoseRefineConfig`)."""
        capture = self.room_capture(name, RoomCaptureConfig(coverage=coverage, noise=noise, noise_seed=noise_seed))
        config = self._train_config(scene_rgbd_preset(device))
        config = dataclasses.replace(config, pose_refine=dataclasses.replace(config.pose_refine, mode=pose_refine))
        return self.rgbd_field(capture, config)
