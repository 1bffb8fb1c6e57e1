//! `surfelize`: glTF mesh scenes built here by hand (JSON + base64 data URIs) → surfel scenes.
//! Checks counts, placement, orientation, opacity (a brute-force leak test), materials and
//! textures, object components, and bad input.

use base64::Engine;
use glam::{DVec3, Quat, Vec3};
use lightfuse::io::mesh::read_mesh_scene;
use lightfuse::scene::color::srgb_to_linear;
use lightfuse::scene::surfelize::{
    surfelize, ObjectSelection, SurfelizeOptions, SIGMA_PER_SPACING,
};
use lightfuse::scene::surfels::quat_axes;
use lightfuse::scene::{Scene, Surfels};
use lightfuse::Error;
use rand::{Rng, SeedableRng};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

// ---------------------------------------------------------------------------------------------
// A tiny glTF writer.

#[derive(Clone, Default)]
struct Prim {
    positions: Vec<[f32; 3]>,
    normals: Option<Vec<[f32; 3]>>,
    uvs: Option<Vec<[f32; 2]>>,
    colors: Option<Vec<[f32; 4]>>,
    indices: Vec<u32>,
    material: Option<usize>,
    mode: Option<u32>,
}

#[derive(Clone, Default)]
struct Node {
    name: Option<String>,
    mesh: Option<Prim>,
    translation: Option<[f32; 3]>,
    rotation: Option<[f32; 4]>,
    children: Vec<Node>,
}

#[derive(Default)]
struct Doc {
    roots: Vec<Node>,
    materials: Vec<Value>,
    textures: Vec<Value>,
    samplers: Vec<Value>,
    /// PNG bytes.
    images: Vec<Vec<u8>>,
}

struct Writer {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
    meshes: Vec<Value>,
    nodes: Vec<Value>,
}

impl Writer {
    fn accessor(
        &mut self,
        bytes: &[u8],
        count: usize,
        ty: &str,
        comp: u32,
        minmax: bool,
        f: &[f32],
    ) -> usize {
        while self.bin.len() % 4 != 0 {
            self.bin.push(0);
        }
        self.views
            .push(json!({"buffer": 0, "byteOffset": self.bin.len(), "byteLength": bytes.len()}));
        self.bin.extend_from_slice(bytes);
        let mut a = json!({"bufferView": self.views.len() - 1, "componentType": comp, "count": count, "type": ty});
        if minmax {
            let mut lo = [f32::INFINITY; 3];
            let mut hi = [f32::NEG_INFINITY; 3];
            for p in f.chunks(3) {
                for k in 0..3 {
                    lo[k] = lo[k].min(p[k]);
                    hi[k] = hi[k].max(p[k]);
                }
            }
            a["min"] = json!(lo);
            a["max"] = json!(hi);
        }
        self.accessors.push(a);
        self.accessors.len() - 1
    }

    fn floats<const N: usize>(&mut self, v: &[[f32; N]], ty: &str, minmax: bool) -> usize {
        let flat: Vec<f32> = v.iter().flatten().copied().collect();
        self.accessor(
            bytemuck::cast_slice(&flat),
            v.len(),
            ty,
            5126,
            minmax,
            &flat,
        )
    }

    fn node(&mut self, n: &Node) -> usize {
        let children: Vec<usize> = n.children.iter().map(|c| self.node(c)).collect();
        let mut node = json!({});
        if let Some(name) = &n.name {
            node["name"] = json!(name);
        }
        if let Some(t) = n.translation {
            node["translation"] = json!(t);
        }
        if let Some(r) = n.rotation {
            node["rotation"] = json!(r);
        }
        if !children.is_empty() {
            node["children"] = json!(children);
        }
        if let Some(p) = &n.mesh {
            let mut attrs = json!({"POSITION": self.floats(&p.positions, "VEC3", true)});
            if let Some(v) = &p.normals {
                attrs["NORMAL"] = json!(self.floats(v, "VEC3", false));
            }
            if let Some(v) = &p.uvs {
                attrs["TEXCOORD_0"] = json!(self.floats(v, "VEC2", false));
            }
            if let Some(v) = &p.colors {
                attrs["COLOR_0"] = json!(self.floats(v, "VEC4", false));
            }
            let idx = self.accessor(
                bytemuck::cast_slice(&p.indices),
                p.indices.len(),
                "SCALAR",
                5125,
                false,
                &[],
            );
            let mut prim = json!({"attributes": attrs, "indices": idx});
            if let Some(m) = p.material {
                prim["material"] = json!(m);
            }
            if let Some(m) = p.mode {
                prim["mode"] = json!(m);
            }
            self.meshes.push(json!({"primitives": [prim]}));
            node["mesh"] = json!(self.meshes.len() - 1);
        }
        self.nodes.push(node);
        self.nodes.len() - 1
    }
}

