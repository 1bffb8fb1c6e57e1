//! OpenUSD `.usda` (docs/formats.md): write a scene and read it back bit for bit.
//!
//! # Layout
//!
//! ```text
//! #usda 1.0  (defaultPrim = "Scene", upAxis = "Y", metersPerUnit = 1)
//! def Xform "Scene" (LightFuseSceneAPI; variantSet "state", selection = reference state)
//!     lightfuse:version, stateNames, stateVariants, referenceState, environmentNames,
//!     environmentFiles
//!     def Xform "<component>" (LightFuseComponentAPI: componentName, componentId;
//!                              objects: xformOpOrder = [translate, orient])
//!         def ParticleField "surfels" (Position/Orientation/Scale/Opacity attribute APIs,
//!             ParticleFieldKernelGaussianSurfletAPI, SphericalHarmonicsAttributeAPI,
//!             LightFuseSurfelMaterialAPI)
//!     variantSet "state" = { "<state>" {
//!         over "<object>" { float3 xformOp:translate; quatf xformOp:orient }
//!         def DomeLight "EnvironmentLight" (LightFuseEnvironmentAPI)   # only if lit
//!     } }
//! ```
//!
//! The LightFuse API schemas are codeless; their plugin is `schemas/usd` (point
//! `PXR_PLUGINPATH_NAME` at it). Environments are float RGB EXR files next to the layer, in
//! `<stem>.env/<name>.exr`, written with the layer and made visible together with it.
//!
//! # Attribute mapping (every value f32, so usd-core reads the same bits)
//!
//! | surfel | USD attribute |
//! |---|---|
//! | μ | `point3f[] positions` (the float variant; `positionsh` is half precision) |
//! | q (x, y, z, w) | `quatf[] orientations`, written as USD does: `(w, x, y, z)` |
//! | (s_u, s_v) | `float3[] scales` = (s_u, s_v, 0). The surflet kernel is a Gaussian disc in the particle's local XY plane (σ = 1, zero off the plane), so X and Y scale the two in-plane axes (the first two columns of R(q), docs/design.md §2) and Z, which scales nothing, is written 0 (flat, like the glTF file) and ignored when read. |
//! | α | `float[] opacities` (linear, post-sigmoid) |
//! | SH | `uniform int radiance:sphericalHarmonicsDegree` = L and `float3[] radiance:sphericalHarmonicsCoefficients`, (L + 1)² RGB triples per particle. USD groups them by particle, then by degree l, then by m = -l..l: exactly the KHR_gaussian_splatting / 3DGS order we store, with the same 0.5 DC bias (USD's fallback "DC signal of 0.5" is the zero coefficient), so they are copied unchanged. |
//! | a, m, r | `color3f[] lightfuse:baseColors`, `float[] lightfuse:metallics`, `float[] lightfuse:roughnesses` |
//!
//! Object transforms x ↦ R x + t are `xformOp:translate` (float3) then `xformOp:orient` (quatf),
//! authored only inside the state variants (a local opinion would win over every variant). The
//! background has no ops: it never moves.
//!
//! # DomeLight convention
//!
//! `DomeLight` (and `DomeLight_1` with `poleAxis` "scene" on this Y-up stage) maps latlong
//! textures the OpenEXR way: the top row is +Y, the image centre looks at +Z and the quarter
//! column at +X. LightFuse maps them as Cycles does after the axis change (docs/design.md §2): the
//! centre looks at +X and the quarter column at −Z, i.e. our map is USD's turned by +90° about
//! +Y. A state's `rotation_deg` θ is a Cycles Mapping node turning the *lookup* by θ about +Y,
//! so the environment seen in the scene is turned by −θ. The DomeLight therefore gets
//! `xformOp:rotateY = 90 − θ`; θ itself is kept exactly in `lightfuse:environmentRotation`,
//! which is what the reader uses.
//!
//! # Reading
//!
//! The `openusd` crate parses the text (it keeps variants, custom API schemas and exact f32
//! values; roughly 160 MB/s); we then read the layer's specs directly, variant by variant,
//! rather than composing a stage, because every state has to be read, not just the selected
//! one. Anything malformed gives an error naming the file, the prim path and the attribute.
//!
//! Strings: the USD text format escapes `\` and `"` in strings; `openusd` hands back the raw
//! text between the quotes, so we unescape it ourselves the way usd-core does.

use crate::error::{Error, Result};
use crate::io::AtomicFiles;
use crate::scene::{
    sh_coeffs, Component, EnvRef, Environment, Rigid, Scene, State, Surfels, MAX_SH_DEGREE,
};
use openusd::sdf::{self, AbstractData, Value};
use rayon::prelude::*;
use std::borrow::Cow;
use std::collections::HashSet;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::str::FromStr;

/// Version of this layout (`lightfuse:version`).
pub const USD_VERSION: i32 = 1;
/// Name of the root prim (the default prim).
pub const ROOT_PRIM: &str = "Scene";
/// Name of the ParticleField under each component's Xform.
pub const SURFELS_PRIM: &str = "surfels";
/// Name of the DomeLight a state variant defines when the state is lit.
pub const DOME_LIGHT_PRIM: &str = "EnvironmentLight";
/// The variant set holding the states.
pub const STATE_VARIANT_SET: &str = "state";

