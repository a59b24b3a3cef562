"""The mesh a field was distilled from, kept for tools that render meshes (the stage's render purpose).

A distilled field is the object's geometry and colour as regnf evaluates it; other tools
(Blender, Isaac Sim, usdview) render triangles with materials. The cache keeps the source
mesh beside the checkpoint it made, as a small safetensors file of its own
(:func:`source_mesh_file`), in the field's world frame (metres, +Z up: the distillation's
``scale`` and ``up`` applied), with what it had of its look:

- face colours (a face or vertex coloured mesh; vertex colours averaged per face), or
- texture coordinates per vertex and one base-colour texture (PNG bytes) with its factor,
- else the base colour alone (a grey 0.7 where the file had no material).

Tensors: ``points`` (n, 3) float32, ``faces`` (f, 3) int32, ``base_color`` (3,) float32, and
optionally ``face_colors`` (f, 3) float32, ``uv`` (n, 2) float32 and ``texture`` (b,) uint8.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np
import trimesh
from PIL import Image
from safetensors import SafetensorError
from safetensors.numpy import load_file, save_file

from regnf.core.atomic_io import atomic_path
from regnf.core.errors import RegnfError

SUFFIX = ".source-mesh.safetensors"
"""What the source mesh's file adds to its checkpoint's stem."""

FORMAT = "regnf.source-mesh/1"
"""The format tag in the file's metadata."""

MAX_FACES = 2_000_000
"""Largest source mesh kept, faces (a larger one is not kept: its field's mesh stands in)."""

MAX_TEXTURE_PIXELS = 4096 * 4096
"""Largest base-colour texture kept, pixels."""

GREY = (0.7, 0.7, 0.7)
"""Base colour of a mesh without any colour (as distillation colours it)."""


class SourceMesh(NamedTuple):
    """A triangle mesh with its colours or texture, in a field's world frame."""

    points: np.ndarray
    """(n, 3) float32 vertices, metres."""
    faces: np.ndarray
    """(f, 3) int32 vertex indices."""
    base_color: np.ndarray
    """(3,) float32 linear base colour in [0, 1] (the texture's factor when textured)."""
    face_colors: np.ndarray | None = None
    """(f, 3) float32 colours in [0, 1] per face, or None."""
    uv: np.ndarray | None = None
    """(n, 2) float32 texture coordinates per vertex (origin bottom left), or None."""
    texture: bytes | None = None
    """The base-colour texture as PNG bytes, or None."""


class SourceMeshError(RegnfError):
    """A source mesh file that cannot be used; the message names the file."""


def source_mesh_file(checkpoint: str | os.PathLike) -> Path:
    """Where the source mesh of ``checkpoint`` is kept: beside it, ``<stem>.source-mesh.safetensors``."""
    path = Path(checkpoint)
    return path.with_name(path.stem + SUFFIX)


def _texture_png(mesh: trimesh.Trimesh) -> tuple[bytes | None, np.ndarray | None, np.ndarray]:
    """The texture (PNG bytes), per-vertex uv and base colour of a textured mesh."""
    material = getattr(mesh.visual, "material", None)
    factor = np.asarray(GREY, np.float32)
    image = None
    if material is not None:
        image = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
        raw = getattr(material, "baseColorFactor", None)
        if raw is None:
            raw = getattr(material, "diffuse", None)
        if raw is not None:
            factor = np.asarray(raw, np.float32)[:3]
            factor = factor / 255.0 if factor.max() > 1.0 else factor
    uv = getattr(mesh.visual, "uv", None)
    if image is None or uv is None or len(uv) != len(mesh.vertices):
        return None, None, factor
    if image.width * image.height > MAX_TEXTURE_PIXELS:
        return None, None, factor
    buf = io.BytesIO()
    image.convert("RGB").save(buf, format="PNG")
    return buf.getvalue(), np.asarray(uv, np.float32)[:, :2], factor


def source_mesh_from_trimesh(mesh: trimesh.Trimesh, scale: float = 1.0, up: str = "z") -> SourceMesh | None:
    """The source mesh of a field distilled from ``mesh`` with ``scale`` and ``up`` (its frame).

    Returns None for a mesh over :data:`MAX_FACES` faces or with a non-finite vertex.
    """
    faces = np.asarray(mesh.faces, np.int64)
    points = np.asarray(mesh.vertices, np.float64) * scale
    if len(faces) == 0 or len(faces) > MAX_FACES or not np.isfinite(points).all():
        return None
    if up != "z":
        # Imported here: mesh_repair brings the solid-geometry libraries, which a stage reader does not need.
        from .mesh_repair import up_rotation

        points = points @ up_rotation(up).T
    kind = getattr(mesh.visual, "kind", None)
    texture, uv, factor = (None, None, np.asarray(GREY, np.float32))
    face_colors = None
    if kind == "texture":
        texture, uv, factor = _texture_png(mesh)
    elif kind in ("face", "vertex"):
        face_colors = np.asarray(mesh.visual.face_colors[:, :3], np.float32) / 255.0
        factor = np.ones(3, np.float32)
    return SourceMesh(points.astype(np.float32), faces.astype(np.int32), factor.astype(np.float32),
                      face_colors, uv, texture)


