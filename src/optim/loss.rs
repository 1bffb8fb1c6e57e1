//! Per-pixel and per-surfel losses of eqs. reconstruction-objective, geometry-objective and
//! training-objectives, each with its gradient. Sums are accumulated in f64. Where a loss has a
//! kink (|·|, max), the gradient at the kink is the subgradient 0 for |·| and the first
//! component for a tie in max.

use super::{ssim::d_ssim, Loss, WeightedLoss};
use rayon::prelude::*;

/// Weight of D-SSIM in L_RGB = (1 − λ) L1 + λ D-SSIM (3DGS, 2DGS).
pub const LAMBDA_DSSIM: f32 = 0.2;

/// Keeps the normalised depth loss finite when the reference has (almost) no valid depth.
const DEPTH_EPS: f64 = 1e-6;

#[inline]
fn sign(x: f32) -> f32 {
    if x > 0.0 {
        1.0
    } else if x < 0.0 {
        -1.0
    } else {
        0.0
    }
}

fn check_len(name: &str, len: usize, expected: usize) {
    assert_eq!(
        len, expected,
        "{name} has {len} pixels, expected {expected}"
    );
}

/// Mean absolute colour error over all pixels and channels, gradient w.r.t. `rendered`.
pub fn l1(rendered: &[[f32; 3]], target: &[[f32; 3]]) -> Loss<Vec<[f32; 3]>> {
    check_len("target", target.len(), rendered.len());
    let count = (3 * rendered.len()).max(1) as f64;
    let g = (1.0 / count) as f32;
    let value: f64 = rendered
        .par_iter()
        .zip(target)
        .map(|(r, t)| (0..3).map(|c| (r[c] - t[c]).abs() as f64).sum::<f64>())
        .sum();
    let grad = rendered
        .par_iter()
        .zip(target)
        .map(|(r, t)| std::array::from_fn(|c| g * sign(r[c] - t[c])))
        .collect();
    Loss {
        value: (value / count) as f32,
        grad,
    }
}

/// L_RGB = (1 − λ) L1 + λ D-SSIM (eq. reconstruction-objective); λ is usually [`LAMBDA_DSSIM`].
pub fn rgb_loss(
    rendered: &[[f32; 3]],
    target: &[[f32; 3]],
    width: usize,
    height: usize,
    lambda: f32,
) -> Loss<Vec<[f32; 3]>> {
    let a = l1(rendered, target);
    let b = d_ssim(rendered, target, width, height);
    let grad = a
        .grad
        .par_iter()
        .zip(&b.grad)
        .map(|(ga, gb)| std::array::from_fn(|c| (1.0 - lambda) * ga[c] + lambda * gb[c]))
        .collect();
    Loss {
        value: (1.0 - lambda) * a.value + lambda * b.value,
        grad,
    }
}

/// The sRGB transfer function continued beyond [0, 1] so that it keeps a gradient: linear with
/// slope 12.92 below the knee (negative values included), the sRGB curve up to 1, and the
/// tangent at 1 above (slope 1.055 / 2.4). Returns the value and its derivative.
pub fn display_encode(x: f32) -> (f32, f32) {
    const KNEE: f32 = 0.003_130_8;
    const SLOPE_AT_1: f32 = 1.055 / 2.4;
    if x <= KNEE {
        (12.92 * x, 12.92)
    } else if x <= 1.0 {
        let p = x.powf(1.0 / 2.4);
        (1.055 * p - 0.055, 1.055 / 2.4 * p / x)
    } else {
        (1.0 + SLOPE_AT_1 * (x - 1.0), SLOPE_AT_1)
    }
}

