"""Output folders never lose or overwrite the user's files, and concurrent or killed runs stay consistent.

Each test is one thing a hostile (or unlucky) user does: generate into a folder that holds
their own files, into the folder of the source stage, twice at once into one folder, after
a kill, with an absurd number of variants; and run the demo into a folder of theirs. The
truths are what is on disk (:mod:`tests.adversarial.disk` snapshots), not the code's own
bookkeeping.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import tracemalloc
from pathlib import Path

import pytest

from regnf.cli.app import EXIT_BAD_INPUT, main
from regnf.cli.demo import REMADE, DemoConfig, demo_folder
from regnf.compositor.cameras_io import OrbitConfig
from regnf.compositor.render_folder import RenderConfig, render_views
from regnf.compositor.stage_config import StageCompositeConfig
from regnf.core.atomic_io import TEMP_PREFIX
from regnf.core.file_lock import LOCK_NAME
from regnf.core.output_dir import MARKER_NAME, OutputFolderError, claim_output_dir
from regnf.datasets.generation import GenerateConfig, generate, prepare_output
from regnf.datasets.manifest import MANIFEST_NAME, load_rows, read_manifest
from regnf.scene_graph import add_instance
from tests.adversarial.disk import changes, snapshot
from tests.compositor import golden_scenes as G
from tests.datasets.test_generate import CLI_VIEWS, ORBIT
from tests.scene_graph.helpers import make_stage, similarity

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PYOPENGL_PLATFORM": "egl"}
"""Environment of the subprocesses: this checkout, one thread each (the machine is small)."""


@pytest.fixture(scope="module")
def stage(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny stage of tests/datasets/test_generate.py: three registered instances, a spare chair."""
    path = make_stage(tmp_path_factory.mktemp("output_folders"), names=("c", "dc", "fc", "fc-nop", "t"))
    add_instance(path, "c", similarity(0.5, (2.2, -0.5, 0.0), 1.0))
    add_instance(path, "dc", similarity(1.5, (-2.2, 0.4, 0.0), 1.0))
    add_instance(path, "t", similarity(-0.3, (0.3, 2.3, 0.0), 1.0))
    return path


def one_variant(**changes_: object) -> GenerateConfig:
    """One variant of three 24 x 18 views on one worker: the cheapest real run."""
    from regnf.core.executors import ExecutorConfig

    cfg = GenerateConfig(variants=1, cameras=ORBIT, executor=ExecutorConfig(workers=1))
    return dataclasses.replace(cfg, **changes_)


def users_folder(out: Path) -> None:
    """A folder of the user's: a git checkout, a secret, and a stage/ subfolder of their own."""
    (out / ".git" / "refs").mkdir(parents=True)
    (out / ".git" / "HEAD").write_text("ref: refs/heads/main\n")
    (out / ".env").write_text("API_KEY=do-not-lose-me\n")
    (out / "stage").mkdir()
    (out / "stage" / "notes.txt").write_text("my own stage notes\n")
    (out / "stage" / ".keep").write_text("")


def disk_variants(out: Path) -> set[str]:
    """Variant folders on disk, as manifest paths (``variants/NNNNNN``); staging folders aside."""
    folder = out / "variants"
    return {f"variants/{p.name}" for p in folder.iterdir() if not p.name.startswith(".")} if folder.is_dir() else set()


def test_a_folder_of_the_user_s_is_refused_and_kept_whole_when_reused(stage: Path, tmp_path: Path) -> None:
    out = tmp_path / "mine"
    users_folder(out)
    before = snapshot(out)
    with pytest.raises(OutputFolderError, match=r"mine: is not empty and was not made by regnf generate "
                                                r"\(it holds 3 entries: \.env, \.git, stage\); .*--reuse") as exc:
        generate(stage, out, one_variant(), progress=False)
    assert "\n" not in str(exc.value)
    assert changes(before, snapshot(out)) == []  # not even a lock file or a marker

    report = generate(stage, out, one_variant(reuse=True), progress=False)
    assert report.made == [0] and not report.failed
    after = snapshot(out)
    assert [k for k in before if after.get(k) != before[k]] == []  # every file of theirs, unchanged
    assert (out / "variants" / "000000" / "rgb_0000.png").is_file() and (out / MARKER_NAME).is_file()
    # Now marked as a data set: a rerun needs no --reuse, and keeps their files still.
    assert generate(stage, out, one_variant(), progress=False).skipped == [0]
    assert [k for k in before if snapshot(out).get(k) != before[k]] == []


