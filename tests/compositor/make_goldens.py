"""Regenerate the golden images of ``test_golden.py``.

Usage (from the repository root)::

    python -m tests.compositor.make_goldens                 # re-render every case

Every golden PNG is rendered again and written (atomically) only if its pixels changed; each
file is reported as ``new``, ``unchanged`` or ``changed`` with its comparison. The tiny neural
field is distilled on the fly (one thread, fixed seed: about 10 s), as the tests do; trained
fields are never committed.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

from . import golden as GD
from . import golden_scenes as G


def _changed(kind: str, new: GD.Images, old: GD.Images | None) -> bool:
    if old is None:
        return True
    return not np.array_equal(getattr(new, kind), getattr(old, kind))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.compositor.make_goldens", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", nargs="*", default=None, help="cases to regenerate (default: all)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # the goldens are made single-threaded, like the tests on CI
    G.GOLDEN_DIR.mkdir(parents=True, exist_ok=True)
    names = args.only or list(GD.CASES)
    unknown = sorted(set(names) - set(GD.CASES))
    if unknown:
        print(f"unknown cases {unknown}; known: {list(GD.CASES)}", file=sys.stderr)
        return 2
    for name in names:
        new = GD.render_case(name)
        have = all(p.is_file() for p in GD.paths(name).values())
        old = GD.read_images(name) if have else None
        kinds = tuple(k for k in GD.KINDS if _changed(k, new, old))
        GD.write_images(new, name, kinds)
        if old is None:
            print(f"{name}: new")
        elif not kinds:
            print(f"{name}: unchanged")
        else:
            print(f"{name}: changed {', '.join(kinds)} ({GD.compare(new, old).summary()})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