const PARTICLE_API_SCHEMAS: [&str; 7] = [
    "ParticleFieldPositionAttributeAPI",
    "ParticleFieldOrientationAttributeAPI",
    "ParticleFieldScaleAttributeAPI",
    "ParticleFieldOpacityAttributeAPI",
    "ParticleFieldKernelGaussianSurfletAPI",
    "ParticleFieldSphericalHarmonicsAttributeAPI",
    "LightFuseSurfelMaterialAPI",
];

// ---------------------------------------------------------------------------------------------
// Writing
// ---------------------------------------------------------------------------------------------

/// Names chosen for the USD side of a scene: prim names, variant names, environment files.
struct Names {
    prims: Vec<String>,
    variants: Vec<String>,
    /// Environment files relative to the layer's directory (`<stem>.env/<name>.exr`).
    env_files: Vec<String>,
}

impl Names {
    fn new(scene: &Scene, path: &Path) -> Names {
        let mut used: HashSet<String> = [DOME_LIGHT_PRIM.to_ascii_lowercase()].into();
        let prims = scene
            .components
            .iter()
            .map(|c| unique(identifier(&c.name), &mut used))
            .collect();
        let mut used = HashSet::new();
        let variants = scene
            .states
            .iter()
            .map(|s| unique(variant_name(&s.name), &mut used))
            .collect();
        let stem = super::file_stem(path).unwrap_or_default();
        let dir = format!("{}.env", file_name(&stem));
        let mut used = HashSet::new();
        let env_files = scene
            .environments
            .iter()
            .map(|e| format!("{dir}/{}.exr", unique(file_name(&e.name), &mut used)))
            .collect();
        Names {
            prims,
            variants,
            env_files,
        }
    }
}

/// A valid USD prim name: `[A-Za-z_][A-Za-z0-9_]*`.
fn identifier(name: &str) -> String {
    let mut s: String = name
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    if !s.starts_with(|c: char| c.is_ascii_alphabetic() || c == '_') {
        s.insert(0, '_');
    }
    s
}

/// A valid variant name: `[A-Za-z0-9_-]+`.
fn variant_name(name: &str) -> String {
    let s: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    if s.is_empty() {
        "_".into()
    } else {
        s
    }
}

/// A portable file name stem: `[A-Za-z0-9_.-]+`, never `.` or `..`-led.
fn file_name(name: &str) -> String {
    let s: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect();
    if s.is_empty() || s.starts_with('.') {
        format!("_{s}")
    } else {
        s
    }
}

/// `base`, or `base_2`, `base_3`, ... if already used (case-insensitively, for file systems).
fn unique(base: String, used: &mut HashSet<String>) -> String {
    let mut name = base.clone();
    let mut k = 2;
    while !used.insert(name.to_ascii_lowercase()) {
        name = format!("{base}_{k}");
        k += 1;
    }
    name
}

/// A USD string literal, escaped as usd-core's text parser unescapes it.
fn quote(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            '\t' => out.push_str("\\t"),
            c if (c as u32) < 0x20 || c as u32 == 0x7f => {
                out.push_str(&format!("\\x{:02x}", c as u32))
            }
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

fn quote_list<'a>(items: impl IntoIterator<Item = &'a str>) -> String {
    let v: Vec<String> = items.into_iter().map(quote).collect();
    format!("[{}]", v.join(", "))
}

/// Shortest decimal that parses back to the same f32 (callers pass finite values only).
#[inline]
fn push_f32(s: &mut String, b: &mut zmij::Buffer, v: f32) {
    s.push_str(b.format_finite(v));
}

fn f32_text(v: f32) -> String {
    zmij::Buffer::new().format_finite(v).to_string()
}

fn tuple_text(v: &[f32]) -> String {
    let mut s = String::from("(");
    let mut b = zmij::Buffer::new();
    for (i, x) in v.iter().enumerate() {
        if i > 0 {
            s.push_str(", ");
        }
        push_f32(&mut s, &mut b, *x);
    }
    s.push(')');
    s
}

/// `(w, x, y, z)`: USD's text order for quaternions, from our (x, y, z, w).
fn quat_text(q: [f32; 4]) -> String {
    tuple_text(&[q[3], q[0], q[1], q[2]])
}

/// Writes `[e0, e1, ...]`, formatting chunks of elements in parallel, a batch at a time so the
/// text in memory stays bounded; a line break after every chunk keeps lines editor-sized.
fn write_array<T: Sync>(
    w: &mut impl Write,
    items: &[T],
    fmt: impl Fn(&mut String, &mut zmij::Buffer, &T) + Sync,
) -> std::io::Result<()> {
    const CHUNK: usize = 4096;
    const BATCH: usize = 64 * CHUNK;
    w.write_all(b"[")?;
    let mut first = true;
    for batch in items.chunks(BATCH) {
        let parts: Vec<String> = batch
            .par_chunks(CHUNK)
            .map(|chunk| {
                let mut s = String::with_capacity(chunk.len() * 48);
                let mut b = zmij::Buffer::new();
                for (i, item) in chunk.iter().enumerate() {
                    if i > 0 {
                        s.push_str(", ");
                    }
                    fmt(&mut s, &mut b, item);
                }
                s
            })
            .collect();
        for part in parts {
            if !first {
                w.write_all(b",\n                ")?;
            }
            first = false;
            w.write_all(part.as_bytes())?;
        }
    }
    w.write_all(b"]")
}