def save_source_mesh(mesh: SourceMesh, path: str | os.PathLike) -> Path:
    """Write ``mesh`` to ``path`` (through a temporary file, then renamed)."""
    tensors = {"points": np.ascontiguousarray(mesh.points, np.float32),
               "faces": np.ascontiguousarray(mesh.faces, np.int32),
               "base_color": np.ascontiguousarray(mesh.base_color, np.float32)}
    if mesh.face_colors is not None:
        tensors["face_colors"] = np.ascontiguousarray(mesh.face_colors, np.float32)
    if mesh.uv is not None and mesh.texture is not None:
        tensors["uv"] = np.ascontiguousarray(mesh.uv, np.float32)
        tensors["texture"] = np.frombuffer(mesh.texture, np.uint8).copy()
    path = Path(path)
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata={"format": FORMAT})
    return path


def _check(ok: bool, path: Path, problem: str) -> None:
    if not ok:
        raise SourceMeshError(f"{path}: {problem}")


def load_source_mesh(path: str | os.PathLike) -> SourceMesh:
    """Read and check a source mesh file.

    Raises
    ------
    SourceMeshError
        Not a source mesh file, or arrays of the wrong shape, type or range.
    """
    path = Path(path)
    try:
        t = load_file(str(path))
    except (OSError, SafetensorError, ValueError) as exc:
        raise SourceMeshError(f"{path}: not a source mesh file ({exc})") from exc
    for key, dtype in (("points", np.float32), ("faces", np.int32), ("base_color", np.float32)):
        _check(key in t and t[key].dtype == dtype, path, f"needs a {np.dtype(dtype).name} tensor '{key}'")
    points, faces, base = t["points"], t["faces"], t["base_color"]
    _check(points.ndim == 2 and points.shape[1] == 3 and len(points) > 0 and np.isfinite(points).all(),
           path, "points must be finite (n, 3), n > 0")
    _check(faces.ndim == 2 and faces.shape[1] == 3 and 0 < len(faces) <= MAX_FACES, path,
           f"faces must be (f, 3), 0 < f <= {MAX_FACES:,}")
    _check(bool((faces >= 0).all() and (faces < len(points)).all()), path, "face indices out of range")
    _check(base.shape == (3,) and bool(((base >= 0) & (base <= 1)).all()), path, "base_color must be 3 values in [0, 1]")
    fc = t.get("face_colors")
    if fc is not None:
        _check(fc.dtype == np.float32 and fc.shape == faces.shape and bool(((fc >= 0) & (fc <= 1)).all()),
               path, "face_colors must be (f, 3) float32 in [0, 1]")
    uv, texture = t.get("uv"), t.get("texture")
    _check((uv is None) == (texture is None), path, "uv and texture go together")
    png = None
    if uv is not None and texture is not None:
        _check(uv.dtype == np.float32 and uv.shape == (len(points), 2) and np.isfinite(uv).all(), path,
               "uv must be finite (n, 2) float32")
        png = texture.tobytes()
        try:
            with Image.open(io.BytesIO(png)) as im:
                _check(im.format == "PNG" and im.width * im.height <= MAX_TEXTURE_PIXELS, path,
                       "the texture must be a PNG of at most 4096 x 4096 pixels")
                im.verify()
        except (OSError, SyntaxError) as exc:
            raise SourceMeshError(f"{path}: the texture is not a readable PNG ({exc})") from exc
    return SourceMesh(points, faces, base, fc, uv, png)


def keep_source_mesh(mesh: trimesh.Trimesh, checkpoint: str | os.PathLike, scale: float = 1.0,
                     up: str = "z") -> Path | None:
    """Keep ``mesh`` as the source mesh of ``checkpoint`` (:func:`source_mesh_file`); None if it
    cannot be kept (see :func:`source_mesh_from_trimesh`)."""
    source = source_mesh_from_trimesh(mesh, scale, up)
    if source is None:
        return None
    return save_source_mesh(source, source_mesh_file(checkpoint))


def read_source_mesh(checkpoint: str | os.PathLike) -> SourceMesh | None:
    """The source mesh kept beside ``checkpoint``, or None if there is none.

    Raises
    ------
    SourceMeshError
        There is one, and it is damaged.
    """
    path = source_mesh_file(checkpoint)
    return load_source_mesh(path) if path.is_file() else None
