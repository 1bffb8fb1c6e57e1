"""usd-core opens LightFuse's `.usda`: ParticleFields with the Gaussian surflet kernel, the
LightFuse PBR schema (schemas/usd, found through PXR_PLUGINPATH_NAME set in conftest.py), the
`state` variants moving the objects and switching the latlong DomeLight, the exact f32 values
we wrote, and no UsdValidation errors.

The scene comes from `cargo run --release --example write_test_scene -- <out.usda>`, which also
writes `<out>.expected.json` with the values to find (f32 bit patterns). Set LIGHTFUSE_USDA to
test an existing file instead (it needs its sidecar)."""
import json
import os
import pathlib
import subprocess

import numpy as np
import pytest

pxr = pytest.importorskip("pxr")
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdValidation, UsdVol  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[2]
SCHEMAS = ROOT / "schemas" / "usd"


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    given = os.environ.get("LIGHTFUSE_USDA")
    if given:
        path = pathlib.Path(given)
    else:
        path = tmp_path_factory.mktemp("usd") / "scene.usda"
        subprocess.run(
            ["cargo", "run", "--release", "--quiet", "--example", "write_test_scene", "--",
             str(path), "64"],
            cwd=ROOT, check=True)
    expected = json.loads(pathlib.Path(str(path) + ".expected.json").read_text())
    return path, expected


@pytest.fixture(scope="module")
def stage(written):
    path, _ = written
    st = Usd.Stage.Open(str(path))
    assert st, path
    return st


def f32_bits(values):
    """Bits of the f32 values usd-core read (Python floats hold f32 exactly)."""
    return np.asarray(values, dtype=np.float32).view(np.uint32).tolist()


def vec_bits(values, n):
    return [f32_bits([v[i] for i in range(n)]) for v in values]


def quat_bits(q):
    im = q.GetImaginary()
    return f32_bits([q.GetReal(), im[0], im[1], im[2]])


def test_schema_plugin_is_loaded():
    reg = Usd.SchemaRegistry()
    for name, props in [
        ("LightFuseSurfelMaterialAPI",
         ["lightfuse:baseColors", "lightfuse:metallics", "lightfuse:roughnesses"]),
        ("LightFuseComponentAPI", ["lightfuse:componentId", "lightfuse:componentName"]),
        ("LightFuseSceneAPI", ["lightfuse:stateNames", "lightfuse:stateVariants"]),
        ("LightFuseEnvironmentAPI", ["lightfuse:environmentRotation"]),
    ]:
        d = reg.FindAppliedAPIPrimDefinition(name)
        assert d is not None, f"{name} not found: is {SCHEMAS} on PXR_PLUGINPATH_NAME?"
        for p in props:
            assert p in d.GetPropertyNames(), (name, p)


def test_stage_metadata(stage):
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/Scene")


def particle_fields(stage):
    """ParticleField prims in scene order (composition may list variant-touched prims first)."""
    fields = [p for p in stage.Traverse() if p.IsA(UsdVol.ParticleField)]
    return sorted(fields, key=lambda p: p.GetParent().GetAttribute("lightfuse:componentId").Get())


def test_particle_fields_carry_surflets_pbr_and_our_values(stage, written):
    _, expected = written
    fields = particle_fields(stage)
    assert len(fields) == len(expected["components"])
    for prim, exp in zip(fields, expected["components"]):
        comp = prim.GetParent()
        assert comp.IsA(UsdGeom.Xform)
        assert comp.HasAPI("LightFuseComponentAPI")
        assert comp.GetAttribute("lightfuse:componentName").Get() == exp["name"]
        assert comp.GetAttribute("lightfuse:componentId").Get() == exp["id"]
        assert prim.HasAPI(UsdVol.ParticleFieldKernelGaussianSurfletAPI)
        assert prim.HasAPI(UsdVol.ParticleFieldKernelBaseAPI)
        assert not prim.HasAPI(UsdVol.ParticleFieldKernelGaussianEllipsoidAPI)
        for api in (UsdVol.ParticleFieldPositionAttributeAPI,
                    UsdVol.ParticleFieldOrientationAttributeAPI,
                    UsdVol.ParticleFieldScaleAttributeAPI,
                    UsdVol.ParticleFieldOpacityAttributeAPI,
                    UsdVol.ParticleFieldSphericalHarmonicsAttributeAPI):
            assert prim.HasAPI(api), api
        assert prim.HasAPI("LightFuseSurfelMaterialAPI")
        # The PBR attributes are the schema's, with the schema's types.
        defn = prim.GetPrimDefinition()
        for name, ty in [("lightfuse:baseColors", Sdf.ValueTypeNames.Color3fArray),
                         ("lightfuse:metallics", Sdf.ValueTypeNames.FloatArray),
                         ("lightfuse:roughnesses", Sdf.ValueTypeNames.FloatArray)]:
            assert name in defn.GetPropertyNames()
            assert prim.GetAttribute(name).GetTypeName() == ty

        n, k = exp["count"], len(exp["positions"])
        pos = UsdVol.ParticleFieldPositionAttributeAPI(prim).GetPositionsAttr().Get()
        assert len(pos) == n
        assert vec_bits(pos[:k], 3) == exp["positions"]
        ori = UsdVol.ParticleFieldOrientationAttributeAPI(prim).GetOrientationsAttr().Get()
        assert len(ori) == n
        assert [quat_bits(q) for q in ori[:k]] == exp["orientations"]
        sc = UsdVol.ParticleFieldScaleAttributeAPI(prim).GetScalesAttr().Get()
        assert vec_bits(sc[:k], 3) == exp["scales"]
        op = UsdVol.ParticleFieldOpacityAttributeAPI(prim).GetOpacitiesAttr().Get()
        assert [[b] for b in f32_bits(op[:k])] == exp["opacities"]
        sh_api = UsdVol.ParticleFieldSphericalHarmonicsAttributeAPI(prim)
        degree = sh_api.GetRadianceSphericalHarmonicsDegreeAttr().Get()
        assert degree == exp["sh_degree"]
        coeffs = sh_api.GetRadianceSphericalHarmonicsCoefficientsAttr().Get()
        stride = (degree + 1) ** 2
        assert len(coeffs) == n * stride
        assert vec_bits(coeffs[:k * stride], 3) == exp["sh"]
        assert vec_bits(prim.GetAttribute("lightfuse:baseColors").Get()[:k], 3) == exp["base_colors"]
        for attr, key in [("lightfuse:metallics", "metallics"),
                          ("lightfuse:roughnesses", "roughnesses")]:
            vals = prim.GetAttribute(attr).Get()
            assert len(vals) == n
            assert [[b] for b in f32_bits(vals[:k])] == exp[key]


