"""Import a LightFuse scene (.glb/.gltf with KHR_gaussian_splatting + LIGHTFUSE_gaussian_surfels)
into Blender and save it as a .blend for editing.

Blender's own glTF importer drops the splat attributes, so the file is read directly
(docs/formats.md).  The result:

* one mesh object per component, named like the component (``background`` first); its vertices
  are the surfel centres and carry every surfel attribute as a named point attribute:
  ``rotation`` (QUATERNION, Blender axes), ``scale`` (FLOAT_VECTOR s_u, s_v, 0), ``opacity``
  (FLOAT), ``sh_<l>_<n>`` (FLOAT_VECTOR RGB, coefficients kept in LightFuse's Y-up frame),
  ``base_color`` (FLOAT_COLOR), ``metallic`` and ``roughness`` (FLOAT);
* a Geometry Nodes modifier that shows each surfel as an oriented disc (a circle rotated by
  ``rotation``, radius 2 x ``scale``) coloured by ``base_color``;
* the object origin at the centroid of its surfels in the reference state;
* the background's transforms locked;
* the states: every object stores its Blender world matrix per state (custom property
  ``lightfuse_states``); ``apply_state(name)`` (``lfstate.py``, saved in the .blend as the text
  block ``lightfuse_states.py``) places the objects as in that state; the scene's
  ``lightfuse_state`` property names the state shown.  The reference state is applied on
  import (or ``--state``).

Axes: LightFuse +Y up (x, y, z) -> Blender (x, -z, y).  Edit the objects (move / rotate only),
then run ``export_layout.py``.

Example::

    .venv/bin/python blender/import_scene.py scene.glb --out scene_edit.blend
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import numpy as np  # noqa: E402

import lfstate  # noqa: E402
from lfaxes import C3, check_rigid, rows, yup_to_bl_matrix  # noqa: E402
from lfblend import ID_PROP  # noqa: E402
from lfcli import Parser, UserError, quiet_stdout, run_main  # noqa: E402
from lfenv import setup_world  # noqa: E402
from lfgltf import (ATTR_BASE_COLOR, ATTR_METALLIC, ATTR_OPACITY, ATTR_ROTATION, ATTR_ROUGHNESS,  # noqa: E402
                    ATTR_SCALE, ATTR_SH_PREFIX, EXT, KHR, read_accessor, read_gltf_json, trs_to_matrix)
from lfstate import COMPONENT_PROP, ORIGIN_PROP, SCENE_PROP, STATES_PROP  # noqa: E402


def yup_quat_to_blender_wxyz(q_xyzw: np.ndarray) -> np.ndarray:
    """Surfel rotations (N, 4) glTF (x, y, z, w) in Y-up -> Blender (w, x, y, z) in Z-up:
    R_bl = C^T R, i.e. left-multiply by the +90 deg rotation about X (Y-up -> Blender)."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    n = np.linalg.norm(q, axis=1, keepdims=True)
    q = q / np.where(n > 0, n, 1.0)
    x, y, z, w = q.T
    cw = sx = math.sqrt(0.5)  # (w, x, 0, 0) of the axis change
    return np.stack([cw * w - sx * x, cw * x + sx * w, cw * y - sx * z, cw * z + sx * y], 1)


