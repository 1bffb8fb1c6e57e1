"""Two scenes the project does not ship, built by the tests in Blender as a user would bring them
to ``generate.py --scene``: a room of primitives with a table and a shelf saved as a .blend
(with a lamp and a camera of its own), and a workshop corner exported to a .glb (read back by
Blender's glTF importer). Blender axes (Z up), metres."""

from __future__ import annotations


def _material(name, color, metallic=0.0, roughness=0.5, roughness_texture=False, checker=False):
    import bpy

    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:
        mat.use_nodes = True
    nt = mat.node_tree
    bsdf = next(n for n in nt.nodes if n.type == "BSDF_PRINCIPLED")
    bsdf.inputs["Base Color"].default_value = (*color, 1)
    bsdf.inputs["Metallic"].default_value = metallic
    bsdf.inputs["Roughness"].default_value = roughness
    if roughness_texture:  # a roughness map: no plain truth to record
        tex = nt.nodes.new("ShaderNodeTexNoise")
        nt.links.new(tex.outputs["Fac"], bsdf.inputs["Roughness"])
    if checker:
        tex = nt.nodes.new("ShaderNodeTexChecker")
        tex.inputs["Scale"].default_value = 7.0
        tex.inputs["Color1"].default_value = (*color, 1)
        tex.inputs["Color2"].default_value = (0.9, 0.9, 0.85, 1)
        nt.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def _box(name, size, loc, mat):
    import bpy

    bpy.ops.mesh.primitive_cube_add(size=1.0, location=loc)
    ob = bpy.context.active_object
    ob.name = name
    ob.scale = size
    bpy.ops.object.transform_apply(location=False, rotation=False, scale=True)
    ob.data.materials.append(mat)
    return ob


def _join(name, parts):
    import bpy

    bpy.ops.object.select_all(action="DESELECT")
    for p in parts:
        p.select_set(True)
    bpy.context.view_layer.objects.active = parts[0]
    bpy.ops.object.join()
    ob = bpy.context.active_object
    ob.name = name
    return ob


def _origin_to_base(ob):
    """A user's object has its origin wherever; put it at the base's centre like a careful
    artist would not: at the bounding box centre (the generator must not rely on either)."""
    import bpy

    bpy.ops.object.select_all(action="DESELECT")
    ob.select_set(True)
    bpy.context.view_layer.objects.active = ob
    bpy.ops.object.origin_set(type="ORIGIN_GEOMETRY", center="BOUNDS")


