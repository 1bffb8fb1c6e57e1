//! SSIM (Wang et al. 2004) and the D-SSIM loss, shared by training (eq.
//! reconstruction-objective, L_RGB) and evaluation ([`crate::eval::metrics`]).
//!
//! Definition, as 3DGS uses it for both training and its reported metrics: per channel, local
//! statistics under an 11×11 Gaussian window with σ = 1.5 (weights normalised to sum 1),
//! C1 = 0.01², C2 = 0.03² (peak 1), and **"same" padding with zeros**: the output has one value
//! per pixel, and window taps that fall outside the image see the value 0 (they are not
//! renormalised, exactly like `conv2d(padding = 5)`). SSIM is the mean of the SSIM map over all
//! pixels and the three channels; D-SSIM = (1 − SSIM) / 2.
//!
//! The window is separable, so the five local moments (μx, μy, E\[x²\], E\[y²\], E\[xy\]) are blurs.
//! The zero-padded blur with a symmetric kernel is its own adjoint, so the backward pass is
//! three more blurs: with S the SSIM map and A = ∂S/∂μx (through σ), B = ∂S/∂E\[x²\],
//! C = ∂S/∂E\[xy\] per pixel, ∂ΣS/∂x = G∗A + 2x·(G∗B) + y·(G∗C).

use super::Loss;
use rayon::prelude::*;

/// Window size in pixels (odd).
pub const WINDOW: usize = 11;
/// Window radius: taps at offsets −RADIUS..=RADIUS.
pub const RADIUS: usize = WINDOW / 2;
/// Standard deviation of the Gaussian window, in pixels.
pub const SIGMA: f64 = 1.5;
/// Stabiliser of the luminance term: (K1·L)² with K1 = 0.01, peak L = 1.
pub const C1: f32 = 0.01 * 0.01;
/// Stabiliser of the contrast-structure term: (K2·L)² with K2 = 0.03, peak L = 1.
pub const C2: f32 = 0.03 * 0.03;

/// The 1-D Gaussian window (sums to 1); the 2-D window is its outer product.
pub fn gaussian_taps() -> [f32; WINDOW] {
    let g: Vec<f64> = (0..WINDOW)
        .map(|i| {
            let d = i as f64 - RADIUS as f64;
            (-d * d / (2.0 * SIGMA * SIGMA)).exp()
        })
        .collect();
    let sum: f64 = g.iter().sum();
    std::array::from_fn(|i| (g[i] / sum) as f32)
}

/// Mean SSIM of two images (see the module doc for the exact definition).
pub fn ssim(a: &[[f32; 3]], b: &[[f32; 3]], width: usize, height: usize) -> f32 {
    check_sizes(a, b, width, height);
    let mut sum = 0.0f64;
    for c in 0..3 {
        let (x, y) = (plane(a, c), plane(b, c));
        sum += ssim_channel(&x, &y, width, height, None);
    }
    (sum / (3 * width * height) as f64) as f32
}

/// D-SSIM = (1 − SSIM(rendered, target)) / 2 and its gradient with respect to `rendered`.
pub fn d_ssim(
    rendered: &[[f32; 3]],
    target: &[[f32; 3]],
    width: usize,
    height: usize,
) -> Loss<Vec<[f32; 3]>> {
    check_sizes(rendered, target, width, height);
    let n = width * height;
    let mut grad = vec![[0.0f32; 3]; n];
    let mut sum = 0.0f64;
    let mut g = vec![0.0f32; n];
    for c in 0..3 {
        let (x, y) = (plane(rendered, c), plane(target, c));
        sum += ssim_channel(&x, &y, width, height, Some(&mut g));
        for (o, gi) in grad.iter_mut().zip(&g) {
            o[c] = *gi;
        }
    }
    let count = (3 * n) as f64;
    // d/dS of (1 − ΣS / count) / 2.
    let scale = (-0.5 / count) as f32;
    grad.par_iter_mut().for_each(|p| {
        for v in p.iter_mut() {
            *v *= scale;
        }
    });
    Loss {
        value: ((1.0 - sum / count) / 2.0) as f32,
        grad,
    }
}

fn check_sizes(a: &[[f32; 3]], b: &[[f32; 3]], width: usize, height: usize) {
    assert!(width > 0 && height > 0, "SSIM of an empty image");
    assert_eq!(a.len(), width * height, "first image is not width×height");
    assert_eq!(b.len(), width * height, "second image is not width×height");
}

fn plane(img: &[[f32; 3]], c: usize) -> Vec<f32> {
    img.par_iter().map(|p| p[c]).collect()
}

