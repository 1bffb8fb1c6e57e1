//! A lat-long map as the sum of coarser maps upsampled to its resolution (a multi-resolution
//! parameterisation, not in the paper): stage 3 fits ln E as `fine + Σ_l up(coarse_l)`, each
//! level its own Adam group ([`crate::stages::invert::train::Settings::env_levels`]).
//!
//! Why: with one value per texel of a 256×128 map, a direction that the captures constrain
//! only through a few diffuse bounces receives a few noisy gradients and, Adam normalising each
//! texel alone, takes full-size steps on that noise (the recovered skies of issue 44: noise
//! above the horizon). A 16×8 level gathers the same samples into texels of 16×16 fine ones, so
//! its gradient is a sum over many and its steps follow what the surfaces actually receive;
//! the finer levels add detail where the data carry it. Starting the coarse levels at zero
//! leaves the initial map as it was.
//!
//! One function lists a fine texel's bilinear taps on a coarse level (`taps`); the upsampling
//! and its adjoint both walk it, so they cannot disagree (checked by the dot-product identity in
//! this module's tests).

/// The coarse levels of a `width × height` map split into `levels` (1: the map alone), coarsest
/// first: each halves the next finer one. `None` if the map is not divisible that often.
pub fn coarse_sizes(width: usize, height: usize, levels: u32) -> Option<Vec<(usize, usize)>> {
    if levels == 0 {
        return None;
    }
    let d = 1usize.checked_shl(levels - 1)?;
    if d == 0 || width % d != 0 || height % d != 0 || width < d || height < d {
        return None;
    }
    Some(
        (1..levels)
            .rev()
            .map(|l| (width >> l, height >> l))
            .collect(),
    )
}

/// Fine texel (x, y) of a `fine` = (W, H) map read bilinearly from a `coarse` = (w, h) one at
/// the same direction (texel centres: u = (x + ½)/W): four (coarse texel, weight) taps summing
/// to 1. Longitude wraps (the last column neighbours the first); latitude clamps at the poles.
fn taps(x: usize, y: usize, fine: (usize, usize), coarse: (usize, usize)) -> [(usize, f32); 4] {
    let (w, h) = coarse;
    let cx = (x as f32 + 0.5) * w as f32 / fine.0 as f32 - 0.5;
    let cy = ((y as f32 + 0.5) * h as f32 / fine.1 as f32 - 0.5).clamp(0.0, (h - 1) as f32);
    let (x0, y0) = (cx.floor(), cy.floor());
    let (fx, fy) = (cx - x0, cy - y0);
    let col = |i: f32| (i as i64).rem_euclid(w as i64) as usize;
    let (c0, c1) = (col(x0), col(x0 + 1.0));
    let r0 = y0 as usize;
    let r1 = (r0 + 1).min(h - 1);
    [
        (r0 * w + c0, (1.0 - fx) * (1.0 - fy)),
        (r0 * w + c1, fx * (1.0 - fy)),
        (r1 * w + c0, (1.0 - fx) * fy),
        (r1 * w + c1, fx * fy),
    ]
}

/// `fine += up(coarse)`: both 3 values per texel, row-major.
pub fn upsample_add(
    coarse: &[f32],
    csize: (usize, usize),
    fine: &mut [f32],
    fsize: (usize, usize),
) {
    assert_eq!(coarse.len(), 3 * csize.0 * csize.1, "coarse level length");
    assert_eq!(fine.len(), 3 * fsize.0 * fsize.1, "fine map length");
    for y in 0..fsize.1 {
        for x in 0..fsize.0 {
            let f = 3 * (y * fsize.0 + x);
            for (t, wgt) in taps(x, y, fsize, csize) {
                for c in 0..3 {
                    fine[f + c] += wgt * coarse[3 * t + c];
                }
            }
        }
    }
}

/// The adjoint of [`upsample_add`]: a gradient on the fine map gathered onto the coarse level.
pub fn upsample_adjoint(d_fine: &[f32], fsize: (usize, usize), csize: (usize, usize)) -> Vec<f32> {
    assert_eq!(d_fine.len(), 3 * fsize.0 * fsize.1, "fine gradient length");
    let mut d = vec![0.0f32; 3 * csize.0 * csize.1];
    for y in 0..fsize.1 {
        for x in 0..fsize.0 {
            let f = 3 * (y * fsize.0 + x);
            for (t, wgt) in taps(x, y, fsize, csize) {
                for c in 0..3 {
                    d[3 * t + c] += wgt * d_fine[f + c];
                }
            }
        }
    }
    d
}