/// L_RGB on display-encoded colours: the rendered colour through [`display_encode`], the capture
/// clamped to [0, 1] and sRGB-encoded, as the PSNR the reconstruction is judged by (and as an
/// 8-bit photograph would be). A sunlit patch far above 1 in the linear capture then asks the
/// render for display white rather than for its full radiance, and dark regions weigh as much
/// as an eye sees them. Gradient w.r.t. the linear `rendered`.
pub fn rgb_loss_display(
    rendered: &[[f32; 3]],
    target: &[[f32; 3]],
    width: usize,
    height: usize,
    lambda: f32,
) -> Loss<Vec<[f32; 3]>> {
    check_len("target", target.len(), rendered.len());
    let (enc, slope): (Vec<[f32; 3]>, Vec<[f32; 3]>) = rendered
        .par_iter()
        .map(|c| {
            let e = c.map(display_encode);
            (e.map(|v| v.0), e.map(|v| v.1))
        })
        .unzip();
    let t: Vec<[f32; 3]> = target
        .par_iter()
        .map(|c| c.map(|v| display_encode(v.clamp(0.0, 1.0)).0))
        .collect();
    let loss = rgb_loss(&enc, &t, width, height, lambda);
    let grad = loss
        .grad
        .par_iter()
        .zip(&slope)
        .map(|(g, s)| std::array::from_fn(|c| g[c] * s[c]))
        .collect();
    Loss {
        value: loss.value,
        grad,
    }
}

/// L_α = ‖Â − 1‖₁ / HW (eq. alpha-coverage), gradient w.r.t. the accumulated opacity Â.
pub fn alpha_coverage(alpha: &[f32]) -> Loss<Vec<f32>> {
    let count = alpha.len().max(1) as f64;
    let g = (1.0 / count) as f32;
    let value: f64 = alpha.par_iter().map(|a| (a - 1.0).abs() as f64).sum();
    Loss {
        value: (value / count) as f32,
        grad: alpha.par_iter().map(|a| g * sign(a - 1.0)).collect(),
    }
}

/// L_s = (1/N) Σ max(0, ‖s_i‖∞ / s_max − 1)² (eq. scale-regularization), gradient w.r.t. the
/// linear in-plane scales (s_u, s_v) (chain with s for a log-scale parameter).
pub fn scale_regularization(scales: &[[f32; 2]], s_max: f32) -> Loss<Vec<[f32; 2]>> {
    assert!(
        s_max.is_finite() && s_max > 0.0,
        "s_max must be positive, got {s_max}"
    );
    let count = scales.len().max(1) as f64;
    let hinge = |s: &[f32; 2]| -> (usize, f32) {
        let k = if s[1] > s[0] { 1 } else { 0 };
        (k, (s[k] / s_max - 1.0).max(0.0))
    };
    let value: f64 = scales.par_iter().map(|s| (hinge(s).1 as f64).powi(2)).sum();
    let g = (2.0 / (count * s_max as f64)) as f32;
    let grad = scales
        .par_iter()
        .map(|s| {
            let (k, t) = hinge(s);
            let mut out = [0.0f32; 2];
            out[k] = g * t;
            out
        })
        .collect();
    Loss {
        value: (value / count) as f32,
        grad,
    }
}