def load_scene(path: str) -> dict:
    """Parse and validate a LightFuse glTF scene; arrays in LightFuse (Y-up) coordinates."""
    js, binc = read_gltf_json(path)
    root = (js.get("extensions") or {}).get(EXT)
    if root is None:
        raise UserError(f"{path}: not a LightFuse scene: no '{EXT}' root extension "
                        "(expected a .glb written by lightfuse, docs/formats.md)")
    comps = root.get("components")
    if not isinstance(comps, list) or not comps:
        raise UserError(f"{path}: extensions.{EXT}.components must be a non-empty list")
    base = os.path.dirname(os.path.abspath(path))
    meshes = js.get("meshes") or []
    out = {"components": [], "states": [], "reference": root.get("referenceState", js.get("scene", 0)),
           "environments": [e.get("name") for e in root.get("environments", [])]}
    for ci, c in enumerate(comps):
        where = f"{path}: extensions.{EXT}.components[{ci}]"
        try:
            name, cid = c["name"], int(c["id"])
            mi = c.get("mesh")
            if mi is None:  # a component without surfels
                out["components"].append(_empty_component(name, cid))
                continue
            prim = meshes[mi]["primitives"][0]
            attrs = prim["attributes"]
        except (KeyError, IndexError, TypeError, ValueError, AttributeError):
            raise UserError(f"{where}: expected name, id and mesh (index of a mesh with one primitive)") from None
        if KHR not in (prim.get("extensions") or {}):
            raise UserError(f"{path}: meshes[{mi}].primitives[0]: no {KHR} extension; not a splat primitive")

        def get(key, nc, required=True):
            if key not in attrs:
                if required:
                    raise UserError(f"{path}: meshes[{mi}].primitives[0].attributes: missing {key}")
                return None
            a = read_accessor(js, binc, base, attrs[key], f"{path}: meshes[{mi}] attribute {key}")
            if a.shape[1] != nc:
                raise UserError(f"{path}: meshes[{mi}] attribute {key}: expected {nc} components, got {a.shape[1]}")
            return a

        pos = get("POSITION", 3)
        n = len(pos)
        d = {"name": name, "id": cid, "position": pos,
             "rotation": get(ATTR_ROTATION, 4), "scale": get(ATTR_SCALE, 3),
             "opacity": get(ATTR_OPACITY, 1)[:, 0],
             "base_color": get(ATTR_BASE_COLOR, 3, False), "metallic": get(ATTR_METALLIC, 1, False),
             "roughness": get(ATTR_ROUGHNESS, 1, False), "sh": {}}
        for key in attrs:
            if key.startswith(ATTR_SH_PREFIX):
                parts = key.split(":")[1].split("_")  # SH DEGREE l COEF n
                d["sh"][f"sh_{parts[2]}_{parts[4]}"] = get(key, 3)
        for k in ("rotation", "scale", "base_color", "metallic", "roughness"):
            if d[k] is not None and len(d[k]) != n:
                raise UserError(f"{path}: meshes[{mi}]: attribute {k} has {len(d[k])} elements, POSITION has {n}")
        out["components"].append(d)
    envs = []
    for ei, e in enumerate(root.get("environments", [])):
        where = f"{path}: extensions.{EXT}.environments[{ei}]"
        if "bufferView" in e:
            try:
                bv = js["bufferViews"][e["bufferView"]]
                o = bv.get("byteOffset", 0)
                data = binc[o:o + bv["byteLength"]]
                if binc is None or len(data) != bv["byteLength"]:
                    raise ValueError
            except (KeyError, IndexError, TypeError, ValueError):
                raise UserError(f"{where}: bufferView is missing or truncated") from None
            envs.append({"name": e.get("name", f"env{ei}"), "bytes": data})
        elif "uri" in e:
            envs.append({"name": e.get("name", f"env{ei}"), "path": os.path.join(base, e["uri"])})
        else:
            raise UserError(f"{where}: expected bufferView or uri")
    out["env_data"] = envs
    nodes = js.get("nodes") or []
    names = {c["name"] for c in out["components"]}
    for si, s in enumerate(js.get("scenes") or []):
        tr = {}
        for ni in s.get("nodes", []):
            nd = nodes[ni]
            nm = nd.get("name")
            if nm in names:
                tr[nm] = check_rigid(trs_to_matrix(nd), f"{path}: scenes[{si}] node {nm!r}")
        ext = (s.get("extensions") or {}).get(EXT, {})
        out["states"].append({"name": s.get("name") or f"state{si}", "transforms": tr,
                              "environment": ext.get("environment"),
                              "environmentRotation": ext.get("environmentRotation", 0.0)})
    if not out["states"]:
        out["states"].append({"name": "state0", "transforms": {}, "environment": None, "environmentRotation": 0.0})
    return out


def _empty_component(name, cid):
    z = np.zeros((0, 3), np.float32)
    return {"name": name, "id": cid, "position": z, "rotation": np.zeros((0, 4), np.float32), "scale": z,
            "opacity": np.zeros(0, np.float32), "base_color": None, "metallic": None, "roughness": None, "sh": {}}


