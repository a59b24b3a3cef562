"""The built wheel installs exactly one top-level package, ``regnf``, with every module in it."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_DIRS = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
FOLDERS = ("regnf", *sorted(set(PACKAGE_DIRS.values()) - {"regnf"}))
"""The repository's package folders: ``regnf`` itself and the ones installed as its subpackages
(from ``pyproject.toml``; the import-layer test checks that every layer is one of them)."""


def test_the_wheel_holds_one_top_level_package(tmp_path: Path) -> None:
    # Build from a copy, so that the build's egg-info and build/ folders never touch the checkout.
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for folder in FOLDERS:
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__"))
    made = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q",
         "-w", str(tmp_path / "dist"), str(src)], capture_output=True, text=True, check=False)
    assert made.returncode == 0, made.stderr
    (wheel,) = (tmp_path / "dist").glob("regnf-*.whl")
    names = zipfile.ZipFile(wheel).namelist()

    tops = {n.split("/")[0] for n in names}
    dist_info = {t for t in tops if t.endswith(".dist-info")}
    assert tops - dist_info == {"regnf"}, sorted(tops)

    # Every module of every folder is in it, under regnf/ (the folders map to subpackages).
    expected = {f"regnf/{p.name}" for p in (ROOT / "regnf").glob("*.py")}
    expected |= {f"regnf/{folder}/{p.name}" for folder in FOLDERS[1:] for p in (ROOT / folder).glob("*.py")}
    assert expected <= set(names), sorted(expected - set(names))
    assert all(f"regnf/{folder}/__init__.py" in names for folder in FOLDERS[1:])
    # And the package's data: the report's template.
    assert {f"regnf/templates/{p.name}" for p in (ROOT / "regnf" / "templates").glob("*.j2")} <= set(names)