#[cfg(test)]
mod tests {
    use super::*;

    fn noise(n: usize, seed: u64) -> Vec<f32> {
        let mut s = seed;
        (0..n)
            .map(|_| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
            })
            .collect()
    }

    #[test]
    fn sizes_halve_down_to_the_coarsest() {
        assert_eq!(coarse_sizes(256, 128, 1), Some(vec![]));
        assert_eq!(
            coarse_sizes(256, 128, 5),
            Some(vec![(16, 8), (32, 16), (64, 32), (128, 64)])
        );
        assert_eq!(
            coarse_sizes(64, 32, 6),
            Some(vec![(2, 1), (4, 2), (8, 4), (16, 8), (32, 16)])
        );
        assert_eq!(coarse_sizes(64, 32, 7), None);
        assert_eq!(coarse_sizes(48, 24, 5), None);
        assert_eq!(coarse_sizes(64, 32, 0), None);
        assert_eq!(coarse_sizes(64, 32, 200), None);
    }

    #[test]
    fn a_constant_level_adds_its_constant_everywhere() {
        let (cs, fs) = ((8, 4), (64, 32));
        let coarse: Vec<f32> = (0..cs.0 * cs.1).flat_map(|_| [0.5, -1.0, 2.0]).collect();
        let mut fine = vec![1.0f32; 3 * fs.0 * fs.1];
        upsample_add(&coarse, cs, &mut fine, fs);
        for p in fine.chunks_exact(3) {
            for (v, want) in p.iter().zip([1.5, 0.0, 3.0]) {
                assert!((v - want).abs() < 1e-6, "{v} vs {want}");
            }
        }
    }

    #[test]
    fn longitude_wraps_and_latitude_clamps() {
        // A coarse level that is one in its first column only: the fine map's last columns
        // read it through the seam, and the top and bottom rows read the pole rows alone.
        let (cs, fs) = ((4, 2), (16, 8));
        let mut coarse = vec![0.0f32; 3 * 8];
        for r in 0..2 {
            coarse[3 * (r * 4)..3 * (r * 4) + 3].copy_from_slice(&[1.0; 3]);
        }
        let mut fine = vec![0.0f32; 3 * 16 * 8];
        upsample_add(&coarse, cs, &mut fine, fs);
        let at = |x: usize, y: usize| fine[3 * (y * 16 + x)];
        // Fine column 15 (u = 31/32) lies 3/8 of the way from coarse column 3 (u = 7/8) to
        // column 0 across the seam (u = 9/8); fine column 0 (u = 1/32) 5/8 of the way from
        // column 3 (u = −1/8) to column 0 (u = 1/8).
        assert!((at(15, 0) - 0.375).abs() < 1e-6);
        assert!((at(0, 0) - 0.625).abs() < 1e-6);
        // The bottom fine row (v = 15/16) is below the last coarse row's centre (v = 3/4):
        // clamped, it reads that row alone, the same value as one row up.
        assert!((at(2, 7) - 0.875).abs() < 1e-6);
        assert!((at(2, 6) - 0.875).abs() < 1e-6);
        assert!(at(8, 3).abs() < 1e-6);
    }

    #[test]
    fn the_adjoint_is_the_transpose() {
        // ⟨up(c), f⟩ = ⟨c, upᵀ(f)⟩ for random c and f, on sizes with and without a wrap
        // tap in every row; f32 sums of ~10³ terms: relative tolerance 1e-5.
        for (cs, fs) in [
            ((4, 2), (16, 8)),
            ((16, 8), (256, 128)),
            ((32, 16), (64, 32)),
        ] {
            let c = noise(3 * cs.0 * cs.1, 1);
            let f = noise(3 * fs.0 * fs.1, 2);
            let mut up = vec![0.0f32; f.len()];
            upsample_add(&c, cs, &mut up, fs);
            let lhs: f64 = up.iter().zip(&f).map(|(a, b)| (a * b) as f64).sum();
            let adj = upsample_adjoint(&f, fs, cs);
            let rhs: f64 = c.iter().zip(&adj).map(|(a, b)| (a * b) as f64).sum();
            assert!(
                (lhs - rhs).abs() <= 1e-5 * lhs.abs().max(1.0),
                "{cs:?} -> {fs:?}: {lhs} vs {rhs}"
            );
        }
    }
}
