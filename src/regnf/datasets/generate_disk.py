"""The disk a data set run will fill, estimated before anything is written, and the refusal when it is not free.

``regnf generate`` checks, before it claims its output folder, that the file system holding
it has room for the variants still to make (each view's files at their uncompressed size) and
for the base stage's export; baking the grids checks their size with the variants' on top
(:func:`regnf.datasets.data_set_grids.bake_for_data_set`), once their node count is known and before
any baking.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

from regnf.core.preflight import check_free_space

if TYPE_CHECKING:
    from regnf.datasets.generate_config import GenerateConfig

BYTES_PER_VIEW_PIXEL = 10
"""Bytes a view's pixel takes in the files of its variant, uncompressed: RGB (3), 16-bit depth (2),
16-bit instance id (2) and its tile of the contact sheet (3); PNG compression only makes them smaller."""
SEQUENCE_BYTES_PER_PIXEL = 3
"""Bytes a view's pixel adds when the variant also writes its views as a sequence (gif or mp4), uncompressed."""
VARIANT_SMALL_FILES_BYTES = 64 * 1024
"""Bytes of a variant's small files: render.json, transforms.json, its replacement layer and manifest row."""


def variant_bytes(config: GenerateConfig) -> int:
    """Bytes one variant of ``config`` writes at most (its views uncompressed, plus its small files)."""
    per_pixel = BYTES_PER_VIEW_PIXEL + (SEQUENCE_BYTES_PER_PIXEL if config.render.sequence != "none" else 0)
    cams = config.cameras
    return cams.n * cams.width * cams.height * per_pixel + VARIANT_SMALL_FILES_BYTES


def pending_variants(out: Path, config: GenerateConfig) -> int:
    """How many of ``config``'s seeds have no variant folder in ``out`` yet (one listing, no file read)."""
    from regnf.datasets.generate_layout import VARIANTS_DIR, variant_name

    try:
        made = set(os.listdir(out / VARIANTS_DIR))
    except OSError:  # no such folder yet: every variant is to make
        made = set()
    return sum(variant_name(s) not in made for s in config.seeds)


def export_bytes(stage: Path, out: Path) -> int:
    """Bytes the export of ``stage`` into ``out/stage/`` writes: its checkpoints (0 once it is there)."""
    from regnf.datasets.generate_layout import STAGE_DIR
    from regnf.scene_graph import read_stage

    if (out / STAGE_DIR / (stage.stem + ".usda")).is_file():
        return 0
    if stage.suffix == ".usdz":
        return stage.stat().st_size  # its checkpoints are inside
    scene = read_stage(stage, check_checkpoints=False)
    files = {Path(r.checkpoint) for r in (scene.scene, *scene.library.values())}
    return sum(p.stat().st_size for p in files if p.is_file())


def check_generation_disk(stage: str | os.PathLike, out: str | os.PathLike, config: GenerateConfig) -> None:
    """Refuse a run whose variants and base stage would not fit in the space free where ``out`` is.

    Raises
    ------
    regnf.core.preflight.PreflightError
        ``"writing N variants (V views of W x H pixels each, uncompressed) and the base stage
        needs about X GB in OUT, Y GB free"``.
    """
    stage, out = Path(stage).absolute(), Path(out).absolute()
    pending = pending_variants(out, config)
    needed = pending * variant_bytes(config) + export_bytes(stage, out)
    cams = config.cameras
    check_free_space(out, needed, f"writing {pending:,} variants ({cams.n} views of {cams.width} x {cams.height} "
                                  "pixels each, uncompressed) and the base stage")
