//! The slow, obvious f64 version of the splatting forward pass, for the tests: for every pixel,
//! intersect every surfel (ray–plane intersection in the world, then projection onto the scaled
//! tangent axes), apply 2DGS's low-pass filter, keep the hits, sort them by the same key as the
//! fast path (centre depth, then global index) and composite front to back. No tiles, no
//! rectangles, no affine tricks. Parameters are f64 so central differences of it are accurate.

use super::{sh, Placement, CUTOFF, FILTER_INV_VARIANCE, MAX_OPACITY, MIN_ALPHA, NEAR, T_MIN};
use crate::scene::Camera;
use glam::{DMat3, DQuat, DVec3};

/// One surfel in its component's frame, f64.
#[derive(Clone, Debug, PartialEq)]
pub struct RefSurfel {
    pub position: [f64; 3],
    /// (x, y, z, w), normalised before use.
    pub rotation: [f64; 4],
    pub scale: [f64; 2],
    pub opacity: f64,
    pub sh: Vec<[f64; 3]>,
}

/// Surfels and their placement `x ↦ R(rotation) x + translation`, f64.
#[derive(Clone, Debug, PartialEq)]
pub struct RefComponent {
    pub surfels: Vec<RefSurfel>,
    pub rotation: [f64; 4],
    pub translation: [f64; 3],
}

impl RefComponent {
    pub fn from_placement(p: &Placement) -> Self {
        let s = p.surfels;
        let surfels = (0..s.len())
            .map(|i| RefSurfel {
                position: s.position[i].map(f64::from),
                rotation: s.rotation[i].map(f64::from),
                scale: s.scale[i].map(f64::from),
                opacity: s.opacity[i] as f64,
                sh: s.sh_of(i).iter().map(|c| c.map(f64::from)).collect(),
            })
            .collect();
        RefComponent {
            surfels,
            rotation: p.transform.rotation.map(f64::from),
            translation: p.transform.translation.map(f64::from),
        }
    }
}

/// The maps of [`super::SplatImage`] in f64.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RefImage {
    pub width: u32,
    pub height: u32,
    pub color: Vec<[f64; 3]>,
    pub alpha: Vec<f64>,
    pub depth: Vec<f64>,
    pub median_depth: Vec<f64>,
    pub normal: Vec<[f64; 3]>,
}

fn quat(q: [f64; 4]) -> DQuat {
    DQuat::from_xyzw(q[0], q[1], q[2], q[3]).normalize()
}

/// A surfel placed in the world, with what does not depend on the pixel.
struct Placed {
    p: DVec3,
    tu: DVec3,
    tv: DVec3,
    n: DVec3,
    scale: [f64; 2],
    opacity: f64,
    color: [f64; 3],
    /// Facing the camera.
    normal: DVec3,
    depth: f64,
    /// Projected centre, pixels.
    c: [f64; 2],
}

struct Hit {
    key: (f64, usize),
    alpha: f64,
    z: f64,
    color: [f64; 3],
    normal: DVec3,
}