fn fmt_vec3(s: &mut String, b: &mut zmij::Buffer, v: &[f32; 3]) {
    s.push('(');
    push_f32(s, b, v[0]);
    s.push_str(", ");
    push_f32(s, b, v[1]);
    s.push_str(", ");
    push_f32(s, b, v[2]);
    s.push(')');
}

fn fmt_quat(s: &mut String, b: &mut zmij::Buffer, q: &[f32; 4]) {
    s.push('(');
    push_f32(s, b, q[3]);
    s.push_str(", ");
    push_f32(s, b, q[0]);
    s.push_str(", ");
    push_f32(s, b, q[1]);
    s.push_str(", ");
    push_f32(s, b, q[2]);
    s.push(')');
}

fn fmt_scale(s: &mut String, b: &mut zmij::Buffer, v: &[f32; 2]) {
    s.push('(');
    push_f32(s, b, v[0]);
    s.push_str(", ");
    push_f32(s, b, v[1]);
    s.push_str(", 0)");
}

fn fmt_scalar(s: &mut String, b: &mut zmij::Buffer, v: &f32) {
    push_f32(s, b, *v);
}

/// Bounds of the surfels' discs: centres grown by 3σ of the larger in-plane scale (the
/// kernel's support, per the surflet schema's doc).
fn extent(s: &Surfels) -> Option<[[f32; 3]; 2]> {
    if s.is_empty() {
        return None;
    }
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for (p, sc) in s.position.iter().zip(&s.scale) {
        let r = 3.0 * sc[0].max(sc[1]);
        for k in 0..3 {
            lo[k] = lo[k].min(p[k] - r);
            hi[k] = hi[k].max(p[k] + r);
        }
    }
    Some([lo, hi])
}

/// Writes `scene` as `path` (`.usda`) and its environments as `<stem>.env/<name>.exr` beside
/// it; nothing is replaced unless every file was written.
pub fn write_usda(scene: &Scene, path: &Path) -> Result<()> {
    scene.validate(path)?;
    let names = Names::new(scene, path);
    let dir = path.parent().unwrap_or(Path::new(""));
    let mut files = AtomicFiles::new();
    let env_bytes: Vec<Vec<u8>> = scene
        .environments
        .par_iter()
        .map(crate::io::exr::environment_bytes)
        .collect();
    for (bytes, rel) in env_bytes.iter().zip(&names.env_files) {
        files.write(&dir.join(rel), bytes)?;
    }
    files.write_with(path, |w| write_layer(w, scene, &names))?;
    files.commit()
}

fn write_layer(w: &mut impl Write, scene: &Scene, names: &Names) -> std::io::Result<()> {
    writeln!(
        w,
        "#usda 1.0\n(\n    defaultPrim = \"{ROOT_PRIM}\"\n    doc = \"\"\"LightFuse scene: 2D Gaussian \
         surfels (UsdVol ParticleField, Gaussian surflet kernel) with PBR materials; one `state` \
         variant per captured state. LightFuse schemas: schemas/usd (PXR_PLUGINPATH_NAME).\"\"\"\n    \
         metersPerUnit = 1\n    upAxis = \"Y\"\n)\n"
    )?;
    let reference = &names.variants[scene.reference_state];
    writeln!(
        w,
        "def Xform \"{ROOT_PRIM}\" (\n    prepend apiSchemas = [\"LightFuseSceneAPI\"]\n    \
         variants = {{\n        string {STATE_VARIANT_SET} = {}\n    }}\n    \
         prepend variantSets = \"{STATE_VARIANT_SET}\"\n)\n{{",
        quote(reference)
    )?;
    writeln!(w, "    uniform int lightfuse:version = {USD_VERSION}")?;
    writeln!(
        w,
        "    uniform string[] lightfuse:stateNames = {}",
        quote_list(scene.states.iter().map(|s| s.name.as_str()))
    )?;
    writeln!(
        w,
        "    uniform token[] lightfuse:stateVariants = {}",
        quote_list(names.variants.iter().map(String::as_str))
    )?;
    writeln!(
        w,
        "    uniform int lightfuse:referenceState = {}",
        scene.reference_state
    )?;
    writeln!(
        w,
        "    uniform string[] lightfuse:environmentNames = {}",
        quote_list(scene.environments.iter().map(|e| e.name.as_str()))
    )?;
    let assets: Vec<String> = names.env_files.iter().map(|f| format!("@./{f}@")).collect();
    writeln!(
        w,
        "    uniform asset[] lightfuse:environmentFiles = [{}]",
        assets.join(", ")
    )?;

    for (i, c) in scene.components.iter().enumerate() {
        write_component(w, i, c, &names.prims[i])?;
    }

    writeln!(w, "\n    variantSet \"{STATE_VARIANT_SET}\" = {{")?;
    for (k, state) in scene.states.iter().enumerate() {
        writeln!(w, "        {} {{", quote(&names.variants[k]))?;
        for (i, t) in state.transforms.iter().enumerate().skip(1) {
            writeln!(
                w,
                "            over \"{}\"\n            {{\n                \
                 float3 xformOp:translate = {}\n                \
                 quatf xformOp:orient = {}\n            }}\n",
                names.prims[i],
                tuple_text(&t.translation),
                quat_text(t.rotation)
            )?;
        }
        if let Some(env) = state.environment {
            writeln!(
                w,
                "            def DomeLight \"{DOME_LIGHT_PRIM}\" (\n                \
                 prepend apiSchemas = [\"LightFuseEnvironmentAPI\"]\n            )\n            {{\n                \
                 uniform int lightfuse:environmentIndex = {}\n                \
                 float lightfuse:environmentRotation = {}\n                \
                 asset inputs:texture:file = @./{}@\n                \
                 token inputs:texture:format = \"latlong\"\n                \
                 float xformOp:rotateY = {}\n                \
                 uniform token[] xformOpOrder = [\"xformOp:rotateY\"]\n            }}",
                env.index,
                f32_text(env.rotation_deg),
                names.env_files[env.index],
                f32_text(dome_rotate_y(env.rotation_deg)),
            )?;
        }
        writeln!(w, "        }}")?;
    }
    writeln!(w, "    }}\n}}")
}

