//! Surfel scenes as glTF 2.0 (`.glb`, `.gltf` + `.bin`): `KHR_gaussian_splatting` point
//! primitives plus our nested `LIGHTFUSE_gaussian_surfels` extension (docs/formats.md).
//!
//! Written by hand on serde_json rather than with the `gltf` crate: that crate folds unknown
//! attribute semantics such as `KHR_gaussian_splatting:ROTATION` into one `Extras` bucket, so
//! it cannot tell the splat attributes apart. The `gltf` crate is still used for ordinary mesh
//! scenes (`io::mesh`).

use super::AtomicFiles;
use crate::error::{Error, Result};
use crate::scene::{
    sh_coeffs, Component, EnvRef, Environment, Rigid, Scene, State, Surfels, MAX_SH_DEGREE,
};
use serde::Deserialize;
use serde_json::{json, Map, Value};
use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};

#[cfg(target_endian = "big")]
compile_error!("glTF buffers are little-endian; LightFuse reads them by casting bytes");

pub const KHR: &str = "KHR_gaussian_splatting";
pub const EXT: &str = "LIGHTFUSE_gaussian_surfels";
pub const ATTR_ROTATION: &str = "KHR_gaussian_splatting:ROTATION";
pub const ATTR_SCALE: &str = "KHR_gaussian_splatting:SCALE";
pub const ATTR_OPACITY: &str = "KHR_gaussian_splatting:OPACITY";
pub const ATTR_BASE_COLOR: &str = "LIGHTFUSE_gaussian_surfels:BASE_COLOR";
pub const ATTR_METALLIC: &str = "LIGHTFUSE_gaussian_surfels:METALLIC";
pub const ATTR_ROUGHNESS: &str = "LIGHTFUSE_gaussian_surfels:ROUGHNESS";
/// Our kernel name inside the KHR object, and the 2DGS kernel inside ours.
pub const KERNEL: &str = "surfel";
pub const SURFEL_KERNEL: &str = "gaussianSurfel";
/// Scene-linear Rec.709; KHR's nearest defined value.
pub const COLOR_SPACE: &str = "lin_rec709_display";
/// The kernel's support and opacity cap, written into the file so a reader knows them.
pub use crate::kernel::{CUTOFF, MAX_OPACITY};

const GLB_MAGIC: &[u8; 4] = b"glTF";
const CHUNK_JSON: u32 = 0x4E4F_534A;
const CHUNK_BIN: u32 = 0x004E_4942;
const FLOAT: u32 = 5126;
const ARRAY_BUFFER: u32 = 34962;

/// Name of the SH attribute for degree `l`, coefficient `n`.
pub fn sh_attribute(l: u8, n: usize) -> String {
    format!("KHR_gaussian_splatting:SH_DEGREE_{l}_COEF_{n}")
}

/// (degree, coefficient) of each SH triple of a surfel, in our storage order.
fn sh_slots(degree: u8) -> impl Iterator<Item = (u8, usize)> {
    (0..=degree).flat_map(|l| (0..(2 * l as usize + 1)).map(move |n| (l, n)))
}

// ---------------------------------------------------------------------------------------------
// Writing

/// One contiguous piece of the binary buffer.
enum Blob<'a> {
    F32(&'a [f32]),
    Owned(Vec<f32>),
    Bytes(Vec<u8>),
}

impl Blob<'_> {
    fn bytes(&self) -> &[u8] {
        match self {
            Blob::F32(v) => bytemuck::cast_slice(v),
            Blob::Owned(v) => bytemuck::cast_slice(v),
            Blob::Bytes(b) => b,
        }
    }
}

/// The glTF JSON and the pieces of its one buffer, laid out 4-byte aligned.
struct Document<'a> {
    json: Value,
    blobs: Vec<(usize, Blob<'a>)>,
    buffer_len: usize,
}

struct Builder<'a> {
    views: Vec<Value>,
    accessors: Vec<Value>,
    blobs: Vec<(usize, Blob<'a>)>,
    len: usize,
}

impl<'a> Builder<'a> {
    fn view(&mut self, blob: Blob<'a>, target: Option<u32>) -> usize {
        let offset = self.len.next_multiple_of(4);
        let n = blob.bytes().len();
        let mut v = json!({ "buffer": 0, "byteOffset": offset, "byteLength": n });
        if let Some(t) = target {
            v["target"] = json!(t);
        }
        self.views.push(v);
        self.blobs.push((offset, blob));
        self.len = offset + n;
        self.views.len() - 1
    }

    fn accessor(
        &mut self,
        blob: Blob<'a>,
        ty: &str,
        count: usize,
        min_max: Option<([f32; 3], [f32; 3])>,
    ) -> usize {
        let view = self.view(blob, Some(ARRAY_BUFFER));
        let mut a =
            json!({ "bufferView": view, "componentType": FLOAT, "count": count, "type": ty });
        if let Some((lo, hi)) = min_max {
            a["min"] = json!(lo);
            a["max"] = json!(hi);
        }
        self.accessors.push(a);
        self.accessors.len() - 1
    }
}

