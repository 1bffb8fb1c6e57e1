//! Ordinary glTF mesh scenes (the input of `surfelize`): world-space triangles with per-vertex
//! shading normals, UVs and colours, PBR metallic-roughness materials and decoded textures.
//!
//! What is read: the default scene (or the first one), every node below it with its world
//! transform, every primitive in `TRIANGLES`, `TRIANGLE_STRIP` or `TRIANGLE_FAN` mode (points
//! and lines are skipped), `POSITION`, `NORMAL`, `TEXCOORD_0/1`, `COLOR_0`, and the materials'
//! metallic-roughness parameters. Not read: skins, morph targets, animations,
//! `KHR_texture_transform`, emission, and any other material extension.

use crate::error::{Error, Result};
use glam::{DMat4, DVec3, Mat4};
use std::path::{Path, PathBuf};

/// A triangle in world space. Vertex attributes the file lacks are filled in: normals with the
/// face normal, UVs with 0, colours with 1.
#[derive(Clone, Debug, PartialEq)]
pub struct MeshTriangle {
    /// Vertex positions, metres, counter-clockwise seen from the front (mirroring transforms
    /// already undone).
    pub position: [[f32; 3]; 3],
    /// Unit shading normals per vertex.
    pub normal: [[f32; 3]; 3],
    /// Texture coordinates per vertex: `uv[set][vertex]` for `TEXCOORD_0` and `TEXCOORD_1`.
    pub uv: [[[f32; 2]; 3]; 2],
    /// `COLOR_0` per vertex, linear RGBA (1 when absent).
    pub color: [[f32; 4]; 3],
    /// Index into [`MeshScene::materials`]; `None` = the glTF default material.
    pub material: Option<usize>,
}

/// A node of the default scene, in depth-first (pre-)order.
#[derive(Clone, Debug, PartialEq)]
pub struct MeshNode {
    pub name: Option<String>,
    /// Index of the parent in [`MeshScene::nodes`]; `None` for a top-level node.
    pub parent: Option<usize>,
    /// The node's own triangles (not its children's), world space.
    pub triangles: Vec<MeshTriangle>,
}

/// Texture coordinate wrapping (glTF sampler `wrapS` / `wrapT`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Wrap {
    Repeat,
    ClampToEdge,
    MirroredRepeat,
}

/// Texture filtering (the sampler's `magFilter`; surfels sample one point, so it is used for
/// minification too).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Filter {
    Linear,
    Nearest,
}

/// Storage of one channel of a decoded image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ChannelType {
    U8,
    /// Native-endian u16.
    U16,
    /// Native-endian f32.
    F32,
}

/// A decoded image: `width * height` texels of `channels` channels, rows top to bottom (glTF
/// UV (0, 0) is the top-left corner).
#[derive(Clone, Debug, PartialEq)]
pub struct MeshImage {
    pub width: u32,
    pub height: u32,
    pub channels: u8,
    pub channel_type: ChannelType,
    pub pixels: Vec<u8>,
}

/// A texture slot of a material: which image, how to sample it, which UV set.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TextureRef {
    /// Index into [`MeshScene::images`].
    pub image: usize,
    pub wrap_s: Wrap,
    pub wrap_t: Wrap,
    pub filter: Filter,
    /// `TEXCOORD_n` set (0 or 1).
    pub tex_coord: u32,
}

/// A glTF PBR metallic-roughness material.
#[derive(Clone, Debug, PartialEq)]
pub struct MeshMaterial {
    pub name: Option<String>,
    /// `baseColorFactor`, linear RGBA.
    pub base_color_factor: [f32; 4],
    /// Its texture holds sRGB-encoded colour and alpha.
    pub base_color_texture: Option<TextureRef>,
    pub metallic_factor: f32,
    pub roughness_factor: f32,
    /// Its texture holds linear values: G = roughness, B = metallic.
    pub metallic_roughness_texture: Option<TextureRef>,
    /// `Some(cutoff)` for `alphaMode: MASK` (fragments with alpha below are discarded);
    /// `OPAQUE` and `BLEND` are both treated as opaque.
    pub alpha_cutoff: Option<f32>,
}

