"""Export a dataset's scene.blend as a standard glTF mesh scene (.glb) for ``lightfuse surfelize``.

* All static geometry (room, furniture) is joined into one node named ``background``; each
  movable object is one node named like the dataset object (``dataset.json`` ``objects``), with
  ``extras.lightfuse_id`` = its mask id (background 0).
* Materials are glTF PBR metallic-roughness: constant colours become ``baseColorFactor``;
  procedural base colours are baked by Cycles into per-object images (``baseColorTexture`` on a
  fresh non-overlapping UV map, ``--bake-res`` pixels).  Metallic and roughness are constant per
  material (``metallicFactor``, ``roughnessFactor``).
* Axes: Blender's glTF exporter converts Blender Z-up to glTF +Y up, i.e. (x, y, z) -> (x, z, -y),
  the LightFuse convention (docs/design.md §2).  Node transforms place the meshes at the chosen state
  (default: the reference state0), so node-world positions are LightFuse world positions.

Example::

    .venv/bin/python blender/export_mesh_scene.py --dataset data/demo --out data/demo/mesh.glb
    .venv/bin/python blender/export_mesh_scene.py --scene data/demo/scene.blend --state state1 --out s1.glb
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from lfaxes import check_rigid  # noqa: E402
from lfblend import ID_PROP, apply_layout_bl, get_record, open_blend  # noqa: E402
from lfcli import Parser, UserError, quiet_stdout, run_main  # noqa: E402
from lffiles import read_layout  # noqa: E402
from lfrender import setup_render  # noqa: E402


def parse_args(argv):
    p = Parser(prog="export_mesh_scene.py", description=__doc__,
                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset", help="dataset folder (uses DATASET/scene.blend)")
    p.add_argument("--scene", help="scene .blend written by generate.py")
    p.add_argument("--state", help="place the objects as in this state (default: reference state)")
    p.add_argument("--layout", help="or: place the objects by this layout.json / .glb")
    p.add_argument("--bake-res", type=int, default=256, help="baked texture size per object (default 256; "
                                                              "background 4x)")
    p.add_argument("--out", required=True, help="output .glb")
    return p.parse_args(argv)


def _base_color_source(mat):
    """(Principled node, the socket linked into its Base Color or None)."""
    nt = mat.node_tree
    bsdf = next((n for n in nt.nodes if n.type == "BSDF_PRINCIPLED"), None)
    if bsdf is None:
        return None, None
    inp = bsdf.inputs["Base Color"]
    return bsdf, (inp.links[0].from_socket if inp.is_linked else None)


def _select_only(ob):
    import bpy

    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    ob.select_set(True)
    bpy.context.view_layer.objects.active = ob


def bake_object(ob, res: int) -> None:
    """Give ``ob`` its own materials; bake procedural base colours into one image on a new UV map."""
    import bpy

    # own copies of the materials (several objects may share one)
    for slot in ob.material_slots:
        if slot.material is not None and slot.material.users > 1:
            slot.material = slot.material.copy()
    textured = [s.material for s in ob.material_slots if s.material and _base_color_source(s.material)[1]]
    for s in ob.material_slots:
        if s.material:
            for n in [n for n in s.material.node_tree.nodes if n.type == "OUTPUT_AOV"]:
                s.material.node_tree.nodes.remove(n)
    if not textured:
        for uv in list(ob.data.uv_layers):
            ob.data.uv_layers.remove(uv)
        return
    me = ob.data
    for uv in list(me.uv_layers):
        me.uv_layers.remove(uv)
    uv = me.uv_layers.new(name="UVMap")
    me.uv_layers.active = uv
    _select_only(ob)
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.select_all(action="SELECT")
    bpy.ops.uv.smart_project(angle_limit=1.15, island_margin=0.01, area_weight=0.0, scale_to_bounds=True)
    bpy.ops.object.mode_set(mode="OBJECT")
    img = bpy.data.images.new(f"{ob.name}_base_color", res, res, alpha=False, float_buffer=False)
    img.colorspace_settings.name = "sRGB"
    saved = []
    for mat in textured:
        nt = mat.node_tree
        bsdf, src = _base_color_source(mat)
        out = next(n for n in nt.nodes if n.type == "OUTPUT_MATERIAL")
        old = out.inputs["Surface"].links[0].from_socket
        em = nt.nodes.new("ShaderNodeEmission")
        nt.links.new(src, em.inputs["Color"])
        nt.links.new(em.outputs["Emission"], out.inputs["Surface"])
        tex = nt.nodes.new("ShaderNodeTexImage")
        tex.image = img
        nt.nodes.active = tex
        saved.append((mat, bsdf, out, old, em, tex))
    sc = bpy.context.scene
    sc.cycles.samples = 4
    sc.render.bake.margin = 4
    sc.render.bake.use_clear = True
    with quiet_stdout():
        bpy.ops.object.bake(type="EMIT", margin=4, use_clear=True)
    img.pack()
    for mat, bsdf, out, old, em, tex in saved:
        nt = mat.node_tree
        nt.nodes.remove(em)
        nt.links.new(old, out.inputs["Surface"])
        nt.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
        # drop the procedural nodes now unused
        keep = {bsdf, out, tex}
        for n in list(nt.nodes):
            if n not in keep:
                nt.nodes.remove(n)


def main(argv=None):
    a = parse_args(argv)
    t0 = time.time()
    scene_path = a.scene or (os.path.join(a.dataset, "scene.blend") if a.dataset else None)
    if not scene_path:
        raise UserError("command line: give --scene FILE.blend or --dataset DIR")
    if not os.path.isfile(scene_path):
        raise UserError(f"{scene_path}: scene file not found")
    if not a.out.lower().endswith(".glb"):
        raise UserError(f"--out {a.out}: expected a .glb file name")
    import bpy

    open_blend(scene_path)
    rec = get_record(scene_path)
    if a.state:
        if a.state not in rec.get("states", {}):
            raise UserError(f"--state: no state {a.state!r} in {scene_path}; states are "
                            f"{', '.join(rec.get('states', {}))}")
        layout = {k: check_rigid(v, f"{scene_path}: states.{a.state}.{k}") for k, v in rec["states"][a.state].items()}
    elif a.layout:
        layout = read_layout(a.layout)
    else:
        layout = {}
    apply_layout_bl(rec, layout, a.layout or f"state {a.state or 'reference'}")
    obj_names = {o["name"]: o["id"] for o in rec["objects"]}
    sc = bpy.context.scene
    for ob in list(bpy.data.objects):
        if ob.type != "MESH":
            bpy.data.objects.remove(ob)
    static = [ob for ob in bpy.data.objects if ob.name not in obj_names]
    # join the static meshes into one "background" object
    for ob in static:
        ob.data = ob.data.copy()
    _select_only(static[0])
    for ob in static[1:]:
        ob.select_set(True)
    bpy.ops.object.join()
    bg = bpy.context.view_layer.objects.active
    bg.name = "background"
    bg.data.name = "background"
    bg[ID_PROP] = 0
    setup_render(4, 0, False)
    sc.render.use_persistent_data = False
    bake_object(bg, a.bake_res * 4)
    for name, oid in obj_names.items():
        ob = bpy.data.objects[name]
        ob[ID_PROP] = oid
        ob.data.name = name
        bake_object(ob, a.bake_res)
    out = os.path.abspath(a.out)
    os.makedirs(os.path.dirname(out), exist_ok=True)
    tmp = out + ".tmp.glb"
    with quiet_stdout():
        bpy.ops.export_scene.gltf(filepath=tmp, export_format="GLB", export_yup=True, export_apply=True,
                                  export_extras=True, export_cameras=False, export_lights=False,
                                  export_materials="EXPORT", export_image_format="AUTO",
                                  export_texcoords=True, export_normals=True, use_selection=False)
    os.replace(tmp, out)
    print(f"[export_mesh_scene] wrote {out} ({1 + len(obj_names)} nodes) in {time.time() - t0:.1f} s", flush=True)


if __name__ == "__main__":
    run_main(main)
