"""Convert a regnf field checkpoint of format version 1 (no content digest) to version 2.

Usage: ``python scripts/convert_checkpoint_v1.py IN.safetensors [OUT.safetensors]`` (default:
IN is replaced). regnf no longer reads version 1: nothing in such a file proves its weights are
the ones that were saved. This script stands outside the package on purpose: it gives the file
the digest it lacks, so run it only on files you trust (your own, unmodified). Every other check
of the file still applies: the header is relabelled version 2 with its digest in a temporary
file, which ``regnf.io.load_field`` must load (header, shapes, dtypes, finite weights, the copies
of ``to_world`` and ``bounds``), and the loaded field is then written with ``save_field``.
Exit status 0 on success, 1 with one line naming the file and the problem otherwise.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

from regnf.io.checkpoint import CheckpointError, load_field, save_field
from regnf.io.checkpoint_digest import DIGEST_KEY, HEADER_KEY, content_digest


def convert(src: Path, dst: Path) -> Path:
    """Read version-1 ``src``, check it as regnf checks any checkpoint, write version 2 to ``dst``."""
    try:
        with safe_open(str(src), framework="pt") as f:
            header = json.loads((f.metadata() or {})[HEADER_KEY])
        tensors = load_file(str(src))
    except (OSError, SafetensorError, KeyError, ValueError) as exc:
        raise CheckpointError(src, f"not a regnf checkpoint ({exc})") from exc
    if not isinstance(header, dict) or header.get("format_version") != 1:
        version = header.get("format_version") if isinstance(header, dict) else None
        raise CheckpointError(src, f"format version {version!r}, not 1: nothing to convert")
    header = {**header, "format_version": 2}
    header.pop(DIGEST_KEY, None)
    header[DIGEST_KEY] = content_digest(header, tensors)
    with tempfile.TemporaryDirectory() as tmp:
        relabelled = Path(tmp) / "v2.safetensors"
        save_file(tensors, str(relabelled), metadata={HEADER_KEY: json.dumps(header)})
        field = load_field(relabelled)
    return save_field(field, dst)


def main(argv: list[str]) -> int:
    if len(argv) not in (1, 2):
        print(__doc__.splitlines()[2], file=sys.stderr)
        return 2
    src = Path(argv[0])
    dst = Path(argv[1]) if len(argv) == 2 else src
    try:
        out = convert(src, dst)
    except CheckpointError as exc:
        print(" ".join(str(exc).split()), file=sys.stderr)
        return 1
    print(f"{src} -> {out} (format version 2)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