impl MeshMaterial {
    /// The glTF default material (spec §3.9.6): white, metallic 1, roughness 1.
    pub fn gltf_default() -> Self {
        MeshMaterial {
            name: None,
            base_color_factor: [1.0; 4],
            base_color_texture: None,
            metallic_factor: 1.0,
            roughness_factor: 1.0,
            metallic_roughness_texture: None,
            alpha_cutoff: None,
        }
    }
}

/// An ordinary glTF mesh scene flattened to world-space triangles, grouped by node.
#[derive(Clone, Debug, PartialEq)]
pub struct MeshScene {
    /// The file it was read from (named in errors).
    pub path: PathBuf,
    /// Nodes of the default scene in depth-first pre-order (parents before children).
    pub nodes: Vec<MeshNode>,
    pub materials: Vec<MeshMaterial>,
    pub images: Vec<MeshImage>,
}

impl MeshScene {
    pub fn triangle_count(&self) -> usize {
        self.nodes.iter().map(|n| n.triangles.len()).sum()
    }

    /// Total triangle area, m².
    pub fn area(&self) -> f64 {
        self.nodes
            .iter()
            .flat_map(|n| &n.triangles)
            .map(|t| t.area())
            .sum()
    }

    /// Index of the top-level node each node belongs to.
    pub fn root_of(&self, node: usize) -> usize {
        let mut i = node;
        while let Some(p) = self.nodes[i].parent {
            i = p;
        }
        i
    }

    /// Top-level nodes (name, world-space triangles of the node and all its descendants), in
    /// file order.
    pub fn roots(&self) -> Vec<(Option<&str>, Vec<&MeshTriangle>)> {
        let mut out: Vec<(usize, Option<&str>, Vec<&MeshTriangle>)> = Vec::new();
        for (i, n) in self.nodes.iter().enumerate() {
            if n.parent.is_none() {
                out.push((i, n.name.as_deref(), Vec::new()));
            }
        }
        for (i, n) in self.nodes.iter().enumerate() {
            let r = self.root_of(i);
            let slot = out
                .iter_mut()
                .find(|(k, _, _)| *k == r)
                .expect("root listed");
            slot.2.extend(&n.triangles);
        }
        out.into_iter().map(|(_, n, t)| (n, t)).collect()
    }

    /// The material of a triangle (the glTF default when it has none).
    pub fn material(&self, index: Option<usize>) -> &MeshMaterial {
        static DEFAULT: std::sync::OnceLock<MeshMaterial> = std::sync::OnceLock::new();
        match index {
            Some(i) => &self.materials[i],
            None => DEFAULT.get_or_init(MeshMaterial::gltf_default),
        }
    }
}

impl MeshTriangle {
    pub fn area(&self) -> f64 {
        let p = self.position.map(|v| DVec3::from_array(v.map(f64::from)));
        0.5 * (p[1] - p[0]).cross(p[2] - p[0]).length()
    }
}

/// sRGB transfer function, encoded → linear.
pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

impl MeshImage {
    /// Raw channel values of texel (x, y) in [0, 1] (floats as stored), RGBA: grey images
    /// fill RGB, a missing alpha is 1.
    pub fn texel(&self, x: u32, y: u32) -> [f32; 4] {
        let c = self.channels as usize;
        let idx = (y as usize * self.width as usize + x as usize) * c;
        let get = |k: usize| -> f32 {
            match self.channel_type {
                ChannelType::U8 => self.pixels[idx + k] as f32 / 255.0,
                ChannelType::U16 => {
                    let o = (idx + k) * 2;
                    u16::from_ne_bytes([self.pixels[o], self.pixels[o + 1]]) as f32 / 65535.0
                }
                ChannelType::F32 => {
                    let o = (idx + k) * 4;
                    f32::from_ne_bytes([
                        self.pixels[o],
                        self.pixels[o + 1],
                        self.pixels[o + 2],
                        self.pixels[o + 3],
                    ])
                }
            }
        };
        match c {
            1 => {
                let v = get(0);
                [v, v, v, 1.0]
            }
            2 => {
                let v = get(0);
                [v, v, v, get(1)]
            }
            3 => [get(0), get(1), get(2), 1.0],
            _ => [get(0), get(1), get(2), get(3)],
        }
    }

    /// Texel (x, y) with RGB decoded from sRGB to linear when `srgb` (alpha is always linear).
    fn texel_decoded(&self, x: u32, y: u32, srgb: bool) -> [f32; 4] {
        let mut t = self.texel(x, y);
        if srgb {
            for v in t.iter_mut().take(3) {
                *v = srgb_to_linear(*v);
            }
        }
        t
    }

