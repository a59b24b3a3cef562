"""CLI command ``regnf demo``: the whole tool on one synthetic room, ending in report.html."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

from tyro.conf import OmitArgPrefixes

from regnf.cli.demo import DemoConfig
from regnf.synthetic.cache import default_cache_dir


@dataclass
class Demo:
    """Run the end-to-end demo: capture, fields, registration, stage, composites, usdz, report.html."""

    out: Path = Path("out/demo")
    """Output folder: its stage, renders and report (what an earlier demo made there) are remade on every run;
    a folder holding anything else is refused unless --reuse is given."""
    demo: Annotated[DemoConfig, OmitArgPrefixes] = dataclasses.field(default_factory=DemoConfig)
    """What the demo makes."""
    cache_dir: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache of captures and trained fields (reused: a second run trains nothing)."""

    def run(self) -> None:
        from regnf.cli.demo import run_demo
        from regnf.core.preflight import check_output_dir
        from regnf.synthetic.cache import Cache

        check_output_dir(self.out)
        check_output_dir(self.cache_dir, "--cache-dir")  # the demo writes its baked grids there, cached or not
        run_demo(self.out, self.demo, Cache(self.cache_dir))