fn flat<const N: usize>(v: &[[f32; N]]) -> &[f32] {
    bytemuck::cast_slice(v)
}

/// Where environment images go: inside the GLB buffer, or files beside a `.gltf`.
enum EnvStorage<'p> {
    Embedded,
    Files { dir_name: String, dir: &'p Path },
}

fn env_file_name(i: usize, env: &Environment) -> String {
    let safe: String = env
        .name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect();
    format!("{i}_{safe}.exr")
}

fn build<'a>(
    scene: &'a Scene,
    envs: &EnvStorage,
    env_files: &mut Vec<(PathBuf, Vec<u8>)>,
) -> Document<'a> {
    let mut b = Builder {
        views: Vec::new(),
        accessors: Vec::new(),
        blobs: Vec::new(),
        len: 0,
    };
    let mut meshes = Vec::new();
    let mut components = Vec::new();
    for (ci, c) in scene.components.iter().enumerate() {
        let s = &c.surfels;
        let mut record = json!({ "name": c.name, "id": c.id, "shDegree": s.sh_degree });
        if !s.is_empty() {
            // glTF accessors need count ≥ 1, so an empty component has no mesh.
            let n = s.len();
            let mut attrs = Map::new();
            attrs.insert(
                "POSITION".into(),
                json!(b.accessor(Blob::F32(flat(&s.position)), "VEC3", n, s.bounds())),
            );
            attrs.insert(
                ATTR_ROTATION.into(),
                json!(b.accessor(Blob::F32(flat(&s.rotation)), "VEC4", n, None)),
            );
            let scale3: Vec<f32> = s.scale.iter().flat_map(|v| [v[0], v[1], 0.0]).collect();
            attrs.insert(
                ATTR_SCALE.into(),
                json!(b.accessor(Blob::Owned(scale3), "VEC3", n, None)),
            );
            attrs.insert(
                ATTR_OPACITY.into(),
                json!(b.accessor(Blob::F32(&s.opacity), "SCALAR", n, None)),
            );
            let stride = s.sh_stride();
            for (j, (l, k)) in sh_slots(s.sh_degree).enumerate() {
                let blob = if stride == 1 {
                    Blob::F32(flat(&s.sh))
                } else {
                    Blob::Owned((0..n).flat_map(|i| s.sh[i * stride + j]).collect())
                };
                attrs.insert(sh_attribute(l, k), json!(b.accessor(blob, "VEC3", n, None)));
            }
            attrs.insert(
                ATTR_BASE_COLOR.into(),
                json!(b.accessor(Blob::F32(flat(&s.base_color)), "VEC3", n, None)),
            );
            attrs.insert(
                ATTR_METALLIC.into(),
                json!(b.accessor(Blob::F32(&s.metallic), "SCALAR", n, None)),
            );
            attrs.insert(
                ATTR_ROUGHNESS.into(),
                json!(b.accessor(Blob::F32(&s.roughness), "SCALAR", n, None)),
            );
            meshes.push(json!({
                "name": c.name,
                "primitives": [{
                    "attributes": attrs,
                    "mode": 0,
                    "extensions": { KHR: {
                        "kernel": KERNEL,
                        "colorSpace": COLOR_SPACE,
                        "projection": "perspective",
                        "sortingMethod": "cameraDistance",
                        "extensions": { EXT: {
                            "kernel": SURFEL_KERNEL, "cutoff": CUTOFF, "maxOpacity": MAX_OPACITY, "component": ci
                        } }
                    } }
                }]
            }));
            record["mesh"] = json!(meshes.len() - 1);
        }
        components.push(record);
    }

    let mut environments = Vec::new();
    for (i, env) in scene.environments.iter().enumerate() {
        let bytes = super::exr::environment_bytes(env);
        let mut e = json!({ "name": env.name, "mimeType": "image/x-exr" });
        match envs {
            EnvStorage::Embedded => e["bufferView"] = json!(b.view(Blob::Bytes(bytes), None)),
            EnvStorage::Files { dir_name, dir } => {
                let file = env_file_name(i, env);
                e["uri"] = json!(format!("{dir_name}/{file}"));
                env_files.push((dir.join(file), bytes));
            }
        }
        environments.push(e);
    }

    let mut nodes = Vec::new();
    let mut scenes = Vec::new();
    for state in &scene.states {
        let mut roots = Vec::new();
        for (ci, (c, t)) in scene.components.iter().zip(&state.transforms).enumerate() {
            let mut node = json!({ "name": c.name });
            if let Some(m) = components[ci].get("mesh") {
                node["mesh"] = m.clone();
            }
            if !t.is_identity() {
                node["rotation"] = json!(t.rotation);
                node["translation"] = json!(t.translation);
            }
            roots.push(nodes.len());
            nodes.push(node);
        }
        let mut ext = Map::new();
        if let Some(e) = state.environment {
            ext.insert("environment".into(), json!(e.index));
            ext.insert("environmentRotation".into(), json!(e.rotation_deg));
        }
        let mut sc = json!({ "name": state.name, "nodes": roots });
        if !ext.is_empty() {
            sc["extensions"] = json!({ EXT: ext });
        }
        scenes.push(sc);
    }

    let json = json!({
        "asset": { "version": "2.0", "generator": concat!("LightFuse ", env!("CARGO_PKG_VERSION")) },
        "extensionsUsed": [KHR, EXT],
        "extensions": { EXT: {
            "version": 1,
            "components": components,
            "referenceState": scene.reference_state,
            "environments": environments,
        } },
        "scene": scene.reference_state,
        "scenes": scenes,
        "nodes": nodes,
        "meshes": meshes,
        "accessors": b.accessors,
        "bufferViews": b.views,
        "buffers": [{ "byteLength": b.len }],
    });
    Document {
        json,
        blobs: b.blobs,
        buffer_len: b.len,
    }
}