    /// Samples at UV (glTF convention: (0, 0) top-left, texel centres at +0.5), with the
    /// slot's wrap modes and filter. sRGB decoding (for base colour) happens per texel, before
    /// filtering, as GPUs do for sRGB textures.
    pub fn sample(&self, slot: &TextureRef, uv: [f32; 2], srgb: bool) -> [f32; 4] {
        let (w, h) = (self.width as i64, self.height as i64);
        let u = if uv[0].is_finite() { uv[0] as f64 } else { 0.0 };
        let v = if uv[1].is_finite() { uv[1] as f64 } else { 0.0 };
        match slot.filter {
            Filter::Nearest => {
                let x = wrap((u * w as f64).floor() as i64, w, slot.wrap_s);
                let y = wrap((v * h as f64).floor() as i64, h, slot.wrap_t);
                self.texel_decoded(x, y, srgb)
            }
            Filter::Linear => {
                let fx = u * w as f64 - 0.5;
                let fy = v * h as f64 - 0.5;
                let (x0, y0) = (fx.floor(), fy.floor());
                let (tx, ty) = ((fx - x0) as f32, (fy - y0) as f32);
                let (x0, y0) = (x0 as i64, y0 as i64);
                let xs = [wrap(x0, w, slot.wrap_s), wrap(x0 + 1, w, slot.wrap_s)];
                let ys = [wrap(y0, h, slot.wrap_t), wrap(y0 + 1, h, slot.wrap_t)];
                let mut out = [0.0f32; 4];
                for (j, &y) in ys.iter().enumerate() {
                    let wy = if j == 0 { 1.0 - ty } else { ty };
                    for (i, &x) in xs.iter().enumerate() {
                        let wx = if i == 0 { 1.0 - tx } else { tx };
                        let t = self.texel_decoded(x, y, srgb);
                        for k in 0..4 {
                            out[k] += wx * wy * t[k];
                        }
                    }
                }
                out
            }
        }
    }
}

/// Texel index `i` wrapped into 0..n.
fn wrap(i: i64, n: i64, mode: Wrap) -> u32 {
    let r = match mode {
        Wrap::ClampToEdge => i.clamp(0, n - 1),
        Wrap::Repeat => i.rem_euclid(n),
        Wrap::MirroredRepeat => {
            let m = i.rem_euclid(2 * n);
            if m < n {
                m
            } else {
                2 * n - 1 - m
            }
        }
    };
    r as u32
}

