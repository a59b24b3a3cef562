"""Each package's ``__init__`` exports its entry points, and each name is the object, not a module.

A lazily exported name that is also a submodule's name would come back as the module once
anything imported that submodule (``from regnf.registration import register`` returning the
module ``register.py``); the test imports every submodule first, then asks for every name.
"""

from __future__ import annotations

import importlib
import pkgutil
import types

import pytest

PACKAGES = ("regnf.core", "regnf.captures", "regnf.synthetic", "regnf.observations", "regnf.fields", "regnf.meshes", "regnf.io", "regnf.training", "regnf.render", "regnf.registration",
            "regnf.scene_graph", "regnf.compositor", "regnf.viewer", "regnf.datasets", "regnf.cli", "regnf.benchmarks")


@pytest.mark.parametrize("name", PACKAGES)
def test_every_export_is_the_object_its_module_defines(name: str) -> None:
    package = importlib.import_module(name)
    for info in pkgutil.iter_modules(package.__path__):
        importlib.import_module(f"{name}.{info.name}")
    for export in getattr(package, "__all__", []):
        value = getattr(package, export)
        assert not isinstance(value, types.ModuleType), f"{name}.{export} is a module"
        defined_in = getattr(value, "__module__", None)
        if defined_in is not None and defined_in.startswith(name + "."):
            assert getattr(importlib.import_module(defined_in), export) is value


def test_the_readme_entry_points_import() -> None:
    from regnf.registration import RegistrationConfig, RegistrationResult, register

    assert callable(register) and RegistrationConfig().init.top_k >= 1
    assert "transform" in RegistrationResult.__dataclass_fields__


def test_an_unknown_name_is_an_attribute_error() -> None:
    import regnf.registration

    with pytest.raises(AttributeError, match="regnf.registration"):
        regnf.registration.no_such_name  # noqa: B018
