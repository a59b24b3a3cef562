"""Generate 100 random instance replacements of a stage from a script.

    python examples/generate_variants.py out/demo/stage/ac-room.usda out/variants [--ray] [--reuse]

The stage is one with registered instances (``make demo`` writes one). Each variant is one
seed: a replacement layer, 8 views (RGB, depth, instance masks) and a nerfstudio
``transforms.json``, recorded in ``out/variants/manifest.jsonl``. Run it again to resume.
The output folder must be new, empty or an earlier run's; ``--reuse`` writes into another
folder anyway (keeping its files).
"""

import sys

from regnf.compositor.cameras_io import OrbitConfig
from regnf.core.executors import ExecutorConfig
from regnf.datasets import GenerateConfig, generate

if __name__ == "__main__":  # the worker processes import this file: run only in the parent
    stage, out = sys.argv[1], sys.argv[2]
    config = GenerateConfig(
        variants=100,
        cameras=OrbitConfig(n=8, width=256, height=192),
        executor=ExecutorConfig(kind="ray" if "--ray" in sys.argv else "local"),
        reuse="--reuse" in sys.argv,
    )
    report = generate(stage, out, config)
    print(f"{len(report.made)} made, {len(report.skipped)} already there, {len(report.failed)} failed "
          f"in {report.seconds:.0f} s -> {report.manifest}")