fn write_gltf(doc: &Doc, path: &Path) {
    let mut w = Writer {
        bin: Vec::new(),
        views: Vec::new(),
        accessors: Vec::new(),
        meshes: Vec::new(),
        nodes: Vec::new(),
    };
    let roots: Vec<usize> = doc.roots.iter().map(|n| w.node(n)).collect();
    let b64 = |b: &[u8]| base64::engine::general_purpose::STANDARD.encode(b);
    let mut gltf = json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": roots}],
        "nodes": w.nodes,
        "meshes": w.meshes,
        "accessors": w.accessors,
        "bufferViews": w.views,
        "buffers": [{"byteLength": w.bin.len(),
                     "uri": format!("data:application/octet-stream;base64,{}", b64(&w.bin))}],
    });
    if !doc.materials.is_empty() {
        gltf["materials"] = json!(doc.materials);
    }
    if !doc.textures.is_empty() {
        gltf["textures"] = json!(doc.textures);
        gltf["samplers"] = json!(doc.samplers);
        gltf["images"] = json!(doc
            .images
            .iter()
            .map(|p| json!({"uri": format!("data:image/png;base64,{}", b64(p))}))
            .collect::<Vec<_>>());
    }
    std::fs::write(path, serde_json::to_vec_pretty(&gltf).unwrap()).unwrap();
}

fn png(w: u32, h: u32, rgb: &[[u8; 3]]) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb(rgb[(y * w + x) as usize]));
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

// ---------------------------------------------------------------------------------------------
// Test meshes.

/// The square [x0, x0 + size] × [z0, z0 + size] at y = 0, normal +Y, as an n × n grid of quads
/// (2n² triangles), UV = ((x − x0) / size, (z − z0) / size).
fn grid_quad(x0: f32, z0: f32, size: f32, n: u32) -> Prim {
    let mut p = Prim::default();
    let (mut pos, mut nor, mut uv) = (vec![], vec![], vec![]);
    for j in 0..=n {
        for i in 0..=n {
            let (u, v) = (i as f32 / n as f32, j as f32 / n as f32);
            pos.push([x0 + u * size, 0.0, z0 + v * size]);
            nor.push([0.0, 1.0, 0.0]);
            uv.push([u, v]);
        }
    }
    for j in 0..n {
        for i in 0..n {
            let a = j * (n + 1) + i;
            let b = a + n + 1;
            // Counter-clockwise seen from +Y: (a, b, a + 1), (a + 1, b, b + 1).
            p.indices.extend([a, b, a + 1, a + 1, b, b + 1]);
        }
    }
    p.positions = pos;
    p.normals = Some(nor);
    p.uvs = Some(uv);
    p
}

/// UV sphere of radius r with vertex normals = radial directions.
fn uv_sphere(r: f32, rings: u32, segs: u32) -> Prim {
    let mut p = Prim::default();
    let (mut pos, mut nor) = (vec![], vec![]);
    for i in 0..=rings {
        for j in 0..=segs {
            let th = std::f32::consts::PI * i as f32 / rings as f32;
            let ph = std::f32::consts::TAU * j as f32 / segs as f32;
            let n = [th.sin() * ph.cos(), th.cos(), th.sin() * ph.sin()];
            pos.push(n.map(|x| x * r));
            nor.push(n);
        }
    }
    for i in 0..rings {
        for j in 0..segs {
            let a = i * (segs + 1) + j;
            let b = a + segs + 1;
            p.indices.extend([a, a + 1, b, a + 1, b + 1, b]);
        }
    }
    p.positions = pos;
    p.normals = Some(nor);
    p
}

fn material(base: [f32; 4], metallic: f32, roughness: f32) -> Value {
    json!({"pbrMetallicRoughness": {"baseColorFactor": base, "metallicFactor": metallic,
                                    "roughnessFactor": roughness}})
}

fn one_node(name: Option<&str>, prim: Prim) -> Doc {
    Doc {
        roots: vec![Node {
            name: name.map(str::to_owned),
            mesh: Some(prim),
            ..Default::default()
        }],
        materials: vec![material([0.8, 0.5, 0.2, 1.0], 0.25, 0.6)],
        ..Default::default()
    }
}

fn surfelize_doc(doc: &Doc, dir: &Path, name: &str, opts: &SurfelizeOptions) -> (PathBuf, Scene) {
    let path = dir.join(name);
    write_gltf(doc, &path);
    let mesh = read_mesh_scene(&path).unwrap();
    let scene = surfelize(&mesh, opts).unwrap();
    scene.validate(&path).unwrap();
    (path, scene)
}

fn all_surfels(scene: &Scene) -> Surfels {
    let mut s = Surfels::with_sh_degree(scene.components[0].surfels.sh_degree);
    for c in &scene.components {
        s.extend(&c.surfels);
    }
    s
}

// ---------------------------------------------------------------------------------------------
// The brute-force leak reference.

/// The surfels whose centres lie within `radius` of a point, found through a hash grid (the
/// compositing itself, [`transmittance`], is brute force over them).
struct Near<'a> {
    s: &'a Surfels,
    radius: f64,
    grid: std::collections::HashMap<[i64; 3], Vec<usize>>,
}

