"""Procedural rooms for the LightFuse dataset generator (no asset downloads).

A preset is an open room (floor + two walls, no ceiling, so the environment lights it), static
furniture (the background, object id 0) and 3-5 movable objects built from primitives (boxes,
cylinders, cones, spheres, tori), with Principled BSDF materials that span diffuse, glossy and
metallic, several with spatially varying (procedural, object-space) base colour.

Each movable object's origin is the centre of its footprint at its base, so "resting on a
surface" is "origin z = surface height".  :func:`arrange` places the movable objects on the
floor or on furniture tops with a seeded rejection sampler (footprint circles must not overlap
each other, the furniture or the walls).
"""

from __future__ import annotations

import math
import random

import bmesh
import bpy
import mathutils
import numpy as np

# ----------------------------------------------------------------------------- materials

# name: (kind, params). kind: "plain" colour, or a procedural texture of two colours.
MATERIALS = {
    "wall": dict(color=(0.70, 0.68, 0.62), roughness=0.9),
    "wall_blue": dict(color=(0.35, 0.45, 0.60), roughness=0.85),
    "floor_wood": dict(tex="wave", c1=(0.42, 0.25, 0.12), c2=(0.25, 0.13, 0.06), scale=2.0, roughness=0.45),
    "floor_tiles": dict(tex="checker", c1=(0.80, 0.80, 0.78), c2=(0.15, 0.16, 0.18), scale=2.5, roughness=0.3),
    "carpet": dict(tex="noise", c1=(0.55, 0.20, 0.20), c2=(0.25, 0.10, 0.12), scale=6.0, roughness=1.0),
    "wood": dict(tex="wave", c1=(0.55, 0.35, 0.18), c2=(0.35, 0.20, 0.09), scale=4.0, roughness=0.5),
    "fabric_green": dict(tex="noise", c1=(0.20, 0.45, 0.25), c2=(0.10, 0.28, 0.14), scale=12.0, roughness=0.95),
    "fabric_grey": dict(color=(0.45, 0.45, 0.48), roughness=0.95),
    "linen": dict(color=(0.85, 0.83, 0.78), roughness=0.9),
    "red_gloss": dict(color=(0.75, 0.06, 0.05), roughness=0.2),
    "blue_gloss": dict(color=(0.08, 0.20, 0.70), roughness=0.25),
    "yellow_matte": dict(color=(0.85, 0.65, 0.10), roughness=0.85),
    "ceramic_white": dict(color=(0.90, 0.90, 0.88), roughness=0.15),
    "checker_toy": dict(tex="checker", c1=(0.90, 0.85, 0.10), c2=(0.10, 0.35, 0.80), scale=6.0, roughness=0.4),
    "stripes": dict(tex="wave", c1=(0.85, 0.30, 0.10), c2=(0.95, 0.90, 0.80), scale=5.0, roughness=0.35, bands=True),
    "gold": dict(color=(1.00, 0.77, 0.34), roughness=0.25, metallic=1.0),
    "steel": dict(color=(0.62, 0.62, 0.64), roughness=0.3, metallic=1.0),
    "copper": dict(color=(0.95, 0.60, 0.45), roughness=0.35, metallic=1.0),
    "black_plastic": dict(color=(0.03, 0.03, 0.035), roughness=0.3),
    "terracotta": dict(tex="noise", c1=(0.70, 0.32, 0.18), c2=(0.55, 0.24, 0.13), scale=20.0, roughness=0.8),
    # The second family's (untextured, or a mirror): nothing but shape and shading to go by.
    "chrome": dict(color=(0.90, 0.90, 0.92), roughness=0.05, metallic=1.0),
    "clay": dict(color=(0.76, 0.60, 0.48), roughness=0.6),
    "mint": dict(color=(0.42, 0.74, 0.62), roughness=0.5),
    "porcelain": dict(color=(0.93, 0.93, 0.95), roughness=0.1),
    "beech": dict(color=(0.78, 0.62, 0.42), roughness=0.55),
    "slate": dict(color=(0.24, 0.26, 0.29), roughness=0.7),
    "concrete": dict(color=(0.52, 0.51, 0.49), roughness=0.85),
}


