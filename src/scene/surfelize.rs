//! `surfelize`: an ordinary glTF mesh scene → a surfel [`Scene`] with the meshes' true
//! materials, the oracle input that lets the renderer be checked against Cycles.
//!
//! **Sampling.** Every triangle is sampled on a square lattice of pitch h (the spacing) lying
//! in its plane, each lattice site jittered by up to ±[`JITTER`]·h per axis; the sites that fall
//! inside the triangle become surfels (their centres are barycentric combinations of the
//! vertices, so they lie exactly on the surface). The lattice is not chosen per triangle but
//! by a rule of the plane, so that neighbouring triangles continue one another's lattice and
//! the seams between them need no special care:
//! - its axes are a fixed frame for the dominant axis of the face normal (±X, ±Y, ±Z; the sign
//!   of the normal is ignored), turned by the smallest rotation onto the face normal;
//! - its origin is the projection onto the plane of an anchor: the point of a 3D grid of pitch
//!   [`ANCHOR_CELL`]·h (offset by the seed) nearest the triangle's centroid;
//! - the jitter of a site is a hash of the seed and of the site's world position rounded to
//!   the grid.
//!
//! Coplanar triangles in axis-aligned planes (floors, walls) thus share one lattice exactly;
//! neighbours on a finely tessellated smooth surface share it up to a shift of about
//! `ANCHOR_CELL·h × (angle between them)`; elsewhere a seam behaves like a random phase. In
//! every case a triangle receives `area / h²` sites on average (for a triangle smaller than
//! h² this is the probability that it gets one), so the count is `area / h²` and no surface is
//! skipped. Everything is a pure function of the triangle and the seed: results do not depend
//! on the thread count.
//!
//! **Orientation.** Normal = interpolated vertex (shading) normal, tangent = the triangle's first
//! edge projected onto the tangent plane, bitangent = normal × tangent: R(q) has columns
//! (t, b, n), a right-handed rotation.
//!
//! **Size and opacity.** See [`SIGMA_PER_SPACING`].
//!
//! **Materials.** base colour = `baseColorFactor` × `baseColorTexture` (sRGB decoded) ×
//! `COLOR_0`; metallic = `metallicFactor` × texture B; roughness = `roughnessFactor` × texture G;
//! all clamped to [0, 1], textures sampled at the surfel centre's UV with the sampler's wrap
//! modes and filter. `alphaMode: MASK` drops the surfels whose alpha is below the cutoff. The
//! SH appearance is set so that it shows the base colour: DC = (a − 0.5) / C₀, higher degrees 0.

use crate::error::{Error, Result};
use crate::scene::mesh::{MeshMaterial, MeshScene, MeshTriangle};
use crate::scene::Rigid;
use crate::scene::{sh_coeffs, Component, Scene, State, Surfels, BACKGROUND, MAX_SH_DEGREE, SH_C0};
use glam::{DMat3, DVec3, Mat3, Quat};
use rayon::prelude::*;