impl<'a> Near<'a> {
    fn new(s: &'a Surfels, radius: f64) -> Self {
        let mut grid: std::collections::HashMap<[i64; 3], Vec<usize>> = Default::default();
        for (i, p) in s.position.iter().enumerate() {
            grid.entry(p.map(|x| (x as f64 / radius).floor() as i64))
                .or_default()
                .push(i);
        }
        Near { s, radius, grid }
    }

    fn around(&self, p: DVec3) -> Vec<usize> {
        let c = p.to_array().map(|x| (x / self.radius).floor() as i64);
        let mut out = Vec::new();
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    for &i in self
                        .grid
                        .get(&[c[0] + dx, c[1] + dy, c[2] + dz])
                        .into_iter()
                        .flatten()
                    {
                        let mu = DVec3::from_array(self.s.position[i].map(f64::from));
                        if (mu - p).length() <= self.radius {
                            out.push(i);
                        }
                    }
                }
            }
        }
        out
    }
}

/// Transmittance along the ray o + t d through the surfels whose centres lie within the
/// radius of `near` (the layer around the aimed-at point; the far side of a closed surface is
/// excluded): 2DGS ray–surfel intersection (the ray meets each surfel's plane), response
/// α·exp(−½|ξ|²) capped at 0.99, dropped below 1/255, support |ξ| ≤ 3, composited front to
/// back.
fn transmittance(near: &Near, o: DVec3, d: DVec3, at: DVec3) -> f64 {
    let s = near.s;
    let mut hits: Vec<(f64, f64)> = Vec::new();
    for i in near.around(at) {
        let mu = DVec3::from_array(s.position[i].map(f64::from));
        let ax = quat_axes(s.rotation[i]).map(|c| Vec3::from_array(c).as_dvec3());
        let denom = ax[2].dot(d);
        if denom.abs() < 1e-9 {
            continue;
        }
        let t = ax[2].dot(mu - o) / denom;
        if t <= 0.0 {
            continue;
        }
        let x = o + d * t - mu;
        let u = x.dot(ax[0]) / s.scale[i][0] as f64;
        let v = x.dot(ax[1]) / s.scale[i][1] as f64;
        let r2 = u * u + v * v;
        if r2 > 9.0 {
            continue;
        }
        let a = (s.opacity[i] as f64 * (-0.5 * r2).exp()).min(0.99);
        if a < 1.0 / 255.0 {
            continue;
        }
        hits.push((t, a));
    }
    hits.sort_by(|a, b| a.0.total_cmp(&b.0));
    hits.iter().fold(1.0, |t, (_, a)| t * (1.0 - a))
}

struct Leak {
    mean: f64,
    max: f64,
    /// 99th percentile.
    p99: f64,
}

fn leak(samples: impl Iterator<Item = f64>) -> Leak {
    let v: Vec<f64> = samples.collect();
    Leak {
        mean: v.iter().sum::<f64>() / v.len() as f64,
        max: v.iter().copied().fold(0.0, f64::max),
        p99: {
            let mut w = v.clone();
            w.sort_by(f64::total_cmp);
            w[w.len() * 99 / 100]
        },
    }
}

/// Unit vector at angle `theta` from `n`, random azimuth.
fn tilted(n: DVec3, theta: f64, rng: &mut impl Rng) -> DVec3 {
    let t = n.any_orthonormal_vector();
    let b = n.cross(t);
    let phi = rng.random::<f64>() * std::f64::consts::TAU;
    (n * theta.cos() + (t * phi.cos() + b * phi.sin()) * theta.sin()).normalize()
}

// ---------------------------------------------------------------------------------------------
// Tests.

const H: f32 = 0.02;