def test_a_folder_of_another_command_is_refused_even_when_reused(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    claim_output_dir(out, "demo")
    with pytest.raises(OutputFolderError, match=r"demo: holds the output of regnf demo; choose another folder"):
        claim_output_dir(out, "generate", reuse=True)


@pytest.mark.parametrize("inside", ["stage", "stage/mine"])
def test_a_source_stage_inside_the_output_stage_folder_is_refused(stage: Path, tmp_path: Path, inside: str) -> None:
    out = tmp_path / "data"
    shutil.copytree(stage.parent, out / inside)
    src = out / inside / stage.name  # "stage": the source IS the base stage generate would write
    before = snapshot(out)
    for reuse in (False, True):
        with pytest.raises(ValueError, match=r"the source stage is inside .*data/stage, where generate writes"):
            generate(src, out, one_variant(reuse=reuse), progress=False)
        with pytest.raises(ValueError, match=r"the source stage is inside"):
            prepare_output(src, out, one_variant(reuse=reuse))
    assert changes(before, snapshot(out)) == []  # the source and its assets are intact


RUNNER = textwrap.dedent('''
    """Wait for a go file, then run regnf generate through the Python API; print the outcome as JSON."""
    import json
    import sys
    import time
    from pathlib import Path

    from regnf.compositor.cameras_io import OrbitConfig
    from regnf.core.executors import ExecutorConfig
    from regnf.datasets.generation import GenerateConfig, generate

    if __name__ == "__main__":
        stage, out, first, ready, go = sys.argv[1:6]
        cfg = GenerateConfig(variants=2, first_seed=int(first), executor=ExecutorConfig(workers=1),
                             cameras=OrbitConfig(n=3, width=24, height=18, radius=4.5))
        Path(ready).touch()
        while not Path(go).exists():
            time.sleep(0.01)
        try:
            report = generate(stage, out, cfg, progress=False)
            print(json.dumps({"made": report.made}))
        except Exception as exc:
            print(json.dumps({"error": type(exc).__name__, "message": str(exc)}))
''')


def wait_for(predicate, seconds: float, what: str) -> None:
    deadline = time.monotonic() + seconds
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def test_two_runs_into_one_folder_at_once_leave_a_consistent_data_set(stage: Path, tmp_path: Path) -> None:
    script = tmp_path / "run_generate.py"
    script.write_text(RUNNER)
    out = tmp_path / "data"
    procs = {}
    for name, first in (("a", 0), ("b", 2)):  # other seeds, same settings: one data set
        procs[name] = subprocess.Popen(
            [sys.executable, str(script), str(stage), str(out), str(first), str(tmp_path / f"ready_{name}"),
             str(tmp_path / f"go_{name}")], cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        wait_for(lambda: all((tmp_path / f"ready_{n}").exists() for n in procs), 60, "the runners to start")
        (tmp_path / "go_a").touch()
        wait_for(lambda: (out / MANIFEST_NAME).exists(), 60, "run a to start writing")  # a holds the lock now
        (tmp_path / "go_b").touch()
        results = {}
        for name, proc in procs.items():
            stdout, stderr = proc.communicate(timeout=120)
            assert proc.returncode == 0, stderr.decode()[-2000:]
            results[name] = json.loads(stdout.decode().strip().splitlines()[-1])
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert results["a"] == {"made": [0, 1]}, results
    b = results["b"]
    if "error" in b:  # refused at once, naming the lock and what to do
        assert b["error"] == "LockBusy" and "the data set folder is in use by another regnf process" in b["message"]
        assert str(out / LOCK_NAME) in b["message"] and "\n" not in b["message"]
    else:  # it ran after a had finished
        assert b == {"made": [2, 3]}, results
    # The invariant: every variant folder on disk is listed by the manifest, and every row checks out.
    rows = load_rows(out)
    listed = {r["variant"] for r in rows if r["status"] == "ok"}
    assert disk_variants(out) == listed
    key = json.loads((out / "generation.json").read_text())["config_key"]
    state = read_manifest(out, key)
    assert state.problems == [] and len(state.rows) == len(rows)
    assert not [p for p in out.rglob(f"{TEMP_PREFIX}*")], "temporaries left behind"


def test_what_a_killed_run_left_is_removed_and_the_user_s_hidden_files_stay(stage: Path, tmp_path: Path) -> None:
    out = tmp_path / "data"
    assert generate(stage, out, one_variant(), progress=False).made == [0]
    umask = os.umask(0)
    os.umask(umask)
    # Renamed into place from a staging folder (mkdtemp makes 0700): it reads as the umask says.
    assert (out / "variants" / "000000").stat().st_mode & 0o777 == 0o777 & ~umask
    # What a kill leaves (names as the writers make them), and hidden files of the user's beside it.
    leftovers = [out / f"{TEMP_PREFIX}work-k1ll3d00" / "000001-abcd" / "rgb_0000.png",
                 out / "variants" / f"{TEMP_PREFIX}000001-k1ll3d00" / "rgb_0000.png",
                 out / "stage" / f"{TEMP_PREFIX}scene.usda.k1ll3d00.usda",
                 out / "errors" / f"{TEMP_PREFIX}000001.txt.k1ll3d00.txt",
                 out / f"{TEMP_PREFIX}manifest.jsonl.k1ll3d00.jsonl"]
    users = [out / ".envrc", out / "variants" / ".DS_Store", out / "stage" / ".keep", out / ".render-notes"]
    for p in leftovers + users:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("x")
    report = generate(stage, out, one_variant(), progress=False)
    assert report.skipped == [0]
    assert [p for p in leftovers if p.exists()] == []
    assert not list(out.rglob(f"{TEMP_PREFIX}*"))
    assert [p.read_text() for p in users] == ["x"] * len(users)


KILLED_RENDER = textwrap.dedent('''
    """Render into a folder and hang after the first views, so that a SIGKILL finds the staging folder."""
    import sys
    import time
    from pathlib import Path

    import numpy as np

    import regnf.compositor.render_folder as RV
    from regnf.compositor.cameras_io import OrbitConfig, orbit_around_bounds
    from regnf.compositor.stage_config import StageCompositeConfig
    from tests.compositor import golden_scenes as G

    if __name__ == "__main__":
        out, ready = Path(sys.argv[1]), Path(sys.argv[2])
        real, calls = RV.render_batch, []

        def hanging(*args, **kwargs):
            calls.append(1)
            if len(calls) == 3:  # views 0 and 1 are written (one or two render at a time)
                ready.touch()
                time.sleep(600)
            return real(*args, **kwargs)

        RV.render_batch = hanging
        cameras = orbit_around_bounds(np.array(BOUNDS), OrbitConfig(**ORBIT))
        RV.render_views(G.composite("own", StageCompositeConfig(mode="scene")), cameras, out,
                        RV.RenderConfig(progress=False, views_per_trace=1))
''')
RENDER_BOUNDS = [[-1.6, -1.4, 0.0], [1.6, 1.4, 1.2]]
"""Bounds of the golden scene the render tests orbit."""
RENDER_ORBIT = {"n": 3, "width": 24, "height": 18, "radius": 2.2, "elevation_deg": 35.0}
"""Three small views from outside it."""


def render_cameras():
    """The cameras the killed render and the next one use."""
    import numpy as np

    from regnf.compositor.cameras_io import orbit_around_bounds

    return orbit_around_bounds(np.array(RENDER_BOUNDS), OrbitConfig(**RENDER_ORBIT))


def test_a_killed_render_s_staging_folder_is_removed_by_the_next_render(tmp_path: Path) -> None:
    out = tmp_path / "render"
    out.mkdir()
    (out / ".render-notes").write_text("a hidden file of the user's\n")
    (out / "replacement.usda").write_text("#usda 1.0\n")  # another command's file in the same folder
    script = tmp_path / "killed_render.py"
    script.write_text(KILLED_RENDER.replace("np.array(BOUNDS)", f"np.array({RENDER_BOUNDS!r})")
                      .replace("OrbitConfig(**ORBIT)", f"OrbitConfig(**{RENDER_ORBIT!r})"))
    proc = subprocess.Popen([sys.executable, str(script), str(out), str(tmp_path / "ready")], cwd=ROOT, env=ENV,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        wait_for(lambda: (tmp_path / "ready").exists() or proc.poll() is not None, 60, "the render to start")
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stderr.close()
    staged = [p for p in out.iterdir() if p.name.startswith(TEMP_PREFIX)]
    assert len(staged) == 1 and staged[0].is_dir() and (staged[0] / "rgb_0000.png").is_file()

    render_views(G.composite("own", StageCompositeConfig(mode="scene")), render_cameras(), out,
                 RenderConfig(progress=False))
    assert not staged[0].exists()
    assert (out / ".render-notes").read_text() == "a hidden file of the user's\n"
    assert (out / "replacement.usda").read_text() == "#usda 1.0\n"
    assert (out / "render.json").is_file() and (out / "rgb_0001.png").is_file()


def test_a_billion_variants_are_refused_at_once(stage: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    tracemalloc.start()
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=r"^variants must be between 1 and 1,000,000, got 1000000000 \(split"):
        GenerateConfig(variants=10**9)
    with pytest.raises(ValueError, match=r"cameras: a view of 5000 x 5000 pixels is more than the 16,777,216"):
        GenerateConfig(cameras=OrbitConfig(n=1, width=5000, height=5000))
    seconds = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert seconds < 0.1 and peak < 1 << 20  # nothing was built per seed
    # On the command line: one line, status 1, before the output folder is made.
    capsys.readouterr()
    t0 = time.perf_counter()
    assert main(["generate", str(stage), "--out", str(tmp_path / "data"), "--variants", "1000000000",
                 *CLI_VIEWS]) == EXIT_BAD_INPUT
    assert time.perf_counter() - t0 < 5.0
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "variants must be between 1 and 1,000,000" in err[0]
    assert not (tmp_path / "data").exists()


def test_the_demo_never_removes_a_folder_it_did_not_make(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    (out / "renders").mkdir(parents=True)
    (out / "renders" / "holiday.png").write_bytes(b"\x89PNG mine")
    (out / "notes.txt").write_text("mine\n")
    before = snapshot(out)
    for reuse in (False, True):  # reused: its renders/ is still not the demo's to remove
        pattern = r"demo: is not empty and was not made by regnf demo" if not reuse else \
            r"demo/renders: exists and was not made by regnf demo; move it away"
        with pytest.raises(OutputFolderError, match=pattern), demo_folder(out, DemoConfig(reuse=reuse)):
            pytest.fail("the folder was accepted")
        assert changes(before, snapshot(out)) == []

    # A folder the demo made: its own folders are remade, a file the user added there stays.
    mine = tmp_path / "made"
    with demo_folder(mine, DemoConfig()) as folder:
        for sub in REMADE:
            folder.remove(sub)
            (mine / sub).mkdir()
            (mine / sub / "old.txt").write_text("from the last demo\n")
    (mine / "notes.txt").write_text("mine\n")
    with demo_folder(mine, DemoConfig()) as folder:
        for sub in REMADE:
            folder.remove(sub)
        with pytest.raises(OutputFolderError, match=r"notes.txt: was not made by regnf demo, so it is not removed"):
            folder.remove("notes.txt")
    assert not any((mine / sub).exists() for sub in REMADE)
    assert (mine / "notes.txt").read_text() == "mine\n"