/// In-plane scale σ of every surfel, as a multiple of the spacing h: σ = 1.0 h.
///
/// The rule: the surface must be opaque, i.e. the transmittance T(x) = Π (1 − min(0.99,
/// α·exp(−½|ξ_i|²))) composited over the surfels around any point x of the surface (terms
/// below 1/255 and beyond |ξ| = 3 dropped, as the ray tracer does) must be negligible. On a
/// square lattice of pitch h with α = 0.99 the worst point is the centre of a cell, h/√2 from
/// its four nearest surfels:
///
/// | σ / h | T at cell centre | T at edge midpoint | T at a site |
/// |---|---|---|---|
/// | 0.7 | 1.4·10⁻² | 9.9·10⁻³ | 9.2·10⁻⁴ |
/// | 0.9 | 5.6·10⁻⁴ | 4.0·10⁻⁴ | 5.9·10⁻⁵ |
/// | 1.0 | 8.0·10⁻⁵ | 6.3·10⁻⁵ | 1.1·10⁻⁵ |
///
/// The jitter and, above all, the seams between non-coplanar triangles (where two unrelated
/// lattice phases meet, leaving gaps up to ~2 h wide) are worse than the lattice: measured by
/// `tests/surfelize.rs` on a UV sphere (4000 rays), σ = 0.9 h gives mean T 7·10⁻⁴ but max
/// 3.8·10⁻², σ = 1.0 h mean 1.3·10⁻⁴ and max 1.0·10⁻², σ = 1.1 h mean 2·10⁻⁵ and max 2·10⁻³.
/// 1.0 is the smallest round factor with max T ≤ 0.02 everywhere; larger σ only blurs the
/// materials more. Open boundaries of a surface are not extended: coverage fades there over
/// ~σ, as the surface ends.
pub const SIGMA_PER_SPACING: f32 = 1.0;

/// Jitter of a lattice site, as a fraction of the spacing, per axis (uniform in ±JITTER).
pub const JITTER: f64 = 0.2;

/// Pitch of the grid of lattice anchors, in spacings (see the module documentation).
pub const ANCHOR_CELL: f64 = 16.0;

/// Refuses runs that would make more surfels than this (the spacing is far too small).
pub const MAX_SURFELS: f64 = 1.0e9;

/// Which nodes become object components.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub enum ObjectSelection {
    /// Every named top-level node of the default scene that has triangles (below it) is an
    /// object; unnamed ones, and one named `background`, are background.
    #[default]
    AllNamedRoots,
    /// Only the nodes of these names (at any depth of the default scene); a name the scene
    /// lacks, or whose node has no triangles, is an error naming the file and the node.
    Named(Vec<String>),
    /// Everything is background.
    None,
}

/// Options of [`surfelize`].
#[derive(Clone, Debug, PartialEq)]
pub struct SurfelizeOptions {
    /// Metres between neighbouring surfels (the lattice pitch h).
    pub spacing: f32,
    pub objects: ObjectSelection,
    /// Peak opacity α of every surfel, in (0, 1]. Default 0.99, the compositing cap of the
    /// renderer (formats.md `maxOpacity`): more changes nothing, and [`SIGMA_PER_SPACING`] is
    /// chosen for it. Less leaks light: on the lattice, T at a cell centre is 8·10⁻⁵ at 0.99,
    /// 3.4·10⁻⁴ at 0.9, 1.3·10⁻³ at 0.8 (and seams are worse, see [`SIGMA_PER_SPACING`]).
    pub opacity: f32,
    /// SH degree of the splatting appearance, 0..=3 (default 0); higher coefficients are 0.
    pub sh_degree: u8,
    /// Seed of the lattice placement and jitter.
    pub seed: u64,
}

impl Default for SurfelizeOptions {
    fn default() -> Self {
        SurfelizeOptions {
            spacing: 0.01,
            objects: ObjectSelection::AllNamedRoots,
            opacity: 0.99,
            sh_degree: 0,
            seed: 0,
        }
    }
}

impl SurfelizeOptions {
    /// Defaults with the given spacing (metres).
    pub fn new(spacing: f32) -> Self {
        SurfelizeOptions {
            spacing,
            ..Default::default()
        }
    }
}