/// Reads an ordinary glTF mesh scene (`.gltf` with external or data-URI buffers, or `.glb`).
/// Errors name the file: it is missing (I/O error), is not glTF, or holds no triangles.
pub fn read_mesh_scene(path: &Path) -> Result<MeshScene> {
    std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    let (doc, buffers, images) = gltf::import(path).map_err(|e| match e {
        gltf::Error::Io(io) => Error::io(path, io),
        other => Error::invalid(
            path,
            "glTF",
            format!("expected a glTF 2.0 mesh scene (.gltf or .glb): {other}"),
        ),
    })?;

    let images = images
        .into_iter()
        .map(|d| {
            use gltf::image::Format as F;
            let (channels, channel_type) = match d.format {
                F::R8 => (1, ChannelType::U8),
                F::R8G8 => (2, ChannelType::U8),
                F::R8G8B8 => (3, ChannelType::U8),
                F::R8G8B8A8 => (4, ChannelType::U8),
                F::R16 => (1, ChannelType::U16),
                F::R16G16 => (2, ChannelType::U16),
                F::R16G16B16 => (3, ChannelType::U16),
                F::R16G16B16A16 => (4, ChannelType::U16),
                F::R32G32B32FLOAT => (3, ChannelType::F32),
                F::R32G32B32A32FLOAT => (4, ChannelType::F32),
            };
            MeshImage {
                width: d.width,
                height: d.height,
                channels,
                channel_type,
                pixels: d.pixels,
            }
        })
        .collect::<Vec<_>>();

    let slot = |info: Option<gltf::texture::Info>| -> Option<TextureRef> {
        let info = info?;
        let tex = info.texture();
        let sampler = tex.sampler();
        let wrap_of = |m: gltf::texture::WrappingMode| match m {
            gltf::texture::WrappingMode::Repeat => Wrap::Repeat,
            gltf::texture::WrappingMode::ClampToEdge => Wrap::ClampToEdge,
            gltf::texture::WrappingMode::MirroredRepeat => Wrap::MirroredRepeat,
        };
        Some(TextureRef {
            image: tex.source().index(),
            wrap_s: wrap_of(sampler.wrap_s()),
            wrap_t: wrap_of(sampler.wrap_t()),
            filter: match sampler.mag_filter() {
                Some(gltf::texture::MagFilter::Nearest) => Filter::Nearest,
                _ => Filter::Linear,
            },
            tex_coord: info.tex_coord(),
        })
    };
    let mut materials = Vec::new();
    for (i, m) in doc.materials().enumerate() {
        let pbr = m.pbr_metallic_roughness();
        let mat = MeshMaterial {
            name: m.name().map(str::to_owned),
            base_color_factor: pbr.base_color_factor(),
            base_color_texture: slot(pbr.base_color_texture()),
            metallic_factor: pbr.metallic_factor(),
            roughness_factor: pbr.roughness_factor(),
            metallic_roughness_texture: slot(pbr.metallic_roughness_texture()),
            alpha_cutoff: match m.alpha_mode() {
                gltf::material::AlphaMode::Mask => Some(m.alpha_cutoff().unwrap_or(0.5)),
                _ => None,
            },
        };
        for (what, s) in [
            ("baseColorTexture", mat.base_color_texture),
            ("metallicRoughnessTexture", mat.metallic_roughness_texture),
        ] {
            if let Some(s) = s {
                if s.tex_coord > 1 {
                    return Err(Error::invalid(
                        path,
                        format!("materials[{i}].pbrMetallicRoughness.{what}.texCoord"),
                        format!("expected 0 or 1, found {}", s.tex_coord),
                    ));
                }
                let img = &images[s.image];
                if img.width == 0 || img.height == 0 {
                    return Err(Error::invalid(
                        path,
                        format!("images[{}]", s.image),
                        "expected a non-empty image",
                    ));
                }
            }
        }
        materials.push(mat);
    }

    let scene = doc
        .default_scene()
        .or_else(|| doc.scenes().next())
        .ok_or_else(|| Error::invalid(path, "scenes", "expected at least one scene"))?;

    let mut nodes = Vec::new();
    let mut stack: Vec<(gltf::Node, Option<usize>, DMat4, usize)> = scene
        .nodes()
        .map(|n| (n, None, DMat4::IDENTITY, 0))
        .collect();
    stack.reverse();
    while let Some((node, parent, parent_world, depth)) = stack.pop() {
        if depth > 1000 {
            return Err(Error::invalid(
                path,
                format!("nodes[{}].children", node.index()),
                "expected a tree of nodes, found a cycle",
            ));
        }
        let local = Mat4::from_cols_array_2d(&node.transform().matrix()).as_dmat4();
        let world = parent_world * local;
        let mut triangles = Vec::new();
        if let Some(mesh) = node.mesh() {
            for (p, prim) in mesh.primitives().enumerate() {
                read_primitive(
                    path,
                    &format!("meshes[{}].primitives[{p}]", mesh.index()),
                    &prim,
                    &buffers,
                    &world,
                    &mut triangles,
                )?;
            }
        }
        let me = nodes.len();
        nodes.push(MeshNode {
            name: node.name().map(str::to_owned),
            parent,
            triangles,
        });
        let children: Vec<_> = node.children().collect();
        for c in children.into_iter().rev() {
            stack.push((c, Some(me), world, depth + 1));
        }
    }

    let out = MeshScene {
        path: path.to_path_buf(),
        nodes,
        materials,
        images,
    };
    if out.triangle_count() == 0 {
        return Err(Error::invalid(
            path,
            "meshes",
            "expected at least one triangle (TRIANGLES, TRIANGLE_STRIP or TRIANGLE_FAN primitive) in the default scene",
        ));
    }
    Ok(out)
}

