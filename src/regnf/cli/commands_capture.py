"""CLI command ``regnf inspect-capture``: what a capture folder holds, and a contact sheet."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from tyro.conf import Positional

from regnf.captures.formats import read_capture
from regnf.core.preflight import PreflightError, check_output_file

SHEET_FOLDER = Path("out") / "inspect"
"""Where the contact sheet goes by default, relative to the working folder."""


def sheet_path(capture_dir: Path, sheet: Path | None) -> Path:
    """The contact sheet's path: ``sheet``, or ``out/inspect/<capture folder name>.png``.

    Raises
    ------
    PreflightError
        A path inside the capture folder (a capture is only read), or one that cannot be written.
    """
    # A metadata file names its folder (as for read_capture); anything else is the folder.
    named_file = capture_dir.suffix == ".json" and not capture_dir.is_dir()
    folder = Path(os.path.realpath(capture_dir.parent if named_file else capture_dir))
    path = sheet if sheet is not None else SHEET_FOLDER / f"{folder.name}.png"
    if Path(os.path.realpath(path)).is_relative_to(folder):
        raise PreflightError(f"--sheet {path}: lies inside the capture folder {folder}; "
                             "regnf only reads a capture: give a --sheet outside it")
    return check_output_file(path, "--sheet", suffix=".png")


@dataclass
class InspectCapture:
    """Show what a capture folder holds (frames, intrinsics, depth, extent, up, preset) and write a contact sheet."""

    capture: Positional[Path]
    """Capture folder (sdfstudio meta_data.json, nerfstudio transforms.json or a ScanNet export)."""
    capture_format: Literal["auto", "sdfstudio", "nerfstudio", "scannet"] = "auto"
    """Capture layout; auto detects it from the folder."""
    sheet: Path | None = None
    """Contact sheet to write (.png): evenly spaced frames, colour above depth (magenta: no
    depth); default out/inspect/<capture folder name>.png in the working folder."""

    def run(self) -> None:
        from regnf.captures.contact_sheet import write_contact_sheet
        from regnf.captures.inspection import (
            depth_line,
            extent_line,
            frames_line,
            intrinsics_line,
            summarise_depth,
        )
        from regnf.captures.up_axis import up_line
        from regnf.cli.capture_plan import up_and_kind

        sheet = sheet_path(self.capture, self.sheet)
        capture, fmt = read_capture(self.capture, self.capture_format)
        summary = summarise_depth(capture)
        up, kind = up_and_kind(capture, points=summary.points)
        zero = ("the ray hit nothing (an ideal render)" if capture.zero_depth_is_empty
                else "unknown (no sensor return)")
        lines = [
            f"capture:    {capture.root}",
            f"format:     {fmt}",
            f"frames:     {frames_line(capture)}",
            f"resolution: {capture.width} x {capture.height}",
            f"intrinsics: {intrinsics_line(capture)}",
            f"depth:      {depth_line(summary, len(capture.frames))}",
            f"zero depth: {zero}",
            f"extent:     {extent_line(summary)}",
            up_line(up).replace("up: ", "up:         ", 1),
            f"poses:      {'estimates (SLAM, COLMAP or a noisy render)' if capture.poses_estimated else 'exact'}",
            f"preset:     {kind.kind} ({kind.reason})",
        ]
        p = summary.percentiles
        near, far = (0.0, 1.0) if np.isnan(p).all() else (float(p[0]), float(p[-1]))
        write_contact_sheet(capture, sheet, near, far)
        lines.append(f"sheet:      {sheet}")
        print("\n".join(lines))