/// The DomeLight's rotation about +Y (degrees) that shows a LightFuse map turned by `rotation`.
pub fn dome_rotate_y(rotation_deg: f32) -> f32 {
    (90.0 - rotation_deg as f64) as f32
}

fn write_component(
    w: &mut impl Write,
    index: usize,
    c: &Component,
    prim: &str,
) -> std::io::Result<()> {
    writeln!(
        w,
        "\n    def Xform \"{prim}\" (\n        prepend apiSchemas = [\"LightFuseComponentAPI\"]\n    )\n    {{"
    )?;
    writeln!(
        w,
        "        uniform string lightfuse:componentName = {}",
        quote(&c.name)
    )?;
    writeln!(w, "        uniform int lightfuse:componentId = {}", c.id)?;
    if index > 0 {
        writeln!(
            w,
            "        uniform token[] xformOpOrder = [\"xformOp:translate\", \"xformOp:orient\"]"
        )?;
    }
    let s = &c.surfels;
    writeln!(
        w,
        "\n        def ParticleField \"{SURFELS_PRIM}\" (\n            prepend apiSchemas = {}\n        )\n        {{",
        quote_list(PARTICLE_API_SCHEMAS)
    )?;
    if let Some([lo, hi]) = extent(s) {
        writeln!(
            w,
            "            float3[] extent = [{}, {}]",
            tuple_text(&lo),
            tuple_text(&hi)
        )?;
    }
    fn attr(w: &mut impl Write, decl: &str) -> std::io::Result<()> {
        write!(w, "            {decl} = ")
    }
    attr(w, "point3f[] positions")?;
    write_array(w, &s.position, fmt_vec3)?;
    attr(w, "\n            quatf[] orientations")?;
    write_array(w, &s.rotation, fmt_quat)?;
    attr(w, "\n            float3[] scales")?;
    write_array(w, &s.scale, fmt_scale)?;
    attr(w, "\n            float[] opacities")?;
    write_array(w, &s.opacity, fmt_scalar)?;
    write!(
        w,
        "\n            uniform int radiance:sphericalHarmonicsDegree = {}\n",
        s.sh_degree
    )?;
    attr(w, "float3[] radiance:sphericalHarmonicsCoefficients")?;
    write_array(w, &s.sh, fmt_vec3)?;
    attr(w, "\n            color3f[] lightfuse:baseColors")?;
    write_array(w, &s.base_color, fmt_vec3)?;
    attr(w, "\n            float[] lightfuse:metallics")?;
    write_array(w, &s.metallic, fmt_scalar)?;
    attr(w, "\n            float[] lightfuse:roughnesses")?;
    write_array(w, &s.roughness, fmt_scalar)?;
    writeln!(w, "\n        }}\n    }}")
}

// ---------------------------------------------------------------------------------------------
// Reading
// ---------------------------------------------------------------------------------------------

/// The parsed layer and the file it came from, for errors.
struct Layer<'a> {
    data: sdf::Data,
    file: &'a Path,
}

