//! Normals from a depth map and the 2DGS depth-normal consistency loss (L_DN of eqs.
//! reconstruction-normal and reconstruction-objective).
//!
//! A pixel (x, y) with planar depth d back-projects to the camera-space point
//! P = d · ((x + 0.5 − cx)/fx, −(y + 0.5 − cy)/fy, −1) (docs/design.md §2: OpenGL camera, pixel centres
//! at +0.5, planar depth). As in 2DGS, the depth normal of an interior pixel is the normalised
//! cross product of the central differences of its four neighbours' points,
//! n = normalize((P(x, y+1) − P(x, y−1)) × (P(x+1, y) − P(x−1, y))), which faces the camera,
//! rotated to world space by the camera's rotation. A pixel has no depth normal (0) on the image
//! border, when one of its four neighbours has no depth (≤ 0 or not finite), or when the
//! neighbours are (numerically) collinear. The pixel's own depth does not enter its normal.

use crate::scene::Camera;
use rayon::prelude::*;

/// Cross products shorter than this (in m², relative to depth²) give no normal.
const MIN_CROSS: f32 = 1e-12;

/// Depth-derived world normals and the 2DGS consistency loss with its gradients.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthNormalLoss {
    /// (1/HW) Σ_p w_p (1 − n_depth,p · n_p) over pixels that have a depth normal.
    pub value: f32,
    /// ∂value/∂depth.
    pub grad_depth: Vec<f32>,
    /// ∂value/∂normals.
    pub grad_normal: Vec<[f32; 3]>,
    /// ∂value/∂weight (usually ignored: 2DGS detaches alpha).
    pub grad_weight: Vec<f32>,
    /// The depth-derived world normals (0 where there is none), e.g. for previews.
    pub depth_normals: Vec<[f32; 3]>,
}

#[inline]
fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline]
fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// Camera-space direction whose z is −1, so that depth · dir is the back-projected point.
#[inline]
fn pixel_dir(cam: &Camera, x: usize, y: usize) -> [f32; 3] {
    cam.camera_direction(x as f32 + 0.5, y as f32 + 0.5)
}

/// Everything the forward pass knows about one pixel's depth normal.
struct Local {
    /// Central differences along x and y of the back-projected points.
    dx: [f32; 3],
    dy: [f32; 3],
    /// Camera-space unit normal and the length of the unnormalised cross product.
    n: [f32; 3],
    len: f32,
}

fn local(depth: &[f32], cam: &Camera, w: usize, h: usize, x: usize, y: usize) -> Option<Local> {
    if x == 0 || y == 0 || x + 1 >= w || y + 1 >= h {
        return None;
    }
    let point = |x: usize, y: usize| -> Option<[f32; 3]> {
        let d = depth[y * w + x];
        if !(d > 0.0 && d.is_finite()) {
            return None;
        }
        let r = pixel_dir(cam, x, y);
        Some([d * r[0], d * r[1], d * r[2]])
    };
    let dx = sub(point(x + 1, y)?, point(x - 1, y)?);
    let dy = sub(point(x, y + 1)?, point(x, y - 1)?);
    let c = cross(dy, dx);
    let len = dot(c, c).sqrt();
    let scale = depth[y * w + x].max(f32::MIN_POSITIVE);
    if len.is_nan() || len <= MIN_CROSS * scale * scale {
        return None;
    }
    Some(Local {
        dx,
        dy,
        n: [c[0] / len, c[1] / len, c[2] / len],
        len,
    })
}

/// Camera-to-world rotation (rows) of the camera.
fn rotation(cam: &Camera) -> [[f32; 3]; 3] {
    let r = cam.rotation();
    std::array::from_fn(|i| r.row(i).to_array())
}

fn rotate(r: &[[f32; 3]; 3], v: [f32; 3]) -> [f32; 3] {
    [dot(r[0], v), dot(r[1], v), dot(r[2], v)]
}

fn rotate_t(r: &[[f32; 3]; 3], v: [f32; 3]) -> [f32; 3] {
    std::array::from_fn(|c| r[0][c] * v[0] + r[1][c] * v[1] + r[2][c] * v[2])
}

fn check_camera(depth: &[f32], cam: &Camera) -> (usize, usize) {
    let (w, h) = (cam.w as usize, cam.h as usize);
    assert_eq!(
        depth.len(),
        w * h,
        "depth map has {} pixels, the camera is {w}×{h}",
        depth.len()
    );
    (w, h)
}

