//! Lookups and importance sampling of a lat-long [`Environment`]: the E_k(ω) of the paper's
//! path estimator (eq. path-estimator) and its next-event estimation.
//!
//! # The mapping: Cycles' World Environment Texture after the axis change (docs/design.md §2)
//!
//! Cycles (intern/cycles/kernel/camera/projection.h; the Environment Texture node calls it
//! with the normalised lookup vector, svm/image.h):
//!
//! ```text
//! direction_to_equirectangular(d) = direction_to_equirectangular_range(d, (−2π, π, −π, π))
//!   u = (atan2(d.y, d.x) − π) / (−2π) = 0.5 − atan2(d.y, d.x) / 2π
//!   v = (acos(d.z / |d|) − π) / (−π)  = 1 − acos(d.z) / π
//! ```
//!
//! and the image is looked up at (u, v) with v = 0 the *bottom* row (Blender keeps images
//! bottom-up), texel centres at (i + ½)/W, bilinear ("Linear"), `EXTENSION_REPEAT` in both
//! axes (`EnvironmentTextureNode::image_params`, scene/shader_nodes.cpp).
//!
//! A LightFuse direction (X, Y, Z) is the Blender direction (X, −Z, Y) (Blender (x, y, z) →
//! (x, z, −y)). So, with row coordinate t = 1 − v counted from our top row (row 0 = top):
//!
//! ```text
//! u = 0.5 − atan2(−Z, X) / 2π = 0.5 + atan2(Z, X) / 2π
//! t = acos(Y) / π
//! ```
//!
//! +X → (u, t) = (½, ½), the image centre; +Z → u = ¾; −Z → u = ¼; +Y → the top row.
//! Continuous texel coordinates are x = uW − ½, y = tH − ½ (our rows are Cycles' rows
//! mirrored, y ↦ H − 1 − y, which keeps centres on centres and periodic wrap periodic).
//!
//! Note on the poles: as Cycles repeats in v too, the half-row nearest each pole is blended
//! with the row at the *opposite* pole. We do the same, to match Cycles exactly.
//!
//! # Rotation (a state's `environmentRotation`, θ degrees about +Y)
//!
//! It is Blender's Mapping node (type POINT) Z rotation on the lookup vector:
//! `svm_mapping` returns `transform_direction(euler_to_transform(rot), v * scale) + loc`, and
//! for a Z-only Euler `euler_to_transform` is the counter-clockwise
//! `[[cos, −sin, 0], [sin, cos, 0], [0, 0, 1]]`. Conjugated by the axis change (a proper
//! rotation taking Blender +Z to our +Y) this is R_Y(θ): X' = X cos θ + Z sin θ, Y' = Y,
//! Z' = −X sin θ + Z cos θ, and the map is looked up at R_Y(θ) ω. Then atan2(Z', X') =
//! atan2(Z, X) − θ, so u' = u − θ/2π: the radiance seen is the image rolled by +θW/360 columns
//! toward larger column indices (`np.roll(img, +θW/360, axis=1)`), i.e. the world is turned by
//! −θ about +Y. This agrees with `blender/lfenv.py::rotate_env`, whose Blender test renders
//! both, and with the DomeLight note in `src/io/usd.rs`.
//!
//! # Importance sampling
//!
//! Piecewise constant over texels: a marginal distribution over rows and a conditional one over
//! the columns of each row, both from the per-texel weight (L̄ + floor) · Ω, with Ω the texel's
//! exact solid angle (the sin θ Jacobian integrated over the row) and L̄ the luminance of the
//! *bilinear* radiance averaged over the texel (a separable [⅛, ¾, ⅛] filter with the same
//! wrap as the lookup). Within the chosen texel the direction is uniform in solid angle
//! (uniform in cos θ and φ), so pdf_ω = p(texel) / Ω(texel): bounded at the poles, unlike
//! uniform-in-(u, v) sampling whose pdf p·WH/(2π² sin θ) diverges there.
//!
//! Since the lookup is bilinear, radiance bleeds half a texel into black neighbours; the filter
//! makes L̄ > 0 in every texel where the bilinear radiance is anywhere > 0, and a small uniform
//! floor ([`UNIFORM_FLOOR`] of the mean) keeps pdf > 0 everywhere besides (an all-black or
//! negative map becomes uniform sampling). So the estimator L/pdf is unbiased.

