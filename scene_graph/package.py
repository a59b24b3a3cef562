"""Export a stage: the root layer as .usda or .usdc, or a self-contained .usdz package.

The package holds the root layer first (as USD requires), then every asset layer and slot at
the same relative paths as on disk, so the layers' relative asset paths work unchanged inside
it (and the regnf tables in ``customLayerData`` still point at the files). Checkpoints go in as
USD layers carrying their bytes (:mod:`scene_graph.embedded_checkpoint`): the usdz
specification admits no other file types.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from pxr import Sdf, UsdUtils

from . import layout as L
from .embedded_checkpoint import (
    CHECKPOINT_SUFFIX,
    checkpoint_file,
    embedded_name,
    is_embedded,
    write_embedded_checkpoint,
)
from .errors import StageError
from .model import ComposedScene
from .transaction import file_transaction
from .usd_read import open_stage, read_stage
from .usd_write import write_stage


def export_stage(stage_path: str | os.PathLike, out_path: str | os.PathLike) -> Path:
    """Export ``stage_path`` to ``out_path``; the format follows its suffix.

    ``.usda`` / ``.usdc``: the whole stage is written again beside ``out_path`` (root layer in
    that format, assets as usual; from a package, its checkpoints are unpacked). ``.usdz``:
    one self-contained package. The stage is read and checked first; nothing is written if
    that fails.
    """
    src = Path(stage_path).absolute()
    out = Path(out_path).absolute()
    scene = read_stage(src)
    if out.suffix in (".usda", ".usdc"):
        with _unpacked(scene) as plain:
            write_stage(plain, out)
        return out
    if out.suffix != ".usdz":
        raise StageError(out, "/", "export to .usda, .usdc or .usdz")
    root = src.parent
    checkpoints = [L.SCENE_CHECKPOINT] + [L.library_checkpoint(n) for n in sorted(scene.library)]
    layers = [L.library_layer(n) for n in sorted(scene.library)]
    slots = [L.slot_layer(c) for c in scene.classes()]
    missing = [f for f in checkpoints + layers + slots if not (root / f).is_file()]
    if missing:
        raise StageError(src, "/", f"assets missing beside the stage: {missing}")
    with file_transaction() as tx, tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        # The root layer as usdc under the stage's name: USD opens the package's first file.
        root_name = src.with_suffix(".usdc").name
        stage = open_stage(src)  # held: the layer lives only as long as its stage
        entries = [(_packaged_layer(stage.GetRootLayer(), tmp / root_name), root_name)]
        for rel in layers:
            entries.append((_packaged_layer(Sdf.Layer.FindOrOpen(str(root / rel)), tmp / rel), rel))
        entries += [(root / rel, rel) for rel in slots]
        for rel in checkpoints:
            name = embedded_name(rel)
            (tmp / name).parent.mkdir(parents=True, exist_ok=True)
            entries.append((write_embedded_checkpoint(root / rel, tmp / name), name))
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


def _packaged_layer(layer: Sdf.Layer, dest: Path) -> Path:
    """A copy of ``layer`` at ``dest`` whose checkpoint paths name the embedded layers."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    layer.Export(str(dest))
    copy = Sdf.Layer.FindOrOpen(str(dest))
    UsdUtils.ModifyAssetPaths(
        copy, lambda p: embedded_name(p) if p.endswith(CHECKPOINT_SUFFIX) else p
    )
    copy.Save()
    return dest