def make_material(name: str) -> bpy.types.Material:
    """Principled BSDF; its base colour also goes to the 'albedo' AOV (dataset albedo)."""
    if name in bpy.data.materials:
        return bpy.data.materials[name]
    spec = MATERIALS[name]
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:
        mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.name = "Principled BSDF"
    bsdf.distribution = "GGX"  # single-scattering GGX: closer to LightFuse's BRDF than multiscatter
    bsdf.inputs["Metallic"].default_value = spec.get("metallic", 0.0)
    bsdf.inputs["Roughness"].default_value = spec["roughness"]
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    aov = nt.nodes.new("ShaderNodeOutputAOV")
    aov.aov_name = "albedo"
    if "tex" in spec:
        tc = nt.nodes.new("ShaderNodeTexCoord")
        kind = spec["tex"]
        if kind == "checker":
            t = nt.nodes.new("ShaderNodeTexChecker")
            t.inputs["Scale"].default_value = spec["scale"]
            t.inputs["Color1"].default_value = (*spec["c1"], 1)
            t.inputs["Color2"].default_value = (*spec["c2"], 1)
            nt.links.new(tc.outputs["Object"], t.inputs["Vector"])
            col = t.outputs["Color"]
        else:
            if kind == "wave":
                t = nt.nodes.new("ShaderNodeTexWave")
                t.wave_type = "BANDS" if spec.get("bands") else "RINGS"
                t.inputs["Scale"].default_value = spec["scale"]
                t.inputs["Distortion"].default_value = 0.0 if spec.get("bands") else 2.0
                t.inputs["Detail"].default_value = 1.0
            else:
                t = nt.nodes.new("ShaderNodeTexNoise")
                t.inputs["Scale"].default_value = spec["scale"]
                t.inputs["Detail"].default_value = 3.0
            nt.links.new(tc.outputs["Object"], t.inputs["Vector"])
            ramp = nt.nodes.new("ShaderNodeMix")
            ramp.data_type = "RGBA"
            ramp.inputs["A"].default_value = (*spec["c1"], 1)
            ramp.inputs["B"].default_value = (*spec["c2"], 1)
            nt.links.new(t.outputs["Fac"], ramp.inputs["Factor"])
            col = ramp.outputs["Result"]
        nt.links.new(col, bsdf.inputs["Base Color"])
        nt.links.new(col, aov.inputs["Color"])
    else:
        bsdf.inputs["Base Color"].default_value = (*spec["color"], 1)
        aov.inputs["Color"].default_value = (*spec["color"], 1)
    return mat


# ----------------------------------------------------------------------------- geometry


def _xf(loc=(0, 0, 0), rot=(0, 0, 0)):
    return mathutils.Matrix.Translation(loc) @ mathutils.Euler(rot).to_matrix().to_4x4()


def _torus(bm, R, r, mat, seg=32, rseg=12):
    verts = []
    for i in range(seg):
        a = 2 * math.pi * i / seg
        row = []
        for j in range(rseg):
            b = 2 * math.pi * j / rseg
            x = (R + r * math.cos(b)) * math.cos(a)
            y = (R + r * math.cos(b)) * math.sin(a)
            z = r * math.sin(b)
            row.append(bm.verts.new(mat @ mathutils.Vector((x, y, z))))
        verts.append(row)
    faces = []
    for i in range(seg):
        for j in range(rseg):
            f = bm.faces.new((verts[i][j], verts[(i + 1) % seg][j],
                              verts[(i + 1) % seg][(j + 1) % rseg], verts[i][(j + 1) % rseg]))
            faces.append(f)
    return faces


def _lathe(bm, profile, m, seg=48):
    """A solid of revolution about +Z: the (r, z) profile (from the axis at the bottom to the
    axis at the top) spun by Blender's own Spin (what the Screw modifier does), the seam and
    the poles merged."""
    verts = [bm.verts.new(m @ mathutils.Vector((r, 0.0, z))) for r, z in profile]
    edges = [bm.edges.new((a, b)) for a, b in zip(verts, verts[1:])]
    before = set(bm.faces)
    bmesh.ops.spin(bm, geom=verts + edges, cent=m @ mathutils.Vector((0, 0, 0)),
                   axis=(m.to_3x3() @ mathutils.Vector((0, 0, 1))).normalized(), angle=2 * math.pi,
                   steps=seg, use_merge=True)
    bmesh.ops.remove_doubles(bm, verts=bm.verts[:], dist=1e-6)
    return [f for f in bm.faces if f not in before and f.is_valid]