fn write_blobs(w: &mut impl Write, doc: &Document, total: usize) -> std::io::Result<()> {
    let mut at = 0;
    let zeros = [0u8; 4];
    for (offset, blob) in &doc.blobs {
        w.write_all(&zeros[..offset - at])?;
        let bytes = blob.bytes();
        w.write_all(bytes)?;
        at = offset + bytes.len();
    }
    w.write_all(&vec![0u8; total - at])
}

/// Writes a binary glTF with every environment embedded.
pub fn write_glb(scene: &Scene, path: &Path) -> Result<()> {
    let doc = build(scene, &EnvStorage::Embedded, &mut Vec::new());
    let mut json = serde_json::to_vec(&doc.json).expect("glTF JSON serialises");
    json.resize(json.len().next_multiple_of(4), b' ');
    let bin_len = doc.buffer_len.next_multiple_of(4);
    let has_bin = doc.buffer_len > 0;
    let total = 12 + 8 + json.len() + if has_bin { 8 + bin_len } else { 0 };
    let total = u32::try_from(total).map_err(|_| {
        Error::invalid(
            path,
            "size",
            "a GLB is limited to 4 GiB; write .gltf instead",
        )
    })?;
    let mut files = AtomicFiles::new();
    files.write_with(path, |w| {
        w.write_all(GLB_MAGIC)?;
        w.write_all(&2u32.to_le_bytes())?;
        w.write_all(&total.to_le_bytes())?;
        w.write_all(&(json.len() as u32).to_le_bytes())?;
        w.write_all(&CHUNK_JSON.to_le_bytes())?;
        w.write_all(&json)?;
        if has_bin {
            w.write_all(&(bin_len as u32).to_le_bytes())?;
            w.write_all(&CHUNK_BIN.to_le_bytes())?;
            write_blobs(w, &doc, bin_len)?;
        }
        Ok(())
    })?;
    files.commit()
}

/// Writes a `.gltf` with its buffer in `<stem>.bin` and environments in `<stem>.env/`.
pub fn write_gltf(scene: &Scene, path: &Path) -> Result<()> {
    let stem = super::file_stem(path).unwrap_or_else(|| "scene".into());
    let dir = path.parent().unwrap_or(Path::new(""));
    let env_dir_name = format!("{stem}.env");
    let env_dir = dir.join(&env_dir_name);
    let mut env_files = Vec::new();
    let mut doc = build(
        scene,
        &EnvStorage::Files {
            dir_name: env_dir_name,
            dir: &env_dir,
        },
        &mut env_files,
    );
    let bin_name = format!("{stem}.bin");
    let mut files = AtomicFiles::new();
    if doc.buffer_len > 0 {
        doc.json["buffers"][0]["uri"] = json!(bin_name);
        files.write_with(&dir.join(&bin_name), |w| {
            write_blobs(w, &doc, doc.buffer_len)
        })?;
    } else {
        doc.json.as_object_mut().expect("object").remove("buffers");
    }
    for (p, bytes) in &env_files {
        files.write(p, bytes)?;
    }
    let text = serde_json::to_vec_pretty(&doc.json).expect("glTF JSON serialises");
    files.write(path, &text)?;
    files.commit()
}

// ---------------------------------------------------------------------------------------------
// Reading

#[derive(Deserialize)]
#[serde(rename_all = "camelCase")]
struct Root {
    asset: Option<Value>,
    #[serde(default)]
    extensions_required: Vec<String>,
    #[serde(default)]
    buffers: Vec<BufferDef>,
    #[serde(default)]
    buffer_views: Vec<ViewDef>,
    #[serde(default)]
    accessors: Vec<AccessorDef>,
    #[serde(default)]
    meshes: Vec<MeshDef>,
    #[serde(default)]
    nodes: Vec<NodeDef>,
    #[serde(default)]
    scenes: Vec<SceneDef>,
    scene: Option<usize>,
    #[serde(default)]
    extensions: Map<String, Value>,
}

#[derive(Deserialize)]
#[serde(rename_all = "camelCase")]
struct BufferDef {
    byte_length: usize,
    uri: Option<String>,
}

#[derive(Deserialize)]
#[serde(rename_all = "camelCase")]
struct ViewDef {
    buffer: usize,
    #[serde(default)]
    byte_offset: usize,
    byte_length: usize,
    byte_stride: Option<usize>,
}