fn type_name(v: &Value) -> &'static str {
    match v {
        Value::Bool(_) => "bool",
        Value::Int(_) => "int",
        Value::Int64(_) => "int64",
        Value::Uint(_) => "uint",
        Value::Float(_) => "float",
        Value::Double(_) => "double",
        Value::Half(_) => "half",
        Value::FloatVec(_) => "float[]",
        Value::DoubleVec(_) => "double[]",
        Value::HalfVec(_) => "half[]",
        Value::IntVec(_) => "int[]",
        Value::String(_) => "string",
        Value::StringVec(_) => "string[]",
        Value::Token(_) => "token",
        Value::TokenVec(_) => "token[]",
        Value::AssetPath(_) => "asset",
        Value::AssetPathVec(_) => "asset[]",
        Value::Quatf(_) => "quatf",
        Value::Quatd(_) => "quatd",
        Value::Quath(_) => "quath",
        Value::QuatfVec(_) => "quatf[]",
        Value::QuathVec(_) => "quath[]",
        Value::QuatdVec(_) => "quatd[]",
        Value::Vec3f(_) => "float3",
        Value::Vec3d(_) => "double3",
        Value::Vec3h(_) => "half3",
        Value::Vec3fVec(_) => "float3[]",
        Value::Vec3dVec(_) => "double3[]",
        Value::Vec3hVec(_) => "half3[]",
        _ => "another type",
    }
}

impl<'a> Layer<'a> {
    fn err(&self, prim: &str, attr: &str, message: impl Into<String>) -> Error {
        let field = if attr.is_empty() {
            format!("<{prim}>")
        } else {
            format!("<{prim}>.{attr}")
        };
        Error::invalid(self.file, field, message)
    }

    fn sdf_path(&self, prim: &str, attr: &str) -> Result<sdf::Path> {
        let text = if attr.is_empty() {
            prim.to_string()
        } else {
            format!("{prim}.{attr}")
        };
        sdf::Path::from_str(&text)
            .map_err(|e| self.err(prim, attr, format!("expected a valid USD path: {e}")))
    }

    fn has_prim(&self, prim: &str) -> Result<bool> {
        Ok(self.data.has_spec(&self.sdf_path(prim, "")?))
    }

