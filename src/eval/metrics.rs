//! Image and depth metrics. PSNR uses peak 1 on images clamped to [0, 1] (scene-linear, or
//! sRGB-encoded after clamping); SSIM is exactly the training definition in
//! [`crate::optim::ssim()`] (11×11 Gaussian window, σ = 1.5, zero-padded "same" statistics).

use crate::scene::color::{srgb_byte, srgb_encode};
use rayon::prelude::*;

fn check(a: &[[f32; 3]], b: &[[f32; 3]]) {
    assert!(!a.is_empty(), "metric of an empty image");
    assert_eq!(a.len(), b.len(), "images differ in size");
}

/// Σ `f(a_i, b_i)` over the pixels, in parallel but in one fixed order: fixed chunks, each summed
/// in pixel order, then the chunks' sums in chunk order. rayon's `sum` splits adaptively, so its
/// rounding could differ between two runs on the same images (an evaluation and its re-run must
/// agree to the bit).
fn ordered_sum(
    a: &[[f32; 3]],
    b: &[[f32; 3]],
    f: impl Fn(&[f32; 3], &[f32; 3]) -> f64 + Sync,
) -> f64 {
    const CHUNK: usize = 4096;
    let partial: Vec<f64> = a
        .par_chunks(CHUNK)
        .zip(b.par_chunks(CHUNK))
        .map(|(x, y)| x.iter().zip(y).map(|(p, q)| f(p, q)).sum::<f64>())
        .collect();
    partial.iter().sum()
}

fn psnr_mapped(a: &[[f32; 3]], b: &[[f32; 3]], f: impl Fn(f32) -> f32 + Sync) -> f64 {
    check(a, b);
    let se = ordered_sum(a, b, |p, q| {
        (0..3)
            .map(|c| ((f(p[c]) - f(q[c])) as f64).powi(2))
            .sum::<f64>()
    });
    let mse = se / (3 * a.len()) as f64;
    // Identical images give +inf, as 10 log10(1 / 0) should.
    -10.0 * mse.log10()
}

/// PSNR in dB of two scene-linear images clamped to [0, 1], peak 1, MSE over all channels.
pub fn psnr(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    psnr_mapped(a, b, |x| x.clamp(0.0, 1.0))
}

/// PSNR in dB after clamping to [0, 1] and sRGB encoding (the usual "display" PSNR).
pub fn psnr_srgb(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    psnr_mapped(a, b, srgb_encode)
}

/// PSNR in dB of scene-linear HDR images, unclamped, with the reference's largest channel
/// value as the peak (so a brighter scene is not judged on a [0, 1] clip of itself).
pub fn psnr_hdr(rendered: &[[f32; 3]], reference: &[[f32; 3]]) -> f64 {
    check(rendered, reference);
    let peak = reference
        .iter()
        .flat_map(|p| p.iter().map(|&v| v as f64))
        .fold(0.0, f64::max)
        .max(1e-6);
    let se = ordered_sum(rendered, reference, |a, b| {
        (0..3).map(|c| ((a[c] - b[c]) as f64).powi(2)).sum::<f64>()
    });
    let mse = se / (3 * rendered.len()) as f64;
    10.0 * (peak * peak / mse).log10()
}

/// The 8-bit sRGB image a PNG of `img` holds, as values k / 255: clamp to [0, 1], sRGB OETF,
/// round to the nearest code (what evaluations on 8-bit images compare).
pub fn srgb8(img: &[[f32; 3]]) -> Vec<[f32; 3]> {
    img.par_iter()
        .map(|p| p.map(|v| srgb_byte(v) as f32 / 255.0))
        .collect()
}

/// PSNR on 8-bit sRGB images ([`srgb8`]), peak 1.
pub fn psnr_srgb8(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    check(a, b);
    psnr_mapped(&srgb8(a), &srgb8(b), |x| x)
}

/// Mean SSIM on 8-bit sRGB images ([`srgb8`]): 3DGS's (11×11 Gaussian window, σ = 1.5).
pub fn ssim_srgb8(a: &[[f32; 3]], b: &[[f32; 3]], width: usize, height: usize) -> f64 {
    check(a, b);
    ssim(&srgb8(a), &srgb8(b), width, height)
}

/// Mean SSIM of the images as given (see [`crate::optim::ssim()`]).
pub fn ssim(a: &[[f32; 3]], b: &[[f32; 3]], width: usize, height: usize) -> f64 {
    crate::optim::ssim::ssim(a, b, width, height) as f64
}

/// Mean SSIM after clamping to [0, 1] and sRGB encoding.
pub fn ssim_srgb(a: &[[f32; 3]], b: &[[f32; 3]], width: usize, height: usize) -> f64 {
    check(a, b);
    let enc = |img: &[[f32; 3]]| -> Vec<[f32; 3]> {
        img.par_iter().map(|p| p.map(srgb_encode)).collect()
    };
    ssim(&enc(a), &enc(b), width, height)
}

/// Absolute depth error over the pixels where the reference has depth (> 0 and finite).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DepthError {
    /// Mean |rendered − reference| in metres (NaN when `count` is 0).
    pub mean: f64,
    /// Median |rendered − reference| in metres (mean of the middle two for an even count).
    pub median: f64,
    /// Number of valid pixels.
    pub count: usize,
}

/// Mean and median absolute depth error on valid pixels; a rendered 0 (no hit) where the
/// reference has depth counts with its full error.
pub fn depth_error(rendered: &[f32], reference: &[f32]) -> DepthError {
    assert_eq!(rendered.len(), reference.len(), "depth maps differ in size");
    let mut err: Vec<f64> = rendered
        .par_iter()
        .zip(reference)
        .filter(|(_, r)| **r > 0.0 && r.is_finite())
        .map(|(d, r)| (*d as f64 - *r as f64).abs())
        .collect();
    let count = err.len();
    if count == 0 {
        return DepthError {
            mean: f64::NAN,
            median: f64::NAN,
            count,
        };
    }
    let mean = err.iter().sum::<f64>() / count as f64;
    err.par_sort_unstable_by(f64::total_cmp);
    let median = if count % 2 == 1 {
        err[count / 2]
    } else {
        0.5 * (err[count / 2 - 1] + err[count / 2])
    };
    DepthError {
        mean,
        median,
        count,
    }
}