def surfel_node_group():
    import bpy

    if "LightFuse surfels" in bpy.data.node_groups:
        return bpy.data.node_groups["LightFuse surfels"]
    ng = bpy.data.node_groups.new("LightFuse surfels", "GeometryNodeTree")
    ng.interface.new_socket(name="Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket(name="Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    N = ng.nodes
    gi = N.new("NodeGroupInput")
    go = N.new("NodeGroupOutput")
    circ = N.new("GeometryNodeMeshCircle")
    circ.fill_type = "NGON"
    circ.inputs["Vertices"].default_value = 8
    circ.inputs["Radius"].default_value = 2.0  # 2 sigma
    rot = N.new("GeometryNodeInputNamedAttribute")
    rot.data_type = "QUATERNION"
    rot.inputs["Name"].default_value = "rotation"
    sca = N.new("GeometryNodeInputNamedAttribute")
    sca.data_type = "FLOAT_VECTOR"
    sca.inputs["Name"].default_value = "scale"
    vm = N.new("ShaderNodeVectorMath")
    vm.operation = "MAXIMUM"
    vm.inputs[1].default_value = (1e-4, 1e-4, 1.0)
    inst = N.new("GeometryNodeInstanceOnPoints")
    mat = surfel_material()
    sm = N.new("GeometryNodeSetMaterial")
    sm.inputs["Material"].default_value = mat
    L = ng.links
    L.new(gi.outputs["Geometry"], inst.inputs["Points"])
    L.new(circ.outputs["Mesh"], sm.inputs["Geometry"])
    L.new(sm.outputs["Geometry"], inst.inputs["Instance"])
    L.new(rot.outputs["Attribute"], inst.inputs["Rotation"])
    L.new(sca.outputs["Attribute"], vm.inputs[0])
    L.new(vm.outputs["Vector"], inst.inputs["Scale"])
    L.new(inst.outputs["Instances"], go.inputs["Geometry"])
    return ng


def surfel_material():
    import bpy

    if "LightFuse surfel" in bpy.data.materials:
        return bpy.data.materials["LightFuse surfel"]
    m = bpy.data.materials.new("LightFuse surfel")
    if m.node_tree is None:
        m.use_nodes = True
    nt = m.node_tree
    bsdf = next(n for n in nt.nodes if n.type == "BSDF_PRINCIPLED")
    at = nt.nodes.new("ShaderNodeAttribute")
    at.attribute_type = "INSTANCER"
    at.attribute_name = "base_color"
    nt.links.new(at.outputs["Color"], bsdf.inputs["Base Color"])
    for key, sock in (("metallic", "Metallic"), ("roughness", "Roughness")):
        a2 = nt.nodes.new("ShaderNodeAttribute")
        a2.attribute_type = "INSTANCER"
        a2.attribute_name = key
        nt.links.new(a2.outputs["Fac"], bsdf.inputs[sock])
    return m


def build(scene: dict, state: str | None, path: str, out_blend: str) -> None:
    import bpy
    import mathutils

    ref_i = scene["reference"] if isinstance(scene["reference"], int) else 0
    state_names = [s["name"] for s in scene["states"]]
    ng = surfel_node_group()
    for c in scene["components"]:
        p_bl = c["position"].astype(np.float64) @ C3  # = (C3^T p) row-wise: Y-up -> Blender
        centre = p_bl.mean(0) if len(p_bl) else np.zeros(3)
        me = bpy.data.meshes.new(c["name"])
        if len(p_bl):
            me.vertices.add(len(p_bl))
            me.vertices.foreach_set("co", (p_bl - centre).astype(np.float32).ravel())
        me.update()
        q = yup_quat_to_blender_wxyz(c["rotation"])  # surfel frame columns in Blender axes

        def attr(name, typ, vals, field="value"):
            a = me.attributes.new(name, typ, "POINT")
            if len(p_bl):
                a.data.foreach_set(field, np.ascontiguousarray(vals, np.float32).ravel())

        attr("rotation", "QUATERNION", q)
        attr("scale", "FLOAT_VECTOR", c["scale"], "vector")
        attr("opacity", "FLOAT", c["opacity"])
        for k, v in sorted(c["sh"].items()):
            attr(k, "FLOAT_VECTOR", v, "vector")
        if c["base_color"] is not None:
            rgba = np.concatenate([c["base_color"], np.ones((len(p_bl), 1), np.float32)], 1)
            attr("base_color", "FLOAT_COLOR", rgba, "color")
        for k in ("metallic", "roughness"):
            if c[k] is not None:
                attr(k, "FLOAT", c[k][:, 0])
        ob = bpy.data.objects.new(c["name"], me)
        bpy.context.scene.collection.objects.link(ob)
        mod = ob.modifiers.new("LightFuse surfels", "NODES")
        mod.node_group = ng
        ob[COMPONENT_PROP] = c["name"]
        ob[ID_PROP] = c["id"]
        ob[ORIGIN_PROP] = [float(x) for x in centre]
        T0 = mathutils.Matrix.Translation(centre.tolist())
        states = {}
        for s in scene["states"]:
            m = s["transforms"].get(c["name"], np.eye(4))
            if c["id"] == 0 and np.abs(np.asarray(m) - np.eye(4)).max() > 1e-6:
                raise UserError(f"{path}: state {s['name']!r} moves the background; it never moves")
            wm = yup_to_bl_matrix(m) @ np.array(T0)
            states[s["name"]] = rows(wm)
        ob[STATES_PROP] = json.dumps(states)
        ob.matrix_world = T0
        if c["id"] == 0:
            ob.lock_location = (True, True, True)
            ob.lock_rotation = (True, True, True)
            ob.lock_scale = (True, True, True)
            ob.lock_rotation_w = True
    # environments: written next to the .blend (relative paths), one world per state
    env_files = []
    if scene["env_data"]:
        d = os.path.splitext(out_blend)[0] + ".env"
        os.makedirs(d, exist_ok=True)
        for i, e in enumerate(scene["env_data"]):
            if "bytes" in e:
                f = os.path.join(d, f"{i:02d}_{''.join(ch if ch.isalnum() or ch in '-_' else '_' for ch in e['name'])}.exr")
                with open(f, "wb") as fh:
                    fh.write(e["bytes"])
            else:
                f = e["path"]
            env_files.append(os.path.abspath(f))
    state_envs = {}
    for s in scene["states"]:
        ei = s.get("environment")
        if isinstance(ei, int) and 0 <= ei < len(env_files):
            state_envs[s["name"]] = [os.path.relpath(env_files[ei], os.path.dirname(out_blend)),
                                     float(s.get("environmentRotation") or 0.0)]
    sc = bpy.context.scene
    sc[SCENE_PROP] = json.dumps({"version": 1, "source": os.path.abspath(path), "states": state_names,
                                 "state_environments": state_envs,
                                 "reference": state_names[ref_i] if ref_i < len(state_names) else state_names[0],
                                 "components": [{"name": c["name"], "id": c["id"]} for c in scene["components"]],
                                 "environments": scene["environments"]})
    txt = bpy.data.texts.new(lfstate.TEXT_BLOCK)
    with open(lfstate.__file__, encoding="utf-8") as f:
        txt.write(f.read())
    txt.use_module = True
    try:
        lfstate.apply_state(state or state_names[ref_i if ref_i < len(state_names) else 0],
                            base_dir=os.path.dirname(out_blend), make_world=setup_world)
    except lfstate.UnknownState as e:
        raise UserError(f"--state: {e}") from None


def main(argv=None):
    p = Parser(prog="import_scene.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", help="LightFuse scene .glb / .gltf")
    p.add_argument("--state", help="state to show (default: the reference state)")
    p.add_argument("--out", required=True, help="output .blend")
    a = p.parse_args(argv)
    if not os.path.isfile(a.scene):
        raise UserError(f"{a.scene}: scene file not found")
    scene = load_scene(a.scene)
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    out = os.path.abspath(a.out)
    os.makedirs(os.path.dirname(out), exist_ok=True)
    build(scene, a.state, a.scene, out)
    with quiet_stdout():
        bpy.ops.wm.save_as_mainfile(filepath=out, compress=True)
    n = sum(len(c["position"]) for c in scene["components"])
    print(f"[import_scene] wrote {out}: {len(scene['components'])} components, {n} surfels, "
          f"states {', '.join(s['name'] for s in scene['states'])}", flush=True)


if __name__ == "__main__":
    run_main(main)