/// Turns a mesh scene into a surfel scene: component 0 "background", then one component per
/// selected node (named after it, ids 1.. in the order the nodes appear in the file, depth
/// first; nodes of the same name share one component); a node's descendants belong to its
/// component unless they are selected themselves. One state "state0" with identity transforms
/// and no environment; surfels in world space.
pub fn surfelize(mesh_scene: &MeshScene, opts: &SurfelizeOptions) -> Result<Scene> {
    let file = &mesh_scene.path;
    if !(opts.spacing.is_finite() && opts.spacing > 0.0) {
        return Err(Error::Usage(format!(
            "surfelize: spacing: expected a positive number of metres, found {}",
            opts.spacing
        )));
    }
    if !(opts.opacity > 0.0 && opts.opacity <= 1.0) {
        return Err(Error::Usage(format!(
            "surfelize: opacity: expected a value in (0, 1], found {}",
            opts.opacity
        )));
    }
    if opts.sh_degree > MAX_SH_DEGREE {
        return Err(Error::Usage(format!(
            "surfelize: SH degree: expected 0..=3, found {}",
            opts.sh_degree
        )));
    }
    let h = opts.spacing as f64;
    let expected = mesh_scene.area() / (h * h);
    if expected > MAX_SURFELS {
        return Err(Error::Usage(format!(
            "surfelize: spacing: {} m over {:.1} m² of surface would make {expected:.3e} surfels \
             (at most {MAX_SURFELS:.0e}); choose a larger spacing",
            opts.spacing,
            mesh_scene.area()
        )));
    }

    let (names, node_component) = assign_components(mesh_scene, &opts.objects)?;

    // Triangles of each component, in file order.
    let mut per_component: Vec<Vec<&MeshTriangle>> = vec![Vec::new(); names.len()];
    for (node, c) in mesh_scene.nodes.iter().zip(&node_component) {
        per_component[*c].extend(&node.triangles);
    }

    let params = Params::new(opts);
    let mut components = Vec::with_capacity(names.len());
    for (id, (name, tris)) in names.into_iter().zip(per_component).enumerate() {
        let lattices: Vec<Option<Lattice>> =
            tris.par_iter().map(|t| Lattice::new(t, &params)).collect();
        let chunks: Vec<Vec<Sample>> = work_items(&lattices)
            .into_par_iter()
            .map(|(first, end, rows)| {
                let mut out = Vec::new();
                for k in first..end {
                    if let Some(l) = &lattices[k] {
                        let rows = rows.unwrap_or(l.i);
                        sample_rows(tris[k], l, rows, mesh_scene, &params, &mut out);
                    }
                }
                out
            })
            .collect();
        let n: usize = chunks.iter().map(Vec::len).sum();
        let mut surfels = Surfels::with_sh_degree(opts.sh_degree);
        reserve(&mut surfels, n);
        let sigma = opts.spacing * SIGMA_PER_SPACING;
        let mut sh = vec![[0.0f32; 3]; sh_coeffs(opts.sh_degree)];
        for s in chunks.iter().flatten() {
            sh[0] = s.base_color.map(|a| (a - 0.5) / SH_C0);
            surfels.push(
                s.position,
                s.rotation,
                [sigma, sigma],
                opts.opacity,
                &sh,
                s.base_color,
                s.metallic,
                s.roughness,
            );
        }
        components.push(Component {
            name,
            id: id as u32,
            surfels,
        });
    }

    if components.iter().all(|c| c.surfels.is_empty()) {
        return Err(Error::invalid(
            file,
            "meshes",
            format!(
                "expected surface to sample: {:.3e} m² of triangles at spacing {} m gave no surfels",
                mesh_scene.area(),
                opts.spacing
            ),
        ));
    }
    let n = components.len();
    let scene = Scene {
        components,
        states: vec![State {
            name: "state0".into(),
            transforms: vec![Rigid::IDENTITY; n],
            environment: None,
        }],
        reference_state: 0,
        environments: Vec::new(),
    };
    scene.validate(file)?;
    Ok(scene)
}

fn reserve(s: &mut Surfels, n: usize) {
    s.position.reserve(n);
    s.rotation.reserve(n);
    s.scale.reserve(n);
    s.opacity.reserve(n);
    s.sh.reserve(n * s.sh_stride());
    s.base_color.reserve(n);
    s.metallic.reserve(n);
    s.roughness.reserve(n);
}

