//! Environment maps: equirectangular lat-long float RGB (docs/design.md §2), scene-linear Rec.709.

/// A lat-long HDR environment. Row 0 is the top (+Y, the zenith); column 0 starts at the
/// direction fixed by the mapping in `shade` (Cycles' convention after the axis change).
#[derive(Clone, Debug, PartialEq)]
pub struct Environment {
    /// Name (unique in a scene): a state name or the file stem of its source.
    pub name: String,
    pub width: usize,
    pub height: usize,
    /// Row-major RGB, `width * height` texels.
    pub pixels: Vec<[f32; 3]>,
}

/// Solid angle of a texel in row `y` of a `width` × `height` lat-long map: the sin θ Jacobian,
/// 2π/width · (cos θ_y − cos θ_{y+1}).
pub fn texel_solid_angle(width: usize, height: usize, y: usize) -> f64 {
    let h = height as f64;
    let dphi = 2.0 * std::f64::consts::PI / width as f64;
    let t0 = std::f64::consts::PI * y as f64 / h;
    let t1 = std::f64::consts::PI * (y + 1) as f64 / h;
    dphi * (t0.cos() - t1.cos())
}

impl Environment {
    /// Refuses anything but an equirectangular (2:1) map; the error names `file` and `field`.
    pub fn check_latlong(&self, file: &std::path::Path, field: &str) -> crate::error::Result<()> {
        if self.width != 2 * self.height {
            return Err(crate::error::Error::invalid(
                file,
                field,
                format!(
                    "expected an equirectangular environment with width = 2 x height, found {}x{}",
                    self.width, self.height
                ),
            ));
        }
        Ok(())
    }

    pub fn new(
        name: impl Into<String>,
        width: usize,
        height: usize,
        pixels: Vec<[f32; 3]>,
    ) -> Self {
        assert_eq!(pixels.len(), width * height, "texel count");
        Environment {
            name: name.into(),
            width,
            height,
            pixels,
        }
    }

    /// Sets negative texels to 0 and returns how many there were. Lossy EXR compression (the
    /// DWAB of Blender's bundled HDRIs) rings slightly below zero near bright spots; radiance
    /// cannot be negative, and scenes refuse it.
    pub fn clamp_negative(&mut self) -> usize {
        let mut n = 0;
        for v in self.pixels.iter_mut().flatten() {
            if *v < 0.0 {
                *v = 0.0;
                n += 1;
            }
        }
        n
    }

    /// A uniform environment (the white furnace).
    pub fn constant(name: impl Into<String>, width: usize, height: usize, rgb: [f32; 3]) -> Self {
        Self::new(name, width, height, vec![rgb; width * height])
    }

    /// Solid angle of a texel in row `y` ([`texel_solid_angle`] of this map's size).
    pub fn texel_solid_angle(&self, y: usize) -> f64 {
        texel_solid_angle(self.width, self.height, y)
    }

    /// ∫ L dω per channel: the energy that resampling must keep.
    pub fn integral(&self) -> [f64; 3] {
        let mut sum = [0.0f64; 3];
        for y in 0..self.height {
            let w = self.texel_solid_angle(y);
            for p in &self.pixels[y * self.width..(y + 1) * self.width] {
                for c in 0..3 {
                    sum[c] += p[c] as f64 * w;
                }
            }
        }
        sum
    }

    /// Resamples to `width` x `height` by exact area weighting on the sphere: each target texel
    /// is the solid-angle-weighted mean of the source texels it overlaps, so ∫ L dω is kept
    /// (up to rounding) for any source and target size, up or down.
    pub fn resample(&self, width: usize, height: usize) -> Environment {
        assert!(width > 0 && height > 0, "target size");
        let (sw, sh) = (self.width, self.height);
        // 1D overlaps; phi is uniform, theta weights by cos θ0 − cos θ1.
        let overlaps = |n_src: usize, n_dst: usize, weight: &dyn Fn(f64, f64) -> f64| {
            let mut out: Vec<Vec<(usize, f64)>> = vec![Vec::new(); n_dst];
            for (d, row) in out.iter_mut().enumerate() {
                let d0 = d as f64 / n_dst as f64;
                let d1 = (d + 1) as f64 / n_dst as f64;
                let s_lo = (d0 * n_src as f64).floor() as usize;
                let s_hi = ((d1 * n_src as f64).ceil() as usize).min(n_src);
                for s in s_lo..s_hi {
                    let a = d0.max(s as f64 / n_src as f64);
                    let b = d1.min((s + 1) as f64 / n_src as f64);
                    if b > a {
                        row.push((s, weight(a, b)));
                    }
                }
            }
            out
        };
        let pi = std::f64::consts::PI;
        let col_w = overlaps(sw, width, &|a, b| b - a);
        let row_w = overlaps(sh, height, &|a, b| (pi * a).cos() - (pi * b).cos());
        let mut pixels = vec![[0.0f32; 3]; width * height];
        for (y, rows) in row_w.iter().enumerate() {
            for (x, cols) in col_w.iter().enumerate() {
                let mut acc = [0.0f64; 3];
                let mut wsum = 0.0f64;
                for &(sy, wy) in rows {
                    for &(sx, wx) in cols {
                        let w = wy * wx;
                        let p = self.pixels[sy * sw + sx];
                        for c in 0..3 {
                            acc[c] += p[c] as f64 * w;
                        }
                        wsum += w;
                    }
                }
                if wsum > 0.0 {
                    pixels[y * width + x] = [
                        (acc[0] / wsum) as f32,
                        (acc[1] / wsum) as f32,
                        (acc[2] / wsum) as f32,
                    ];
                }
            }
        }
        Environment::new(self.name.clone(), width, height, pixels)
    }
}

