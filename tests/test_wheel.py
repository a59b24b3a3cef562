"""The built wheel installs exactly one top-level package, ``regnf``, with every module in it but the benchmarks."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "src" / "regnf"


def test_the_wheel_holds_one_top_level_package(tmp_path: Path) -> None:
    # Build from a copy, so that the build's egg-info and build/ folders never touch the checkout.
    src = tmp_path / "checkout"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    shutil.copytree(ROOT / "src", src / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    made = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q",
         "-w", str(tmp_path / "dist"), str(src)], capture_output=True, text=True, check=False)
    assert made.returncode == 0, made.stderr
    (wheel,) = (tmp_path / "dist").glob("regnf-*.whl")
    names = zipfile.ZipFile(wheel).namelist()

    tops = {n.split("/")[0] for n in names}
    dist_info = {t for t in tops if t.endswith(".dist-info")}
    assert tops - dist_info == {"regnf"}, sorted(tops)

    # Every module of the package is in it, but none of the benchmarks (they run from a checkout).
    modules = {f"regnf/{p.relative_to(PACKAGE).as_posix()}" for p in PACKAGE.rglob("*.py")}
    bench = {m for m in modules if m.startswith("regnf/benchmarks/")}
    assert bench and not bench & set(names), sorted(bench & set(names))
    assert modules - bench <= set(names), sorted(modules - bench - set(names))
    # And the package's data: the report's template.
    assert {f"regnf/templates/{p.name}" for p in (PACKAGE / "templates").glob("*.j2")} <= set(names)