use crate::scene::Environment;
use glam::Vec3;
use std::f32::consts::PI;

/// Share of the mean luminance added to every texel's sampling weight: pdf > 0 everywhere at
/// the cost of ~0.1 % of samples spent uniformly.
pub const UNIFORM_FLOOR: f32 = 1e-3;
/// Rec.709 luminance weights (scene-linear).
const LUMA: [f32; 3] = [0.2126, 0.7152, 0.0722];

/// (u, t) of a LightFuse direction (no rotation): u = 0.5 + atan2(Z, X)/2π along the row,
/// t = acos(Y)/π down from the top row. See the module docs for the derivation from Cycles.
pub fn direction_to_uv(dir: Vec3) -> [f32; 2] {
    let len = dir.length();
    if len == 0.0 {
        return [0.0, 0.0]; // Cycles: zero vector → (0, 0)
    }
    // Written as Cycles writes it (Blender b = (X, −Z, Y)), so that even the signed zeros at the
    // poles and the seam land on the same u.
    let u = ((-dir.z).atan2(dir.x) - PI) / (-2.0 * PI);
    let t = (dir.y / len).clamp(-1.0, 1.0).acos() / PI;
    [u, t]
}

/// The inverse of [`direction_to_uv`]: unit direction for (u, t).
pub fn uv_to_direction(uv: [f32; 2]) -> Vec3 {
    let phi = 2.0 * PI * (uv[0] - 0.5);
    let theta = PI * uv[1];
    let (st, ct) = theta.sin_cos();
    let (sp, cp) = phi.sin_cos();
    Vec3::new(st * cp, ct, st * sp)
}

/// A direction drawn by [`EnvMap::sample`]: its radiance (= `eval(dir)`) and pdf in solid
/// angle (= `pdf(dir)`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EnvSample {
    pub dir: Vec3,
    pub radiance: [f32; 3],
    pub pdf: f32,
}

/// An environment ready for lookups and sampling, with its rotation about +Y.
#[derive(Clone, Debug)]
pub struct EnvMap {
    width: usize,
    height: usize,
    pixels: Vec<[f32; 3]>,
    rotation_deg: f32,
    /// cos θ, sin θ of the rotation.
    rot: (f32, f32),
    /// Marginal CDF over rows, `height + 1` entries from 0 to 1.
    row_cdf: Vec<f32>,
    /// Conditional CDFs over columns, `width + 1` entries per row.
    col_cdf: Vec<f32>,
    /// pdf in solid angle per texel: p(texel) / Ω(texel).
    texel_pdf: Vec<f32>,
    /// cos θ at the `height + 1` row boundaries (θ = π y / H).
    row_cos: Vec<f32>,
}