#[test]
fn quad_count_placement_orientation_and_material() {
    let dir = tempfile::tempdir().unwrap();
    let mut doc = one_node(None, grid_quad(-0.5, -0.5, 1.0, 4));
    doc.roots[0].mesh.as_mut().unwrap().material = Some(0);
    let (_, scene) = surfelize_doc(&doc, dir.path(), "quad.gltf", &SurfelizeOptions::new(H));
    assert_eq!(scene.components.len(), 1);
    assert_eq!(scene.components[0].name, "background");
    assert_eq!(scene.states.len(), 1);
    assert_eq!(scene.states[0].name, "state0");
    assert!(scene.environments.is_empty());
    let s = &scene.components[0].surfels;
    // An axis-aligned plane is one jittered lattice over all 32 triangles: the count can only
    // differ from area / h² = 2500 by sites whose jitter moves them across the boundary (a
    // strip of ±0.2 h along the 4 m perimeter: ±~40 at most, ~±6 typically).
    let expected = 1.0 / (H * H) as f64;
    let n = s.len() as f64;
    assert!(
        (n - expected).abs() < 0.02 * expected,
        "count {n} vs {expected}"
    );
    let sigma = H * SIGMA_PER_SPACING;
    for i in 0..s.len() {
        let p = s.position[i];
        assert!(p[1].abs() < 1e-5, "off the plane: {p:?}");
        assert!(
            p[0].abs() <= 0.5 + 1e-6 && p[2].abs() <= 0.5 + 1e-6,
            "outside: {p:?}"
        );
        let ax = quat_axes(s.rotation[i]);
        let n = Vec3::from_array(ax[2]);
        assert!((n - Vec3::Y).length() < 1e-5, "normal {n:?}");
        // Right-handed: t × b = n, and the tangent is the triangle's first edge's direction:
        // +Z for the (a, b, a + 1) triangles, the diagonal for the (a + 1, b, b + 1) ones.
        let (t, b) = (Vec3::from_array(ax[0]), Vec3::from_array(ax[1]));
        assert!((t.cross(b) - n).length() < 1e-5);
        let diagonal = Vec3::new(-1.0, 0.0, 1.0).normalize();
        assert!(
            (t - Vec3::Z).length() < 1e-5 || (t - diagonal).length() < 1e-5,
            "tangent {t:?}"
        );
        assert_eq!(s.scale[i], [sigma, sigma]);
        assert_eq!(s.opacity[i], 0.99);
        assert_eq!(s.base_color[i], [0.8, 0.5, 0.2]);
        assert_eq!((s.metallic[i], s.roughness[i]), (0.25, 0.6));
        let sh = s.sh_of(i)[0];
        for (c, a) in sh.iter().zip(s.base_color[i]) {
            assert!((c * lightfuse::scene::SH_C0 + 0.5 - a).abs() < 1e-6);
        }
    }
    // Nearest-neighbour distances: the lattice with ±0.2 h jitter keeps them in [0.6 h, 1.4 h].
    let nn = nearest_neighbour_distances(s);
    let (lo, hi) = nn
        .iter()
        .fold((f32::MAX, 0.0f32), |(a, b), &d| (a.min(d), b.max(d)));
    assert!(
        lo > 0.5 * H && hi < 1.5 * H,
        "nearest neighbours in [{lo}, {hi}]"
    );
}

fn nearest_neighbour_distances(s: &Surfels) -> Vec<f32> {
    // Grid hash of cell H.
    let mut grid: std::collections::HashMap<[i32; 3], Vec<usize>> = Default::default();
    let cell = |p: [f32; 3]| p.map(|x| (x / H).floor() as i32);
    for (i, p) in s.position.iter().enumerate() {
        grid.entry(cell(*p)).or_default().push(i);
    }
    (0..s.len())
        .map(|i| {
            let c = cell(s.position[i]);
            let mut best = f32::MAX;
            for dx in -2..=2 {
                for dy in -2..=2 {
                    for dz in -2..=2 {
                        if let Some(v) = grid.get(&[c[0] + dx, c[1] + dy, c[2] + dz]) {
                            for &j in v {
                                if j != i {
                                    let d = Vec3::from_array(s.position[i])
                                        .distance(Vec3::from_array(s.position[j]));
                                    best = best.min(d);
                                }
                            }
                        }
                    }
                }
            }
            best
        })
        .collect()
}

#[test]
fn quad_does_not_leak() {
    let dir = tempfile::tempdir().unwrap();
    // An axis-aligned quad (one shared lattice) and the same quad turned by an oblique rotation
    // (its 2 triangles sampled with unrelated lattice phases: a seam along the diagonal).
    let turn = Quat::from_axis_angle(Vec3::new(1.0, 2.0, 0.5).normalize(), 0.9);
    for (label, prim, rotation) in [
        ("axis-aligned", grid_quad(-0.5, -0.5, 1.0, 4), None),
        (
            "oblique",
            grid_quad(-0.5, -0.5, 1.0, 1),
            Some(turn.to_array()),
        ),
    ] {
        let mut doc = one_node(None, prim);
        doc.roots[0].rotation = rotation;
        let (_, scene) = surfelize_doc(&doc, dir.path(), "q.gltf", &SurfelizeOptions::new(H));
        let s = &scene.components[0].surfels;
        let near = Near::new(s, 0.2);
        let r = turn.as_dquat();
        let rot = |v: DVec3| if rotation.is_some() { r * v } else { v };
        let n = rot(DVec3::Y);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        for deg in [0.0f64, 60.0] {
            // Interior points, one spacing away from the open boundary (where coverage fades
            // over ~σ, as the true surface ends).
            let m = H as f64;
            let l = leak((0..1500).map(|_| {
                let x = -0.5 + m + rng.random::<f64>() * (1.0 - 2.0 * m);
                let z = -0.5 + m + rng.random::<f64>() * (1.0 - 2.0 * m);
                let p = rot(DVec3::new(x, 0.0, z));
                let d = -tilted(n, deg.to_radians(), &mut rng);
                transmittance(&near, p - d * 0.5, d, p)
            }));
            println!(
                "leak {label} quad at {deg}°: mean {:.2e}, p99 {:.2e}, max {:.2e}",
                l.mean, l.p99, l.max
            );
            assert!(
                l.mean < 1e-3 && l.max < 0.02,
                "{label} {deg}°: mean {} max {}",
                l.mean,
                l.max
            );
        }
    }
}