def build_mesh(name: str, parts: list, modifiers: list = ()) -> bpy.types.Object:
    """parts: (kind, dict, material name). Kinds: box(size, loc, rot), cyl(r, h, loc, rot)
    (loc = centre of the base), cone(r1, r2, h, loc, rot), sphere(r, loc, scale),
    torus(R, r, loc, rot), lathe(profile [(r, z)], loc, rot), monkey(size, loc, rot: Blender's
    Suzanne, `size` wide, standing on its lowest point), plane(size (w, h), loc, rot: upright in
    XZ).  Curved parts are smooth shaded. `modifiers`: (Blender modifier type, properties),
    applied in order to the whole mesh (e.g. BEVEL, SUBSURF, SOLIDIFY)."""
    bm = bmesh.new()
    mats = []
    for kind, p, mname in parts:
        if mname not in mats:
            mats.append(mname)
        mi = mats.index(mname)
        before = set(bm.faces)
        smooth = False
        if kind == "box":
            sx, sy, sz = p["size"]
            m = _xf(p.get("loc", (0, 0, 0)), p.get("rot", (0, 0, 0))) @ mathutils.Matrix.Diagonal((sx, sy, sz, 1))
            bmesh.ops.create_cube(bm, size=1.0, matrix=m, calc_uvs=True)
        elif kind in ("cyl", "cone"):
            r1 = p["r"] if kind == "cyl" else p["r1"]
            r2 = p["r"] if kind == "cyl" else p["r2"]
            h = p["h"]
            m = _xf(p.get("loc", (0, 0, 0)), p.get("rot", (0, 0, 0))) @ mathutils.Matrix.Translation((0, 0, h / 2))
            bmesh.ops.create_cone(bm, cap_ends=True, cap_tris=False, segments=p.get("seg", 32),
                                  radius1=r1, radius2=r2, depth=h, matrix=m, calc_uvs=True)
        elif kind == "sphere":
            sc = p.get("scale", (1, 1, 1))
            m = _xf(p.get("loc", (0, 0, 0))) @ mathutils.Matrix.Diagonal((*sc, 1))
            bmesh.ops.create_uvsphere(bm, u_segments=32, v_segments=16, radius=p["r"], matrix=m, calc_uvs=True)
            smooth = True
        elif kind == "torus":
            _torus(bm, p["R"], p["r"], _xf(p.get("loc", (0, 0, 0)), p.get("rot", (0, 0, 0))))
            smooth = True
        elif kind == "lathe":
            _lathe(bm, p["profile"], _xf(p.get("loc", (0, 0, 0)), p.get("rot", (0, 0, 0))), p.get("seg", 48))
            smooth = True
        elif kind == "monkey":
            # Suzanne spans 2.73 units in x, faces -Y with +Z up.
            k = p["size"] / 2.734
            m = _xf(p.get("loc", (0, 0, 0)), p.get("rot", (0, 0, 0))) @ mathutils.Matrix.Scale(k, 4)
            new = bmesh.ops.create_monkey(bm, matrix=m)["verts"]
            low = min(v.co.z for v in new)
            for v in new:
                v.co.z -= low - p.get("loc", (0, 0, 0))[2]
            smooth = True
        elif kind == "plane":
            w, h = p["size"]
            m = _xf(p.get("loc", (0, 0, 0)), p.get("rot", (0, 0, 0)))
            c = [m @ mathutils.Vector((x * w / 2, 0.0, z)) for x, z in ((-1, 0), (1, 0), (1, h), (-1, h))]
            bm.faces.new([bm.verts.new(v) for v in c])
        else:
            raise ValueError(kind)
        for f in set(bm.faces) - before:
            f.material_index = mi
            f.smooth = smooth
    me = bpy.data.meshes.new(name)
    bm.to_mesh(me)
    bm.free()
    for mname in mats:
        me.materials.append(make_material(mname))
    ob = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(ob)
    if modifiers:
        for mtype, props in modifiers:
            mod = ob.modifiers.new(mtype.lower(), mtype)
            for k, v in props.items():
                setattr(mod, k, v)
        # The evaluated mesh replaces the object's: datasets record plain meshes.
        ev = ob.evaluated_get(bpy.context.evaluated_depsgraph_get())
        applied = bpy.data.meshes.new_from_object(ev)
        ob.modifiers.clear()
        ob.data = applied
        bpy.data.meshes.remove(me)
        # A modifier may lift the lowest point (Subdivision shrinks towards the cage): the
        # object stands on its base again.
        low = min(v.co.z for v in applied.vertices)
        applied.transform(mathutils.Matrix.Translation((0, 0, -low)))
    return ob


# ----------------------------------------------------------------------------- catalogue