/// Component names (index = id) and the component of every node.
fn assign_components(
    mesh: &MeshScene,
    selection: &ObjectSelection,
) -> Result<(Vec<String>, Vec<usize>)> {
    let file = &mesh.path;
    let nodes = &mesh.nodes;
    // Whether each node's subtree holds triangles (children come after parents).
    let mut has_tris: Vec<bool> = nodes.iter().map(|n| !n.triangles.is_empty()).collect();
    for i in (0..nodes.len()).rev() {
        if let (true, Some(p)) = (has_tris[i], nodes[i].parent) {
            has_tris[p] = true;
        }
    }
    let selected: Vec<bool> = match selection {
        ObjectSelection::None => vec![false; nodes.len()],
        ObjectSelection::AllNamedRoots => nodes
            .iter()
            .zip(&has_tris)
            .map(|(n, &t)| {
                n.parent.is_none()
                    && t
                    && n.name
                        .as_deref()
                        .is_some_and(|s| !s.is_empty() && s != BACKGROUND)
            })
            .collect(),
        ObjectSelection::Named(wanted) => {
            for w in wanted {
                if w == BACKGROUND {
                    return Err(Error::invalid(
                        file,
                        format!("objects: node \"{w}\""),
                        "\"background\" is the name of component 0; rename the node",
                    ));
                }
                let found: Vec<usize> = (0..nodes.len())
                    .filter(|&i| nodes[i].name.as_deref() == Some(w.as_str()))
                    .collect();
                if found.is_empty() {
                    let mut known: Vec<&str> =
                        nodes.iter().filter_map(|n| n.name.as_deref()).collect();
                    known.dedup();
                    return Err(Error::invalid(
                        file,
                        format!("objects: node \"{w}\""),
                        format!(
                            "expected a node of that name in the default scene; it has {known:?}"
                        ),
                    ));
                }
                if !found.iter().any(|&i| has_tris[i]) {
                    return Err(Error::invalid(
                        file,
                        format!("objects: node \"{w}\""),
                        "expected a node with triangles (in it or below it); it has none",
                    ));
                }
            }
            nodes
                .iter()
                .map(|n| n.name.as_ref().is_some_and(|s| wanted.contains(s)))
                .collect()
        }
    };
    let mut names = vec![BACKGROUND.to_string()];
    let mut of_node = Vec::with_capacity(nodes.len());
    for (i, n) in nodes.iter().enumerate() {
        let c = if selected[i] {
            let name = n.name.clone().expect("selected nodes are named");
            match names.iter().position(|x| *x == name) {
                Some(k) => k,
                None => {
                    names.push(name);
                    names.len() - 1
                }
            }
        } else {
            n.parent.map_or(0, |p| of_node[p])
        };
        of_node.push(c);
    }
    Ok((names, of_node))
}

/// Per-run constants of the sampler.
struct Params {
    h: f64,
    seed: u64,
    /// Offset of the anchor grid, in [0, cell)³.
    anchor_offset: DVec3,
    cell: f64,
}

impl Params {
    fn new(opts: &SurfelizeOptions) -> Self {
        let h = opts.spacing as f64;
        let cell = ANCHOR_CELL * h;
        let r = |k: u64| unit(splitmix(opts.seed ^ splitmix(k)));
        Params {
            h,
            seed: opts.seed,
            anchor_offset: DVec3::new(r(1), r(2), r(3)) * cell,
            cell,
        }
    }
}

/// One surfel before assembly.
struct Sample {
    position: [f32; 3],
    rotation: [f32; 4],
    base_color: [f32; 3],
    metallic: f32,
    roughness: f32,
}

