"""Check a stage with OpenUSD's own validators (``pxr.UsdValidation``).

Every validator registered in this usd-core build runs over the composed stage (which also
validates the asset layers it references); the result is the list of issues as text, split
into errors and warnings. The stage is opened inside its trust boundary
(:func:`regnf.scene_graph.usd_read.open_stage`): a layer outside its folder is refused, not validated.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

from pxr import UsdValidation

from .usd_read import open_stage


class ValidationReport(NamedTuple):
    """What OpenUSD's validators said about a stage."""

    validators: list[str]
    """Names of the validators that ran."""
    errors: list[str]
    """Issues of type Error, as ``validator: message (sites)``."""
    warnings: list[str]
    """Issues of type Warn or Info."""


def _describe(err: UsdValidation.ValidationError) -> str:
    validator = err.GetValidator()
    name = validator.GetMetadata().name if validator is not None else "?"
    sites = []
    for site in err.GetSites():
        if site.IsPrim():
            sites.append(str(site.GetPrim().GetPath()))
        elif site.IsProperty():
            sites.append(str(site.GetProperty().GetPath()))
        elif site.GetLayer():
            sites.append(site.GetLayer().identifier)
    return f"{name}: {err.GetMessage()}" + (f" ({', '.join(sites)})" if sites else "")


def validate_stage(path: str | os.PathLike, exclude: tuple[str, ...] = (),
                   allow_outside: bool = False) -> ValidationReport:
    """Run every registered validator (but ``exclude``) on the stage at ``path``.

    Raises
    ------
    StageError
        The stage cannot be opened, or one of its layers lies outside its folder (unless
        ``allow_outside``).
    """
    stage = open_stage(Path(path), allow_outside)
    registry = UsdValidation.ValidationRegistry()
    validators = [v for v in registry.GetOrLoadAllValidators() if v.GetMetadata().name not in exclude]
    issues = UsdValidation.ValidationContext(validators).Validate(stage)
    errors, warnings = [], []
    for err in issues:
        (errors if err.GetType() == UsdValidation.ValidationErrorType.Error else warnings).append(_describe(err))
    return ValidationReport(sorted(v.GetMetadata().name for v in validators), errors, warnings)
