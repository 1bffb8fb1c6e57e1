//! Ordinary mesh scenes (the input of `surfelize`, read by [`crate::io::mesh`]): world-space
//! triangles with per-vertex shading normals, UVs and colours, PBR metallic-roughness materials
//! and decoded textures, and how those textures are sampled.

use glam::DVec3;
use std::path::PathBuf;

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
                *v = crate::scene::color::srgb_to_linear(*v);
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
