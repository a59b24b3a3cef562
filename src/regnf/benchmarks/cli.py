"""``regnf bench ...`` commands."""

from __future__ import annotations

import dataclasses
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
from rich.console import Console
from tyro.conf import Positional

from regnf.core.atomic_io import write_json
from regnf.core.preflight import check_output_file
from regnf.synthetic.cache import Cache, default_cache_dir

console = Console(stderr=True)


def check_outputs(command: object) -> None:
    """Refuse, before a benchmark's minutes of work, a ``--json`` or ``--markdown`` that cannot be written."""
    check_output_file(command.json, "--json")
    if getattr(command, "markdown", None) is not None:
        check_output_file(command.markdown, "--markdown")


def run_meta(command: str, device: str) -> dict:
    """Where and when a benchmark ran."""
    return {
        "command": command,
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "device": device,
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu": platform.processor() or platform.machine(),
    }


@dataclass
class BenchFields:
    """Train (or reuse) every library object and room field and measure time and accuracy."""

    json: Path = Path("out/bench_fields.json")
    """Where to write the results (JSON)."""
    quick: bool = False
    """Two library objects (both sources), no room: a few minutes."""
    markdown: Path | None = None
    """Also write the results as a Markdown table here."""
    device: str = "cpu"
    """Torch device."""
    cache_dir: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory (fields already there are reused, not retrained)."""

    def run(self) -> None:
        check_outputs(self)
        from regnf.benchmarks.fields import (
            contact_sheet,
            markdown_table,
            run_fields_benchmark,
            write_results,
        )

        command = "regnf bench fields" + (" --quick" if self.quick else "") + f" --json {self.json}"
        rows, renders = run_fields_benchmark(Cache(self.cache_dir), quick=self.quick, device=self.device)
        write_results(rows, self.json, run_meta(command, self.device))
        sheet = self.json.with_suffix(".png")
        contact_sheet(renders, sheet)
        table = markdown_table(rows)
        if self.markdown:
            from regnf.core.atomic_io import write_text

            write_text(self.markdown, f"Command: `{command}`\n\n{table}")
        console.print(table)
        console.print(f"results: {self.json}; held-out renders (render | truth): {sheet}")


@dataclass
class BenchEncodings:
    """Measure the CPU/GPU throughput of the candidate feature encodings."""

    json: Path = Path("out/bench_encodings.json")
    """Where to write the results (JSON)."""
    device: str = "cpu"
    """Torch device."""

    def run(self) -> None:
        check_outputs(self)
        from regnf.benchmarks.encodings import markdown_table, run_encodings_benchmark

        rows = run_encodings_benchmark(self.device)
        write_json(self.json, {"meta": run_meta("regnf bench encodings", self.device), "rows": rows})
        console.print(markdown_table(rows))


@dataclass
class BenchRegistration:
    """Register the paper's 11 scene/object pairs with every method; Tables I and II."""

    json: Path = Path("out/bench_registration.json")
    """Where to write the rows (JSON); before/after PNGs go in a folder beside it."""
    quick: bool = False
    """3 pairs, every method, no single-view or scale rows."""
    single_view: bool = True
    """Also run Table II (one uninformative scene view per object)."""
    coverage: Literal["full", "low", "both"] = "both"
    """Scene fields trained on the full-coverage captures, the low-coverage ones (objects seen from
    one or two sides), or both. Table I with every method runs on full coverage only."""
    library: Literal["rgbd", "mesh", "both"] = "both"
    """Library fields trained from RGB-D captures, distilled from the meshes, or both (Table I
    with every method: RGB-D only)."""
    wrong_pairs: bool = True
    """Also register every object into the boxes of the other class and every chair into every
    other chair's box, in every setting, and report the false-accept rates."""
    markdown: Path | None = None
    """Also write the tables as Markdown here."""
    device: str = "cpu"
    """Torch device."""
    cache_dir: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory (fields are trained there if missing)."""
    executor: Literal["local", "ray"] = "local"
    """local: a process pool on this machine; ray: a Ray cluster (pip install 'regnf[distributed]')."""
    address: str | None = None
    """Ray cluster to join ('auto', 'ray://head:10001'); default: a local Ray instance."""
    workers: int = 1
    """Pairs at once; 1 (the default) times each pair on the whole machine."""
    threads_per_task: int = 0
    """Torch threads per pair; 0: the CPU count / workers."""

    def run(self) -> None:
        check_outputs(self)
        import os

        from regnf.benchmarks.registration import PAPER_REGNF, run_registration_benchmark
        from regnf.benchmarks.registration_report import (
            before_after_png,
            coverage_table,
            is_reference,
            medians,
            pair_table,
            table_one,
            table_two,
            wrong_pair_table,
        )
        from regnf.core.executors import ExecutorConfig

        command = ("regnf bench registration" + (" --quick" if self.quick else "")
                   + ("" if self.single_view else " --no-single-view") + f" --json {self.json}"
                   + f" --coverage {self.coverage} --library {self.library}"
                   + ("" if self.wrong_pairs else " --no-wrong-pairs")
                   + (f" --executor {self.executor}" if self.executor != "local" else "")
                   + (f" --workers {self.workers}" if self.workers != 1 else ""))
        threads = self.threads_per_task or max(1, (os.cpu_count() or 1) // max(1, self.workers))
        try:
            executor = ExecutorConfig(kind=self.executor, workers=self.workers, threads_per_task=threads,
                                      address=self.address)
        except ValueError as exc:
            raise SystemExit(f"regnf bench registration: {exc}") from exc
        coverages = ("full", "low") if self.coverage == "both" else (self.coverage,)
        sources = ("rgbd", "mesh") if self.library == "both" else (self.library,)
        rows = run_registration_benchmark(Cache(self.cache_dir), quick=self.quick,
                                          single_view=self.single_view, device=self.device,
                                          executor=executor, coverages=coverages, library_sources=sources,
                                          with_wrong_pairs=self.wrong_pairs)
        pngs = self.json.parent / (self.json.stem + "_png")
        for r in rows:
            if r["method"] == "regnf" and r["views"] == "multi" and not r["wrong_pair"]:
                tag = "" if is_reference(r) else f"_{r['coverage']}_{r['library_source']}"
                before_after_png(r["_result"], pngs / f"{r['scene']}_{r['object']}{tag}.png")
        clean = [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]
        write_json(self.json, {"meta": run_meta(command, self.device), "rows": clean})
        text = f"Command: `{command}`\n\n"
        if any(is_reference(r) for r in clean):
            text += (f"### Table I\n\n{table_one(clean, PAPER_REGNF)}\n"
                     f"### Medians over the pairs\n\n{medians(clean)}\n### Table II\n\n{table_two(clean)}\n")
        text += f"### Every coverage and library source (method regnf)\n\n{coverage_table(clean)}\n"
        for cov in coverages:
            for src in sources:
                if (cov, src) != ("full", "rgbd"):
                    text += f"#### {cov} coverage, {src} library\n\n{pair_table(clean, cov, src)}\n"
        if self.wrong_pairs:
            text += f"### Wrong-object pairs\n\n{wrong_pair_table(clean)}"
        if self.markdown:
            from regnf.core.atomic_io import write_text

            write_text(self.markdown, text)
        console.print(text)
        console.print(f"results: {self.json}; before/after pictures: {pngs}/")


@dataclass
class BenchDiscover:
    """Discover the 3 rooms' furniture with no boxes and the whole library; score against the truth."""

    json: Path = Path("out/bench_discover.json")
    """Where to write the rows (JSON); one top view per room and coverage goes in a folder beside it."""
    coverage: Literal["full", "low", "both"] = "both"
    """Scene fields of the full-coverage captures, the low-coverage ones, or both."""
    library: Literal["mesh", "rgbd"] = "mesh"
    """Library fields distilled from the meshes or trained from RGB-D captures."""
    markdown: Path | None = None
    """Also write the table as Markdown here."""
    device: str = "cpu"
    """Torch device."""
    cache_dir: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory (fields are trained there if missing)."""

    def run(self) -> None:
        check_outputs(self)
        from regnf.benchmarks.discover import markdown_table, run_discover_benchmark

        command = f"regnf bench discover --json {self.json} --coverage {self.coverage} --library {self.library}"
        coverages = ("full", "low") if self.coverage == "both" else (self.coverage,)
        images = self.json.parent / (self.json.stem + "_png")
        rows = run_discover_benchmark(Cache(self.cache_dir), coverages, self.library, images=images,
                                      device=self.device)
        write_json(self.json, {"meta": run_meta(command, self.device), "rows": rows})
        table = f"Command: `{command}`\n\n{markdown_table(rows)}"
        if self.markdown:
            from regnf.core.atomic_io import write_text

            write_text(self.markdown, table)
        console.print(table)
        console.print(f"results: {self.json}; top views: {images}/")


@dataclass
class BenchDistill:
    """Distil defective meshes (holes, flipped faces, parts...) and measure them against the clean shape."""

    json: Path = Path("out/bench_distill.json")
    """Where to write the rows (JSON); rewritten after each row."""
    quick: bool = False
    """Four chair rows (clean, holes, flipped, components) instead of every shape and defect."""
    markdown: Path | None = None
    """Also write the table as Markdown here."""
    device: str = "cpu"
    """Torch device."""

    def run(self) -> None:
        check_outputs(self)
        from regnf.benchmarks.distill import markdown_table, run_distill_benchmark

        command = "regnf bench distill" + (" --quick" if self.quick else "") + f" --json {self.json}"
        meta = run_meta(command, self.device)
        rows = run_distill_benchmark(
            quick=self.quick, device=self.device,
            on_row=lambda done: write_json(self.json, {"meta": meta, "rows": done}),
        )
        table = markdown_table(rows)
        if self.markdown:
            from regnf.core.atomic_io import write_text

            write_text(self.markdown, f"Command: `{command}`\n\n{table}")
        console.print(table)
        console.print(f"results: {self.json}")


@dataclass
class BenchRender:
    """Sphere tracer against volume rendering on the composite room; object completion."""

    json: Path = Path("out/bench_render.json")
    """Where to write the rows and the completion record (JSON); PNGs go beside it."""
    quick: bool = False
    """The speed rows alone (sphere tracer, baked grids, volume renderer) on 2 views; no completion
    or replacement (no low-coverage field to train)."""
    markdown: Path | None = None
    """Also write the tables as Markdown here."""
    device: str = "cpu"
    """Torch device."""
    cache_dir: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory (fields are trained there if missing)."""

    def run(self) -> None:
        check_outputs(self)
        from regnf.benchmarks.render import run_render_benchmark
        from regnf.benchmarks.render_report import markdown_tables, write_images

        command = "regnf bench render" + (" --quick" if self.quick else "") + f" --json {self.json}"
        result, images = run_render_benchmark(Cache(self.cache_dir), device=self.device, quick=self.quick)
        pngs = write_images(images, self.json.parent, self.json.stem)
        write_json(self.json, {"meta": run_meta(command, self.device), **result})
        text = f"Command: `{command}`\n\n{markdown_tables(result)}"
        if self.markdown:
            from regnf.core.atomic_io import write_text

            write_text(self.markdown, text)
        console.print(text)
        console.print(f"results: {self.json}; images: {', '.join(str(p) for p in pngs)}")