/// Renders with the camera's image size.
pub fn render(components: &[RefComponent], camera: &Camera) -> RefImage {
    let col = |c: usize| DVec3::from_array(camera.axis(c).map(f64::from));
    let (right, up, fwd, o) = (col(0), col(1), -col(2), col(3));
    let (fx, fy, cx, cy) = (
        camera.fl_x as f64,
        camera.fl_y as f64,
        camera.cx as f64,
        camera.cy as f64,
    );

    // Place every surfel (eq. state-assembly) and cull those whose centre is nearer than NEAR.
    let mut placed: Vec<Option<Placed>> = Vec::new();
    for comp in components {
        let rt = quat(comp.rotation);
        let t = DVec3::from_array(comp.translation);
        for s in &comp.surfels {
            let p = rt * DVec3::from_array(s.position) + t;
            let r = DMat3::from_quat(rt) * DMat3::from_quat(quat(s.rotation));
            let a = p - o;
            let depth = a.dot(fwd);
            // NaN depths (non-finite inputs) are culled too.
            if depth.is_nan() || depth < NEAR as f64 {
                placed.push(None);
                continue;
            }
            let (d, _) = sh::view_dir(o.to_array(), p.to_array());
            let color = sh::eval(d, &s.sh).map(|x| x.max(0.0));
            let n = r.z_axis;
            let normal = if n.dot(a) > 0.0 { -n } else { n };
            placed.push(Some(Placed {
                p,
                tu: r.x_axis,
                tv: r.y_axis,
                n,
                scale: s.scale,
                opacity: s.opacity,
                color,
                normal,
                depth,
                c: [cx + fx * a.dot(right) / depth, cy - fy * a.dot(up) / depth],
            }));
        }
    }

    let (w, h) = (camera.w, camera.h);
    let n = w as usize * h as usize;
    let mut img = RefImage {
        width: w,
        height: h,
        color: vec![[0.0; 3]; n],
        alpha: vec![0.0; n],
        depth: vec![0.0; n],
        median_depth: vec![0.0; n],
        normal: vec![[0.0; 3]; n],
    };
    let mut hits: Vec<Hit> = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let (u, v) = (x as f64 + 0.5, y as f64 + 0.5);
            // The same ray as Camera::ray, scaled so that d · fwd = 1: t is planar depth.
            let d = fwd + right * ((u - cx) / fx) - up * ((v - cy) / fy);
            hits.clear();
            for (index, s) in placed.iter().enumerate() {
                let Some(s) = s else { continue };
                // Ray–plane intersection, then the hit's offset on the scaled tangent axes.
                let t = (s.p - o).dot(s.n) / d.dot(s.n);
                let x_hit = o + t * d;
                let xi_u = (x_hit - s.p).dot(s.tu) / s.scale[0];
                let xi_v = (x_hit - s.p).dot(s.tv) / s.scale[1];
                let rho_3d = xi_u * xi_u + xi_v * xi_v;
                // 2DGS low-pass filter: G(|p − c| / σ), σ = √2/2 pixel.
                let (ex, ey) = (u - s.c[0], v - s.c[1]);
                let rho_2d = FILTER_INV_VARIANCE as f64 * (ex * ex + ey * ey);
                let (rho, z) = if rho_3d <= rho_2d {
                    (rho_3d, t)
                } else {
                    (rho_2d, s.depth)
                };
                if rho > (CUTOFF * CUTOFF) as f64 || z < NEAR as f64 {
                    continue;
                }
                let alpha = (s.opacity * (-0.5 * rho).exp()).min(MAX_OPACITY as f64);
                if alpha < MIN_ALPHA as f64 {
                    continue;
                }
                hits.push(Hit {
                    key: (s.depth, index),
                    alpha,
                    z,
                    color: s.color,
                    normal: s.normal,
                });
            }
            hits.sort_by(|a, b| a.key.partial_cmp(&b.key).expect("finite keys"));
            let i = (y * w + x) as usize;
            let mut tr = 1.0;
            let (mut color, mut alpha, mut depth, mut normal) = ([0.0; 3], 0.0, 0.0, DVec3::ZERO);
            for hit in &hits {
                let wgt = tr * hit.alpha;
                for (c, hc) in color.iter_mut().zip(hit.color) {
                    *c += wgt * hc;
                }
                alpha += wgt;
                depth += wgt * hit.z;
                normal += wgt * hit.normal;
                if tr > 0.5 {
                    img.median_depth[i] = hit.z;
                }
                tr *= 1.0 - hit.alpha;
                if tr < T_MIN as f64 {
                    break;
                }
            }
            img.color[i] = color;
            img.alpha[i] = alpha;
            img.depth[i] = if alpha > 0.0 { depth / alpha } else { 0.0 };
            img.normal[i] = normal.to_array();
        }
    }
    img
}