def obj_parts(kind: str) -> list:
    """Movable objects; origin at the base centre."""
    if kind == "ball":
        return [("sphere", dict(r=0.12, loc=(0, 0, 0.12)), "checker_toy")]
    if kind == "small_ball":
        return [("sphere", dict(r=0.07, loc=(0, 0, 0.07)), "red_gloss")]
    if kind == "orange":
        return [("sphere", dict(r=0.07, loc=(0, 0, 0.07)), "terracotta")]
    if kind == "vase":
        return [("sphere", dict(r=0.09, loc=(0, 0, 0.1), scale=(1, 1, 1.1)), "blue_gloss"),
                ("cyl", dict(r=0.045, h=0.12, loc=(0, 0, 0.17)), "blue_gloss"),
                ("cyl", dict(r=0.06, h=0.012, loc=(0, 0, 0.0)), "blue_gloss")]
    if kind == "pot":
        return [("cyl", dict(r=0.12, h=0.14, loc=(0, 0, 0)), "steel"),
                ("torus", dict(R=0.12, r=0.012, loc=(0, 0, 0.14)), "steel"),
                ("box", dict(size=(0.06, 0.03, 0.02), loc=(0.15, 0, 0.12)), "black_plastic"),
                ("box", dict(size=(0.06, 0.03, 0.02), loc=(-0.15, 0, 0.12)), "black_plastic")]
    if kind == "mug":
        return [("cyl", dict(r=0.045, h=0.1, loc=(0, 0, 0)), "ceramic_white"),
                ("torus", dict(R=0.03, r=0.008, loc=(0.05, 0, 0.05), rot=(math.pi / 2, 0, 0)), "ceramic_white")]
    if kind == "ring":
        return [("torus", dict(R=0.1, r=0.03, loc=(0, 0, 0.03)), "gold")]
    if kind == "blocks":
        return [("box", dict(size=(0.16, 0.16, 0.16), loc=(0, 0, 0.08)), "yellow_matte"),
                ("box", dict(size=(0.12, 0.12, 0.12), loc=(0.01, -0.01, 0.22), rot=(0, 0, 0.4)), "red_gloss"),
                ("box", dict(size=(0.08, 0.08, 0.08), loc=(-0.01, 0.0, 0.32), rot=(0, 0, 0.9)), "blue_gloss")]
    if kind == "lamp":
        return [("cyl", dict(r=0.08, h=0.02, loc=(0, 0, 0)), "copper"),
                ("cyl", dict(r=0.012, h=0.3, loc=(0, 0, 0.02)), "copper"),
                ("cone", dict(r1=0.13, r2=0.07, h=0.14, loc=(0, 0, 0.26)), "stripes")]
    if kind == "kettle":
        return [("sphere", dict(r=0.1, loc=(0, 0, 0.09), scale=(1, 1, 0.9)), "copper"),
                ("cyl", dict(r=0.015, h=0.12, loc=(0.08, 0, 0.06), rot=(0, 0.9, 0)), "copper"),
                ("torus", dict(R=0.06, r=0.01, loc=(0, 0, 0.19), rot=(math.pi / 2, 0, 0)), "black_plastic")]
    if kind == "books":
        return [("box", dict(size=(0.22, 0.16, 0.04), loc=(0, 0, 0.02)), "red_gloss"),
                ("box", dict(size=(0.2, 0.15, 0.035), loc=(0.01, 0, 0.0575), rot=(0, 0, 0.2)), "fabric_green"),
                ("box", dict(size=(0.18, 0.13, 0.03), loc=(0, 0.01, 0.09), rot=(0, 0, -0.15)), "stripes")]
    if kind == "cone_toy":
        return [("cone", dict(r1=0.09, r2=0.0, h=0.22, loc=(0, 0, 0), seg=24), "stripes")]
    if kind == "plant":
        return [("cyl", dict(r=0.08, h=0.14, loc=(0, 0, 0)), "terracotta"),
                ("sphere", dict(r=0.13, loc=(0, 0, 0.24)), "fabric_green")]
    if kind == "cushion":
        return [("box", dict(size=(0.35, 0.35, 0.1), loc=(0, 0, 0.05)), "fabric_green")]
    # The second family (see FAMILY): Blender's own primitives and modifiers, untextured or chrome.
    if kind == "monkey":  # no symmetry; untextured: its shape is the only cue
        return [("monkey", dict(size=0.22, loc=(0, 0, 0), rot=(0, 0, 0)), "clay")]
    if kind == "chrome_bottle":  # a solid of revolution, a mirror: turning it changes nothing
        return [("lathe", dict(profile=[(0.0, 0.0), (0.05, 0.0), (0.056, 0.012), (0.056, 0.13), (0.042, 0.17),
                                        (0.018, 0.2), (0.018, 0.25), (0.0, 0.25)]), "chrome")]
    if kind == "square_tin":  # four-fold about its axis, and upside down the same (plain, bevelled)
        return [("box", dict(size=(0.14, 0.14, 0.2), loc=(0, 0, 0.1)), "mint")]
    if kind == "plate":  # thin: 1.5 cm
        return [("cyl", dict(r=0.13, h=0.015, loc=(0, 0, 0), seg=48), "porcelain")]
    if kind == "sign":  # thin (a 1.2 cm panel) standing on a foot; striped front, black back
        return [("plane", dict(size=(0.24, 0.17), loc=(0, 0, 0.025)), "stripes"),
                ("box", dict(size=(0.16, 0.08, 0.025), loc=(0, 0, 0.0125)), "black_plastic")]
    if kind == "rolling_pin":  # lying on its side: a long thin cylinder, handles at both ends
        return [("cyl", dict(r=0.03, h=0.26, loc=(-0.13, 0, 0.03), rot=(0, math.pi / 2, 0)), "beech"),
                ("cyl", dict(r=0.013, h=0.07, loc=(-0.2, 0, 0.03), rot=(0, math.pi / 2, 0)), "beech"),
                ("cyl", dict(r=0.013, h=0.07, loc=(0.13, 0, 0.03), rot=(0, math.pi / 2, 0)), "beech")]
    raise KeyError(kind)