/// SplitMix64 finaliser: a good 64-bit hash.
fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Uniform in [0, 1) from the top 53 bits.
fn unit(x: u64) -> f64 {
    (x >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// The lattice axes of a plane with unit normal `n` (see the module documentation): the fixed
/// frame of the dominant axis, turned by the smallest rotation onto ±n.
fn lattice_frame(n: DVec3) -> (DVec3, DVec3) {
    let a = n.abs();
    let k = if a.x >= a.y && a.x >= a.z {
        0
    } else if a.y >= a.z {
        1
    } else {
        2
    };
    let n = if n[k] < 0.0 { -n } else { n };
    // Right-handed (t0, b0, axis) per dominant axis.
    let (t0, b0, axis) = match k {
        0 => (DVec3::Y, DVec3::Z, DVec3::X),
        1 => (DVec3::Z, DVec3::X, DVec3::Y),
        _ => (DVec3::X, DVec3::Y, DVec3::Z),
    };
    // Rodrigues with v = axis × n, c = axis · n ≥ 1/√3: R x = c x + v × x + v (v · x) / (1 + c).
    let v = axis.cross(n);
    let c = axis.dot(n);
    let rot = |x: DVec3| c * x + v.cross(x) + v * (v.dot(x) / (1.0 + c));
    (rot(t0), rot(b0))
}

/// A triangle's lattice: everything [`sample_rows`] needs.
struct Lattice {
    face: DVec3,
    origin: DVec3,
    t0: DVec3,
    b0: DVec3,
    /// Vertices in lattice units.
    q: [[f64; 2]; 3],
    d1: [f64; 2],
    d2: [f64; 2],
    det: f64,
    /// Site index ranges (inclusive) covering the triangle's bounds widened by the jitter.
    i: (i64, i64),
    j: (i64, i64),
}

impl Lattice {
    /// None for a degenerate triangle.
    fn new(tri: &MeshTriangle, p: &Params) -> Option<Lattice> {
        let v = tri.position.map(|x| DVec3::from_array(x.map(f64::from)));
        let face = (v[1] - v[0]).cross(v[2] - v[0]);
        let len = face.length();
        if !(len > 0.0 && len.is_finite()) {
            return None;
        }
        let face = face / len;
        let (t0, b0) = lattice_frame(face);
        let h = p.h;
        let centroid = (v[0] + v[1] + v[2]) / 3.0;
        let anchor = p.anchor_offset + ((centroid - p.anchor_offset) / p.cell).round() * p.cell;
        let origin = anchor - face * (anchor - v[0]).dot(face);
        let q = v.map(|x| {
            let d = x - origin;
            [d.dot(t0) / h, d.dot(b0) / h]
        });
        let lo = |k: usize| q[0][k].min(q[1][k]).min(q[2][k]) - JITTER;
        let hi = |k: usize| q[0][k].max(q[1][k]).max(q[2][k]) + JITTER;
        // 2D barycentrics: λ1 = cross(p − q0, q2 − q0) / D, λ2 = cross(q1 − q0, p − q0) / D.
        let d1 = [q[1][0] - q[0][0], q[1][1] - q[0][1]];
        let d2 = [q[2][0] - q[0][0], q[2][1] - q[0][1]];
        let det = d1[0] * d2[1] - d1[1] * d2[0];
        if det == 0.0 || !det.is_finite() {
            return None;
        }
        Some(Lattice {
            face,
            origin,
            t0,
            b0,
            q,
            d1,
            d2,
            det,
            i: (lo(0).ceil() as i64, hi(0).floor() as i64),
            j: (lo(1).ceil() as i64, hi(1).floor() as i64),
        })
    }

    /// Sites in the bounds of row `i`.
    fn row_len(&self) -> i64 {
        (self.j.1 - self.j.0 + 1).max(0)
    }
}

/// Sites per parallel work item: a large triangle is split into bands of rows, small ones are
/// grouped, so that a room of a dozen huge triangles still uses every core.
const SITES_PER_ITEM: i64 = 16_384;

/// A parallel work item: (first triangle, end triangle, rows of the first triangle) — either a
/// band of rows of one triangle, or a run of whole triangles.
type WorkItem = (usize, usize, Option<(i64, i64)>);

/// The work items, in triangle order, so concatenating their results is deterministic.
fn work_items(lattices: &[Option<Lattice>]) -> Vec<WorkItem> {
    let mut items = Vec::new();
    let mut start = 0;
    let mut acc = 0i64;
    for (k, l) in lattices.iter().enumerate() {
        let Some(l) = l else { continue };
        let rows = (l.i.1 - l.i.0 + 1).max(0);
        let sites = rows * l.row_len();
        if sites > SITES_PER_ITEM {
            if start < k {
                items.push((start, k, None));
            }
            let band = (SITES_PER_ITEM / l.row_len().max(1)).max(1);
            let mut i = l.i.0;
            while i <= l.i.1 {
                let end = (i + band - 1).min(l.i.1);
                items.push((k, k + 1, Some((i, end))));
                i = end + 1;
            }
            start = k + 1;
            acc = 0;
        } else {
            acc += sites;
            if acc >= SITES_PER_ITEM {
                items.push((start, k + 1, None));
                start = k + 1;
                acc = 0;
            }
        }
    }
    if start < lattices.len() {
        items.push((start, lattices.len(), None));
    }
    items
}

/// Appends the surfels of rows `rows` (inclusive) of a triangle's lattice.
fn sample_rows(
    tri: &MeshTriangle,
    lat: &Lattice,
    rows: (i64, i64),
    mesh: &MeshScene,
    p: &Params,
    out: &mut Vec<Sample>,
) {
    let Lattice {
        face,
        origin,
        t0,
        b0,
        q,
        d1,
        d2,
        det,
        ..
    } = *lat;
    let (i0, i1) = rows;
    let (j0, j1) = lat.j;
    let h = p.h;
    let material = mesh.material(tri.material);
    for i in i0..=i1 {
        for j in j0..=j1 {
            // The site's world position, rounded to the anchor grid's lattice, keys its jitter
            // (so coplanar triangles with different anchors agree).
            let site = origin + t0 * (i as f64 * h) + b0 * (j as f64 * h);
            let key = ((site - p.anchor_offset) / h).round();
            let hsh = splitmix(
                p.seed
                    ^ splitmix(
                        (key.x as i64 as u64)
                            ^ splitmix((key.y as i64 as u64) ^ splitmix(key.z as i64 as u64)),
                    ),
            );
            let ju = (unit(hsh) * 2.0 - 1.0) * JITTER;
            let jv = (unit(splitmix(hsh)) * 2.0 - 1.0) * JITTER;
            let pu = i as f64 + ju - q[0][0];
            let pv = j as f64 + jv - q[0][1];
            let l1 = (pu * d2[1] - pv * d2[0]) / det;
            let l2 = (d1[0] * pv - d1[1] * pu) / det;
            let l0 = 1.0 - l1 - l2;
            if l0 < 0.0 || l1 < 0.0 || l2 < 0.0 {
                continue;
            }
            if let Some(s) = make_sample(tri, material, mesh, [l0, l1, l2], face) {
                out.push(s);
            }
        }
    }
}

/// The surfel at barycentric `l` of the triangle (None when alpha masking removes it).
fn make_sample(
    tri: &MeshTriangle,
    mat: &MeshMaterial,
    mesh: &MeshScene,
    l: [f64; 3],
    face: DVec3,
) -> Option<Sample> {
    let lerp3 = |a: [[f32; 3]; 3]| -> DVec3 {
        (0..3)
            .map(|k| DVec3::from_array(a[k].map(f64::from)) * l[k])
            .sum()
    };
    let position = lerp3(tri.position);
    let mut n = lerp3(tri.normal);
    n = if n.length_squared() > 1e-20 {
        n.normalize()
    } else {
        face
    };
    let e1 = DVec3::from_array(tri.position[1].map(f64::from))
        - DVec3::from_array(tri.position[0].map(f64::from));
    let mut t = e1 - n * n.dot(e1);
    if t.length_squared() < 1e-24 * e1.length_squared().max(1e-300) {
        t = n.any_orthonormal_vector();
    }
    let t = t.normalize();
    let b = n.cross(t);
    let m = Mat3::from_cols(t.as_vec3(), b.as_vec3(), n.as_vec3());
    debug_assert!((DMat3::from_cols(t, b, n).determinant() - 1.0).abs() < 1e-6);
    let rotation = Quat::from_mat3(&m).normalize().to_array();

    let uv = |set: u32| -> [f32; 2] {
        let a = tri.uv[set.min(1) as usize];
        let mut o = [0.0f64; 2];
        for k in 0..3 {
            o[0] += a[k][0] as f64 * l[k];
            o[1] += a[k][1] as f64 * l[k];
        }
        [o[0] as f32, o[1] as f32]
    };
    let mut color = [0.0f32; 4];
    for (k, c) in color.iter_mut().enumerate() {
        *c = (0..3).map(|v| tri.color[v][k] as f64 * l[v]).sum::<f64>() as f32;
    }
    let mut base = mat.base_color_factor;
    if let Some(slot) = &mat.base_color_texture {
        let tex = mesh.images[slot.image].sample(slot, uv(slot.tex_coord), true);
        for k in 0..4 {
            base[k] *= tex[k];
        }
    }
    for k in 0..4 {
        base[k] *= color[k];
    }
    if let Some(cut) = mat.alpha_cutoff {
        if base[3] < cut {
            return None;
        }
    }
    let (mut metallic, mut roughness) = (mat.metallic_factor, mat.roughness_factor);
    if let Some(slot) = &mat.metallic_roughness_texture {
        let tex = mesh.images[slot.image].sample(slot, uv(slot.tex_coord), false);
        roughness *= tex[1];
        metallic *= tex[2];
    }
    let clamp = |x: f32| {
        if x.is_finite() {
            x.clamp(0.0, 1.0)
        } else {
            0.0
        }
    };
    Some(Sample {
        position: position.as_vec3().to_array(),
        rotation,
        base_color: [clamp(base[0]), clamp(base[1]), clamp(base[2])],
        metallic: clamp(metallic),
        roughness: clamp(roughness),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn lattice_frame_is_orthonormal_and_ignores_normal_sign() {
        for n in [
            DVec3::X,
            DVec3::NEG_Y,
            DVec3::new(0.3, -0.5, 0.8).normalize(),
            DVec3::new(-0.7, 0.7, 0.1).normalize(),
        ] {
            let (t, b) = lattice_frame(n);
            let (t2, b2) = lattice_frame(-n);
            assert!((t - t2).length() < 1e-12 && (b - b2).length() < 1e-12);
            assert!((t.length() - 1.0).abs() < 1e-12 && (b.length() - 1.0).abs() < 1e-12);
            assert!(t.dot(b).abs() < 1e-12 && t.dot(n).abs() < 1e-12 && b.dot(n).abs() < 1e-12);
        }
        // Axis-aligned planes get axis-aligned lattices.
        let (t, b) = lattice_frame(DVec3::Y);
        assert_eq!((t, b), (DVec3::Z, DVec3::X));
    }

    #[test]
    fn hash_is_uniform_enough() {
        let n = 100_000u64;
        let mean = (0..n).map(|i| unit(splitmix(i))).sum::<f64>() / n as f64;
        assert!((mean - 0.5).abs() < 0.01);
    }

    #[test]
    fn vec3_roundtrip() {
        // Quaternion columns are (t, b, n).
        let n = Vec3::new(0.0, 0.0, 1.0);
        let m = Mat3::from_cols(Vec3::X, Vec3::Y, n);
        let q = Quat::from_mat3(&m);
        assert!((q * Vec3::Z - n).length() < 1e-6);
    }
}