    /// A field of a prim (or of the pseudo-root "/").
    fn prim_field(&self, prim: &str, field: &str) -> Result<Option<Cow<'_, Value>>> {
        let p = self.sdf_path(prim, "")?;
        self.data
            .try_field(&p, field)
            .map_err(|e| self.err(prim, "", format!("cannot read {field}: {e}")))
    }

    fn attr(&self, prim: &str, attr: &str) -> Result<Option<Cow<'_, Value>>> {
        let p = self.sdf_path(prim, attr)?;
        let v = self
            .data
            .try_field(&p, "default")
            .map_err(|e| self.err(prim, attr, format!("cannot read the value: {e}")))?;
        if let Some(Value::ValueBlock) = v.as_deref() {
            return Ok(None);
        }
        Ok(v)
    }

    fn require(&self, prim: &str, attr: &str, ty: &str) -> Result<Cow<'_, Value>> {
        self.attr(prim, attr)?.ok_or_else(|| {
            self.err(
                prim,
                attr,
                format!("missing attribute: expected a {ty} value"),
            )
        })
    }

    fn wrong(&self, prim: &str, attr: &str, ty: &str, v: &Value) -> Error {
        self.err(
            prim,
            attr,
            format!("expected a {ty} value, found {}", type_name(v)),
        )
    }

    fn int(&self, prim: &str, attr: &str) -> Result<i64> {
        match &*self.require(prim, attr, "int")? {
            Value::Int(i) => Ok(*i as i64),
            Value::Int64(i) => Ok(*i),
            Value::Uint(i) => Ok(*i as i64),
            v => Err(self.wrong(prim, attr, "int", v)),
        }
    }

    fn float(&self, prim: &str, attr: &str) -> Result<f32> {
        match &*self.require(prim, attr, "float")? {
            Value::Float(x) => Ok(*x),
            v => Err(self.wrong(prim, attr, "float", v)),
        }
    }

    fn string(&self, prim: &str, attr: &str) -> Result<String> {
        match &*self.require(prim, attr, "string")? {
            Value::String(s) => unescape(s).map_err(|m| self.err(prim, attr, m)),
            Value::Token(s) => unescape(s.as_str()).map_err(|m| self.err(prim, attr, m)),
            v => Err(self.wrong(prim, attr, "string", v)),
        }
    }

    fn strings(&self, prim: &str, attr: &str) -> Result<Vec<String>> {
        match &*self.require(prim, attr, "string[]")? {
            Value::StringVec(v) => v
                .iter()
                .map(|s| unescape(s).map_err(|m| self.err(prim, attr, m)))
                .collect(),
            // openusd 0.6 hands `string[]` values back as tokens.
            Value::TokenVec(v) => v
                .iter()
                .map(|s| unescape(s.as_str()).map_err(|m| self.err(prim, attr, m)))
                .collect(),
            v => Err(self.wrong(prim, attr, "string[]", v)),
        }
    }

    fn tokens(&self, prim: &str, attr: &str) -> Result<Vec<String>> {
        match &*self.require(prim, attr, "token[]")? {
            Value::TokenVec(v) => v
                .iter()
                .map(|s| unescape(s.as_str()).map_err(|m| self.err(prim, attr, m)))
                .collect(),
            v => Err(self.wrong(prim, attr, "token[]", v)),
        }
    }

    fn assets(&self, prim: &str, attr: &str) -> Result<Vec<String>> {
        match &*self.require(prim, attr, "asset[]")? {
            Value::AssetPathVec(v) => Ok(v.iter().map(|a| a.authored_path.clone()).collect()),
            v => Err(self.wrong(prim, attr, "asset[]", v)),
        }
    }

    fn vec3(&self, prim: &str, attr: &str) -> Result<[f32; 3]> {
        match &*self.require(prim, attr, "float3")? {
            Value::Vec3f(v) => Ok([v.x, v.y, v.z]),
            v => Err(self.wrong(prim, attr, "float3", v)),
        }
    }

    /// A quatf as our (x, y, z, w).
    fn quat(&self, prim: &str, attr: &str) -> Result<[f32; 4]> {
        match &*self.require(prim, attr, "quatf")? {
            Value::Quatf(q) => Ok([q.x, q.y, q.z, q.w]),
            v => Err(self.wrong(prim, attr, "quatf", v)),
        }
    }

    /// A float3-valued array (`point3f[]`, `color3f[]`, `float3[]`) of exactly `n` elements.
    fn vec3s(&self, prim: &str, attr: &str, n: Option<usize>) -> Result<Vec<[f32; 3]>> {
        match &*self.require(prim, attr, "float3[]")? {
            Value::Vec3fVec(v) => {
                self.count(prim, attr, v.len(), n)?;
                Ok(v.iter().map(|e| [e.x, e.y, e.z]).collect())
            }
            v => Err(self.wrong(prim, attr, "float3[]", v)),
        }
    }

    fn floats(&self, prim: &str, attr: &str, n: usize) -> Result<Vec<f32>> {
        match &*self.require(prim, attr, "float[]")? {
            Value::FloatVec(v) => {
                self.count(prim, attr, v.len(), Some(n))?;
                Ok(v.clone())
            }
            v => Err(self.wrong(prim, attr, "float[]", v)),
        }
    }

    fn quats(&self, prim: &str, attr: &str, n: usize) -> Result<Vec<[f32; 4]>> {
        match &*self.require(prim, attr, "quatf[]")? {
            Value::QuatfVec(v) => {
                self.count(prim, attr, v.len(), Some(n))?;
                Ok(v.iter().map(|q| [q.x, q.y, q.z, q.w]).collect())
            }
            v => Err(self.wrong(prim, attr, "quatf[]", v)),
        }
    }

    fn count(&self, prim: &str, attr: &str, found: usize, expected: Option<usize>) -> Result<()> {
        match expected {
            Some(n) if n != found => Err(self.err(
                prim,
                attr,
                format!("expected {n} elements (one per particle of positions), found {found}"),
            )),
            _ => Ok(()),
        }
    }

    fn children(&self, prim: &str) -> Result<Vec<String>> {
        match self.prim_field(prim, "primChildren")?.as_deref() {
            None => Ok(Vec::new()),
            Some(Value::TokenVec(v)) => Ok(v.iter().map(|t| t.as_str().to_string()).collect()),
            Some(v) => Err(self.wrong(prim, "primChildren", "token[]", v)),
        }
    }

    fn type_name(&self, prim: &str) -> Result<Option<String>> {
        Ok(match self.prim_field(prim, "typeName")?.as_deref() {
            Some(Value::Token(t)) => Some(t.as_str().to_string()),
            Some(Value::String(s)) => Some(s.clone()),
            _ => None,
        })
    }

    fn api_schemas(&self, prim: &str) -> Result<Vec<String>> {
        Ok(match self.prim_field(prim, "apiSchemas")?.as_deref() {
            Some(Value::TokenListOp(op)) => op
                .explicit_items
                .iter()
                .chain(&op.prepended_items)
                .chain(&op.appended_items)
                .chain(&op.added_items)
                .map(|t| t.as_str().to_string())
                .collect(),
            _ => Vec::new(),
        })
    }
}

/// Undoes the USD text format's string escapes (as usd-core's `TfEscapeString`).
fn unescape(s: &str) -> std::result::Result<String, String> {
    if !s.contains('\\') {
        return Ok(s.to_string());
    }
    let mut out = String::with_capacity(s.len());
    let mut it = s.chars().peekable();
    while let Some(c) = it.next() {
        if c != '\\' {
            out.push(c);
            continue;
        }
        let e = it
            .next()
            .ok_or_else(|| format!("unfinished escape at the end of {s:?}"))?;
        match e {
            'n' => out.push('\n'),
            'r' => out.push('\r'),
            't' => out.push('\t'),
            'a' => out.push('\x07'),
            'b' => out.push('\x08'),
            'f' => out.push('\x0c'),
            'v' => out.push('\x0b'),
            'x' => {
                let mut v = 0u32;
                let mut digits = 0;
                while digits < 2 {
                    match it.peek().and_then(|d| d.to_digit(16)) {
                        Some(d) => {
                            v = v * 16 + d;
                            it.next();
                            digits += 1;
                        }
                        None => break,
                    }
                }
                if digits == 0 {
                    return Err(format!("expected hex digits after \\x in {s:?}"));
                }
                out.push(char::from_u32(v).unwrap_or('\u{fffd}'));
            }
            '0'..='7' => {
                let mut v = e.to_digit(8).unwrap_or(0);
                for _ in 0..2 {
                    match it.peek().and_then(|d| d.to_digit(8)) {
                        Some(d) => {
                            v = v * 8 + d;
                            it.next();
                        }
                        None => break,
                    }
                }
                out.push(char::from_u32(v).unwrap_or('\u{fffd}'));
            }
            other => out.push(other),
        }
    }
    Ok(out)
}