/// World-space unit normals of the surface seen in a planar depth map (0 where there is none).
pub fn depth_normals(depth: &[f32], cam: &Camera) -> Vec<[f32; 3]> {
    let (w, h) = check_camera(depth, cam);
    let rot = rotation(cam);
    (0..w * h)
        .into_par_iter()
        .map(|i| local(depth, cam, w, h, i % w, i / w).map_or([0.0; 3], |l| rotate(&rot, l.n)))
        .collect()
}

/// 2DGS depth-normal consistency: (1/HW) Σ_p w_p (1 − n_depth,p · n_p) over the pixels that
/// have a depth normal, where n_depth comes from `depth` (see [`depth_normals`]), `normals` are
/// world normals (the splatted ones for 2DGS consistency, or the reference ones for L_DN of
/// eq. reconstruction-normal) and `weight` is the per-pixel weight (2DGS: the accumulated
/// alpha; 1 when `None`). Gradients w.r.t. the depth map, the normals and the weights.
pub fn depth_normal_loss(
    depth: &[f32],
    cam: &Camera,
    normals: &[[f32; 3]],
    weight: Option<&[f32]>,
) -> DepthNormalLoss {
    let (w, h) = check_camera(depth, cam);
    let n = w * h;
    assert_eq!(normals.len(), n, "normal map is not the depth map's size");
    if let Some(wt) = weight {
        assert_eq!(wt.len(), n, "weight map is not the depth map's size");
    }
    let rot = rotation(cam);
    let inv = 1.0 / n.max(1) as f32;
    let wt = |i: usize| weight.map_or(1.0, |wt| wt[i]);

    // Per pixel: its depth normal, its loss term, and the gradients of the loss w.r.t. its two
    // central differences (camera space), to be gathered by the neighbours' depths below.
    struct Pixel {
        n_world: [f32; 3],
        term: f32,
        g_dx: [f32; 3],
        g_dy: [f32; 3],
    }
    let pixels: Vec<Option<Pixel>> = (0..n)
        .into_par_iter()
        .map(|i| {
            let l = local(depth, cam, w, h, i % w, i / w)?;
            let n_world = rotate(&rot, l.n);
            let e = 1.0 - dot(n_world, normals[i]);
            // dL/dn_world = −w/HW · normal; back to camera space, through the normalisation.
            let g_nw = normals[i].map(|v| -wt(i) * inv * v);
            let g_n = rotate_t(&rot, g_nw);
            let gn_dot = dot(g_n, l.n);
            let g_c: [f32; 3] = std::array::from_fn(|k| (g_n[k] - gn_dot * l.n[k]) / l.len);
            // c = dy × dx: dL/d(dy) = dx × g_c, dL/d(dx) = g_c × dy.
            Some(Pixel {
                n_world,
                term: e,
                g_dx: cross(g_c, l.dy),
                g_dy: cross(l.dx, g_c),
            })
        })
        .collect();

    let value: f64 = pixels
        .par_iter()
        .enumerate()
        .filter_map(|(i, p)| p.as_ref().map(|p| (wt(i) * p.term) as f64))
        .sum();
    let grad_depth = (0..n)
        .into_par_iter()
        .map(|i| {
            let (x, y) = (i % w, i / w);
            // P(x, y) enters dx of (x−1, y) with +, dx of (x+1, y) with −, and likewise dy.
            let mut g = [0.0f32; 3];
            let mut add = |j: Option<usize>, f: fn(&Pixel) -> [f32; 3], s: f32| {
                if let Some(p) = j.and_then(|j| pixels[j].as_ref()) {
                    let v = f(p);
                    for k in 0..3 {
                        g[k] += s * v[k];
                    }
                }
            };
            add((x > 0).then(|| i - 1), |p| p.g_dx, 1.0);
            add((x + 1 < w).then_some(i + 1), |p| p.g_dx, -1.0);
            add((y > 0).then(|| i - w), |p| p.g_dy, 1.0);
            add((y + 1 < h).then_some(i + w), |p| p.g_dy, -1.0);
            dot(pixel_dir(cam, x, y), g)
        })
        .collect();
    let grad_normal = pixels
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            p.as_ref()
                .map_or([0.0; 3], |p| p.n_world.map(|v| -wt(i) * inv * v))
        })
        .collect();
    let grad_weight = pixels
        .par_iter()
        .map(|p| p.as_ref().map_or(0.0, |p| inv * p.term))
        .collect();
    let depth_normals = pixels
        .iter()
        .map(|p| p.as_ref().map_or([0.0; 3], |p| p.n_world))
        .collect();
    DepthNormalLoss {
        value: (value * inv as f64) as f32,
        grad_depth,
        grad_normal,
        grad_weight,
        depth_normals,
    }
}
