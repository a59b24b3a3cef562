"""CLI command ``regnf view``: a web viewer of a stage."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console
from tyro.conf import Positional

from regnf.viewer.viewer_config import ViewerConfig

console = Console(stderr=True)


@dataclass(frozen=True, kw_only=True)
class View(ViewerConfig):
    """Serve a web viewer of a stage: proxies, instances and renders of its fields (Ctrl-C stops it)."""

    stage: Positional[Path]
    """The stage (.usda, .usdc, a replacement layer or a .usdz package)."""

    def __post_init__(self) -> None:
        # Checked when the settings are taken (first thing in :meth:`run`): a value out of range
        # is then one line and status 1, not a usage error.
        pass

    def config(self) -> ViewerConfig:
        """The settings alone (every option but the stage)."""
        return ViewerConfig(**{f.name: getattr(self, f.name) for f in dataclasses.fields(ViewerConfig)})

    def run(self) -> None:
        from regnf.scene_graph import StageError
        from regnf.viewer import serve
        from regnf.viewer.trust import is_loopback

        cfg = self.config()
        try:
            viewer = serve(self.stage, cfg)  # reads the stage before any server starts
        except StageError as exc:  # the same message as `regnf stage show`
            raise SystemExit(f"regnf view: {exc}") from exc
        except OSError as exc:
            raise SystemExit(f"regnf view: cannot listen on {cfg.host}:{cfg.port}: {exc.strerror or exc}") from exc
        if is_loopback(cfg.host):
            where = "in a browser on this machine"
        else:
            console.print(f"[yellow]warning[/]: the viewer listens on {cfg.host}: anyone on the network who "
                          f"has the URL below can edit {self.stage}", soft_wrap=True)
            where = "in a browser"
        console.print(f"[green]viewer[/] of {self.stage}: open {viewer.url} {where} (Ctrl-C stops it)",
                      soft_wrap=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            console.print("viewer stopped")
        finally:
            viewer.close()
