"""Helpers shared by the Blender toolkit tests (imported by name; pytest's conftest modules
of different folders would shadow each other): running the toolkit's scripts and the
lightfuse binary, and the work folders the stage tests start from."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

BLENDER_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
REPO = os.path.dirname(BLENDER_DIR)
SCHEMAS = os.path.join(REPO, "schemas")
LIGHTFUSE = os.environ.get("LIGHTFUSE_BIN", os.path.join(REPO, "target", "release", "lightfuse"))
sys.path.insert(0, BLENDER_DIR)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

TINY_ARGS = ["--preset", "demo", "--res", "32x32", "--views", "3", "--states", "2", "--relight", "2",
             "--test-views", "2", "--spp", "4", "--seed", "7"]


def run_script(name: str, *args, check: bool = True) -> subprocess.CompletedProcess:
    """Run blender/<name> with the venv's Python; returns the completed process."""
    cmd = [sys.executable, os.path.join(BLENDER_DIR, name), *map(str, args)]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    if check and p.returncode != 0:
        raise AssertionError(f"{name} failed ({p.returncode}):\nstdout:\n{p.stdout[-3000:]}\nstderr:\n{p.stderr[-3000:]}")
    return p


def run(*args):
    """Run the lightfuse binary (``LIGHTFUSE_BIN``, default the release build)."""
    return subprocess.run([LIGHTFUSE, *map(str, args)], capture_output=True, text=True)


def ok(*args):
    """Run the lightfuse binary, which must succeed; returns its stdout."""
    p = run(*args)
    assert p.returncode == 0, f"lightfuse {' '.join(map(str, args))}:\n{p.stderr[-3000:]}"
    return p.stdout


def a_day_of_training(checkpoint, report):
    """Writes a day's training time into a stage's checkpoint, as after a run over several
    sittings, once checked that it holds what the report of the run that wrote it says."""
    c = json.loads(checkpoint.read_text())
    assert 0 < report["training_seconds"] <= report["seconds"]
    assert c["training_seconds"] == report["training_seconds"]
    c["training_seconds"] = 86400.0
    checkpoint.write_text(json.dumps(c))


def assert_a_day_carried_over(resumed, log, resumed_from):
    """A run resumed after `a_day_of_training`: its report and the log lines it wrote (after
    iteration `resumed_from`) count the day and this run's training on top of it."""
    assert 86400.0 < resumed["training_seconds"] < 86400.0 + resumed["seconds"]
    for line in log:
        assert (line["training_seconds"] > 86400.0) == (line["iteration"] > resumed_from), line
    assert log[-1]["training_seconds"] == resumed["training_seconds"]


def stages(tiny_dataset, tmp_path, refine=False):
    """A work folder with stage 1 (20 iterations) and, with `refine`, stage 2 (5) on the tiny
    dataset: the starting point of the later stages' tests."""
    work = tmp_path / "work"
    ok("--quiet", "reconstruct", tiny_dataset["path"], "-o", work, "--iterations", "20")
    if refine:
        ok("--quiet", "refine", tiny_dataset["path"], work, "--iterations", "5")
    return work


def renamed_object_dataset(ds, dest, name="teapot"):
    """A copy of dataset folder `ds` at `dest` whose first object is called `name` (its poses
    too): a dataset that does not match a scene reconstructed from `ds`."""
    shutil.copytree(ds, dest)
    d = json.loads((dest / "dataset.json").read_text())
    old = d["objects"][0]["name"]
    d["objects"][0]["name"] = name
    for s in d["states"]:
        if s.get("object_poses"):
            s["object_poses"] = {(name if k == old else k): v for k, v in s["object_poses"].items()}
    (dest / "dataset.json").write_text(json.dumps(d))
    return dest
