//! Slow, obviously correct references for the tests: every surfel of every component, placed in
//! the world (eq. state-assembly), intersected in f64, sorted, composited. No BVH, no batches,
//! no frames other than the world. The parameters are f64 ([`RefComponent`]) so that central
//! differences of [`composite_ref`] are accurate enough to check the backward pass.

use super::record::SurfaceRecord;
use super::{CUTOFF, MAX_OPACITY, MIN_ALPHA, T_MIN};
use crate::scene::{Rigid, Scene, Surfels};
use glam::{DMat3, DQuat, DVec3};

/// One component's surfels, component frame, f64, and its placement `x ↦ R(rotation) x +
/// translation`. Quaternions are (x, y, z, w), normalised before use, like the stored ones.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RefComponent {
    pub position: Vec<[f64; 3]>,
    pub rotation: Vec<[f64; 4]>,
    pub scale: Vec<[f64; 2]>,
    pub opacity: Vec<f64>,
    pub base_color: Vec<[f64; 3]>,
    pub metallic: Vec<f64>,
    pub roughness: Vec<f64>,
    pub placement_rotation: [f64; 4],
    pub placement_translation: [f64; 3],
}

impl RefComponent {
    pub fn new(s: &Surfels, transform: &Rigid) -> Self {
        RefComponent {
            position: s.position.iter().map(|v| v.map(f64::from)).collect(),
            rotation: s.rotation.iter().map(|v| v.map(f64::from)).collect(),
            scale: s.scale.iter().map(|v| v.map(f64::from)).collect(),
            opacity: s.opacity.iter().map(|&v| v as f64).collect(),
            base_color: s.base_color.iter().map(|v| v.map(f64::from)).collect(),
            metallic: s.metallic.iter().map(|&v| v as f64).collect(),
            roughness: s.roughness.iter().map(|&v| v as f64).collect(),
            placement_rotation: transform.rotation.map(f64::from),
            placement_translation: transform.translation.map(f64::from),
        }
    }

    pub fn len(&self) -> usize {
        self.position.len()
    }

    pub fn is_empty(&self) -> bool {
        self.position.is_empty()
    }

    /// The placement's left increment `x ↦ exp([ω]×) R x + t + δ` (as `scene::transform::perturb`).
    pub fn perturb(&mut self, delta: [f64; 3], omega: [f64; 3]) {
        let q = DQuat::from_scaled_axis(DVec3::from_array(omega)) * quat(self.placement_rotation);
        self.placement_rotation = q.normalize().to_array();
        for (t, dt) in self.placement_translation.iter_mut().zip(delta) {
            *t += dt;
        }
    }
}

/// [`SurfaceRecord`] in f64.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RefRecord {
    pub depth: f64,
    pub position: [f64; 3],
    pub normal: [f64; 3],
    pub base_color: [f64; 3],
    pub metallic: f64,
    pub roughness: f64,
    pub alpha: f64,
    pub hits: u32,
}

impl RefRecord {
    /// The sums in a fixed order: depth, position, normal, base colour, metallic, roughness,
    /// alpha (the order of `RecordGrad`'s fields).
    pub fn sums(&self) -> [f64; 13] {
        let (p, n, a) = (self.position, self.normal, self.base_color);
        [
            self.depth,
            p[0],
            p[1],
            p[2],
            n[0],
            n[1],
            n[2],
            a[0],
            a[1],
            a[2],
            self.metallic,
            self.roughness,
            self.alpha,
        ]
    }
}

struct RefHit {
    t: f64,
    component: usize,
    index: usize,
    alpha: f64,
    n: DVec3,
}

fn quat(q: [f64; 4]) -> DQuat {
    DQuat::from_xyzw(q[0], q[1], q[2], q[3]).normalize()
}