# Blender modifiers applied to a kind's mesh (build_mesh's `modifiers`).
MODIFIERS = {
    "monkey": [("SUBSURF", dict(levels=1, render_levels=1))],
    "square_tin": [("BEVEL", dict(width=0.01, segments=3))],
    # The panel gets its thickness from Solidify (inwards); its back faces take the next
    # material (the foot's black), so the sign has a front.
    "sign": [("SOLIDIFY", dict(thickness=0.012, offset=-1.0, material_offset=1))],
}


# Rotations about axes through a point of an object (its origin, the base centre, unless "offset"
# gives another) that leave its shape *and* appearance unchanged, in its Y-up frame (Blender's +Z
# is +Y): {"axis", "order"[, "offset"]}, order 0 = continuous, n = n-fold (as BOP's
# symmetries_continuous/discrete). Written to dataset.json for
# evaluation only: a pose error forgives them (src/eval/pose.rs), since no image can tell them
# apart. Only symmetries checked against obj_parts and MATERIALS are listed; kinds absent have none.
SYMMETRIES = {
    # Blender's checker (object coordinates, cells of 1/scale with a boundary through the axis)
    # takes parity(|floor(x)|) + parity(|floor(y)|); a half turn about +Z flips both parities.
    "ball": [{"axis": [0, 1, 0], "order": 2}],
    # Blender's Wave bands along object x with the sine profile are 0.5 - 0.5 cos(k x), even in
    # x, and a half turn about +Z maps x to -x: the striped cone and the lamp (a solid of
    # revolution in plain copper under a striped shade) look the same after it.
    "cone_toy": [{"axis": [0, 1, 0], "order": 2}],
    "lamp": [{"axis": [0, 1, 0], "order": 2}],
    "pot": [{"axis": [0, 1, 0], "order": 2}],  # plain steel body, one handle each side
    "vase": [{"axis": [0, 1, 0], "order": 0}],  # plain glossy solid of revolution
    "ring": [{"axis": [0, 1, 0], "order": 0}],  # plain gold torus about +Z
    # A plain sphere standing on its origin: every turn about its centre (0.07 m up) looks the
    # same; two continuous axes through the centre say so (the error is then measured there).
    "small_ball": [{"axis": [0, 1, 0], "order": 0, "offset": [0, 0.07, 0]},
                   {"axis": [1, 0, 0], "order": 0, "offset": [0, 0.07, 0]}],
    # The second family. A plain square prism (not a cube) is the same after a quarter turn
    # about its axis and after a half turn about a horizontal axis through its centre (upside
    # down), so the axes meet at the centre, 0.1 m up; the rotation group has 8 elements.
    "chrome_bottle": [{"axis": [0, 1, 0], "order": 0}],
    "square_tin": [{"axis": [0, 1, 0], "order": 4, "offset": [0, 0.1, 0]},
                   {"axis": [1, 0, 0], "order": 2, "offset": [0, 0.1, 0]}],
    "plate": [{"axis": [0, 1, 0], "order": 0, "offset": [0, 0.0075, 0]},
              {"axis": [1, 0, 0], "order": 2, "offset": [0, 0.0075, 0]}],
    # Lying along x: any turn about its own long axis, and end for end about the vertical.
    "rolling_pin": [{"axis": [1, 0, 0], "order": 0, "offset": [0, 0.03, 0]},
                    {"axis": [0, 1, 0], "order": 2, "offset": [0, 0.03, 0]}],
}


