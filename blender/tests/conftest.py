"""Shared fixtures: a tiny generated dataset (made once per session) and script runners."""

from __future__ import annotations

import json
import os
import sys
import time

import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bltest import SCHEMAS, TINY_ARGS, run_script  # noqa: E402


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "tiny"
    t = time.time()
    run_script("generate.py", *TINY_ARGS, "--out", out)
    elapsed = time.time() - t
    with open(out / "dataset.json") as f:
        ds = json.load(f)
    return {"path": str(out), "json": ds, "seconds": elapsed}


@pytest.fixture(scope="session")
def schema():
    def load(name):
        with open(os.path.join(SCHEMAS, name)) as f:
            return json.load(f)
    return load