#[derive(Deserialize)]
#[serde(rename_all = "camelCase")]
struct AccessorDef {
    buffer_view: Option<usize>,
    #[serde(default)]
    byte_offset: usize,
    component_type: u32,
    #[serde(default)]
    normalized: bool,
    count: usize,
    #[serde(rename = "type")]
    ty: String,
    sparse: Option<Value>,
}

#[derive(Deserialize)]
struct MeshDef {
    primitives: Vec<PrimitiveDef>,
}

#[derive(Deserialize)]
struct PrimitiveDef {
    attributes: HashMap<String, usize>,
    mode: Option<u32>,
    #[serde(default)]
    extensions: Map<String, Value>,
}

#[derive(Deserialize)]
struct NodeDef {
    name: Option<String>,
    mesh: Option<usize>,
    rotation: Option<[f32; 4]>,
    translation: Option<[f32; 3]>,
    scale: Option<[f32; 3]>,
    matrix: Option<[f32; 16]>,
    children: Option<Vec<usize>>,
}

#[derive(Deserialize)]
struct SceneDef {
    name: Option<String>,
    #[serde(default)]
    nodes: Vec<usize>,
    #[serde(default)]
    extensions: Map<String, Value>,
}

#[derive(Deserialize)]
#[serde(rename_all = "camelCase", deny_unknown_fields)]
struct RootExt {
    version: u32,
    components: Vec<ComponentDef>,
    reference_state: usize,
    #[serde(default)]
    environments: Vec<EnvironmentDef>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
#[serde(rename_all = "camelCase")]
struct ComponentDef {
    name: String,
    id: u32,
    sh_degree: u8,
    mesh: Option<usize>,
}

#[derive(Deserialize)]
#[serde(rename_all = "camelCase", deny_unknown_fields)]
struct EnvironmentDef {
    name: String,
    buffer_view: Option<usize>,
    uri: Option<String>,
    mime_type: Option<String>,
}

#[derive(Deserialize, Default)]
#[serde(rename_all = "camelCase", deny_unknown_fields)]
struct SceneExt {
    environment: Option<usize>,
    #[serde(default)]
    environment_rotation: f32,
}

/// The parsed JSON plus resolved buffers, with the file name for errors.
struct Reader<'a> {
    file: &'a Path,
    root: Root,
    buffers: Vec<Vec<u8>>,
}

fn invalid(file: &Path, field: impl Into<String>, message: impl Into<String>) -> Error {
    Error::invalid(file, field, message)
}

/// Splits a GLB into its JSON chunk and optional BIN chunk, checking every length.
fn split_glb<'b>(file: &Path, bytes: &'b [u8]) -> Result<(&'b [u8], Option<&'b [u8]>)> {
    if bytes.len() < 12 {
        return Err(invalid(
            file,
            "GLB header",
            format!(
                "expected at least 12 bytes, found {} (truncated file?)",
                bytes.len()
            ),
        ));
    }
    if &bytes[0..4] != GLB_MAGIC {
        return Err(invalid(
            file,
            "GLB header magic",
            format!(
                "expected \"glTF\", found {:?}",
                String::from_utf8_lossy(&bytes[0..4])
            ),
        ));
    }
    let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
    let version = u32_at(4);
    if version != 2 {
        return Err(invalid(
            file,
            "GLB header version",
            format!("expected 2, found {version}"),
        ));
    }
    let declared = u32_at(8) as usize;
    if declared != bytes.len() {
        return Err(invalid(
            file,
            "GLB header length",
            format!(
                "header declares {declared} bytes but the file has {} (truncated or padded file?)",
                bytes.len()
            ),
        ));
    }
    let mut chunks = Vec::new();
    let mut at = 12;
    while at < bytes.len() {
        if at + 8 > bytes.len() {
            return Err(invalid(
                file,
                format!("GLB chunk {}", chunks.len()),
                "expected an 8-byte chunk header, found the end of the file",
            ));
        }
        let len = u32_at(at) as usize;
        let ty = u32_at(at + 4);
        let start = at + 8;
        if len > bytes.len() - start {
            return Err(invalid(
                file,
                format!("GLB chunk {} length", chunks.len()),
                format!(
                    "chunk declares {len} bytes but only {} remain",
                    bytes.len() - start
                ),
            ));
        }
        chunks.push((ty, &bytes[start..start + len]));
        at = start + len.next_multiple_of(4).min(bytes.len() - start);
    }
    let Some(&(CHUNK_JSON, json)) = chunks.first() else {
        return Err(invalid(
            file,
            "GLB chunk 0",
            "expected the JSON chunk first",
        ));
    };
    let bin = chunks
        .get(1)
        .filter(|(ty, _)| *ty == CHUNK_BIN)
        .map(|(_, b)| *b);
    Ok((json, bin))
}

