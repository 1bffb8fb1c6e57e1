"""Layout readers: layout.json, glTF node TRS and USD Xforms give the same Y-up transform."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from lfgltf_writer import random_component, write_glb

from lfaxes import C3, bl_to_yup_matrix, check_rigid, yup_to_bl_matrix
from lfcli import UserError
from lffiles import read_layout


def _rot_y(deg, t):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0, s, t[0]], [0, 1, 0, t[1]], [-s, 0, c, t[2]], [0, 0, 0, 1.0]])


def test_three_layout_formats_agree(tmp_path):
    want = _rot_y(30, (0.1, 0.0, 0.2))
    j = tmp_path / "layout.json"
    j.write_text(json.dumps({"format": "lightfuse-layout/1", "objects": {"ball": want.tolist()}}))
    h = math.radians(30) / 2
    rng = np.random.default_rng(0)
    g = tmp_path / "layout.glb"
    write_glb(g, [random_component("background", 0, 3, rng), random_component("ball", 1, 3, rng)],
              [("s", {"ball": ((0.1, 0.0, 0.2), (0, math.sin(h), 0, math.cos(h)))})])
    u = tmp_path / "layout.usda"
    u.write_text('#usda 1.0\n(\n defaultPrim = "scene"\n upAxis = "Y"\n)\ndef Xform "scene"\n{\n'
                 ' def Xform "background" {}\n def Xform "ball"\n {\n'
                 '  double3 xformOp:translate = (0.1, 0, 0.2)\n  float3 xformOp:rotateXYZ = (0, 30, 0)\n'
                 '  uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:rotateXYZ"]\n }\n}\n')
    for f in (j, g, u):
        got = read_layout(str(f))
        assert set(got) == {"ball"}, f
        assert np.allclose(got["ball"], want, atol=1e-6), f


def test_axis_change_round_trip():
    m = _rot_y(75, (1, 2, 3))
    assert np.allclose(bl_to_yup_matrix(yup_to_bl_matrix(m)), m)
    # Blender +Z up is LightFuse +Y; Blender +Y (forward) is LightFuse -Z
    assert np.allclose(C3 @ [0, 0, 1], [0, 1, 0]) and np.allclose(C3 @ [0, 1, 0], [0, 0, -1])


@pytest.mark.parametrize("m, msg", [
    (np.diag([1, 1, 2.0, 1]), "scale or shear"),
    (np.array([[1, 0.2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]), "scale or shear"),
    (np.diag([-1, 1, 1, 1.0]), "reflection"),
    (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0.1, 0, 1.0]]), "last row"),
    ([[1, 0, 0], [0, 1, 0]], "4x4"),
])
def test_check_rigid_refuses(m, msg):
    with pytest.raises(UserError, match=msg):
        check_rigid(m, "layout.json: objects.x")