/// All hits with t_min < t < t_max, sorted by (t, component, index).
fn hits(components: &[RefComponent], o: DVec3, d: DVec3, t_min: f64, t_max: f64) -> Vec<RefHit> {
    let mut out = Vec::new();
    for (c, s) in components.iter().enumerate() {
        let rot = quat(s.placement_rotation);
        let trans = DVec3::from_array(s.placement_translation);
        for i in 0..s.len() {
            let mu = rot * DVec3::from_array(s.position[i]) + trans;
            let r = DMat3::from_quat(rot * quat(s.rotation[i]));
            let (tu, tv, n) = (r.x_axis, r.y_axis, r.z_axis);
            let dn = d.dot(n);
            if dn == 0.0 {
                continue;
            }
            let t = (mu - o).dot(n) / dn;
            if !(t > t_min && t < t_max) {
                continue;
            }
            let x = o + t * d;
            let xi_u = (x - mu).dot(tu) / s.scale[i][0];
            let xi_v = (x - mu).dot(tv) / s.scale[i][1];
            let r2 = xi_u * xi_u + xi_v * xi_v;
            if r2 > (CUTOFF * CUTOFF) as f64 {
                continue;
            }
            let alpha = (s.opacity[i] * (-0.5 * r2).exp()).min(MAX_OPACITY as f64);
            if alpha < MIN_ALPHA as f64 {
                continue;
            }
            out.push(RefHit {
                t,
                component: c,
                index: i,
                alpha,
                n,
            });
        }
    }
    out.sort_by(|a, b| {
        a.t.total_cmp(&b.t)
            .then(a.component.cmp(&b.component))
            .then(a.index.cmp(&b.index))
    });
    out
}

fn ref_components(scene: &Scene, transforms: &[Rigid]) -> Vec<RefComponent> {
    scene
        .components
        .iter()
        .zip(transforms)
        .map(|(c, tf)| RefComponent::new(&c.surfels, tf))
        .collect()
}

/// eq. surface-record by brute force in f64: all hits sorted, composited until the
/// transmittance falls below [`T_MIN`], normals turned to face the ray.
pub fn composite_ref(
    components: &[RefComponent],
    origin: [f64; 3],
    dir: [f64; 3],
    t_min: f64,
    t_max: f64,
) -> RefRecord {
    let (o, d) = (DVec3::from_array(origin), DVec3::from_array(dir));
    let mut tr = 1.0f64;
    let mut r = RefRecord::default();
    let (mut position, mut normal, mut base_color) = (DVec3::ZERO, DVec3::ZERO, DVec3::ZERO);
    for h in hits(components, o, d, t_min, t_max) {
        let w = tr * h.alpha;
        let s = &components[h.component];
        let n = if h.n.dot(d) > 0.0 { -h.n } else { h.n };
        r.depth += w * h.t;
        position += w * (o + h.t * d);
        normal += w * n;
        base_color += w * DVec3::from_array(s.base_color[h.index]);
        r.metallic += w * s.metallic[h.index];
        r.roughness += w * s.roughness[h.index];
        r.alpha += w;
        r.hits += 1;
        tr *= 1.0 - h.alpha;
        if tr < T_MIN as f64 {
            break;
        }
    }
    r.position = position.to_array();
    r.normal = normal.to_array();
    r.base_color = base_color.to_array();
    r
}

/// [`composite_ref`] of a scene placed by `transforms`, rounded to a [`SurfaceRecord`].
pub fn composite_brute(
    scene: &Scene,
    transforms: &[Rigid],
    origin: [f32; 3],
    dir: [f32; 3],
    t_min: f32,
    t_max: f32,
) -> SurfaceRecord {
    let r = composite_ref(
        &ref_components(scene, transforms),
        origin.map(f64::from),
        dir.map(f64::from),
        t_min as f64,
        t_max as f64,
    );
    SurfaceRecord {
        depth: r.depth as f32,
        position: r.position.map(|x| x as f32),
        normal: r.normal.map(|x| x as f32),
        base_color: r.base_color.map(|x| x as f32),
        metallic: r.metallic as f32,
        roughness: r.roughness as f32,
        alpha: r.alpha as f32,
        hits: r.hits,
    }
}

/// Π (1 − α_eff) over every hit with t_min < t < t_max, without early exit.
pub fn transmittance_brute(
    scene: &Scene,
    transforms: &[Rigid],
    origin: [f32; 3],
    dir: [f32; 3],
    t_min: f32,
    t_max: f32,
) -> f64 {
    hits(
        &ref_components(scene, transforms),
        DVec3::new(origin[0] as f64, origin[1] as f64, origin[2] as f64),
        DVec3::new(dir[0] as f64, dir[1] as f64, dir[2] as f64),
        t_min as f64,
        t_max as f64,
    )
    .iter()
    .map(|h| 1.0 - h.alpha)
    .product()
}
