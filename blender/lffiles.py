"""The files of the LightFuse Blender scripts: JSON (dataset.json, layout.json, frames.json)
and layouts read from layout.json, glTF or USD."""

from __future__ import annotations

import json
import os

import numpy as np

from lfaxes import check_rigid
from lfcli import UserError
from lfgltf import read_gltf_json, trs_to_matrix

DATASET_FORMAT = "lightfuse-dataset/1"
LAYOUT_FORMAT = "lightfuse-layout/1"


def read_json(path: str, what: str) -> dict:
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except FileNotFoundError:
        raise UserError(f"{path}: {what} not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"{path}: cannot read {what} ({e})") from None
    except json.JSONDecodeError as e:
        raise UserError(f"{path}: not valid JSON (line {e.lineno}: {e.msg}); expected {what}") from None


def write_json(path: str, obj) -> None:
    import re

    text = json.dumps(obj, indent=1)
    # one line per innermost list of numbers (matrix rows)
    text = re.sub(r"\[\s+([-0-9.eE+,\s]+?)\s+\]",
                  lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]", text)
    tmp = path + ".tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text + "\n")
    os.replace(tmp, path)


def read_layout(path: str) -> dict:
    """layout.json -> {name: 4x4 array}; glTF/GLB with named nodes accepted too (node TRS)."""
    low = path.lower()
    if low.endswith((".glb", ".gltf")):
        return read_layout_gltf(path)
    if low.endswith((".usd", ".usda", ".usdc", ".usdz")):
        return read_layout_usd(path)
    d = read_json(path, "a layout.json")
    if not isinstance(d, dict) or d.get("format") != LAYOUT_FORMAT:
        raise UserError(f"{path}: field 'format' must be {LAYOUT_FORMAT!r}, got {d.get('format') if isinstance(d, dict) else type(d).__name__!r}")
    objs = d.get("objects")
    if not isinstance(objs, dict):
        raise UserError(f"{path}: field 'objects' must be an object mapping names to 4x4 matrices")
    return {k: check_rigid(v, f"{path}: objects.{k}") for k, v in objs.items()}


def read_layout_usd(path: str) -> dict:
    """Transforms of the Xform children of a USD stage's default prim (components), as authored
    (default variant selections), relative to the reference state.  The stage must be Y-up."""
    if not os.path.isfile(path):
        raise UserError(f"{path}: layout file not found")
    try:
        from pxr import Usd, UsdGeom
    except ImportError:
        raise UserError(f"{path}: reading USD needs usd-core (pip install usd-core)") from None
    try:
        stage = Usd.Stage.Open(path)
    except Exception as e:  # pxr raises Tf.ErrorException
        raise UserError(f"{path}: cannot open as USD ({str(e).strip().splitlines()[-1]})") from None
    up = UsdGeom.GetStageUpAxis(stage)
    if up != UsdGeom.Tokens.y:
        raise UserError(f"{path}: upAxis is {up!r}; expected 'Y' (LightFuse is +Y up)")
    root = stage.GetDefaultPrim() or stage.GetPseudoRoot()
    out = {}
    for prim in root.GetChildren():
        if not prim.IsA(UsdGeom.Xformable) or prim.GetName() == "background":
            continue
        m = np.array(UsdGeom.Xformable(prim).GetLocalTransformation(), dtype=np.float64).T  # row-vector
        out[prim.GetName()] = check_rigid(m, f"{path}: {prim.GetPath()}")
    return out


def read_layout_gltf(path: str, scene_index: int | None = None) -> dict:
    """Object nodes of a glTF scene (default scene) -> {name: 4x4}; nodes are the layout's
    transforms relative to the reference state (LightFuse scene convention)."""
    js, _ = read_gltf_json(path)
    scenes = js.get("scenes") or []
    si = js.get("scene", 0) if scene_index is None else scene_index
    if not scenes or si >= len(scenes):
        raise UserError(f"{path}: field 'scenes' has no scene {si}")
    nodes = js.get("nodes") or []
    out = {}
    for ni in scenes[si].get("nodes", []):
        nd = nodes[ni]
        name = nd.get("name")
        if not name or name == "background":
            continue
        out[name] = check_rigid(trs_to_matrix(nd), f"{path}: nodes[{ni}] ({name})")
    return out
