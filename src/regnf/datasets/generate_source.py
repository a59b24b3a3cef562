"""The source stage of a data set run: what of it the variants depend on, and the refusals made
before the output folder is claimed (:func:`regnf.datasets.generation.generate`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from regnf.core.errors import RegnfError

from .generate_layout import STAGE_DIR


def source_summary(stage: Path) -> dict[str, Any]:
    """What of the source stage the variants depend on: its instances, library and scene field."""
    from regnf.scene_graph import read_stage

    scene = read_stage(stage)
    return {
        "scene": scene.scene.name,
        "library": {n: r.label for n, r in sorted(scene.library.items())},
        "instances": {i: {"library_name": r.library_name,
                          "object_to_scene": np.round(r.object_to_scene, 9).tolist()}
                      for i, r in sorted(scene.instances.items())},
    }


def check_variant_sizes(stage: Path) -> None:
    """Refuse a stage where a variant could swap in an object of another size
    (:func:`regnf.compositor.size_change.check_swap_sizes` over every object a seed may pick)."""
    from regnf.compositor.replace import replacement_candidates
    from regnf.compositor.size_change import check_swap_sizes
    from regnf.scene_graph import read_stage

    scene = read_stage(stage)
    check_swap_sizes(scene, replacement_candidates(scene), stage)


def check_source(stage: str | os.PathLike, out: str | os.PathLike) -> None:
    """Refuse a source stage inside ``out/stage/``, where the base stage and the layers are written.

    Raises
    ------
    ValueError
        The stage (or the file it links to) is inside ``out/stage/``, or is that folder.
    """
    src = Path(stage).absolute()
    stage_dir = Path(out).absolute() / STAGE_DIR
    for s, d in ((src, stage_dir), (Path(os.path.realpath(src)), Path(os.path.realpath(stage_dir)))):
        if s == d or s.is_relative_to(d):
            raise RegnfError(f"{src}: the source stage is inside {stage_dir}, where generate writes its base "
                             "stage and layers; copy the stage elsewhere, or choose another output folder")
