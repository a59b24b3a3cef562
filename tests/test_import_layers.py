"""The package's layers: a module imports only from its own layer or the layers below it.

Bottom to top, each a folder of ``src/regnf``: ``core`` (atomic writes, locks, output folders,
executors, pre-flight checks), ``captures`` (the capture readers), ``observations`` (rays, depth
samples and the space the views saw), ``fields``, ``meshes``, ``io`` (checkpoints), ``training``,
``render``, ``registration``, ``scene_graph``, ``compositor``, ``viewer``, ``datasets`` (the
library), then ``synthetic`` (the synthetic data set and its cache of trained fields),
``benchmarks``, and ``cli`` (the command line): the library imports neither the synthetic data
set nor the benchmarks. Every import counts, including those inside functions, and nothing
imports a folder by its bare name (``import compositor`` would load a second copy of the module
beside ``regnf.compositor``).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "src" / "regnf"

LAYERS = ("core", "captures", "observations", "fields", "meshes", "io", "training", "render",
          "registration", "scene_graph", "compositor", "viewer", "datasets", "synthetic", "benchmarks", "cli")
"""Bottom to top."""
LIBRARY = LAYERS[:LAYERS.index("synthetic")]
"""The layers below the synthetic data set: what a user of the library imports."""

FOLDERS = {layer: PACKAGE / layer for layer in LAYERS}


def layer_of(module: str) -> str | None:
    """The layer of an absolute module name, or None for a module outside the project."""
    parts = module.split(".")
    if parts[0] != "regnf":
        return None
    if len(parts) > 1 and parts[1] in LAYERS:
        return parts[1]
    return "cli"  # the package itself and its __main__


def module_name(path: Path) -> str:
    """The dotted name a file under one of :data:`FOLDERS` is imported as."""
    for layer, folder in FOLDERS.items():
        if path.parent == folder:
            package = f"regnf.{layer}"
            return package if path.stem == "__init__" else f"{package}.{path.stem}"
    raise ValueError(f"{path} is in no layer's folder")


def imported_modules(source: str, package: str) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``source``, a module of ``package``
    (relative imports resolved against it)."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                name = ".".join([*base, node.module] if node.module else base)
            else:
                name = node.module or ""
            out.append((node.lineno, name))
            # ``from regnf import compositor`` imports the subpackage.
            out += [(node.lineno, f"{name}.{a.name}") for a in node.names if name == "regnf"]
    return out


def violations(source: str, module: str, is_package: bool = False) -> list[str]:
    """Every import in ``source`` (the text of ``module``) that breaks the layering."""
    own = LAYERS.index(layer_of(module))
    package = module if is_package else module.rsplit(".", 1)[0]
    bad = []
    for line, name in imported_modules(source, package):
        top = name.split(".")[0]
        if top in FOLDERS and top != "io":  # the standard library's io is not the layer
            bad.append(f"{module}:{line} imports {name!r} by its bare name (use regnf.{name})")
            continue
        layer = layer_of(name)
        if layer is not None and name != "regnf" and LAYERS.index(layer) > own:
            bad.append(f"{module}:{line} ({LAYERS[own]}) imports {name} ({layer}, a layer above)")
    return bad


def test_every_module_imports_only_from_below() -> None:
    files = [p for folder in FOLDERS.values() for p in sorted(folder.glob("*.py"))]
    assert len(files) > 100  # every folder was found
    bad = [v for p in files for v in violations(p.read_text(), module_name(p), p.stem == "__init__")]
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize(("module", "source", "expected"), [
    ("regnf.training.training", "from regnf.registration.pipeline import register\n", 1),
    ("regnf.training.training", "def f():\n    import regnf.compositor.composite_field\n", 1),
    ("regnf.registration.pipeline", "from regnf.synthetic.library import make_library_object\n", 1),
    ("regnf.training.training", "def f():\n    from regnf.synthetic import cache\n", 1),
    ("regnf.registration.metrics", "from regnf.benchmarks import registration\n", 1),
    ("regnf.registration.metrics", "from regnf import demo\n", 1),
    ("regnf.compositor.placement", "from . import substitution\nfrom ..scene_graph import read_stage\n", 0),
    ("regnf.core.atomic_io", "from ..synthetic import rooms\n", 1),
    ("regnf.captures.model", "from regnf.synthetic.rooms import make_room\n", 1),
    ("regnf.scene_graph.fields", "import compositor.camera\n", 1),
    ("regnf.benchmarks.registration", "from regnf.registration.pipeline import register\n", 0),
    ("regnf.cli.demo", "from regnf.benchmarks.registration import run_pair\nimport numpy\n", 0),
])
def test_the_check_sees_an_upward_import(module: str, source: str, expected: int) -> None:
    # The test above can fail: an upward import, a lazy one or a bare name is each reported.
    assert len(violations(source, module)) == expected


def test_every_layer_is_an_installed_package() -> None:
    import tomllib

    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert setuptools["package-dir"] == {"": "src"}
    assert {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()} == set(LAYERS)
    # Every layer but the benchmarks goes into the wheel (tests/test_wheel.py builds it).
    assert set(setuptools["packages"]) == {f"regnf.{layer}" for layer in LAYERS if layer != "benchmarks"} | {
        "regnf", "regnf.templates"}


def test_the_library_loads_without_the_synthetic_data_set_or_the_benchmarks() -> None:
    # Every module of the library imported in a fresh interpreter: none pulls in either.
    import subprocess
    import sys

    library = [module_name(p) for layer in LIBRARY for p in sorted(FOLDERS[layer].glob("*.py"))]
    code = ("import importlib, sys\n"
            f"for m in {library!r}: importlib.import_module(m)\n"
            "print(sorted(m for m in sys.modules if m.startswith(('regnf.synthetic', 'regnf.benchmarks'))))")
    out = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]", out.stdout