impl EnvMap {
    /// Builds lookups and the sampling distribution for `env` turned by `rotation_deg` (a
    /// state's `environmentRotation`).
    pub fn new(env: &Environment, rotation_deg: f32) -> EnvMap {
        let (w, h) = (env.width, env.height);
        assert!(w > 0 && h > 0, "environment {:?} is empty", env.name);
        let lum: Vec<f64> = env
            .pixels
            .iter()
            .map(|p| {
                (0..3)
                    .map(|c| p[c].max(0.0) as f64 * LUMA[c] as f64)
                    .sum::<f64>()
            })
            .collect();
        // Mean of the bilinear interpolant over each texel: [1/8, 3/4, 1/8] in x then y, with
        // the lookup's periodic wrap.
        const K: [f64; 3] = [0.125, 0.75, 0.125];
        let mut tmp = vec![0.0f64; w * h];
        for y in 0..h {
            for x in 0..w {
                tmp[y * w + x] = (0..3)
                    .map(|k| K[k] * lum[y * w + (x + w + k - 1) % w])
                    .sum();
            }
        }
        let mut filtered = vec![0.0f64; w * h];
        for y in 0..h {
            for x in 0..w {
                filtered[y * w + x] = (0..3)
                    .map(|k| K[k] * tmp[((y + h + k - 1) % h) * w + x])
                    .sum();
            }
        }
        let omega: Vec<f64> = (0..h).map(|y| env.texel_solid_angle(y)).collect();
        let total_lum: f64 = (0..w * h).map(|i| filtered[i] * omega[i / w]).sum();
        let mean = total_lum / (4.0 * std::f64::consts::PI);
        let floor = if mean > 0.0 && mean.is_finite() {
            UNIFORM_FLOOR as f64 * mean
        } else {
            1.0
        };
        let weight = |i: usize| {
            let l = filtered[i];
            (if l.is_finite() { l } else { 0.0 } + floor) * omega[i / w]
        };

        let mut row_sum = vec![0.0f64; h];
        let mut col_cdf = vec![0.0f32; h * (w + 1)];
        for y in 0..h {
            let mut acc = 0.0f64;
            let mut cdf = vec![0.0f64; w + 1];
            for x in 0..w {
                acc += weight(y * w + x);
                cdf[x + 1] = acc;
            }
            row_sum[y] = acc;
            for x in 0..=w {
                col_cdf[y * (w + 1) + x] = (cdf[x] / acc) as f32;
            }
            col_cdf[y * (w + 1) + w] = 1.0;
        }
        let total: f64 = row_sum.iter().sum();
        let mut row_cdf = vec![0.0f32; h + 1];
        let mut acc = 0.0f64;
        for y in 0..h {
            acc += row_sum[y];
            row_cdf[y + 1] = (acc / total) as f32;
        }
        row_cdf[h] = 1.0;
        let texel_pdf = (0..w * h)
            .map(|i| (weight(i) / total / omega[i / w]) as f32)
            .collect();
        let row_cos = (0..=h)
            .map(|y| (std::f64::consts::PI * y as f64 / h as f64).cos() as f32)
            .collect();
        let r = (rotation_deg as f64).to_radians();
        EnvMap {
            width: w,
            height: h,
            pixels: env.pixels.clone(),
            rotation_deg,
            rot: (r.cos() as f32, r.sin() as f32),
            row_cdf,
            col_cdf,
            texel_pdf,
            row_cos,
        }
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    pub fn rotation_deg(&self) -> f32 {
        self.rotation_deg
    }

    /// World direction → the direction the map is looked up at: R_Y(θ) ω.
    fn world_to_map(&self, d: Vec3) -> Vec3 {
        let (c, s) = self.rot;
        Vec3::new(c * d.x + s * d.z, d.y, -s * d.x + c * d.z)
    }

    /// The inverse: R_Y(−θ) ω.
    fn map_to_world(&self, d: Vec3) -> Vec3 {
        let (c, s) = self.rot;
        Vec3::new(c * d.x - s * d.z, d.y, s * d.x + c * d.z)
    }

    /// (u, t) at which the world direction `dir` reads the map (rotation included).
    pub fn uv(&self, dir: Vec3) -> [f32; 2] {
        direction_to_uv(self.world_to_map(dir))
    }

    /// The bilinear footprint of `dir`: four (texel index, weight) pairs, weights summing to
    /// one; `eval` is Σ weight · texel, so this is also ∂eval/∂texel (path replay).
    pub fn texel_weights(&self, dir: Vec3) -> [(usize, f32); 4] {
        let [u, t] = self.uv(dir);
        let (w, h) = (self.width as i64, self.height as i64);
        let x = u * self.width as f32 - 0.5;
        let y = t * self.height as f32 - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (x0, y0) = (x0 as i64, y0 as i64);
        let ix = |x: i64| x.rem_euclid(w) as usize;
        let iy = |y: i64| y.rem_euclid(h) as usize;
        let idx = |x: i64, y: i64| iy(y) * self.width + ix(x);
        [
            (idx(x0, y0), (1.0 - fx) * (1.0 - fy)),
            (idx(x0 + 1, y0), fx * (1.0 - fy)),
            (idx(x0, y0 + 1), (1.0 - fx) * fy),
            (idx(x0 + 1, y0 + 1), fx * fy),
        ]
    }

    /// Radiance arriving from direction `dir` (pointing away from the scene): bilinear, wrap in
    /// u and (as Cycles) in v.
    pub fn eval(&self, dir: Vec3) -> [f32; 3] {
        let mut out = [0.0f32; 3];
        for (i, wgt) in self.texel_weights(dir) {
            let p = self.pixels[i];
            for c in 0..3 {
                out[c] += wgt * p[c];
            }
        }
        out
    }

    /// Texel (column, row) holding `dir` for the sampling distribution.
    fn texel_of(&self, dir: Vec3) -> (usize, usize) {
        let [u, t] = self.uv(dir);
        let x = ((u * self.width as f32).floor() as i64).rem_euclid(self.width as i64) as usize;
        let y = ((t * self.height as f32) as usize).min(self.height - 1);
        (x, y)
    }

    /// Density of [`EnvMap::sample`] in solid angle at the world direction `dir`.
    pub fn pdf(&self, dir: Vec3) -> f32 {
        let (x, y) = self.texel_of(dir);
        self.texel_pdf[y * self.width + x]
    }

    /// Draws a direction with density ∝ (filtered luminance + floor): row from the marginal,
    /// column from the row's conditional, then uniform in solid angle inside the texel (the
    /// remainders of `u` rescaled, which keeps a low-discrepancy `u` stratified).
    pub fn sample(&self, u: [f32; 2]) -> EnvSample {
        let (y, fy) = sample_cdf(&self.row_cdf, u[0]);
        let w1 = self.width + 1;
        let (x, fx) = sample_cdf(&self.col_cdf[y * w1..(y + 1) * w1], u[1]);
        let (c0, c1) = (self.row_cos[y], self.row_cos[y + 1]);
        let cos_t = (c0 + (c1 - c0) * fy).clamp(-1.0, 1.0);
        let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
        let u_col = (x as f32 + fx) / self.width as f32;
        let (sp, cp) = (2.0 * PI * (u_col - 0.5)).sin_cos();
        let dir = self.map_to_world(Vec3::new(sin_t * cp, cos_t, sin_t * sp));
        // pdf from the direction, not from (x, y): `sample` and `pdf` then agree exactly, as
        // MIS needs, even for the (measure-zero) directions that round onto a texel border.
        EnvSample {
            dir,
            radiance: self.eval(dir),
            pdf: self.pdf(dir),
        }
    }
}

/// Inverts a CDF (`n + 1` entries, 0 … 1): the bin i with cdf[i] ≤ u < cdf[i + 1] and the
/// position of u inside it, in [0, 1). Empty bins are never chosen.
fn sample_cdf(cdf: &[f32], u: f32) -> (usize, f32) {
    let n = cdf.len() - 1;
    let i = cdf.partition_point(|&c| c <= u).clamp(1, n) - 1;
    let (a, b) = (cdf[i], cdf[i + 1]);
    let f = if b > a { (u - a) / (b - a) } else { 0.5 };
    (i, f.clamp(0.0, 1.0 - f32::EPSILON))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uv_round_trips() {
        for &(u, t) in &[(0.1f32, 0.2f32), (0.5, 0.5), (0.9, 0.7), (0.3, 0.95)] {
            let [u2, t2] = direction_to_uv(uv_to_direction([u, t]));
            assert!((u - u2).abs() < 1e-5 && (t - t2).abs() < 1e-5, "{u},{t}");
        }
    }

    #[test]
    fn sample_cdf_skips_empty_bins() {
        let cdf = [0.0, 0.5, 0.5, 1.0];
        assert_eq!(sample_cdf(&cdf, 0.0).0, 0);
        assert_eq!(sample_cdf(&cdf, 0.5).0, 2);
        assert_eq!(sample_cdf(&cdf, 0.99999).0, 2);
    }

    #[test]
    fn black_map_samples_uniformly() {
        let env = Environment::constant("black", 8, 4, [0.0; 3]);
        let map = EnvMap::new(&env, 0.0);
        let p = map.pdf(Vec3::new(0.3, 0.4, 0.5).normalize());
        assert!((p - 1.0 / (4.0 * PI)).abs() < 1e-6, "{p}");
    }
}