def room_blend(path):
    """A 3 m x 3 m room (floor, two walls) with a table, a shelf unit against a wall, a lamp and
    a camera; movable: crate (checker base colour), can (metal, roughness map), and in the
    collection Toys a ball and a cone."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    wall = _material("wall_paint", (0.75, 0.72, 0.66), roughness=0.9)
    floor = _material("floor_paint", (0.45, 0.40, 0.35), roughness=0.7)
    wood = _material("oak", (0.55, 0.38, 0.22), roughness=0.6)
    _box("floor", (3.0, 3.0, 0.05), (0, 0, -0.025), floor)
    _box("wall_back", (3.0, 0.1, 2.2), (0, -1.55, 1.1), wall)
    _box("wall_left", (0.1, 3.0, 2.2), (-1.55, 0, 1.1), wall)
    top = _box("table_top", (1.0, 0.7, 0.04), (0.7, 0.5, 0.70), wood)
    legs = [_box(f"leg{i}", (0.05, 0.05, 0.68), (0.7 + sx * 0.45, 0.5 + sy * 0.3, 0.34), wood)
            for i, (sx, sy) in enumerate([(-1, -1), (-1, 1), (1, -1), (1, 1)])]
    _join("table", [top, *legs])
    sides = [_box(f"side{i}", (0.03, 0.35, 1.2), (-0.9 + i * 0.8, -1.3, 0.6), wood) for i in range(2)]
    boards = [_box(f"board{i}", (0.8, 0.35, 0.03), (-0.5, -1.3, 0.015 + 0.4 * i), wood) for i in range(4)]
    _join("shelf", [*sides, *boards])
    crate = _box("crate", (0.26, 0.18, 0.16), (-0.1, 0.3, 0.08), _material("crate_red", (0.7, 0.12, 0.08), roughness=0.5,
                                                                        checker=True))
    _origin_to_base(crate)
    bpy.ops.mesh.primitive_cylinder_add(vertices=32, radius=0.06, depth=0.15, location=(0.6, 0.4, 0.795))
    can = bpy.context.active_object
    can.name = "can"
    can.data.materials.append(_material("tin", (0.8, 0.8, 0.82), metallic=1.0, roughness=0.25, roughness_texture=True))
    bpy.ops.mesh.primitive_uv_sphere_add(segments=32, ring_count=16, radius=0.07, location=(-0.3, 0.6, 0.07))
    ball = bpy.context.active_object
    ball.name = "ball"
    ball.data.materials.append(_material("blue_plastic", (0.1, 0.25, 0.7), roughness=0.3))
    bpy.ops.mesh.primitive_cone_add(vertices=32, radius1=0.07, radius2=0.0, depth=0.18, location=(-0.5, -1.3, 0.52))
    cone = bpy.context.active_object
    cone.name = "cone"
    cone.data.materials.append(_material("yellow", (0.85, 0.65, 0.1), roughness=0.8))
    toys = bpy.data.collections.new("Toys")  # a collection: --movable Toys takes ball and cone
    bpy.context.scene.collection.children.link(toys)
    for ob in (ball, cone):
        for c in list(ob.users_collection):
            c.objects.unlink(ob)
        toys.objects.link(ob)
    bpy.ops.object.light_add(type="POINT", location=(0, 0, 2))
    bpy.context.active_object.name = "ceiling_lamp"
    bpy.ops.object.camera_add(location=(1.6, 1.8, 1.5))
    cam = bpy.context.active_object
    cam.name = "artist_cam"
    from mathutils import Vector

    cam.rotation_euler = (Vector((0.1, 0.1, 0.3)) - cam.location).to_track_quat("-Z", "Y").to_euler()
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    return ["crate", "can", "ball", "cone"]


def corner_glb(path):
    """A workshop corner (floor, one wall, a low bench) with a block (a knob on top as its child),
    a pyramid and a mug-like ring, exported as a binary glTF: what another DCC tool would hand
    over."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    grey = _material("concrete", (0.5, 0.5, 0.48), roughness=0.85)
    blue = _material("blue_wall", (0.35, 0.45, 0.6), roughness=0.85)
    _box("ground", (2.5, 2.5, 0.04), (0, 0, -0.02), grey)
    _box("backwall", (2.5, 0.08, 1.6), (0, -1.25, 0.8), blue)
    _box("bench", (1.0, 0.5, 0.4), (0.5, -0.9, 0.2), _material("bench_wood", (0.6, 0.45, 0.3), roughness=0.6))
    block = _box("block", (0.15, 0.15, 0.15), (-0.3, 0.2, 0.075), _material("green", (0.2, 0.5, 0.25), roughness=0.6))
    knob = _box("knob", (0.04, 0.04, 0.03), (-0.3, 0.2, 0.165), _material("black", (0.03, 0.03, 0.03), roughness=0.4))
    knob.parent = block  # a child: moves with the block, carries its mask id
    knob.matrix_parent_inverse = block.matrix_world.inverted()
    bpy.ops.mesh.primitive_cone_add(vertices=4, radius1=0.1, radius2=0.0, depth=0.14, location=(0.4, 0.3, 0.07))
    pyr = bpy.context.active_object
    pyr.name = "pyramid"
    pyr.data.materials.append(_material("copper", (0.95, 0.6, 0.45), metallic=1.0, roughness=0.3))
    bpy.ops.mesh.primitive_torus_add(major_radius=0.07, minor_radius=0.025, location=(0.0, -0.2, 0.025))
    ring = bpy.context.active_object
    ring.name = "ring"
    ring.data.materials.append(_material("white_glaze", (0.9, 0.9, 0.88), roughness=0.15))
    bpy.ops.export_scene.gltf(filepath=str(path), export_format="GLB")
    return ["block", "pyramid", "ring"]