#[test]
fn sphere_count_surface_normals_and_leak() {
    let dir = tempfile::tempdir().unwrap();
    let (rings, segs) = (24u32, 48u32);
    let doc = one_node(Some("ball"), uv_sphere(1.0, rings, segs));
    let (path, scene) = surfelize_doc(&doc, dir.path(), "sphere.gltf", &SurfelizeOptions::new(H));
    let mesh = read_mesh_scene(&path).unwrap();
    assert_eq!(scene.components.len(), 2);
    assert_eq!(scene.components[1].name, "ball");
    assert!(scene.components[0].surfels.is_empty());
    let s = &scene.components[1].surfels;
    // Each triangle gets area / h² sites in expectation; the triangles' lattices are unrelated
    // except for the share of an anchor cell, so the total fluctuates like a sum of ~2300
    // independent boundary effects: a few tenths of a percent. 2% leaves room.
    let expected = mesh.area() / (H as f64 * H as f64);
    let n = s.len() as f64;
    println!("sphere: {n} surfels, area / h² = {expected:.0}");
    assert!(
        (n - expected).abs() < 0.02 * expected,
        "count {n} vs {expected}"
    );

    // Every centre lies on a triangle of the mesh (its UV cell or a neighbour).
    let tris: Vec<[DVec3; 3]> = mesh.nodes[0]
        .triangles
        .iter()
        .map(|t| t.position.map(|p| DVec3::from_array(p.map(f64::from))))
        .collect();
    let mut by_cell: std::collections::HashMap<(i32, i32), Vec<usize>> = Default::default();
    let cell_of = |p: DVec3| {
        let th = (p.y / p.length()).clamp(-1.0, 1.0).acos();
        let ph = p.z.atan2(p.x).rem_euclid(std::f64::consts::TAU);
        (
            (th / std::f64::consts::PI * rings as f64).floor() as i32,
            (ph / std::f64::consts::TAU * segs as f64).floor() as i32,
        )
    };
    for (k, t) in tris.iter().enumerate() {
        by_cell
            .entry(cell_of((t[0] + t[1] + t[2]) / 3.0))
            .or_default()
            .push(k);
    }
    for i in 0..s.len() {
        let p = DVec3::from_array(s.position[i].map(f64::from));
        let (ci, cj) = cell_of(p);
        let mut best = f64::MAX;
        for di in -1..=1 {
            for dj in -1..=1 {
                let key = (ci + di, (cj + dj).rem_euclid(segs as i32));
                for &k in by_cell.get(&key).into_iter().flatten() {
                    best = best.min(point_triangle_distance(p, &tris[k]));
                }
            }
        }
        assert!(best < 1e-5, "surfel {i} at {p:?} is {best} m off the mesh");
        // Vertex normals are radial, so the interpolated shading normal is p / |p| exactly.
        let n = Vec3::from_array(quat_axes(s.rotation[i])[2]).as_dvec3();
        assert!((n - p.normalize()).length() < 2e-5, "normal {n:?} at {p:?}");
    }

    // Tolerances: the lattice alone gives T ≤ 8·10⁻⁵ (SIGMA_PER_SPACING); the sphere's ~3400
    // seams between non-coplanar triangles meet unrelated lattice phases, and a ray landing in
    // the widest gaps sees T ~ 10⁻². Measured (4000 rays): mean 1.3·10⁻⁴, p99 1.4·10⁻³, max
    // 1.0·10⁻² at normal and 60° incidence, so mean < 10⁻³ and max < 0.02 hold with margins
    // of 7x and 2x, while σ = 0.9 h (max 3.8·10⁻²) would fail.
    let near = Near::new(s, 0.15);
    let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
    for deg in [0.0f64, 60.0] {
        let l = leak((0..4000).map(|_| {
            // A uniform direction; aim at the mesh surface point in that direction.
            let dir = loop {
                let v = DVec3::new(
                    rng.random::<f64>() * 2.0 - 1.0,
                    rng.random::<f64>() * 2.0 - 1.0,
                    rng.random::<f64>() * 2.0 - 1.0,
                );
                if v.length_squared() <= 1.0 && v.length_squared() > 1e-4 {
                    break v.normalize();
                }
            };
            let p = dir * 0.995; // within the chord sag (≤ 1 − cos(π/48) ≈ 0.0021 below 1)
            let d = -tilted(dir, deg.to_radians(), &mut rng);
            transmittance(&near, p - d * 0.3, d, p)
        }));
        println!(
            "leak sphere at {deg}°: mean {:.2e}, p99 {:.2e}, max {:.2e}",
            l.mean, l.p99, l.max
        );
        assert!(
            l.mean < 1e-3 && l.max < 0.02,
            "sphere {deg}°: mean {} max {}",
            l.mean,
            l.max
        );
    }
}