fn resolve_uri(file: &Path, field: &str, uri: &str) -> Result<Vec<u8>> {
    if let Some(rest) = uri.strip_prefix("data:") {
        let (_, data) = rest
            .split_once(";base64,")
            .ok_or_else(|| invalid(file, field, "expected a base64 data URI"))?;
        use base64::Engine;
        return base64::engine::general_purpose::STANDARD
            .decode(data)
            .map_err(|e| invalid(file, field, format!("expected valid base64: {e}")));
    }
    if uri.contains("://") {
        return Err(invalid(
            file,
            field,
            format!(
                "expected a relative file path, found the URL {uri:?} (LightFuse never downloads)"
            ),
        ));
    }
    let decoded = percent_decode(uri);
    let path = file.parent().unwrap_or(Path::new("")).join(decoded);
    std::fs::read(&path).map_err(|e| Error::io(&path, e))
}

fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' && i + 2 < b.len() {
            if let Ok(v) = u8::from_str_radix(&s[i + 1..i + 3], 16) {
                out.push(v);
                i += 3;
                continue;
            }
        }
        out.push(b[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

impl<'a> Reader<'a> {
    fn new(file: &'a Path, json: &[u8], bin: Option<&[u8]>) -> Result<Self> {
        let root: Root = serde_json::from_slice(json).map_err(|e| {
            invalid(
                file,
                "glTF JSON",
                format!("expected valid glTF 2.0 JSON: {e}"),
            )
        })?;
        if root.asset.is_none() {
            return Err(invalid(
                file,
                "asset",
                "expected the required glTF `asset` object",
            ));
        }
        for ext in &root.extensions_required {
            if ext != KHR && ext != EXT {
                return Err(invalid(
                    file,
                    "extensionsRequired",
                    format!("the file requires the unknown extension {ext:?}; LightFuse supports {KHR} and {EXT} (compressed or quantized splats are not supported)"),
                ));
            }
        }
        let mut buffers = Vec::with_capacity(root.buffers.len());
        for (i, b) in root.buffers.iter().enumerate() {
            let field = format!("buffers[{i}]");
            let data = match (&b.uri, i, bin) {
                (Some(uri), _, _) => resolve_uri(file, &field, uri)?,
                (None, 0, Some(bin)) => bin.to_vec(),
                (None, _, _) => {
                    return Err(invalid(
                        file,
                        &field,
                        "expected a uri (only buffer 0 of a GLB may use the BIN chunk)",
                    ))
                }
            };
            if data.len() < b.byte_length {
                return Err(invalid(
                    file,
                    format!("{field}.byteLength"),
                    format!(
                        "declares {} bytes but the data has {}",
                        b.byte_length,
                        data.len()
                    ),
                ));
            }
            buffers.push(data);
        }
        Ok(Reader {
            file,
            root,
            buffers,
        })
    }

    fn err(&self, field: impl Into<String>, message: impl Into<String>) -> Error {
        invalid(self.file, field, message)
    }

    /// The bytes of a buffer view, bounds-checked.
    fn view(&self, index: usize, field: &str) -> Result<(&[u8], Option<usize>)> {
        let v = self.root.buffer_views.get(index).ok_or_else(|| {
            self.err(
                field,
                format!(
                    "bufferView {index} does not exist ({} defined)",
                    self.root.buffer_views.len()
                ),
            )
        })?;
        let buf = self.buffers.get(v.buffer).ok_or_else(|| {
            self.err(
                format!("bufferViews[{index}].buffer"),
                format!("buffer {} does not exist", v.buffer),
            )
        })?;
        let declared = self.root.buffers[v.buffer].byte_length;
        let end = v
            .byte_offset
            .checked_add(v.byte_length)
            .filter(|&e| e <= declared && e <= buf.len());
        let end = end.ok_or_else(|| {
            self.err(
                format!("bufferViews[{index}]"),
                format!(
                    "range {}..{} is out of buffer {} ({} bytes)",
                    v.byte_offset,
                    v.byte_offset as u128 + v.byte_length as u128,
                    v.buffer,
                    declared
                ),
            )
        })?;
        Ok((&buf[v.byte_offset..end], v.byte_stride))
    }

    /// Reads a float accessor of `ty` with `count` elements of `N` floats.
    fn floats<const N: usize>(
        &self,
        index: usize,
        attr: &str,
        ty: &str,
        count: Option<usize>,
    ) -> Result<Vec<[f32; N]>> {
        let field = format!("attributes.{attr}");
        let a = self.root.accessors.get(index).ok_or_else(|| {
            self.err(
                &field,
                format!(
                    "accessor {index} does not exist ({} defined)",
                    self.root.accessors.len()
                ),
            )
        })?;
        let afield = format!("accessors[{index}] ({attr})");
        if a.component_type != FLOAT || a.normalized {
            return Err(self.err(
                format!("{afield}.componentType"),
                format!(
                    "expected 5126 (FLOAT), found {}{} (quantized splats are not supported)",
                    a.component_type,
                    if a.normalized { " normalized" } else { "" }
                ),
            ));
        }
        if a.ty != ty {
            return Err(self.err(
                format!("{afield}.type"),
                format!("expected {ty}, found {}", a.ty),
            ));
        }
        if let Some(c) = count {
            if a.count != c {
                return Err(self.err(
                    format!("{afield}.count"),
                    format!("expected {c} (the POSITION count), found {}", a.count),
                ));
            }
        }
        if a.sparse.is_some() {
            return Err(self.err(
                format!("{afield}.sparse"),
                "sparse accessors are not supported for splat attributes",
            ));
        }
        let view = a
            .buffer_view
            .ok_or_else(|| self.err(format!("{afield}.bufferView"), "expected a buffer view"))?;
        let (bytes, stride) = self.view(view, &format!("{afield}.bufferView"))?;
        let elem = 4 * N;
        let stride = stride.unwrap_or(elem);
        if stride < elem {
            return Err(self.err(
                format!("bufferViews[{view}].byteStride"),
                format!("expected at least {elem}, found {stride}"),
            ));
        }
        let need = if a.count == 0 {
            0
        } else {
            a.byte_offset as u128 + (a.count as u128 - 1) * stride as u128 + elem as u128
        };
        if need > bytes.len() as u128 {
            return Err(self.err(
                &afield,
                format!(
                    "{} elements at offset {} need {need} bytes but bufferView {view} has {}",
                    a.count,
                    a.byte_offset,
                    bytes.len()
                ),
            ));
        }
        let data = bytes.get(a.byte_offset..).ok_or_else(|| {
            self.err(
                format!("{afield}.byteOffset"),
                format!(
                    "offset {} is past the end of bufferView {view} ({} bytes)",
                    a.byte_offset,
                    bytes.len()
                ),
            )
        })?;
        if stride == elem {
            Ok(bytemuck::pod_collect_to_vec(&data[..a.count * elem]))
        } else {
            Ok((0..a.count)
                .map(|i| bytemuck::pod_read_unaligned(&data[i * stride..i * stride + elem]))
                .collect())
        }
    }

    fn root_ext(&self) -> Result<RootExt> {
        let v = self.root.extensions.get(EXT).ok_or_else(|| {
            self.err(format!("extensions.{EXT}"), "not a LightFuse scene: expected our root extension (components, states, environments)")
        })?;
        let ext: RootExt = serde_json::from_value(v.clone())
            .map_err(|e| self.err(format!("extensions.{EXT}"), e.to_string()))?;
        if ext.version != 1 {
            return Err(self.err(
                format!("extensions.{EXT}.version"),
                format!("expected 1, found {}", ext.version),
            ));
        }
        Ok(ext)
    }

    fn surfels(&self, mesh_index: usize, comp: &str) -> Result<Surfels> {
        let mesh = self.root.meshes.get(mesh_index).ok_or_else(|| {
            self.err(
                format!("component \"{comp}\".mesh"),
                format!("mesh {mesh_index} does not exist"),
            )
        })?;
        let [prim] = mesh.primitives.as_slice() else {
            return Err(self.err(
                format!("meshes[{mesh_index}].primitives"),
                format!(
                    "expected exactly one primitive, found {}",
                    mesh.primitives.len()
                ),
            ));
        };
        let pfield = format!("meshes[{mesh_index}].primitives[0]");
        if prim.mode != Some(0) {
            return Err(self.err(
                format!("{pfield}.mode"),
                format!("expected 0 (POINTS), found {:?}", prim.mode),
            ));
        }
        let khr = prim
            .extensions
            .get(KHR)
            .and_then(Value::as_object)
            .ok_or_else(|| {
                self.err(
                    format!("{pfield}.extensions.{KHR}"),
                    "expected the KHR_gaussian_splatting extension object",
                )
            })?;
        for key in ["kernel", "colorSpace"] {
            if !khr.get(key).is_some_and(Value::is_string) {
                return Err(self.err(
                    format!("{pfield}.extensions.{KHR}.{key}"),
                    "expected the required string property",
                ));
            }
        }
        if khr["kernel"] != KERNEL {
            return Err(self.err(
                format!("{pfield}.extensions.{KHR}.kernel"),
                format!(
                    "expected {KERNEL:?} (flat 2D Gaussian surfels), found {}",
                    khr["kernel"]
                ),
            ));
        }
        let ours = khr
            .get("extensions")
            .and_then(|e| e.get(EXT))
            .and_then(Value::as_object)
            .ok_or_else(|| {
                self.err(
                    format!("{pfield}.extensions.{KHR}.extensions.{EXT}"),
                    "expected our nested surfel extension",
                )
            })?;
        if ours.get("kernel").and_then(Value::as_str) != Some(SURFEL_KERNEL) {
            return Err(self.err(
                format!("{pfield}.extensions.{KHR}.extensions.{EXT}.kernel"),
                format!("expected {SURFEL_KERNEL:?}"),
            ));
        }
        let attr = |name: &str| {
            prim.attributes.get(name).copied().ok_or_else(|| {
                self.err(
                    format!("{pfield}.attributes.{name}"),
                    "expected the required attribute",
                )
            })
        };
        let position: Vec<[f32; 3]> = self.floats(attr("POSITION")?, "POSITION", "VEC3", None)?;
        let n = Some(position.len());
        let rotation = self.floats::<4>(attr(ATTR_ROTATION)?, ATTR_ROTATION, "VEC4", n)?;
        let scale3 = self.floats::<3>(attr(ATTR_SCALE)?, ATTR_SCALE, "VEC3", n)?;
        if let Some(i) = scale3.iter().position(|s| s[2] != 0.0) {
            return Err(self.err(
                format!("{pfield}.attributes.{ATTR_SCALE}"),
                format!(
                    "surfel {i}: expected flat surfels (third scale axis 0), found {}",
                    scale3[i][2]
                ),
            ));
        }
        let opacity: Vec<[f32; 1]> = self.floats(attr(ATTR_OPACITY)?, ATTR_OPACITY, "SCALAR", n)?;
        let mut sh_degree = 0u8;
        while sh_degree < MAX_SH_DEGREE
            && prim
                .attributes
                .contains_key(&sh_attribute(sh_degree + 1, 0))
        {
            sh_degree += 1;
        }
        let mut coefs = Vec::new();
        for (l, k) in sh_slots(sh_degree) {
            let name = sh_attribute(l, k);
            coefs.push(self.floats::<3>(attr(&name)?, &name, "VEC3", n)?);
        }
        let stride = sh_coeffs(sh_degree);
        let sh = if stride == 1 {
            coefs.pop().expect("DC")
        } else {
            (0..position.len())
                .flat_map(|i| coefs.iter().map(move |c| c[i]))
                .collect()
        };
        let base_color = self.floats::<3>(attr(ATTR_BASE_COLOR)?, ATTR_BASE_COLOR, "VEC3", n)?;
        let metallic: Vec<[f32; 1]> =
            self.floats(attr(ATTR_METALLIC)?, ATTR_METALLIC, "SCALAR", n)?;
        let roughness: Vec<[f32; 1]> =
            self.floats(attr(ATTR_ROUGHNESS)?, ATTR_ROUGHNESS, "SCALAR", n)?;
        Ok(Surfels {
            position,
            rotation,
            scale: scale3.iter().map(|s| [s[0], s[1]]).collect(),
            opacity: bytemuck::cast_vec(opacity),
            sh_degree,
            sh,
            base_color,
            metallic: bytemuck::cast_vec(metallic),
            roughness: bytemuck::cast_vec(roughness),
        })
    }

    fn node_transform(&self, index: usize, node: &NodeDef) -> Result<Rigid> {
        let field = format!("nodes[{index}]");
        if let Some(m) = node.matrix {
            // Column-major in glTF.
            let rows = [0, 1, 2, 3].map(|r| [m[r], m[4 + r], m[8 + r], m[12 + r]]);
            return Rigid::from_rows(&rows).map_err(|msg| self.err(format!("{field}.matrix"), msg));
        }
        if let Some(s) = node.scale {
            if s != [1.0; 3] {
                return Err(self.err(
                    format!("{field}.scale"),
                    format!("expected a rigid placement (scale 1), found {s:?}"),
                ));
            }
        }
        let rotation = node.rotation.unwrap_or([0.0, 0.0, 0.0, 1.0]);
        let n2: f32 = rotation.iter().map(|x| x * x).sum();
        if !n2.is_finite() || (n2 - 1.0).abs() > 1e-3 {
            return Err(self.err(
                format!("{field}.rotation"),
                format!("expected a unit quaternion, found {rotation:?}"),
            ));
        }
        Ok(Rigid {
            rotation,
            translation: node.translation.unwrap_or([0.0; 3]),
        })
    }

    fn environment(&self, i: usize, def: &EnvironmentDef) -> Result<Environment> {
        let field = format!("extensions.{EXT}.environments[{i}]");
        if let Some(m) = &def.mime_type {
            if m != "image/x-exr" {
                return Err(self.err(
                    format!("{field}.mimeType"),
                    format!("expected \"image/x-exr\", found {m:?}"),
                ));
            }
        }
        match (def.buffer_view, &def.uri) {
            (Some(v), None) => {
                let (bytes, _) = self.view(v, &format!("{field}.bufferView"))?;
                super::exr::read_environment_bytes(
                    bytes,
                    &self.file.join(format!("#{field}")),
                    &def.name,
                )
            }
            (None, Some(uri)) => {
                if uri.starts_with("data:") {
                    let bytes = resolve_uri(self.file, &format!("{field}.uri"), uri)?;
                    return super::exr::read_environment_bytes(&bytes, self.file, &def.name);
                }
                let path = self
                    .file
                    .parent()
                    .unwrap_or(Path::new(""))
                    .join(percent_decode(uri));
                if !path.is_file() {
                    return Err(self.err(
                        format!("{field}.uri"),
                        format!("environment file {} is missing", path.display()),
                    ));
                }
                super::exr::read_environment(&path, &def.name)
            }
            _ => Err(self.err(&field, "expected exactly one of bufferView and uri")),
        }
    }

    fn scene(&self) -> Result<Scene> {
        let ext = self.root_ext()?;
        let ext_field = format!("extensions.{EXT}");
        let mut components = Vec::with_capacity(ext.components.len());
        let mut by_name = HashMap::new();
        for (i, c) in ext.components.iter().enumerate() {
            let surfels = match c.mesh {
                Some(m) => self.surfels(m, &c.name)?,
                None => Surfels::with_sh_degree(c.sh_degree),
            };
            if surfels.sh_degree != c.sh_degree {
                return Err(self.err(
                    format!("{ext_field}.components[{i}].shDegree"),
                    format!(
                        "declares SH degree {} but mesh {:?} carries SH attributes up to degree {}",
                        c.sh_degree, c.mesh, surfels.sh_degree
                    ),
                ));
            }
            if by_name.insert(c.name.clone(), i).is_some() {
                return Err(self.err(
                    format!("{ext_field}.components[{i}].name"),
                    format!(
                        "expected unique component names, {:?} appears twice",
                        c.name
                    ),
                ));
            }
            components.push(Component {
                name: c.name.clone(),
                id: c.id,
                surfels,
            });
        }
        if components.is_empty() {
            return Err(self.err(
                format!("{ext_field}.components"),
                "expected at least the background",
            ));
        }
        let mut environments = Vec::with_capacity(ext.environments.len());
        for (i, e) in ext.environments.iter().enumerate() {
            environments.push(self.environment(i, e)?);
        }
        if self.root.scenes.is_empty() {
            return Err(self.err("scenes", "expected one glTF scene per state"));
        }
        let mut states = Vec::with_capacity(self.root.scenes.len());
        for (k, sc) in self.root.scenes.iter().enumerate() {
            let field = format!("scenes[{k}]");
            let name = sc
                .name
                .clone()
                .ok_or_else(|| self.err(format!("{field}.name"), "expected the state's name"))?;
            let mut transforms = vec![None; components.len()];
            for &ni in &sc.nodes {
                let node = self.root.nodes.get(ni).ok_or_else(|| {
                    self.err(
                        format!("{field}.nodes"),
                        format!("node {ni} does not exist"),
                    )
                })?;
                if node.children.as_ref().is_some_and(|c| !c.is_empty()) {
                    return Err(self.err(
                        format!("nodes[{ni}].children"),
                        "expected component nodes without children",
                    ));
                }
                let cname = node.name.as_deref().ok_or_else(|| {
                    self.err(format!("nodes[{ni}].name"), "expected the component's name")
                })?;
                let ci = *by_name.get(cname).ok_or_else(|| {
                    self.err(
                        format!("nodes[{ni}].name"),
                        format!("expected a component name, found {cname:?}"),
                    )
                })?;
                if node.mesh != ext.components[ci].mesh {
                    return Err(self.err(
                        format!("nodes[{ni}].mesh"),
                        format!(
                            "expected mesh {:?} of component {cname:?}, found {:?}",
                            ext.components[ci].mesh, node.mesh
                        ),
                    ));
                }
                if transforms[ci]
                    .replace(self.node_transform(ni, node)?)
                    .is_some()
                {
                    return Err(self.err(&field, format!("component {cname:?} is placed twice")));
                }
            }
            let transforms = transforms
                .into_iter()
                .enumerate()
                .map(|(ci, t)| {
                    t.ok_or_else(|| {
                        self.err(
                            &field,
                            format!(
                                "state {name:?} does not place component {:?}",
                                components[ci].name
                            ),
                        )
                    })
                })
                .collect::<Result<Vec<_>>>()?;
            let sext: SceneExt = match sc.extensions.get(EXT) {
                Some(v) => serde_json::from_value(v.clone())
                    .map_err(|e| self.err(format!("{field}.extensions.{EXT}"), e.to_string()))?,
                None => SceneExt::default(),
            };
            let environment = sext.environment.map(|index| EnvRef {
                index,
                rotation_deg: sext.environment_rotation,
            });
            states.push(State {
                name,
                transforms,
                environment,
            });
        }
        if let Some(s) = self.root.scene {
            if s != ext.reference_state {
                return Err(self.err(
                    "scene",
                    format!(
                        "expected the reference state {} as the default scene, found {s}",
                        ext.reference_state
                    ),
                ));
            }
        }
        Ok(Scene {
            components,
            states,
            reference_state: ext.reference_state,
            environments,
        })
    }
}

/// Reads a LightFuse `.glb` or `.gltf`; `io::read_scene` also validates every surfel.
pub fn read(path: &Path) -> Result<Scene> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    read_bytes(path, &bytes)
}

/// Parses a `.glb` (by magic) or `.gltf` JSON from memory; `path` names it in errors and
/// anchors relative URIs. Never panics on any input (fuzzed).
pub fn read_bytes(path: &Path, bytes: &[u8]) -> Result<Scene> {
    let is_glb = bytes.starts_with(GLB_MAGIC)
        || path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("glb"));
    let reader = if is_glb {
        let (json, bin) = split_glb(path, bytes)?;
        Reader::new(path, json, bin)?
    } else {
        Reader::new(path, bytes, None)?
    };
    reader.scene()
}
