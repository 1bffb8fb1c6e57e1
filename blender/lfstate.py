"""LightFuse: place the objects as in a stored state: apply_state("state1").

The records import_scene.py keeps in the .blend it writes, and the one function that places
that .blend's objects as in one of its states.  This file needs nothing but Python and Blender:
import_scene.py saves it in the .blend as the text block ``lightfuse_states.py`` (a module,
which offers the operator ``lightfuse.apply_state`` when the .blend is opened with scripts
allowed), so the .blend places its states without this toolkit.
"""

import json
import math
import os

SCENE_PROP = "lightfuse_scene"  # scene: the record (states, their environments, components, ...)
STATE_PROP = "lightfuse_state"  # scene: the state shown
STATES_PROP = "lightfuse_states"  # object: its Blender world matrix per state (JSON)
COMPONENT_PROP = "lightfuse_component"  # object: the component it shows
ORIGIN_PROP = "lightfuse_origin"  # object: its pivot in the reference state (Blender axes)
ENV_NODE = "lightfuse_env"  # world: the Environment Texture node of a LightFuse world
TEXT_BLOCK = "lightfuse_states.py"  # the text block holding this file


class UnknownState(ValueError):
    """The scene has no state of that name."""


def apply_state(name, base_dir=None, make_world=None):
    """Place every object as in the stored state ``name`` and light the scene with that state's
    environment (its image and its rotation about +Y).

    ``base_dir`` is the folder the environments' paths are relative to (default: the open
    .blend's).  ``make_world(path, rotation_deg)`` builds the world when the scene has no
    LightFuse world (no ``ENV_NODE`` node) yet; without it, such a scene keeps its world.

    What the callers rely on: import_scene.py applies a state while it builds a .blend that is
    not saved yet and has no world, so it passes the folder the .blend will be saved in and
    ``lfenv.setup_world``; the text block in the saved .blend (and its operator) runs in Blender
    without this toolkit and passes neither: the world built on import is there, and only its
    image and rotation change.  An unknown state raises :class:`UnknownState`.
    """
    import bpy
    import mathutils

    sc = bpy.context.scene
    rec = json.loads(sc[SCENE_PROP])
    if name not in rec["states"]:
        raise UnknownState(f"unknown state {name!r}; the scene's states are {', '.join(rec['states'])}")
    for ob in bpy.data.objects:
        st = ob.get(STATES_PROP)
        if st is not None:
            ob.matrix_world = mathutils.Matrix(json.loads(st)[name])
    env = rec.get("state_environments", {}).get(name)
    if env:
        base = os.path.dirname(bpy.data.filepath) if base_dir is None else base_dir
        path = os.path.normpath(os.path.join(base, env[0]))
        world = sc.world
        if world and world.node_tree and ENV_NODE in world.node_tree.nodes:
            tex = world.node_tree.nodes[ENV_NODE]
            tex.image = bpy.data.images.load(path, check_existing=True)
            tex.inputs["Vector"].links[0].from_node.inputs["Rotation"].default_value = (0, 0, math.radians(env[1]))
        elif make_world is not None:
            make_world(path, env[1])
    sc[STATE_PROP] = name
    bpy.context.view_layer.update()


def register():
    """Offer :func:`apply_state` as the operator ``lightfuse.apply_state``."""
    import bpy

    class LIGHTFUSE_OT_apply_state(bpy.types.Operator):
        """Place the objects as in a LightFuse state"""
        bl_idname = "lightfuse.apply_state"
        bl_label = "LightFuse: Apply State"
        state: bpy.props.StringProperty(name="State")

        def execute(self, context):
            apply_state(self.state)
            return {"FINISHED"}

    try:
        bpy.utils.register_class(LIGHTFUSE_OT_apply_state)
    except ValueError:
        pass


if __name__ != "lfstate":  # run by Blender as the .blend's text block lightfuse_states.py
    register()
