"""What is on disk under a folder, to assert that a refused command changed nothing."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path


def snapshot(root: str | os.PathLike) -> dict[str, tuple[str, int]]:
    """Every entry below ``root`` (hidden ones included): relative path -> (content digest, mode).

    Folders map to ``("dir", mode)``; files to the SHA-256 of their bytes.
    """
    root = Path(root)
    out: dict[str, tuple[str, int]] = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        mode = p.lstat().st_mode & 0o7777
        if p.is_symlink():
            out[rel] = (f"link:{os.readlink(p)}", mode)
        elif p.is_dir():
            out[rel] = ("dir", mode)
        else:
            out[rel] = (hashlib.sha256(p.read_bytes()).hexdigest(), mode)
    return out


def changes(before: dict[str, tuple[str, int]], after: dict[str, tuple[str, int]]) -> list[str]:
    """Readable differences between two snapshots (empty when nothing changed)."""
    lines = [f"removed {k}" for k in sorted(set(before) - set(after))]
    lines += [f"added {k}" for k in sorted(set(after) - set(before))]
    lines += [f"changed {k}" for k in sorted(set(before) & set(after)) if before[k] != after[k]]
    return lines
