"""Names in a generated data set's folder, shared by the driver, its workers and the formats."""

from __future__ import annotations

STAGE_DIR = "stage"
"""Folder of the base stage and the replacement layers."""
VARIANTS_DIR = "variants"
"""Folder of the per-variant folders."""


def variant_name(seed: int) -> str:
    """Folder name of a variant: the seed on 6 digits."""
    return f"{seed:06d}"


def layer_name(seed: int) -> str:
    """File name of a variant's replacement layer."""
    return f"variant_{variant_name(seed)}.usda"