def test_state_variants_move_objects_and_switch_the_dome_light(stage, written):
    path, expected = written
    root = stage.GetPrimAtPath("/Scene")
    vset = root.GetVariantSets().GetVariantSet("state")
    names = list(root.GetAttribute("lightfuse:stateNames").Get())
    variants = list(root.GetAttribute("lightfuse:stateVariants").Get())
    assert names == [s["name"] for s in expected["states"]]
    assert sorted(vset.GetVariantNames()) == sorted(variants)
    assert vset.GetVariantSelection() == variants[expected["reference_state"]]
    comps = [f.GetParent() for f in particle_fields(stage)]
    textures = []
    for variant, exp in zip(variants, expected["states"]):
        assert vset.SetVariantSelection(variant)
        for i, comp in enumerate(comps):
            xf = UsdGeom.Xformable(comp)
            if i == 0:
                assert xf.GetLocalTransformation() == Gf.Matrix4d(1.0)
                continue
            ops = xf.GetOrderedXformOps()
            assert [op.GetOpName() for op in ops] == ["xformOp:translate", "xformOp:orient"]
            assert ops[0].GetPrecision() == UsdGeom.XformOp.PrecisionFloat
            assert f32_bits(list(ops[0].Get())) == exp["translations"][i]
            assert quat_bits(ops[1].Get()) == exp["orients"][i]
        dome = stage.GetPrimAtPath("/Scene/EnvironmentLight")
        env = exp["environment"]
        if env is None:
            assert not dome
            continue
        assert dome.IsA(UsdLux.DomeLight)
        light = UsdLux.DomeLight(dome)
        assert light.GetTextureFormatAttr().Get() == UsdLux.Tokens.latlong
        asset = light.GetTextureFileAttr().Get()
        resolved = pathlib.Path(asset.resolvedPath)
        assert resolved.is_file(), asset
        textures.append(resolved)
        assert dome.GetAttribute("lightfuse:environmentIndex").Get() == env["index"]
        rot = dome.GetAttribute("lightfuse:environmentRotation").Get()
        assert f32_bits([rot]) == [env["rotation_deg_bits"]]
        ops = UsdGeom.Xformable(dome).GetOrderedXformOps()
        assert [op.GetOpName() for op in ops] == ["xformOp:rotateY"]
        assert f32_bits([ops[0].Get()]) == [env["dome_rotate_y_bits"]]
    # Switching the variant switches the texture.
    assert len(set(textures)) == len({s["environment"]["index"] for s in expected["states"]
                                      if s["environment"]})


def test_usd_validation_reports_no_errors(stage):
    reg = UsdValidation.ValidationRegistry()
    validators = reg.GetOrLoadAllValidators()
    assert validators
    ctx = UsdValidation.ValidationContext(validators)
    vset = stage.GetPrimAtPath("/Scene").GetVariantSets().GetVariantSet("state")
    for variant in vset.GetVariantNames():  # every state composes cleanly
        vset.SetVariantSelection(variant)
        errors = ctx.Validate(stage)
        bad = [e for e in errors if e.GetType() == UsdValidation.ValidationErrorType.Error]
        assert not bad, variant + ":\n" + "\n".join(e.GetErrorAsString() for e in bad)
