"""The scene.blend that generate.py writes: opening it, its ``lightfuse`` record (objects, reference
matrices, states' poses) and placing its objects by a layout.

(The .blend that import_scene.py writes keeps other records, and ``lfstate.apply_state`` places
its objects.)
"""

from __future__ import annotations

import json
import os

import numpy as np

from lfaxes import check_rigid, yup_to_bl_matrix
from lfcli import UserError, quiet_stdout

SCENE_KEY = "lightfuse"  # scene custom property holding the LightFuse record (JSON string)
ID_PROP = "lightfuse_id"  # object custom property (and glTF node extras): its mask id, 0 = background


def open_blend(path: str) -> None:
    """Open a .blend as the current file, quietly; a file Blender cannot open is a UserError."""
    import bpy

    try:
        with quiet_stdout():
            bpy.ops.wm.open_mainfile(filepath=os.path.abspath(path))
    except RuntimeError as e:
        raise UserError(f"{path}: cannot open as a Blender file ({str(e).strip()})") from None


def get_record(where: str) -> dict:
    """The LightFuse record stored in a generated scene.blend (objects, reference matrices)."""
    import bpy

    sc = bpy.context.scene
    raw = sc.get(SCENE_KEY)
    if raw is None:
        raise UserError(f"{where}: not a LightFuse scene (scene has no '{SCENE_KEY}' record); "
                        "expected a scene.blend written by blender/generate.py")
    try:
        rec = json.loads(raw)
        rec["objects"], rec["reference"]
    except (ValueError, KeyError, TypeError):
        raise UserError(f"{where}: the scene's '{SCENE_KEY}' record is malformed") from None
    return rec


def apply_layout_bl(rec: dict, layout_yup: dict, where: str) -> None:
    """Place objects: world = layout (Y-up, relative to reference) applied to the reference.

    Objects the layout leaves out go back to the reference.  render_layout.py (``--layout``) and
    export_mesh_scene.py (``--layout``, or a ``--state``'s poses from the record) call it; the
    states of a .blend from import_scene.py are stored matrices, placed by ``lfstate.apply_state``.
    """
    import bpy
    import mathutils

    names = {o["name"] for o in rec["objects"]}
    for name, m in layout_yup.items():
        if name not in names:
            raise UserError(f"{where}: objects.{name}: unknown object; the scene's objects are "
                            f"{', '.join(sorted(names))}")
        rigid = check_rigid(m, f"{where}: objects.{name}")
        ref = np.asarray(rec["reference"][name], dtype=np.float64)
        world = yup_to_bl_matrix(rigid) @ ref
        bpy.data.objects[name].matrix_world = mathutils.Matrix(world.tolist())
    for name in names - set(layout_yup):
        ref = np.asarray(rec["reference"][name], dtype=np.float64)
        bpy.data.objects[name].matrix_world = mathutils.Matrix(ref.tolist())
    bpy.context.view_layer.update()