fn point_triangle_distance(p: DVec3, t: &[DVec3; 3]) -> f64 {
    let n = (t[1] - t[0]).cross(t[2] - t[0]);
    if n.length_squared() == 0.0 {
        return f64::MAX;
    }
    let n = n.normalize();
    let q = p - n * n.dot(p - t[0]);
    let inside = (0..3).all(|k| (t[(k + 1) % 3] - t[k]).cross(q - t[k]).dot(n) >= -1e-9);
    if inside {
        return (p - q).length();
    }
    (0..3)
        .map(|k| {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            let s = ((p - a).dot(b - a) / (b - a).length_squared()).clamp(0.0, 1.0);
            (p - (a + (b - a) * s)).length()
        })
        .fold(f64::MAX, f64::min)
}

#[test]
fn textured_quad_takes_texture_colours() {
    let dir = tempfile::tempdir().unwrap();
    let colours = [[255, 0, 0], [0, 200, 0], [30, 60, 255], [128, 128, 128]];
    // metallicRoughness: G = roughness, B = metallic (R unused).
    let mr = [[0, 50, 255], [0, 100, 0], [0, 150, 128], [0, 250, 64]];
    let mut prim = grid_quad(0.0, 0.0, 1.0, 1);
    prim.material = Some(0);
    let mut bilinear = grid_quad(2.0, 0.0, 1.0, 1);
    bilinear.material = Some(1);
    bilinear.colors = Some(vec![[1.0, 0.5, 1.0, 1.0]; 4]);
    let doc = Doc {
        roots: vec![
            Node {
                name: Some("nearest".into()),
                mesh: Some(prim),
                ..Default::default()
            },
            Node {
                name: Some("linear".into()),
                mesh: Some(bilinear),
                ..Default::default()
            },
        ],
        materials: vec![
            json!({"pbrMetallicRoughness": {
                "baseColorFactor": [0.5, 1.0, 1.0, 1.0],
                "baseColorTexture": {"index": 0},
                "metallicFactor": 1.0, "roughnessFactor": 0.5,
                "metallicRoughnessTexture": {"index": 1}}}),
            json!({"pbrMetallicRoughness": {"baseColorTexture": {"index": 2}}}),
        ],
        textures: vec![
            json!({"source": 0, "sampler": 0}),
            json!({"source": 1, "sampler": 0}),
            json!({"source": 0, "sampler": 1}),
        ],
        samplers: vec![
            json!({"magFilter": 9728, "wrapS": 33071, "wrapT": 33071}),
            json!({"magFilter": 9729, "wrapS": 10497, "wrapT": 33648}),
        ],
        images: vec![png(2, 2, &colours), png(2, 2, &mr)],
    };
    let (_, scene) = surfelize_doc(&doc, dir.path(), "tex.gltf", &SurfelizeOptions::new(H));
    let dec = |c: [u8; 3]| c.map(|v| srgb_to_linear(v as f32 / 255.0));

    // Nearest: each surfel takes its texel's decoded colour × factor.
    let s = &scene.components[scene.component_index("nearest").unwrap()].surfels;
    assert!(!s.is_empty());
    let mut checked = 0;
    for i in 0..s.len() {
        let [x, _, z] = s.position[i];
        if (x - 0.5).abs() < 1e-4 || (z - 0.5).abs() < 1e-4 {
            continue;
        }
        let texel = (z >= 0.5) as usize * 2 + (x >= 0.5) as usize;
        let want = dec(colours[texel]);
        let want = [want[0] * 0.5, want[1], want[2]];
        for k in 0..3 {
            assert!(
                (s.base_color[i][k] - want[k]).abs() < 1e-5,
                "texel {texel}: {:?} vs {want:?}",
                s.base_color[i]
            );
        }
        assert!((s.roughness[i] - 0.5 * mr[texel][1] as f32 / 255.0).abs() < 1e-5);
        assert!((s.metallic[i] - mr[texel][2] as f32 / 255.0).abs() < 1e-5);
        checked += 1;
    }
    assert!(checked > 2000);

    // Linear with REPEAT / MIRRORED_REPEAT: bilinear of the decoded texels at the UV, × COLOR_0.
    let s = &scene.components[scene.component_index("linear").unwrap()].surfels;
    let texel = |x: i64, y: i64| {
        let x = x.rem_euclid(2); // REPEAT
        let m = y.rem_euclid(4); // MIRRORED_REPEAT, period 2n
        let y = if m < 2 { m } else { 3 - m };
        dec(colours[(y * 2 + x) as usize])
    };
    for i in 0..s.len() {
        let [x, _, z] = s.position[i];
        let (u, v) = ((x - 2.0) as f64, z as f64);
        let (fx, fy) = (u * 2.0 - 0.5, v * 2.0 - 0.5);
        let (x0, y0) = (fx.floor(), fy.floor());
        let (tx, ty) = ((fx - x0) as f32, (fy - y0) as f32);
        let (x0, y0) = (x0 as i64, y0 as i64);
        for k in 0..3 {
            let want = (1.0 - ty) * ((1.0 - tx) * texel(x0, y0)[k] + tx * texel(x0 + 1, y0)[k])
                + ty * ((1.0 - tx) * texel(x0, y0 + 1)[k] + tx * texel(x0 + 1, y0 + 1)[k]);
            let want = want * [1.0, 0.5, 1.0][k];
            assert!(
                (s.base_color[i][k] - want).abs() < 1e-4,
                "{:?} vs {want} at {u},{v}",
                s.base_color[i]
            );
        }
        // Untextured metallic / roughness: glTF defaults 1, 1.
        assert_eq!((s.metallic[i], s.roughness[i]), (1.0, 1.0));
    }
}

