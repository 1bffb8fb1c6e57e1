"""Helpers shared by the Blender toolkit tests (imported by name; pytest's conftest modules
of different folders would shadow each other)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest

BLENDER_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
REPO = os.path.dirname(BLENDER_DIR)
SCHEMAS = os.path.join(REPO, "schemas")
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