/// Σ over pixels of the SSIM map of one channel; with `grad`, writes ∂(ΣS)/∂x into it.
fn ssim_channel(x: &[f32], y: &[f32], w: usize, h: usize, grad: Option<&mut [f32]>) -> f64 {
    let taps = gaussian_taps();
    let n = w * h;
    let mut tmp = vec![0.0f32; n];
    let blurred = |src: &[f32], tmp: &mut [f32]| {
        let mut out = vec![0.0f32; n];
        blur(src, w, h, &taps, tmp, &mut out);
        out
    };
    let xx: Vec<f32> = x.par_iter().map(|v| v * v).collect();
    let yy: Vec<f32> = y.par_iter().map(|v| v * v).collect();
    let xy: Vec<f32> = x.par_iter().zip(y).map(|(a, b)| a * b).collect();
    let mu_x = blurred(x, &mut tmp);
    let mu_y = blurred(y, &mut tmp);
    let e_xx = blurred(&xx, &mut tmp);
    let e_yy = blurred(&yy, &mut tmp);
    let e_xy = blurred(&xy, &mut tmp);

    let Some(grad) = grad else {
        return (0..n)
            .into_par_iter()
            .map(|i| ssim_pixel(mu_x[i], mu_y[i], e_xx[i], e_yy[i], e_xy[i]).0 as f64)
            .sum();
    };
    // Reuse the second-moment buffers of x for the per-pixel partials A, B, C.
    let (mut da, mut db, mut dc) = (xx, yy, xy);
    let sum: f64 = da
        .par_iter_mut()
        .zip(db.par_iter_mut())
        .zip(dc.par_iter_mut())
        .enumerate()
        .map(|(i, ((a, b), c))| {
            let (s, d_mu, d_xx, d_xy) = ssim_pixel(mu_x[i], mu_y[i], e_xx[i], e_yy[i], e_xy[i]);
            (*a, *b, *c) = (d_mu, d_xx, d_xy);
            s as f64
        })
        .sum();
    let ga = blurred(&da, &mut tmp);
    let gb = blurred(&db, &mut tmp);
    let gc = blurred(&dc, &mut tmp);
    grad.par_iter_mut().enumerate().for_each(|(i, g)| {
        *g = ga[i] + 2.0 * x[i] * gb[i] + y[i] * gc[i];
    });
    sum
}

/// SSIM of one pixel from its local moments, and its partials with respect to μx, E[x²] and
/// E[xy] (μx's partial includes its effect through σx² = E[x²] − μx² and σxy = E[xy] − μxμy).
#[inline]
fn ssim_pixel(mu_x: f32, mu_y: f32, e_xx: f32, e_yy: f32, e_xy: f32) -> (f32, f32, f32, f32) {
    let var_x = e_xx - mu_x * mu_x;
    let var_y = e_yy - mu_y * mu_y;
    let cov = e_xy - mu_x * mu_y;
    let a = 2.0 * mu_x * mu_y + C1;
    let b = 2.0 * cov + C2;
    let c = mu_x * mu_x + mu_y * mu_y + C1;
    let d = var_x + var_y + C2;
    let cd = c * d;
    let s = a * b / cd;
    let ds_dmu = 2.0 * mu_y * b / cd - s * 2.0 * mu_x / c;
    let ds_dvar = -s / d;
    let ds_dcov = 2.0 * a / cd;
    (
        s,
        ds_dmu - 2.0 * mu_x * ds_dvar - mu_y * ds_dcov,
        ds_dvar,
        ds_dcov,
    )
}

/// Separable zero-padded "same" blur of a w×h plane; `tmp` holds the horizontal pass.
fn blur(src: &[f32], w: usize, h: usize, taps: &[f32; WINDOW], tmp: &mut [f32], dst: &mut [f32]) {
    tmp.par_chunks_mut(w)
        .zip(src.par_chunks(w))
        .for_each(|(t, s)| {
            let edge = |x: usize| -> f32 {
                let lo = x.saturating_sub(RADIUS);
                let hi = (x + RADIUS).min(w - 1);
                (lo..=hi).map(|xx| taps[xx + RADIUS - x] * s[xx]).sum()
            };
            if w < WINDOW {
                for (x, tx) in t.iter_mut().enumerate() {
                    *tx = edge(x);
                }
                return;
            }
            for x in (0..RADIUS).chain(w - RADIUS..w) {
                t[x] = edge(x);
            }
            // Interior: a fixed-size window the compiler unrolls.
            for (tx, win) in t[RADIUS..w - RADIUS].iter_mut().zip(s.windows(WINDOW)) {
                let win: &[f32; WINDOW] = win.try_into().expect("windows(WINDOW)");
                *tx = (0..WINDOW).map(|k| taps[k] * win[k]).sum();
            }
        });
    let tmp = &*tmp;
    dst.par_chunks_mut(w).enumerate().for_each(|(y, d)| {
        d.fill(0.0);
        let lo = y.saturating_sub(RADIUS);
        let hi = (y + RADIUS).min(h - 1);
        for yy in lo..=hi {
            let k = taps[yy + RADIUS - y];
            for (dx, t) in d.iter_mut().zip(&tmp[yy * w..(yy + 1) * w]) {
                *dx += k * t;
            }
        }
    });
}
