"""Export the layout of an edited LightFuse .blend (from import_scene.py) as layout.json.

For every object component, the rigid transform (4x4, rows, LightFuse +Y up, metres) that maps
its surfels in the reference state to where the object now is:
``T = C4 @ matrix_world @ Translation(-origin) @ C4^-1`` with ``origin`` the object's
reference-state pivot stored by import_scene.py.  Objects are found by their
``lightfuse_component`` property, so renaming them in Blender is harmless.  Scale or shear
is refused (moves and rotations only), naming the object; so is a moved background.

Example::

    .venv/bin/python blender/export_layout.py scene_edit.blend --out layout.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import numpy as np  # noqa: E402

from lfaxes import bl_to_yup_matrix, rows  # noqa: E402
from lfblend import open_blend  # noqa: E402
from lfcli import Parser, UserError, run_main  # noqa: E402
from lffiles import LAYOUT_FORMAT, write_json  # noqa: E402
from lfstate import COMPONENT_PROP, ORIGIN_PROP, SCENE_PROP  # noqa: E402


def layout_from_blend(where: str) -> dict:
    """{component name: 4x4 Y-up} for the objects of the open .blend."""
    import bpy

    sc = bpy.context.scene
    if SCENE_PROP not in sc:
        raise UserError(f"{where}: not a LightFuse scene (no '{SCENE_PROP}' record); expected a .blend "
                        "written by blender/import_scene.py")
    rec = json.loads(sc[SCENE_PROP])
    found = {}
    for ob in bpy.data.objects:
        name = ob.get(COMPONENT_PROP)
        if name is not None:
            found[name] = ob
    out = {}
    for c in rec["components"]:
        name = c["name"]
        ob = found.get(name)
        if ob is None:
            raise UserError(f"{where}: object for component {name!r} is missing (deleted?)")
        origin = np.asarray(ob.get(ORIGIN_PROP, [0, 0, 0]), dtype=np.float64)
        T0inv = np.eye(4)
        T0inv[:3, 3] = -origin
        m_bl = np.array(ob.matrix_world, dtype=np.float64) @ T0inv
        m = bl_to_yup_matrix(m_bl)
        label = f"{where}: object {ob.name!r}" + (f" (component {name!r})" if ob.name != name else "")
        r = m[:3, :3]
        sv = np.linalg.svd(r, compute_uv=False)
        if np.abs(sv - 1).max() > 1e-4 or np.abs(r.T @ r - np.eye(3)).max() > 1e-4:
            raise UserError(f"{label} has scale or shear (singular values {np.round(sv, 5).tolist()}); "
                            "a layout is rigid: only move and rotate objects, and reset the scale to 1")
        if np.linalg.det(r) < 0:
            raise UserError(f"{label} is mirrored (negative scale); a layout is rigid")
        if c["id"] == 0:
            if np.abs(m - np.eye(4)).max() > 1e-5:
                raise UserError(f"{label}: the background never moves; reset its transform")
            continue
        # orthonormalise away float noise
        u, _, vt = np.linalg.svd(r)
        m[:3, :3] = u @ vt
        m[3] = [0, 0, 0, 1]
        out[name] = m
    return out


def main(argv=None):
    p = Parser(prog="export_layout.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("blend", help="edited .blend from import_scene.py")
    p.add_argument("--out", required=True, help="output layout.json")
    a = p.parse_args(argv)
    if not os.path.isfile(a.blend):
        raise UserError(f"{a.blend}: file not found")
    import bpy

    open_blend(a.blend)
    layout = layout_from_blend(a.blend)
    write_json(a.out, {"format": LAYOUT_FORMAT, "objects": {k: rows(v) for k, v in layout.items()}})
    print(f"[export_layout] wrote {a.out}: {len(layout)} objects", flush=True)


if __name__ == "__main__":
    run_main(main)
