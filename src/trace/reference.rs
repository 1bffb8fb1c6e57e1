//! Slow, obviously correct references for the tests: every surfel of every component, placed in
//! the world (eq. state-assembly), intersected in f64, sorted, composited. No BVH, no batches,
//! no frames other than the world.

use super::record::SurfaceRecord;
use super::{CUTOFF, MAX_OPACITY, MIN_ALPHA, T_MIN};
use crate::scene::{Rigid, Scene};
use glam::{DMat3, DQuat, DVec3};

struct RefHit {
    t: f64,
    component: usize,
    index: usize,
    alpha: f64,
    n: DVec3,
}

fn d3(v: [f32; 3]) -> DVec3 {
    DVec3::new(v[0] as f64, v[1] as f64, v[2] as f64)
}

fn dq(q: [f32; 4]) -> DQuat {
    DQuat::from_xyzw(q[0] as f64, q[1] as f64, q[2] as f64, q[3] as f64).normalize()
}

/// All hits with t_min < t < t_max, sorted by (t, component, index).
fn hits(
    scene: &Scene,
    transforms: &[Rigid],
    o: DVec3,
    d: DVec3,
    t_min: f64,
    t_max: f64,
) -> Vec<RefHit> {
    let mut out = Vec::new();
    for (c, (comp, tf)) in scene.components.iter().zip(transforms).enumerate() {
        let s = &comp.surfels;
        let rot = dq(tf.rotation);
        for i in 0..s.len() {
            let mu = rot * d3(s.position[i]) + d3(tf.translation);
            let r = DMat3::from_quat(rot * dq(s.rotation[i]));
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
            let xi_u = (x - mu).dot(tu) / s.scale[i][0] as f64;
            let xi_v = (x - mu).dot(tv) / s.scale[i][1] as f64;
            let r2 = xi_u * xi_u + xi_v * xi_v;
            if r2 > (CUTOFF * CUTOFF) as f64 {
                continue;
            }
            let alpha = (s.opacity[i] as f64 * (-0.5 * r2).exp()).min(MAX_OPACITY as f64);
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

/// eq. surface-record by brute force: all hits sorted, composited until the transmittance
/// falls below [`T_MIN`], normals turned to face the ray.
pub fn composite_brute(
    scene: &Scene,
    transforms: &[Rigid],
    origin: [f32; 3],
    dir: [f32; 3],
    t_min: f32,
    t_max: f32,
) -> SurfaceRecord {
    let (o, d) = (d3(origin), d3(dir));
    let mut tr = 1.0f64;
    let mut depth = 0.0;
    let mut position = DVec3::ZERO;
    let mut normal = DVec3::ZERO;
    let mut base_color = DVec3::ZERO;
    let (mut metallic, mut roughness, mut alpha) = (0.0, 0.0, 0.0);
    let mut count = 0;
    for h in hits(scene, transforms, o, d, t_min as f64, t_max as f64) {
        let w = tr * h.alpha;
        let s = &scene.components[h.component].surfels;
        let n = if h.n.dot(d) > 0.0 { -h.n } else { h.n };
        depth += w * h.t;
        position += w * (o + h.t * d);
        normal += w * n;
        base_color += w * d3(s.base_color[h.index]);
        metallic += w * s.metallic[h.index] as f64;
        roughness += w * s.roughness[h.index] as f64;
        alpha += w;
        count += 1;
        tr *= 1.0 - h.alpha;
        if tr < T_MIN as f64 {
            break;
        }
    }
    SurfaceRecord {
        depth: depth as f32,
        position: position.as_vec3().to_array(),
        normal: normal.as_vec3().to_array(),
        base_color: base_color.as_vec3().to_array(),
        metallic: metallic as f32,
        roughness: roughness as f32,
        alpha: alpha as f32,
        hits: count,
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
        scene,
        transforms,
        d3(origin),
        d3(dir),
        t_min as f64,
        t_max as f64,
    )
    .iter()
    .map(|h| 1.0 - h.alpha)
    .product()
}
