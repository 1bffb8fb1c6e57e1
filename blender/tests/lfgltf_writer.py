"""A small, test-only writer of LightFuse scenes (.glb) following docs/formats.md.

Components: list of dicts with name, id, and arrays position (N,3), rotation (N,4 xyzw),
scale (N,3, third 0), opacity (N,), sh0 (N,3), base_color (N,3), metallic (N,), roughness (N,)
(all Y-up).  States: list of (name, {component name: (translation xyz, rotation xyzw)}).
"""

from __future__ import annotations

import json
import struct

import numpy as np

from lfgltf import (ATTR_BASE_COLOR, ATTR_METALLIC, ATTR_OPACITY, ATTR_ROTATION, ATTR_ROUGHNESS, ATTR_SCALE, CHUNK_BIN,
                    CHUNK_JSON, EXT, GLB_MAGIC, KHR, attr_sh)


def random_component(name, cid, n, rng, centre=(0, 0, 0)):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    sc = np.zeros((n, 3))
    sc[:, :2] = rng.uniform(0.005, 0.03, size=(n, 2))
    return {"name": name, "id": cid,
            "position": rng.uniform(-0.2, 0.2, size=(n, 3)) + np.asarray(centre),
            "rotation": q, "scale": sc, "opacity": rng.uniform(0.1, 0.99, n),
            "sh0": rng.uniform(-0.5, 0.5, size=(n, 3)), "base_color": rng.uniform(0, 1, size=(n, 3)),
            "metallic": rng.uniform(0, 1, n), "roughness": rng.uniform(0.05, 1, n)}


def write_glb(path, components, states, extension=True):
    blob = bytearray()
    views, accessors = [], []

    def add(arr, typ):
        a = np.ascontiguousarray(arr, dtype="<f4")
        while len(blob) % 4:
            blob.append(0)
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": a.nbytes})
        blob.extend(a.tobytes())
        acc = {"bufferView": len(views) - 1, "componentType": 5126, "count": int(a.shape[0]), "type": typ}
        if typ == "VEC3" and len(a):
            acc["min"] = a.min(0).tolist()
            acc["max"] = a.max(0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    meshes = []
    for c in components:
        attrs = {"POSITION": add(c["position"], "VEC3"),
                 ATTR_ROTATION: add(c["rotation"], "VEC4"),
                 ATTR_SCALE: add(c["scale"], "VEC3"),
                 ATTR_OPACITY: add(np.asarray(c["opacity"])[:, None], "SCALAR"),
                 attr_sh(0, 0): add(c["sh0"], "VEC3"),
                 ATTR_BASE_COLOR: add(c["base_color"], "VEC3"),
                 ATTR_METALLIC: add(np.asarray(c["metallic"])[:, None], "SCALAR"),
                 ATTR_ROUGHNESS: add(np.asarray(c["roughness"])[:, None], "SCALAR")}
        ext = {"kernel": "surfel", "colorSpace": "lin_rec709_display", "projection": "perspective",
               "sortingMethod": "cameraDistance",
               "extensions": {EXT: {"kernel": "gaussianSurfel", "cutoff": 3.0, "maxOpacity": 0.99,
                                    "component": c["id"]}}}
        prim = {"attributes": attrs, "mode": 0}
        if extension:
            prim["extensions"] = {KHR: ext}
        meshes.append({"name": c["name"], "primitives": [prim]})
    nodes, scenes = [], []
    for sname, tr in states:
        ids = []
        for mi, c in enumerate(components):
            t, r = tr.get(c["name"], ((0, 0, 0), (0, 0, 0, 1)))
            nodes.append({"name": c["name"], "mesh": mi, "translation": list(map(float, t)),
                          "rotation": list(map(float, r))})
            ids.append(len(nodes) - 1)
        scenes.append({"name": sname, "nodes": ids,
                       "extensions": {EXT: {"environmentRotation": 0.0}} if extension else {}})
    js = {"asset": {"version": "2.0", "generator": "lightfuse test writer"},
          "extensionsUsed": [KHR, EXT] if extension else [],
          "scene": 0, "scenes": scenes, "nodes": nodes, "meshes": meshes,
          "accessors": accessors, "bufferViews": views, "buffers": [{"byteLength": len(blob)}]}
    if extension:
        js["extensions"] = {EXT: {"version": 1, "referenceState": 0, "environments": [],
                                  "components": [{"name": c["name"], "mesh": i, "id": c["id"]}
                                                 for i, c in enumerate(components)]}}
    jb = json.dumps(js).encode()
    jb += b" " * (-len(jb) % 4)
    while len(blob) % 4:
        blob.append(0)
    total = 12 + 8 + len(jb) + 8 + len(blob)
    with open(path, "wb") as f:
        f.write(struct.pack("<4sII", GLB_MAGIC, 2, total))
        f.write(struct.pack("<II", len(jb), CHUNK_JSON) + jb)
        f.write(struct.pack("<II", len(blob), CHUNK_BIN) + bytes(blob))