/// chair (a quad), an unnamed quad, table (quad) with child leg (quad), and a named node
/// without a mesh (like Blender's camera).
fn objects_doc() -> Doc {
    let quad = |x: f32| {
        let mut p = grid_quad(x, 0.0, 0.5, 1);
        p.material = Some(0);
        p
    };
    let mut d = one_node(Some("chair"), quad(0.0));
    d.roots.push(Node {
        mesh: Some(quad(1.0)),
        ..Default::default()
    });
    d.roots.push(Node {
        name: Some("table".into()),
        mesh: Some(quad(2.0)),
        translation: Some([0.0, 1.0, 0.0]),
        children: vec![Node {
            name: Some("leg".into()),
            mesh: Some(quad(3.0)),
            ..Default::default()
        }],
        ..Default::default()
    });
    d.roots.push(Node {
        name: Some("Camera".into()),
        ..Default::default()
    });
    d
}

#[test]
fn named_nodes_become_objects() {
    let dir = tempfile::tempdir().unwrap();
    let doc = objects_doc();
    let path = dir.path().join("objects.gltf");
    write_gltf(&doc, &path);
    let mesh = read_mesh_scene(&path).unwrap();
    let per_quad = 0.25 / (H * H) as f64;
    let count =
        |s: &Scene, name: &str| s.components[s.component_index(name).unwrap()].surfels.len() as f64;
    let near = |n: f64, k: f64| (n - k * per_quad).abs() < 0.03 * k * per_quad;

    let scene = surfelize(&mesh, &SurfelizeOptions::new(H)).unwrap();
    let names: Vec<(&str, u32)> = scene
        .components
        .iter()
        .map(|c| (c.name.as_str(), c.id))
        .collect();
    assert_eq!(names, [("background", 0), ("chair", 1), ("table", 2)]);
    assert!(near(count(&scene, "background"), 1.0));
    assert!(near(count(&scene, "chair"), 1.0));
    assert!(near(count(&scene, "table"), 2.0)); // with its leg
    assert_eq!(scene.states[0].transforms.len(), 3);
    assert!(scene.states[0].transforms.iter().all(|t| t.is_identity()));
    // The table node's translation is applied: surfels in world space.
    let t = &scene.components[2].surfels;
    assert!(t.position.iter().all(|p| (p[1] - 1.0).abs() < 1e-5));

    let opts = SurfelizeOptions {
        objects: ObjectSelection::Named(vec!["leg".into(), "chair".into()]),
        ..SurfelizeOptions::new(H)
    };
    let scene = surfelize(&mesh, &opts).unwrap();
    let names: Vec<&str> = scene.components.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["background", "chair", "leg"]); // file order
    assert!(near(count(&scene, "background"), 2.0)); // the unnamed quad and the table
    assert!(near(count(&scene, "leg"), 1.0));

    let opts = SurfelizeOptions {
        objects: ObjectSelection::None,
        ..SurfelizeOptions::new(H)
    };
    let scene = surfelize(&mesh, &opts).unwrap();
    assert_eq!(scene.components.len(), 1);
    assert!(near(count(&scene, "background"), 4.0));

    for (wanted, says) in [("sofa", "expected a node of that name"), ("Camera", "no")] {
        let opts = SurfelizeOptions {
            objects: ObjectSelection::Named(vec!["chair".into(), wanted.into()]),
            ..SurfelizeOptions::new(H)
        };
        let err = surfelize(&mesh, &opts).unwrap_err();
        let msg = err.to_string();
        assert!(matches!(err, Error::Invalid { .. }) && err.is_user_error());
        assert!(
            msg.contains("objects.gltf") && msg.contains(wanted) && msg.contains(says),
            "{msg}"
        );
    }
}

