"""Export a stage: the root layer as .usda or .usdc, or a self-contained .usdz package.

The package holds the root layer first (as USD requires), then every asset layer and slot at
the same relative paths as on disk, so the layers' relative asset paths work unchanged inside
it (and the regnf tables in ``customLayerData`` still point at the files). Checkpoints go in as
USD layers carrying their bytes (:mod:`regnf.scene_graph.embedded_checkpoint`): the usdz
specification admits no other file types.

Both kinds of export are made from the stage as read (:func:`read_stage`, which keeps every
asset path inside the stage's folder unless told otherwise), never by copying the files that
happen to lie beside it: what is exported is exactly what the stage names.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path

from pxr import Sdf, UsdUtils

from regnf.core.atomic_io import TEMP_PREFIX

from . import layout as L
from .embedded_checkpoint import (
    CHECKPOINT_SUFFIX,
    checkpoint_file,
    embedded_name,
    is_embedded,
    write_embedded_checkpoint,
)
from .errors import StageError
from .locking import stage_lock
from .model import ComposedScene, ProxyMesh
from .transaction import file_transaction
from .usd_read import read_stage
from .usd_write import write_stage


def export_stage(stage_path: str | os.PathLike, out_path: str | os.PathLike, allow_outside: bool = False,
                 edited_scene: ProxyMesh | None = None, density: float | None = None,
                 library_meshes: Mapping[str, ProxyMesh] | None = None) -> Path:
    """Export ``stage_path`` to ``out_path``; the format follows its suffix.

    ``.usda`` / ``.usdc``: the whole stage is written again beside ``out_path`` (root layer in
    that format, assets as usual; from a package, its checkpoints are unpacked). ``.usdz``:
    one self-contained package. Either way the export is made from the stage as
    :func:`read_stage` read it (not from whatever files lie beside it), so it holds exactly the
    fields the stage names: the stage is read and checked first, and nothing is written if
    that fails. The output folder's lock is held while writing.

    Parameters
    ----------
    stage_path : str or PathLike
        A stage, replacement layer (exported flattened: its selections applied) or package.
    out_path : str or PathLike
        ``.usda``, ``.usdc`` or ``.usdz``.
    allow_outside : bool
        Read a stage whose asset paths leave its folder (see :func:`read_stage`); the files
        they name are then copied INTO the export, which is self-contained.
    edited_scene : ProxyMesh, optional
        The scene less its instances' removal regions, room metres
        (:func:`regnf.compositor.scene_mesh.edited_scene_mesh`): the export shows it (render
        purpose) in place of the whole scene (kept as the proxy).
    density : float, optional
        Give the export physics (``UsdPhysics``): library objects of this density, kg / m^3
        (see :attr:`ComposedScene.physics_density`); None keeps the stage's own setting.
    library_meshes : mapping of str -> ProxyMesh, optional
        Meshes (canonical object metres) that replace the named library objects' proxies in
        the export, e.g. finer ones than the stage keeps.

    Raises
    ------
    StageError
        Anything :func:`read_stage` refuses (an asset path outside the stage's folder among
        them), another suffix.
    regnf.core.file_lock.LockBusy
        Another process kept the output folder locked for too long.
    """
    src = Path(stage_path).absolute()
    out = Path(out_path).absolute()
    if out.suffix not in (".usda", ".usdc", ".usdz"):
        raise StageError(out, "/", "export to .usda, .usdc or .usdz")
    scene = read_stage(src, allow_outside=allow_outside)
    if edited_scene is not None:
        scene = dataclasses.replace(scene, edited_scene=edited_scene)
    if density is not None:
        scene = dataclasses.replace(scene, physics_density=density)
    for name, mesh in (library_meshes or {}).items():
        if name not in scene.library:
            raise StageError(src, "/", f"no library object {name!r} to give a mesh to")
        scene.library[name] = dataclasses.replace(scene.library[name], proxy=mesh)
    if out.suffix in (".usda", ".usdc"):
        with _unpacked(scene) as plain:
            write_stage(plain, out)
        return out
    with contextlib.ExitStack() as stack:
        plain = stack.enter_context(_unpacked(scene))
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix=TEMP_PREFIX)))
        # A loose copy first, written from the model: the package then holds what was read.
        loose = tmp / "loose"
        loose_root = loose / f"{src.stem}.usda"
        write_stage(plain, loose_root)
        packed = tmp / "package"
        root_name = f"{src.stem}.usdc"  # the root layer comes first: USD opens a package's first file
        checkpoints = [L.SCENE_CHECKPOINT] + [L.library_checkpoint(n) for n in sorted(scene.library)]
        layers = [L.library_layer(n) for n in sorted(scene.library)]
        slots = [L.slot_layer(c) for c in scene.classes()]
        entries = [(_packaged_layer(loose_root, packed / root_name), root_name)]
        entries += [(_packaged_layer(loose / rel, packed / rel), rel) for rel in layers]
        entries += [(loose / rel, rel) for rel in slots]
        entries += [(loose / rel, rel) for rel in (L.library_texture(n) for n in sorted(scene.library))
                    if (loose / rel).is_file()]
        for rel in checkpoints:
            name = embedded_name(rel)
            (packed / name).parent.mkdir(parents=True, exist_ok=True)
            entries.append((write_embedded_checkpoint(loose / rel, packed / name), name))
        stack.enter_context(stage_lock(out, create=True))
        tx = stack.enter_context(file_transaction())
        writer = Sdf.ZipFileWriter.CreateNew(str(tx.temp_path(out)))
        for file, rel in entries:
            writer.AddFile(str(file), rel)
        writer.Save()
    return out


@contextlib.contextmanager
def _unpacked(scene: ComposedScene) -> Iterator[ComposedScene]:
    """``scene`` with every checkpoint embedded in a package as a plain (temporary) file."""
    with contextlib.ExitStack() as stack:

        def plain(rec):
            if not is_embedded(str(rec.checkpoint)):
                return rec
            return dataclasses.replace(rec, checkpoint=stack.enter_context(checkpoint_file(rec.checkpoint)))

        yield dataclasses.replace(
            scene,
            scene=plain(scene.scene),
            library={name: plain(rec) for name, rec in scene.library.items()},
        )


def _packaged_layer(src: Path, dest: Path) -> Path:
    """A copy of the layer ``src`` at ``dest`` whose checkpoint paths name the embedded layers."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    layer = Sdf.Layer.FindOrOpen(str(src))
    if layer is None:
        raise StageError(src, "/", "the exported layer cannot be opened")
    layer.Export(str(dest))
    copy = Sdf.Layer.FindOrOpen(str(dest))
    UsdUtils.ModifyAssetPaths(
        copy, lambda p: embedded_name(p) if p.endswith(CHECKPOINT_SUFFIX) else p
    )
    copy.Save()
    return dest