/// Reads a scene written by [`write_usda`] (and its environment EXRs), validated.
pub fn read_usda(path: &Path) -> Result<Scene> {
    std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    let data = openusd::usda::read_file(path).map_err(|e| {
        Error::invalid(
            path,
            "USD text",
            format!("expected a valid .usda layer: {e:#}"),
        )
    })?;
    let layer = Layer { data, file: path };
    let scene = read_layer(&layer)?;
    scene.validate(path)?;
    Ok(scene)
}

fn read_layer(l: &Layer<'_>) -> Result<Scene> {
    // Stage metadata: we never convert units or axes, so refuse what would need it.
    match l.prim_field("/", "upAxis")?.as_deref() {
        Some(Value::Token(t)) if t.as_str() == "Y" => {}
        Some(Value::String(s)) if s == "Y" => {}
        other => {
            return Err(Error::invalid(
                l.file,
                "upAxis",
                format!(
                    "expected layer metadata upAxis = \"Y\" (LightFuse is Y-up), found {}",
                    other.map_or("nothing".to_string(), |v| format!("{v:?}"))
                ),
            ))
        }
    }
    let mpu = match l.prim_field("/", "metersPerUnit")?.as_deref() {
        Some(Value::Double(d)) => Some(*d),
        Some(Value::Float(f)) => Some(*f as f64),
        Some(Value::Int(i)) => Some(*i as f64),
        Some(Value::Int64(i)) => Some(*i as f64),
        _ => None,
    };
    if mpu != Some(1.0) {
        return Err(Error::invalid(
            l.file,
            "metersPerUnit",
            format!("expected layer metadata metersPerUnit = 1 (LightFuse works in metres), found {mpu:?}"),
        ));
    }
    let root_name = match l.prim_field("/", "defaultPrim")?.as_deref() {
        Some(Value::Token(t)) => t.as_str().to_string(),
        Some(Value::String(s)) => s.clone(),
        _ => ROOT_PRIM.to_string(),
    };
    let root = format!("/{root_name}");
    if !l.has_prim(&root)? {
        return Err(l.err(&root, "", "missing prim: expected the scene's root Xform"));
    }
    let version = l.int(&root, "lightfuse:version")?;
    if version != USD_VERSION as i64 {
        return Err(l.err(
            &root,
            "lightfuse:version",
            format!("expected version {USD_VERSION}, found {version}"),
        ));
    }

    // Components: the root's children that carry LightFuseComponentAPI's attributes, in order.
    let mut components = Vec::new();
    let mut prim_of = Vec::new();
    for child in l.children(&root)? {
        let prim = format!("{root}/{child}");
        if l.attr(&prim, "lightfuse:componentName")?.is_none() {
            continue;
        }
        components.push(read_component(l, &prim)?);
        prim_of.push(child);
    }

    // Environments.
    let env_names = l.strings(&root, "lightfuse:environmentNames")?;
    let env_files = l.assets(&root, "lightfuse:environmentFiles")?;
    if env_files.len() != env_names.len() {
        return Err(l.err(
            &root,
            "lightfuse:environmentFiles",
            format!(
                "expected one file per environment name ({}), found {}",
                env_names.len(),
                env_files.len()
            ),
        ));
    }
    let dir = l.file.parent().unwrap_or(Path::new(""));
    let env_paths: Vec<PathBuf> = env_files.iter().map(|f| dir.join(f)).collect();
    let environments = env_names
        .par_iter()
        .zip(&env_paths)
        .map(|(name, p)| crate::io::exr::read_environment(p, name))
        .collect::<Result<Vec<Environment>>>()?;

    // States: one variant each.
    let state_names = l.strings(&root, "lightfuse:stateNames")?;
    let variants = l.tokens(&root, "lightfuse:stateVariants")?;
    if variants.len() != state_names.len() {
        return Err(l.err(
            &root,
            "lightfuse:stateVariants",
            format!(
                "expected one variant per state name ({}), found {}",
                state_names.len(),
                variants.len()
            ),
        ));
    }
    let mut states = Vec::with_capacity(state_names.len());
    for (name, variant) in state_names.iter().zip(&variants) {
        let vprim = format!("{root}{{{STATE_VARIANT_SET}={variant}}}");
        if !l.has_prim(&vprim)? {
            return Err(l.err(
                &root,
                "",
                format!(
                    "missing variant \"{variant}\" of variant set \"{STATE_VARIANT_SET}\" for state \"{name}\""
                ),
            ));
        }
        let mut transforms = Vec::with_capacity(components.len());
        for (i, child) in prim_of.iter().enumerate() {
            let over = format!("{vprim}{child}");
            let authored = l.attr(&over, "xformOp:translate")?.is_some()
                || l.attr(&over, "xformOp:orient")?.is_some();
            if i == 0 && !authored {
                transforms.push(Rigid::IDENTITY);
                continue;
            }
            transforms.push(Rigid {
                translation: l.vec3(&over, "xformOp:translate")?,
                rotation: l.quat(&over, "xformOp:orient")?,
            });
        }
        let dome = format!("{vprim}{DOME_LIGHT_PRIM}");
        let environment = if l.has_prim(&dome)? {
            let index = l.int(&dome, "lightfuse:environmentIndex")?;
            if index < 0 || index as usize >= environments.len() {
                return Err(l.err(
                    &dome,
                    "lightfuse:environmentIndex",
                    format!(
                        "expected an index below {} (the number of environments), found {index}",
                        environments.len()
                    ),
                ));
            }
            Some(EnvRef {
                index: index as usize,
                rotation_deg: l.float(&dome, "lightfuse:environmentRotation")?,
            })
        } else {
            None
        };
        states.push(State {
            name: name.clone(),
            transforms,
            environment,
        });
    }
    let reference = l.int(&root, "lightfuse:referenceState")?;
    if reference < 0 || reference as usize >= states.len() {
        return Err(l.err(
            &root,
            "lightfuse:referenceState",
            format!(
                "expected an index below {}, found {reference}",
                states.len()
            ),
        ));
    }
    Ok(Scene {
        components,
        states,
        reference_state: reference as usize,
        environments,
    })
}