#[test]
fn deterministic_for_a_seed_and_any_thread_count() {
    let dir = tempfile::tempdir().unwrap();
    let doc = one_node(Some("ball"), uv_sphere(0.5, 12, 24));
    let path = dir.path().join("s.gltf");
    write_gltf(&doc, &path);
    let mesh = read_mesh_scene(&path).unwrap();
    let opts = SurfelizeOptions {
        seed: 5,
        sh_degree: 2,
        ..SurfelizeOptions::new(H)
    };
    let a = surfelize(&mesh, &opts).unwrap();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let b = pool.install(|| surfelize(&mesh, &opts).unwrap());
    assert_eq!(a, b);
    let s = &a.components[1].surfels;
    assert_eq!(s.sh_degree, 2);
    assert!(s
        .sh
        .chunks(9)
        .all(|c| c[1..].iter().all(|x| *x == [0.0; 3])));
    let c = surfelize(
        &mesh,
        &SurfelizeOptions {
            seed: 6,
            ..opts.clone()
        },
    )
    .unwrap();
    assert_ne!(
        a.components[1].surfels.position,
        c.components[1].surfels.position
    );
    let (na, nc) = (a.surfel_count() as f64, c.surfel_count() as f64);
    assert!((na - nc).abs() < 0.03 * na);
}

#[test]
fn small_triangles_get_surfels_in_proportion_to_area() {
    // A 1 m² quad cut into 100 × 100 cells (20 000 triangles of 5·10⁻⁵ m², an eighth of h²),
    // tilted so that it is not axis-aligned: the count still follows the area.
    let dir = tempfile::tempdir().unwrap();
    let mut doc = one_node(None, grid_quad(-0.5, -0.5, 1.0, 100));
    doc.roots[0].rotation = Some(Quat::from_rotation_x(0.3).to_array());
    let (_, scene) = surfelize_doc(&doc, dir.path(), "fine.gltf", &SurfelizeOptions::new(H));
    let n = scene.surfel_count() as f64;
    assert!((n - 2500.0).abs() < 0.03 * 2500.0, "{n}");
    let s = all_surfels(&scene);
    let near = Near::new(&s, 0.2);
    let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
    let r = Quat::from_rotation_x(0.3).as_dquat();
    let l = leak((0..500).map(|_| {
        let p = r * DVec3::new(
            rng.random::<f64>() * 0.9 - 0.45,
            0.0,
            rng.random::<f64>() * 0.9 - 0.45,
        );
        let d = -(r * DVec3::Y);
        transmittance(&near, p - d * 0.5, d, p)
    }));
    println!(
        "leak finely tessellated tilted quad: mean {:.2e}, p99 {:.2e}, max {:.2e}",
        l.mean, l.p99, l.max
    );
    assert!(l.mean < 1e-3 && l.max < 0.02);
}

#[test]
fn bad_input_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing.glb");
    let err = read_mesh_scene(&missing).unwrap_err();
    assert!(
        err.is_user_error() && err.to_string().contains("missing.glb"),
        "{err}"
    );

    let junk = dir.path().join("junk.gltf");
    std::fs::write(&junk, b"this is not glTF").unwrap();
    let err = read_mesh_scene(&junk).unwrap_err();
    assert!(matches!(err, Error::Invalid { .. }), "{err}");
    assert!(
        err.to_string().contains("junk.gltf") && err.to_string().contains("glTF"),
        "{err}"
    );

    // Only a POINTS primitive and a mesh-less node: no triangles.
    let mut p = grid_quad(0.0, 0.0, 1.0, 1);
    p.mode = Some(0);
    let mut doc = one_node(Some("points"), p);
    doc.roots.push(Node {
        name: Some("empty".into()),
        ..Default::default()
    });
    let pts = dir.path().join("points.gltf");
    write_gltf(&doc, &pts);
    let err = read_mesh_scene(&pts).unwrap_err();
    assert!(matches!(err, Error::Invalid { .. }));
    assert!(
        err.to_string().contains("points.gltf") && err.to_string().contains("triangle"),
        "{err}"
    );

    // Bad options.
    let quad = dir.path().join("quad.gltf");
    write_gltf(&one_node(None, grid_quad(0.0, 0.0, 1.0, 1)), &quad);
    let mesh = read_mesh_scene(&quad).unwrap();
    for opts in [
        SurfelizeOptions::new(0.0),
        SurfelizeOptions::new(f32::NAN),
        SurfelizeOptions {
            opacity: 1.5,
            ..SurfelizeOptions::new(H)
        },
        SurfelizeOptions {
            sh_degree: 4,
            ..SurfelizeOptions::new(H)
        },
        SurfelizeOptions::new(1e-7), // 10¹⁴ surfels
    ] {
        assert!(surfelize(&mesh, &opts).unwrap_err().is_user_error());
    }
    // A spacing far larger than the surface yields nothing: an error, not an empty scene.
    let tiny = dir.path().join("tiny.gltf");
    write_gltf(&one_node(None, grid_quad(0.0, 0.0, 1e-3, 1)), &tiny);
    let mesh = read_mesh_scene(&tiny).unwrap();
    let err = surfelize(&mesh, &SurfelizeOptions::new(1.0)).unwrap_err();
    assert!(err.to_string().contains("tiny.gltf"), "{err}");
}
