//! Reading ordinary glTF mesh scenes (the input of `surfelize`) into [`MeshScene`]: world-space
//! triangles with per-vertex shading normals, UVs and colours, PBR metallic-roughness materials
//! and decoded textures.
//!
//! What is read: the default scene (or the first one), every node below it with its world
//! transform, every primitive in `TRIANGLES`, `TRIANGLE_STRIP` or `TRIANGLE_FAN` mode (points
//! and lines are skipped), `POSITION`, `NORMAL`, `TEXCOORD_0/1`, `COLOR_0`, and the materials'
//! metallic-roughness parameters. Not read: skins, morph targets, animations,
//! `KHR_texture_transform`, emission, and any other material extension.

use crate::error::{Error, Result};
use crate::scene::mesh::{
    ChannelType, Filter, MeshImage, MeshMaterial, MeshNode, MeshScene, MeshTriangle, TextureRef,
    Wrap,
};
use glam::{DMat4, DVec3, Mat4};
use std::path::Path;

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