fn read_component(l: &Layer<'_>, prim: &str) -> Result<Component> {
    let name = l.string(prim, "lightfuse:componentName")?;
    let id = l.int(prim, "lightfuse:componentId")?;
    let id = u32::try_from(id).map_err(|_| {
        l.err(
            prim,
            "lightfuse:componentId",
            format!("expected a non-negative object id, found {id}"),
        )
    })?;
    let pf = format!("{prim}/{SURFELS_PRIM}");
    if !l.has_prim(&pf)? {
        return Err(l.err(
            &pf,
            "",
            "missing prim: expected the component's ParticleField",
        ));
    }
    match l.type_name(&pf)?.as_deref() {
        Some("ParticleField") => {}
        other => {
            return Err(l.err(
                &pf,
                "",
                format!("expected a ParticleField prim, found type {other:?}"),
            ))
        }
    }
    let apis = l.api_schemas(&pf)?;
    if !apis
        .iter()
        .any(|a| a == "ParticleFieldKernelGaussianSurfletAPI")
    {
        return Err(l.err(
            &pf,
            "apiSchemas",
            "expected ParticleFieldKernelGaussianSurfletAPI (LightFuse surfels are 2D Gaussian discs)",
        ));
    }
    let position = l.vec3s(&pf, "positions", None)?;
    let n = position.len();
    let rotation = l.quats(&pf, "orientations", n)?;
    let scale = l
        .vec3s(&pf, "scales", Some(n))?
        .into_iter()
        .map(|s| [s[0], s[1]])
        .collect();
    let opacity = l.floats(&pf, "opacities", n)?;
    let degree = l.int(&pf, "radiance:sphericalHarmonicsDegree")?;
    if !(0..=MAX_SH_DEGREE as i64).contains(&degree) {
        return Err(l.err(
            &pf,
            "radiance:sphericalHarmonicsDegree",
            format!("expected a degree in 0..={MAX_SH_DEGREE}, found {degree}"),
        ));
    }
    let sh_degree = degree as u8;
    let attr = "radiance:sphericalHarmonicsCoefficients";
    let sh = l.vec3s(&pf, attr, None)?;
    let k = sh_coeffs(sh_degree);
    if sh.len() != n * k {
        return Err(l.err(
            &pf,
            attr,
            format!(
                "expected {} elements ({k} per particle for degree {degree}, {n} particles), found {}",
                n * k,
                sh.len()
            ),
        ));
    }
    let base_color = l.vec3s(&pf, "lightfuse:baseColors", Some(n))?;
    let metallic = l.floats(&pf, "lightfuse:metallics", n)?;
    let roughness = l.floats(&pf, "lightfuse:roughnesses", n)?;
    Ok(Component {
        name,
        id,
        surfels: Surfels {
            position,
            rotation,
            scale,
            opacity,
            sh_degree,
            sh,
            base_color,
            metallic,
            roughness,
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_valid_and_unique() {
        assert_eq!(identifier("chair.001"), "chair_001");
        assert_eq!(identifier("3d"), "_3d");
        assert_eq!(variant_name("state 1"), "state_1");
        assert_eq!(file_name("../x"), "_.._x");
        let mut used = HashSet::new();
        assert_eq!(unique("a".into(), &mut used), "a");
        assert_eq!(unique("A".into(), &mut used), "A_2");
    }

    #[test]
    fn strings_round_trip_through_escapes() {
        for s in [
            "plain",
            "q\"uote",
            "back\\slash",
            "new\nline\ttab",
            "ctl\x01",
            "ünï",
        ] {
            let q = quote(s);
            assert_eq!(unescape(&q[1..q.len() - 1]).unwrap(), s);
        }
    }

    #[test]
    fn dome_rotation_follows_the_convention() {
        assert_eq!(dome_rotate_y(0.0), 90.0);
        assert_eq!(dome_rotate_y(90.0), 0.0);
    }
}