/// A `w × h` test map with structure in both directions and every channel different (unit
/// tests of environments and of the lighting metrics share it).
#[cfg(test)]
pub(crate) fn test_pattern(w: usize, h: usize) -> Environment {
    let px = (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            [
                (x * 7 % 13) as f32 * 0.25 + 0.1,
                (y * 3 % 5) as f32 + 0.5,
                ((x + y) % 4) as f32 * 10.0,
            ]
        })
        .collect();
    Environment::new("p", w, h, px)
}

/// A lat-long map of `width` columns from the texels some view saw (`texels`, row-major; None:
/// unseen): each unseen texel takes the mean of its row's seen texels, rows with none the
/// nearest such row's (the upper one on a tie). None when no texel was seen. The one home of
/// this guess: stage 3 starts its loop from it (`stages::invert::train::initial_environment`)
/// and its light fit holds the texels its data barely reach to it
/// (`stages::invert::lightfit::fill`).
pub fn fill_by_rows(width: usize, texels: &[Option<[f64; 3]>]) -> Option<Vec<[f64; 3]>> {
    let height = texels.len() / width;
    let rows: Vec<Option<[f64; 3]>> = texels
        .chunks(width)
        .map(|row| {
            let (mut s, mut n) = ([0.0f64; 3], 0u32);
            for v in row.iter().flatten() {
                for c in 0..3 {
                    s[c] += v[c];
                }
                n += 1;
            }
            (n > 0).then(|| s.map(|v| v / n as f64))
        })
        .collect();
    let seen: Vec<usize> = (0..height).filter(|&y| rows[y].is_some()).collect();
    if seen.is_empty() {
        return None;
    }
    Some(
        texels
            .iter()
            .enumerate()
            .map(|(j, v)| {
                let y = j / width;
                v.or(rows[y]).unwrap_or_else(|| {
                    let near = *seen
                        .iter()
                        .min_by_key(|&&r| r.abs_diff(y))
                        .expect("a seen row");
                    rows[near].expect("seen row")
                })
            })
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pattern(w: usize, h: usize) -> Environment {
        test_pattern(w, h)
    }

    #[test]
    fn resample_keeps_energy_down_and_up() {
        let env = pattern(96, 48);
        let e0 = env.integral();
        for (w, h) in [(32, 16), (256, 128), (50, 27), (1, 1)] {
            let e1 = env.resample(w, h).integral();
            for c in 0..3 {
                // f32 texels: relative error of a sum of ~5k terms stays near 1e-6.
                assert!(
                    (e0[c] - e1[c]).abs() <= 1e-5 * e0[c].abs().max(1.0),
                    "{w}x{h} ch {c}: {} vs {}",
                    e0[c],
                    e1[c]
                );
            }
        }
    }

    #[test]
    fn resample_to_same_size_is_identity_and_constant_stays_constant() {
        let env = pattern(16, 8);
        assert_eq!(env.resample(16, 8).pixels, env.pixels);
        let c = Environment::constant("c", 40, 20, [2.0, 1.0, 0.5]);
        for p in c.resample(7, 5).pixels {
            for (a, b) in p.iter().zip([2.0, 1.0, 0.5]) {
                assert!((a - b).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn solid_angles_sum_to_four_pi() {
        let env = Environment::constant("c", 8, 13, [1.0; 3]);
        let total: f64 = (0..13).map(|y| env.texel_solid_angle(y) * 8.0).sum();
        assert!((total - 4.0 * std::f64::consts::PI).abs() < 1e-12);
    }
}
