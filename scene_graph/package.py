"""Export a stage: the root layer as .usda or .usdc, or a self-contained .usdz package.

The package holds the root layer first (as USD requires), then every asset layer, slot and
checkpoint at the same relative paths as on disk, so the layers' relative asset paths work
unchanged inside it (and the regnf tables in ``customLayerData`` still point at the files).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from pxr import Sdf

from . import layout as L
from .errors import StageError
from .transaction import file_transaction
from .usd_read import open_stage, read_stage
from .usd_write import write_stage


def export_stage(stage_path: str | os.PathLike, out_path: str | os.PathLike) -> Path:
    """Export ``stage_path`` to ``out_path``; the format follows its suffix.

    ``.usda`` / ``.usdc``: the whole stage is written again beside ``out_path`` (root layer in
    that format, assets as usual). ``.usdz``: one self-contained package. The stage is read
    and checked first; nothing is written if that fails.
    """
    src = Path(stage_path).absolute()
    out = Path(out_path).absolute()
    scene = read_stage(src)
    if out.suffix in (".usda", ".usdc"):
        write_stage(scene, out)
        return out
    if out.suffix != ".usdz":
        raise StageError(out, "/", "export to .usda, .usdc or .usdz")
    root = src.parent
    files = [L.SCENE_CHECKPOINT]
    for name in sorted(scene.library):
        files += [L.library_layer(name), L.library_checkpoint(name)]
    files += [L.slot_layer(c) for c in scene.classes()]
    missing = [f for f in files if not (root / f).is_file()]
    if missing:
        raise StageError(src, "/", f"assets missing beside the stage: {missing}")
    with file_transaction() as tx, tempfile.TemporaryDirectory() as tmpdir:
        # The root layer as usdc under the stage's name: USD opens the package's first file.
        root_name = src.with_suffix(".usdc").name
        staged_root = Path(tmpdir) / root_name
        stage = open_stage(src)  # held: the layer lives only as long as its stage
        stage.GetRootLayer().Export(str(staged_root))
        writer = Sdf.ZipFileWriter.CreateNew(str(tx.temp_path(out)))
        writer.AddFile(str(staged_root), root_name)
        for rel in files:
            writer.AddFile(str(root / rel), rel)
        writer.Save()
    return out
