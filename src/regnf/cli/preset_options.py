"""Command-line options for every setting of a config whose defaults are a preset's.

``regnf train`` picks its preset (object or scene) only once it has read the capture, so its
options cannot default to the preset's values the way ``register``'s default to
``RegistrationConfig()``. :func:`preset_options` makes, from the config class itself, an options
class with one optional field per setting (``None``: the preset's value, which the help shows),
and :func:`with_options` applies what was given to the chosen preset. The settings, their
help and their checks are the config's own: nothing is copied by hand.
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Collection, Mapping
from typing import Annotated, Any

import tyro

from regnf.cli.help_text import install


def _shown(value: Any) -> str:
    """A preset's value as the help shows it."""
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, tuple):
        return " ".join(_shown(v) for v in value)
    return str(value)


def _preset_values(values: Mapping[str, Any]) -> str:
    """``200`` when every preset has the same value, else ``object: 200, scene: 400``."""
    shown = {name: _shown(v) for name, v in values.items()}
    if len(set(shown.values())) == 1:
        return next(iter(shown.values()))
    return ", ".join(f"{name}: {v}" for name, v in shown.items())


def _docstring(config_type: type, name: str) -> str:
    """The docstring under field ``name`` of ``config_type`` (or a base), as the help shows it."""
    from tyro import _docstrings

    install()  # tyro's docstrings in plain text, as for every other option
    return _docstrings.get_field_docstring(config_type, name, ()) or ""


def preset_options(config_type: type, presets: Mapping[str, Any], skip: Collection[str] = ()) -> type:
    """A frozen dataclass with an optional field for every setting of ``config_type``.

    Parameters
    ----------
    config_type : type
        A config dataclass; nested config dataclasses become nested options classes.
    presets : mapping of str to config
        The presets the command may start from, by name: their values are shown as the defaults.
    skip : collection of str
        Settings the command sets from options of its own (``seed``, ``pose_refine.mode``).

    Returns
    -------
    type
        ``<config_type>Options``: each leaf ``T | None = None`` (``None``: the preset's value).
    """
    hints = typing.get_type_hints(config_type)
    fields: list[tuple[str, Any, Any]] = []
    for f in dataclasses.fields(config_type):
        if f.name in skip:
            continue
        kind, doc = hints[f.name], _docstring(config_type, f.name)
        values = {name: getattr(p, f.name) for name, p in presets.items()}
        if dataclasses.is_dataclass(kind):
            inner = {s.partition(".")[2] for s in skip if s.startswith(f"{f.name}.")}
            nested = preset_options(kind, values, inner)
            fields.append((f.name, Annotated[nested, tyro.conf.arg(help=doc)], dataclasses.field(default_factory=nested)))
        else:
            hint = f"(default: {_preset_values(values)})"
            fields.append((f.name, Annotated[kind | None, tyro.conf.arg(help=doc, help_behavior_hint=hint)],
                           dataclasses.field(default=None)))
    return dataclasses.make_dataclass(f"{config_type.__name__}Options", fields, frozen=True)


def with_options(config: Any, options: Any) -> Any:
    """``config`` with every setting ``options`` gives (not ``None``) replaced, checked by the config."""
    changes: dict[str, Any] = {}
    for f in dataclasses.fields(options):
        value = getattr(options, f.name)
        if dataclasses.is_dataclass(value):
            changes[f.name] = with_options(getattr(config, f.name), value)
        elif value is not None:
            changes[f.name] = value
    return dataclasses.replace(config, **changes)