@dataclass
class BenchViewer:
    """The viewer in headless Chromium on a registered stage: time to the first and refined images, pose corrections."""

    stage: Positional[Path]
    """A stage of one of the synthetic rooms with registered instances (``make demo`` writes
    ``out/demo/stage/ac-room.usda``)."""
    room: Literal["ac-room", "atbl-room", "mix-room"] = "ac-room"
    """The room the stage holds (its capture instances are the ground truth of the corrections)."""
    coverage: Literal["full", "low"] = "low"
    """The capture the stage's scene field was trained from (the demo's: low)."""
    json: Path = Path("out/bench_viewer.json")
    """Where to write the measurements (JSON)."""
    images: Path = Path("out/bench_viewer")
    """Folder for the screenshots."""
    cache_dir: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory (the room's capture is made there if missing)."""

    def run(self) -> None:
        check_outputs(self)
        from regnf.benchmarks.viewer import run_viewer_benchmark
        from regnf.scene_graph import StageError
        from regnf.synthetic.capture import RoomCaptureConfig

        capture = Cache(self.cache_dir).room_capture(self.room, RoomCaptureConfig(coverage=self.coverage))
        command = f"regnf bench viewer {self.stage} --json {self.json}"
        try:
            result = run_viewer_benchmark(self.stage, list(capture.instances), self.images)
        except StageError as exc:
            raise SystemExit(f"regnf bench viewer: {exc}") from exc
        write_json(self.json, {"meta": run_meta(command, "cpu"), **result})
        console.print(f"instances listed after {result['instances_listed_s']:.1f} s, first image "
                      f"{result['first_render_s']:.1f} s, refined {result['refined_render_s']:.1f} s")
        for row in result["corrections"]:
            console.print(f"  {row['instance']}: refined from the dragged pose, confidence {row['confidence']:.3f}, "
                          f"rotation {row['rot_geodesic_rad']:.4f} rad, translation {100 * row['trans_rel_diag']:.2f} %, "
                          f"scale {100 * row['scale_rel']:.2f} %, within the bars: {row['within_bars']}")
        console.print(f"results: {self.json}; screenshots: {self.images}")


@dataclass
class BenchGpuCheck:
    """The field, registration and render benchmarks' quick modes on one device (a GPU), in one JSON and table."""

    device: str = "cuda"
    """Torch device of every part."""
    json: Path = Path("out/gpu_check.json")
    """Where to write the results (JSON, layout in docs/benchmarks.md); rewritten after each part."""
    markdown: Path | None = None
    """Also write the tables as Markdown here."""
    tests: Path | None = None
    """The CUDA-marked tests' report (``pytest -m cuda --device cuda --junitxml FILE``), summarised
    in the results; ``make gpu-check`` runs them first."""
    size: Literal["quick", "tiny"] = "quick"
    """``quick``: the benchmarks' quick modes with the measured captures and training presets.
    ``tiny``: the same code on small captures and briefly trained fields (seconds; its accuracy
    means nothing), what the tests run on the CPU."""
    cache_dir: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory (fields already there are reused, not retrained)."""

    def run(self) -> None:
        check_outputs(self)
        from regnf.benchmarks.gpu_check import (
            device_name,
            markdown_table,
            run_gpu_check,
            summarise_tests,
        )
        from regnf.core.preflight import check_device

        check_device(self.device)
        if self.tests is not None:
            summarise_tests(self.tests)  # a bad report fails now, not after the benchmarks
        command = (f"regnf bench gpu-check --device {self.device} --size {self.size} --json {self.json}"
                   + (f" --tests {self.tests}" if self.tests else ""))
        cache = Cache(self.cache_dir, size="tiny" if self.size == "tiny" else "full")
        meta = {**run_meta(command, self.device), "size": self.size, "device_name": device_name(self.device)}
        # Rewritten after each part: a run stopped half-way keeps the parts it finished.
        result = run_gpu_check(cache, self.device, self.tests,
                               on_part=lambda done: write_json(self.json, {"meta": meta, **done}))
        result = {"meta": meta, **result}
        text = f"Command: `{command}`\n\n{markdown_table(result)}"
        if self.markdown:
            from regnf.core.atomic_io import write_text

            write_text(self.markdown, text)
        console.print(text)
        console.print(f"results: {self.json}")


@dataclass
class BenchSensor:
    """Fields, true-box registrations and discovery on room captures with sensor noise and pose error, four levels."""

    json: Path = Path("out/bench_sensor.json")
    """Where to write the rows, the summary and the verdicts (JSON); rewritten after each room."""
    markdown: Path | None = None
    """Also write the tables as Markdown here (e.g. docs/benchmarks_sensor.md)."""
    levels: tuple[Literal["ideal", "sensor", "slam", "harsh"], ...] = ("ideal", "sensor", "slam", "harsh")
    """Noise levels of the room captures (regnf synth --noise)."""
    coverages: tuple[Literal["low", "full"], ...] = ("low", "full")
    """Room captures: the low-coverage arc, the full trajectory, or both."""
    rooms: tuple[Literal["ac-room", "atbl-room", "mix-room"], ...] = ("ac-room", "atbl-room", "mix-room")
    """Rooms to run."""
    objects: tuple[str, ...] = ()
    """Only the true-box pairs of these library objects (and the wrong pairs into their boxes); empty: all."""
    wrong_pairs: bool = True
    """Also register every object into the boxes of the other class and every chair into every
    other chair's box (a wrong object accepted fails the level)."""
    discovery: bool = True
    """Also discover each room's objects with no boxes and the whole mesh library."""
    noise_seed: int = 0
    """Seed of the sensor and pose noise of every noisy capture."""
    pose_refine: Literal["auto", "on", "off"] = "auto"
    """Pose refinement of the noisy rooms' fields (``regnf train --pose-refine``)."""
    size: Literal["full", "tiny"] = "full"
    """``full``: the measured captures and presets. ``tiny``: small captures and briefly trained
    fields (a smoke test; its figures mean nothing)."""
    device: str = "cpu"
    """Torch device."""
    cache_dir: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory (captures and fields are made there if missing)."""

    def run(self) -> None:
        check_outputs(self)
        from regnf.benchmarks.sensor import check_selection, run_sensor_benchmark
        from regnf.benchmarks.sensor_report import markdown_tables
        from regnf.core.preflight import check_device

        check_device(self.device)
        check_selection(self.levels, self.coverages, self.rooms, self.objects)
        command = (f"regnf bench sensor --json {self.json} --levels {' '.join(self.levels)} "
                   f"--coverages {' '.join(self.coverages)} --rooms {' '.join(self.rooms)}"
                   + (f" --objects {' '.join(self.objects)}" if self.objects else "")
                   + ("" if self.wrong_pairs else " --no-wrong-pairs")
                   + ("" if self.discovery else " --no-discovery")
                   + (f" --noise-seed {self.noise_seed}" if self.noise_seed else "")
                   + (f" --pose-refine {self.pose_refine}" if self.pose_refine != "auto" else "")
                   + (f" --size {self.size}" if self.size != "full" else ""))
        meta = {**run_meta(command, self.device), "size": self.size}
        result = run_sensor_benchmark(
            Cache(self.cache_dir, size=self.size), self.levels, self.coverages, self.rooms, self.objects,
            with_wrong_pairs=self.wrong_pairs, with_discovery=self.discovery, noise_seed=self.noise_seed,
            device=self.device, on_room=lambda done: write_json(self.json, {"meta": meta, **done}),
            pose_refine=self.pose_refine)
        write_json(self.json, {"meta": meta, **result})
        text = f"Command: `{command}`\n\n{markdown_tables(result)}"
        if self.markdown:
            from regnf.core.atomic_io import write_text

            write_text(self.markdown, text)
        console.print(text)
        console.print(f"results: {self.json}")


@dataclass
class BenchCaptureScale:
    """Time and peak memory of sample building and training against a capture's number of frames."""

    json: Path = Path("out/bench_capture_scale.json")
    """Where to write the measurements (JSON); rewritten after each run."""
    markdown: Path | None = None
    """Also write the table as Markdown here."""
    frames: tuple[int, ...] = (100, 300, 600)
    """Frame counts at which sample building is measured (each in a process of its own)."""
    width: int = 640
    """Image width of the capture, pixels."""
    height: int = 480
    """Image height of the capture, pixels."""
    train_frames: int = 600
    """Frames of the training run (room preset, a process of its own); 0: no training run."""
    room: Literal["ac-room", "atbl-room", "mix-room"] = "ac-room"
    """Room captured (full-coverage trajectory, every frame a training frame)."""
    steps: int = 0
    """Training steps; 0: the room preset's."""
    memory_limit_gib: float = 0.0
    """Address-space cap of each run, GiB (a run beyond it is reported out of memory); 0: 90 % of the
    memory available when the run starts."""
    pixel_stride: int = 1
    """Samples from every this-many-th row and column of each frame, in every run."""
    device: str = "cpu"
    """Torch device of the training run."""
    cache_dir: Path = dataclasses.field(default_factory=default_cache_dir)
    """Cache directory (the capture is made there once)."""

    def run(self) -> None:
        check_outputs(self)
        from regnf.benchmarks.capture_scale import check_plan, markdown_table, run_capture_scale
        from regnf.core.preflight import check_device

        check_device(self.device)
        check_plan(self.frames, self.width, self.height, self.train_frames, self.steps, self.memory_limit_gib,
                   self.pixel_stride)
        command = (f"regnf bench capture-scale --json {self.json} --frames {' '.join(map(str, self.frames))} "
                   f"--width {self.width} --height {self.height} --train-frames {self.train_frames}"
                   + (f" --room {self.room}" if self.room != "ac-room" else "")
                   + (f" --steps {self.steps}" if self.steps else "")
                   + (f" --pixel-stride {self.pixel_stride}" if self.pixel_stride != 1 else ""))
        meta = run_meta(command, self.device)
        result = run_capture_scale(Cache(self.cache_dir), self.room, self.frames, self.width, self.height,
                                   self.train_frames, self.device, self.steps, self.memory_limit_gib,
                                   self.pixel_stride, on_row=lambda done: write_json(self.json, {"meta": meta, **done}))
        write_json(self.json, {"meta": meta, **result})
        text = f"Command: `{command}`\n\n{markdown_table(result)}"
        if self.markdown:
            from regnf.core.atomic_io import write_text

            write_text(self.markdown, text)
        console.print(text)
        console.print(f"results: {self.json}")


@dataclass
class BenchPage:
    """Regenerate docs/benchmarks.md from the benchmarks' JSON results (never edited by hand)."""

    results: Path = Path("docs/results")
    """Folder of the results, one ``<benchmark>.json`` each (what ``--json`` wrote)."""
    out: Path = Path("docs/benchmarks.md")
    """The page to write (Markdown)."""

    def run(self) -> None:
        check_output_file(self.out, "--out")
        from regnf.benchmarks.page import write_results_page

        path = write_results_page(self.results, self.out)
        console.print(f"{path}: {len(path.read_text(encoding='utf-8').splitlines())} lines", soft_wrap=True)