/// Confidence-weighted depth L1 normalised by the weighted reference depth (eq.
/// reconstruction-depth): L_D = ‖C ⊙ (D̃ − D*)‖₁ / (‖C ⊙ D*‖₁ + ε), where C is `confidence`
/// (1 when `None`) times the validity mask \[D* > 0\] (reference 0 = no data). Returns the
/// gradients w.r.t. the rendered depth D̃ and w.r.t. the confidence.
pub fn depth_l1(
    rendered: &[f32],
    reference: &[f32],
    confidence: Option<&[f32]>,
) -> WeightedLoss<Vec<f32>> {
    check_len("reference depth", reference.len(), rendered.len());
    if let Some(c) = confidence {
        check_len("depth confidence", c.len(), rendered.len());
    }
    let valid = |d: f32| d > 0.0 && d.is_finite();
    let conf = |i: usize| confidence.map_or(1.0, |c| c[i]);
    let (num, den) = (0..rendered.len())
        .into_par_iter()
        .filter(|&i| valid(reference[i]))
        .map(|i| {
            let c = conf(i) as f64;
            (
                c * (rendered[i] - reference[i]).abs() as f64,
                c * reference[i].abs() as f64,
            )
        })
        .reduce(|| (0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
    let den = den + DEPTH_EPS;
    let value = num / den;
    let (grad, grad_weight) = (0..rendered.len())
        .into_par_iter()
        .map(|i| {
            if !valid(reference[i]) {
                return (0.0, 0.0);
            }
            let r = rendered[i] - reference[i];
            let gd = (conf(i) as f64 * sign(r) as f64 / den) as f32;
            let gc = ((r.abs() as f64 - value * reference[i] as f64) / den) as f32;
            (gd, gc)
        })
        .unzip();
    WeightedLoss {
        value: value as f32,
        grad,
        grad_weight,
    }
}

/// Normal loss L_N = (1/HW) Σ_p w_p (1 − n̂_p·n*_p) (eq. reconstruction-normal), gradient w.r.t.
/// the rendered normals n̂ and the weights w. w is `weight` (1 when `None`) times the validity
/// mask [n* ≠ 0] (reference 0 = no data). Pixels without reference contribute 0 instead of the
/// paper's 1: a constant offset, the gradient is the same. Rendered normals are used as given
/// (whether they are renormalised is the renderer's choice).
pub fn normal_loss(
    rendered: &[[f32; 3]],
    reference: &[[f32; 3]],
    weight: Option<&[f32]>,
) -> WeightedLoss<Vec<[f32; 3]>> {
    check_len("reference normals", reference.len(), rendered.len());
    if let Some(w) = weight {
        check_len("normal weights", w.len(), rendered.len());
    }
    let inv = (1.0 / rendered.len().max(1) as f64) as f32;
    let per_pixel = |i: usize| -> (f32, f32, [f32; 3]) {
        let (n, t) = (rendered[i], reference[i]);
        if t == [0.0; 3] {
            return (0.0, 0.0, [0.0; 3]);
        }
        let w = weight.map_or(1.0, |w| w[i]);
        let e = 1.0 - (n[0] * t[0] + n[1] * t[1] + n[2] * t[2]);
        (w * e, inv * e, std::array::from_fn(|c| -inv * w * t[c]))
    };
    let value: f64 = (0..rendered.len())
        .into_par_iter()
        .map(|i| per_pixel(i).0 as f64)
        .sum();
    let (grad_weight, grad) = (0..rendered.len())
        .into_par_iter()
        .map(|i| {
            let (_, gw, gn) = per_pixel(i);
            (gw, gn)
        })
        .unzip();
    WeightedLoss {
        value: (value * inv as f64) as f32,
        grad,
        grad_weight,
    }
}

/// Total variation of a lat-long environment map (L_TV of eq. training-objectives): the mean
/// absolute difference between horizontal neighbours (longitude wraps around: the last column
/// neighbours the first) and vertical neighbours (latitude does not wrap), over all channels.
/// The map is row-major, `width` × `height` texels, values as given (scene-linear HDR).
pub fn env_tv(env: &[[f32; 3]], width: usize, height: usize) -> Loss<Vec<[f32; 3]>> {
    check_len("environment", env.len(), width * height);
    let terms = 3 * (width * height + width * height.saturating_sub(1));
    if terms == 0 {
        return Loss {
            value: 0.0,
            grad: vec![[0.0; 3]; env.len()],
        };
    }
    let inv = 1.0 / terms as f64;
    let right = |x: usize, y: usize| env[y * width + (x + 1) % width];
    let value: f64 = env
        .par_chunks(width)
        .enumerate()
        .map(|(y, row)| {
            let mut s = 0.0f64;
            for (x, p) in row.iter().enumerate() {
                let r = right(x, y);
                for c in 0..3 {
                    s += (r[c] - p[c]).abs() as f64;
                    if y + 1 < height {
                        s += (env[(y + 1) * width + x][c] - p[c]).abs() as f64;
                    }
                }
            }
            s
        })
        .sum();
    let g = inv as f32;
    let grad = (0..env.len())
        .into_par_iter()
        .map(|i| {
            let (x, y) = (i % width, i / width);
            let p = env[i];
            let left = env[y * width + (x + width - 1) % width];
            let r = right(x, y);
            std::array::from_fn(|c| {
                // p appears in |right − p| (as −p) and in |p − left| (as +p); same vertically.
                let mut d = sign(p[c] - r[c]) + sign(p[c] - left[c]);
                if y + 1 < height {
                    d += sign(p[c] - env[i + width][c]);
                }
                if y > 0 {
                    d += sign(p[c] - env[i - width][c]);
                }
                g * d
            })
        })
        .collect();
    Loss {
        value: (value * inv) as f32,
        grad,
    }
}