def table(name, w, d, h, x, y, mat="wood", top=0.04, leg=0.05):
    parts = [("box", dict(size=(w, d, top), loc=(x, y, h - top / 2)), mat)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append(("box", dict(size=(leg, leg, h - top),
                                      loc=(x + sx * (w / 2 - leg), y + sy * (d / 2 - leg), (h - top) / 2)), mat))
    return name, parts, (x - w / 2, x + w / 2, y - d / 2, y + d / 2), h


def block(name, w, d, h, x, y, mat):
    return name, [("box", dict(size=(w, d, h), loc=(x, y, h / 2)), mat)], (x - w / 2, x + w / 2, y - d / 2, y + d / 2), h


# room: half size S (interior x, y in [-S, S]); walls on -y (back) and -x (left) sides.
PRESETS = {
    "demo": dict(size=1.2, wall_h=0.8, obj_scale=1.5, floor="floor_tiles", wall="wall",
                 furniture=[table("table", 0.8, 0.6, 0.45, 0.25, -0.35)],
                 surfaces=["table"],
                 objects=[("ball", "ball"), ("pot", "pot"), ("vase", "vase")]),
    "bedroom": dict(size=2.0, wall_h=1.3, floor="floor_wood", wall="wall_blue",
                    furniture=[
                        ("bed", [("box", dict(size=(1.5, 2.0, 0.35), loc=(-1.2, -0.95, 0.175)), "wood"),
                                 ("box", dict(size=(1.45, 1.95, 0.18), loc=(-1.2, -0.95, 0.44)), "linen"),
                                 ("box", dict(size=(1.5, 0.08, 0.9), loc=(-1.2, -1.96, 0.45)), "wood")],
                         (-1.95, -0.45, -2.0, 0.05), 0.53),
                        table("nightstand", 0.45, 0.45, 0.5, 0.05, -1.7),
                        block("rug", 1.4, 1.0, 0.01, 0.6, 0.6, "carpet"),
                        table("desk", 1.0, 0.55, 0.72, 1.4, -1.65)],
                    surfaces=["nightstand", "desk", ("bed", (-1.9, -0.5, -1.85, 0.0))],
                    objects=[("lamp", "lamp"), ("books", "books"), ("ball", "ball"), ("vase", "vase"),
                             ("cushion", "cushion")]),
    "playroom": dict(size=2.0, wall_h=1.2, floor="carpet", wall="wall",
                     furniture=[table("low_table", 1.0, 0.7, 0.4, 0.6, -0.8, mat="yellow_matte"),
                                block("shelf", 1.2, 0.35, 0.9, -1.2, -1.8, "wood"),
                                block("toy_box", 0.6, 0.45, 0.35, -1.6, 0.3, "blue_gloss")],
                     surfaces=["low_table", "shelf", "toy_box"],
                     objects=[("blocks", "blocks"), ("ball", "ball"), ("ring", "ring"), ("cone_toy", "cone_toy"),
                              ("small_ball", "small_ball")]),
    "livingroom": dict(size=2.2, wall_h=1.3, floor="floor_wood", wall="wall",
                       furniture=[
                           ("sofa", [("box", dict(size=(2.0, 0.85, 0.42), loc=(-0.3, -1.72, 0.21)), "fabric_grey"),
                                     ("box", dict(size=(2.0, 0.2, 0.45), loc=(-0.3, -2.05, 0.65)), "fabric_grey"),
                                     ("box", dict(size=(0.2, 0.85, 0.25), loc=(-1.2, -1.72, 0.545)), "fabric_grey"),
                                     ("box", dict(size=(0.2, 0.85, 0.25), loc=(0.6, -1.72, 0.545)), "fabric_grey")],
                            (-1.3, 0.7, -2.15, -1.3), 0.42),
                           table("coffee_table", 1.1, 0.6, 0.4, -0.3, -0.5),
                           block("tv_stand", 0.45, 1.4, 0.5, -1.95, 0.7, "black_plastic"),
                           block("rug", 1.8, 1.2, 0.01, -0.3, -0.4, "carpet")],
                       surfaces=["coffee_table", "tv_stand", ("sofa", (-1.1, 0.5, -1.95, -1.3))],
                       objects=[("vase", "vase"), ("plant", "plant"), ("mug", "mug"), ("books", "books"),
                                ("ring", "ring")]),
    "kitchen": dict(size=2.0, wall_h=1.4, floor="floor_tiles", wall="wall",
                    furniture=[block("counter", 2.4, 0.6, 0.9, -0.4, -1.7, "ceramic_white"),
                               block("counter_side", 0.6, 1.4, 0.9, -1.7, -0.3, "wood"),
                               table("dining_table", 1.0, 0.8, 0.75, 0.7, 0.5)],
                    surfaces=["counter", "counter_side", "dining_table"],
                    objects=[("pot", "pot"), ("kettle", "kettle"), ("mug", "mug"), ("plant", "plant"),
                             ("orange", "orange")]),
}


# The second family: rooms with what the presets above do not have, to measure on scenes
# nothing was tuned on (issue 15). Shapes from Blender's own primitives and modifiers
# (Suzanne, a lathed chrome bottle, a bevelled four-fold tin, thin plates, signs and rolling
# pins), untextured or mirror materials, objects on furniture tops only ("on_furniture"), and
# other camera paths ("cameras": "low" at 8-18° over the open sides, "high" at 65-82°, "inside"
# at eye height close to the walls, within the room; the presets above orbit at 28-62°).
FAMILY = {
    "study": dict(size=2.0, wall_h=1.3, floor="concrete", wall="wall", cameras="low", on_furniture=True,
                  furniture=[table("desk", 1.2, 0.6, 0.75, 0.8, -1.6, mat="beech"),
                             block("bookshelf", 0.4, 1.2, 1.1, -1.75, -0.3, "slate"),
                             block("ottoman", 0.8, 0.8, 0.45, 0.7, 0.8, "fabric_grey")],
                  surfaces=["desk", "bookshelf", "ottoman"],
                  objects=[("monkey", "monkey"), ("square_tin", "square_tin"), ("sign", "sign"),
                           ("chrome_bottle", "chrome_bottle")]),
    "gallery": dict(size=2.4, wall_h=1.6, floor="slate", wall="wall", cameras="high", on_furniture=True,
                    furniture=[block("plinth_a", 0.6, 0.6, 0.9, -1.2, -1.2, "porcelain"),
                               block("plinth_b", 0.6, 0.6, 0.7, 0.9, -1.3, "porcelain"),
                               block("plinth_c", 0.6, 0.6, 1.0, -1.3, 0.9, "porcelain"),
                               block("plinth_d", 0.6, 0.6, 0.55, 0.8, 0.8, "porcelain")],
                    surfaces=["plinth_a", "plinth_b", "plinth_c", "plinth_d"],
                    objects=[("chrome_bottle", "chrome_bottle"), ("monkey", "monkey"), ("plate", "plate"),
                             ("square_tin", "square_tin")]),
    "workshop": dict(size=1.8, wall_h=1.2, floor="floor_tiles", wall="wall_blue", cameras="inside",
                     furniture=[table("workbench", 1.4, 0.7, 0.85, 0.1, -1.3, mat="beech"),
                                block("crate", 0.5, 0.5, 0.5, -1.35, 0.6, "wood"),
                                block("stool", 0.4, 0.4, 0.45, 0.9, 0.7, "slate")],
                     surfaces=["workbench", "crate", "stool"],
                     objects=[("sign", "sign"), ("rolling_pin", "rolling_pin"), ("square_tin", "square_tin"),
                              ("monkey", "monkey")]),
}
PRESETS.update(FAMILY)


# The plain family (issue 44): what hides a method that paints shadows into the base colour.
# Untextured floors and walls (a shadow baked into a checker or wood grain is hard to see; on a
# plain floor it is a dark blob every relit image shows), training states lit by procedural
# skies with a sun (lfenv.SUN_SKIES: hard shadows, 80 % of the light from one direction) and
# one soft HDRI, objects standing on the open floor so each state's shadows fall where another
# state's floor is lit, chrome and glossy objects, a third wall (fewer open sides: less of each
# environment is seen directly). "train_envs" / "test_envs": each state's environment, in
# order, unless --train-envs / --test-envs say otherwise. Default size: generate.PLAIN_SIZE.
PLAIN = {
    "sunroom": dict(size=0.8, wall_h=0.6, obj_scale=1.6, floor="concrete", wall="wall",
                    walls=("-y", "-x", "+x"), cameras="high",
                    furniture=[block("bench", 0.5, 0.18, 0.22, 0.0, -0.65, "porcelain")],
                    surfaces=[],
                    objects=[("chrome_bottle", "chrome_bottle"), ("square_tin", "square_tin"),
                             ("small_ball", "small_ball"), ("monkey", "monkey")],
                    train_envs=["sun_low", "sun_mid", "interior"],
                    test_envs=["sun_high", "courtyard", "studio"]),
    "atelier": dict(size=0.75, wall_h=0.55, obj_scale=1.5, floor="linen", wall="slate", cameras="orbit",
                    furniture=[],
                    surfaces=[],
                    objects=[("blocks", "blocks"), ("pot", "pot"), ("mug", "mug"),
                             ("chrome_bottle", "chrome_bottle")],
                    train_envs=["sun_mid", "city", "sun_low"],
                    test_envs=["sun_high", "forest", "sunset"]),
}
PRESETS.update(PLAIN)

# Which wall stands on which side: the box's size and centre for a room of half size S, wall
# thickness T and height H ("-y" back, "-x" left, "+x" right; the presets have the first two).
WALLS = {
    "-y": lambda S, T, H: ((2 * S + 2 * T, T, H), (0, -S - T / 2, H / 2)),
    "-x": lambda S, T, H: ((T, 2 * S, H), (-S - T / 2, 0, H / 2)),
    "+x": lambda S, T, H: ((T, 2 * S, H), (S + T / 2, 0, H / 2)),
}


def build_scene(preset: str) -> dict:
    """Create the static room and the movable objects at the origin.  Returns a description:
    {size, surfaces: {name: (rect, z)}, obstacles: [rect], movables: [(name, object, radius)]}."""
    P = PRESETS[preset]
    S = P["size"]
    T = 0.1  # wall / floor thickness
    build_mesh("floor", [("box", dict(size=(2 * S + 2 * T, 2 * S + 2 * T, T), loc=(0, 0, -T / 2)), P["floor"])])
    walls = [WALLS[side](S, T, P["wall_h"]) for side in P.get("walls", ("-y", "-x"))]
    build_mesh("walls", [("box", dict(size=size, loc=loc), P["wall"]) for size, loc in walls])
    surfaces = {"floor": ((-S, S, -S, S), 0.0)}
    obstacles = []
    surf_rects = {}
    for sname in P["surfaces"]:
        if isinstance(sname, tuple):
            surf_rects[sname[0]] = sname[1]
        else:
            surf_rects[sname] = None
    for name, parts, rect, top in P["furniture"]:
        build_mesh(name, parts)
        obstacles.append(rect)  # (a rug too: objects stand on the floor, not half in a rug)
        if name in surf_rects:
            surfaces[name] = (surf_rects[name] or rect, top)
    movables = []
    if P.get("on_furniture"):
        del surfaces["floor"]
    for name, kind in P["objects"]:
        parts = obj_parts(kind)
        ob = build_mesh(name, parts, MODIFIERS.get(kind, ()))
        k = P.get("obj_scale", 1.0)
        if k != 1.0:
            ob.data.transform(mathutils.Matrix.Scale(k, 4))
        co = np.array([v.co[:] for v in ob.data.vertices])
        radius = float(np.max(np.linalg.norm(co[:, :2], axis=1)))
        height = float(co[:, 2].max())
        movables.append((name, ob, radius, height))
    symmetries = {name: SYMMETRIES.get(kind, []) for name, kind in P["objects"]}
    return dict(size=S, surfaces=surfaces, obstacles=obstacles, movables=movables, symmetries=symmetries,
                cameras=P.get("cameras", "orbit"), tops=[top for *_r, top in P["furniture"]])


def _circle_rect_overlap(c, r, rect):
    x0, x1, y0, y1 = rect
    dx = max(x0 - c[0], 0, c[0] - x1)
    dy = max(y0 - c[1], 0, c[1] - y1)
    return dx * dx + dy * dy < r * r


def arrange(desc: dict, rng: random.Random, margin: float = 0.02) -> dict:
    """A physically plausible arrangement: {object name: 4x4 Blender world matrix}.
    Objects stand upright on the floor or a furniture top (z = surface height), with a random
    yaw; footprint circles don't overlap each other, the furniture or the walls."""
    placed = []  # (surface, centre, radius)
    out = {}
    names = list(desc["surfaces"])
    for name, ob, radius, height in desc["movables"]:
        r = radius + margin
        for _attempt in range(2000):
            surf = rng.choice(names)
            (x0, x1, y0, y1), z = desc["surfaces"][surf]
            if x1 - x0 < 2 * r or y1 - y0 < 2 * r:
                continue
            c = (rng.uniform(x0 + r, x1 - r), rng.uniform(y0 + r, y1 - r))
            if surf == "floor" and any(_circle_rect_overlap(c, r, o) for o in desc["obstacles"]):
                continue
            if any(s == surf and math.dist(c, pc) < r + pr for s, pc, pr in placed):
                continue
            break
        else:
            raise RuntimeError(f"could not place {name}")
        placed.append((surf, c, r))
        yaw = rng.uniform(-math.pi, math.pi)
        m = _xf((c[0], c[1], z), (0, 0, yaw))
        out[name] = np.array(m)
    return out