/// Appends the primitive's non-degenerate triangles, transformed to world space.
fn read_primitive(
    path: &Path,
    field: &str,
    prim: &gltf::Primitive,
    buffers: &[gltf::buffer::Data],
    world: &DMat4,
    out: &mut Vec<MeshTriangle>,
) -> Result<()> {
    use gltf::mesh::Mode;
    let mode = prim.mode();
    if !matches!(
        mode,
        Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
    ) {
        return Ok(());
    }
    let reader = prim.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
    let Some(positions) = reader.read_positions() else {
        return Err(Error::invalid(
            path,
            format!("{field}.attributes.POSITION"),
            "expected vertex positions",
        ));
    };
    let positions: Vec<[f32; 3]> = positions.collect();
    let n = positions.len();
    let normals: Option<Vec<[f32; 3]>> = reader.read_normals().map(|r| r.collect());
    let uv0: Option<Vec<[f32; 2]>> = reader.read_tex_coords(0).map(|r| r.into_f32().collect());
    let uv1: Option<Vec<[f32; 2]>> = reader.read_tex_coords(1).map(|r| r.into_f32().collect());
    let colors: Option<Vec<[f32; 4]>> = reader.read_colors(0).map(|r| r.into_rgba_f32().collect());
    for (name, len) in [
        ("NORMAL", normals.as_ref().map(Vec::len)),
        ("TEXCOORD_0", uv0.as_ref().map(Vec::len)),
        ("TEXCOORD_1", uv1.as_ref().map(Vec::len)),
        ("COLOR_0", colors.as_ref().map(Vec::len)),
    ] {
        if let Some(len) = len {
            if len != n {
                return Err(Error::invalid(
                    path,
                    format!("{field}.attributes.{name}"),
                    format!("expected {n} elements (as POSITION), found {len}"),
                ));
            }
        }
    }
    let indices: Vec<u32> = match reader.read_indices() {
        Some(i) => i.into_u32().collect(),
        None => (0..n as u32).collect(),
    };
    if let Some(bad) = indices.iter().find(|&&i| i as usize >= n) {
        return Err(Error::invalid(
            path,
            format!("{field}.indices"),
            format!("expected vertex indices below {n}, found {bad}"),
        ));
    }
    let tris: Vec<[u32; 3]> = match mode {
        Mode::Triangles => indices
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect(),
        Mode::TriangleStrip => (2..indices.len())
            .map(|k| {
                if k % 2 == 0 {
                    [indices[k - 2], indices[k - 1], indices[k]]
                } else {
                    [indices[k - 1], indices[k - 2], indices[k]]
                }
            })
            .collect(),
        _ => (2..indices.len())
            .map(|k| [indices[0], indices[k - 1], indices[k]])
            .collect(),
    };

    let normal_matrix = world_normal_matrix(world);
    let mirrored = world.determinant() < 0.0;
    let material = prim.material().index();
    let to_world = |p: [f32; 3]| world.transform_point3(DVec3::from_array(p.map(f64::from)));
    for mut t in tris {
        if mirrored {
            // A mirroring transform flips the winding (glTF spec §3.7.4): undo it so the
            // cross product of the edges stays the front-facing normal.
            t.swap(1, 2);
        }
        let p = t.map(|i| to_world(positions[i as usize]));
        let face = (p[1] - p[0]).cross(p[2] - p[0]);
        let len = face.length();
        if !(len > 0.0 && len.is_finite()) {
            continue; // degenerate (or non-finite): covers no surface
        }
        let face = face / len;
        let normal = t.map(|i| {
            normals
                .as_ref()
                .map(|ns| normal_matrix * DVec3::from_array(ns[i as usize].map(f64::from)))
                .filter(|v| v.length_squared() > 1e-24 && v.is_finite())
                .map(|v| v.normalize())
                .unwrap_or(face)
                .as_vec3()
                .to_array()
        });
        let uv_of = |set: &Option<Vec<[f32; 2]>>| {
            t.map(|i| set.as_ref().map(|s| s[i as usize]).unwrap_or([0.0; 2]))
        };
        out.push(MeshTriangle {
            position: p.map(|v| v.as_vec3().to_array()),
            normal,
            uv: [uv_of(&uv0), uv_of(&uv1)],
            color: t.map(|i| colors.as_ref().map(|c| c[i as usize]).unwrap_or([1.0; 4])),
            material,
        });
    }
    Ok(())
}

/// Inverse transpose of the upper 3x3 (normals under non-uniform scale).
fn world_normal_matrix(world: &DMat4) -> glam::DMat3 {
    let m = glam::DMat3::from_mat4(*world);
    if m.determinant().abs() > 1e-300 {
        m.inverse().transpose()
    } else {
        m
    }
}
