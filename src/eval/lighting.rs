//! Stage 3's lighting and material figures against ground truth (evaluation only): a recovered
//! environment against the map that lit the state, recovered base colour against the dataset's
//! albedo pass, and per-object metallic / roughness against the values the generator recorded.
//! The definitions are in `docs/lighting-metrics.md`.
//!
//! Environments are compared texel by texel in one map frame: the caller passes the recovered
//! map and the truth in the same frame (LightFuse's lat-long convention, `shade::envmap`). A
//! dataset's truth environments are already rotated as Cycles used them
//! ([`crate::io::dataset::Dataset::environment`]), which is the frame stage 3 recovers in; no
//! rotation is applied or searched for here.

use crate::io::dataset::DatasetObject;
use crate::scene::Environment;
use serde::{Deserialize, Serialize};

/// Rec. 709 / sRGB luminance weights (scene-linear).
pub const LUMINANCE: [f64; 3] = [0.2126, 0.7152, 0.0722];

/// A recovered environment against the truth (see [`compare_environments`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EnvFigures {
    /// PSNR in dB of `scale`·recovered against the resampled truth: solid-angle-weighted MSE
    /// over all texels and channels, peak = the resampled truth's largest texel value (any
    /// channel). +inf when they agree exactly (serde_json writes that as null).
    pub psnr_db: f64,
    /// The global factor s minimising Σ_i Ω_i |s·R_i − T_i|² over texels and channels.
    pub scale: f64,
    /// (P_R − P_T) / P_T, P = ∫ luminance dΩ, of the maps as given (no scale fit).
    pub power_error: f64,
    /// Texels compared: the recovered map's width × height.
    pub texels: usize,
    /// Solid-angle-weighted RMS of ln((s'·R + ε) / (T + ε)) over texels, on luminance, with s'
    /// the log-space fit (the weighted mean log ratio) and ε = 1 % of the truth's mean
    /// luminance: the typical factor by which a direction's brightness is off, exp(·) − 1 as a
    /// relative error. Judges the whole sphere where `psnr_db` judges the sun.
    pub log_rmse: f64,
    /// `log_rmse` of the best uniform map: the bar a recovery has to clear.
    pub log_rmse_uniform: f64,
    /// `log_rmse` over the upper hemisphere alone (texel centres above the horizon, with their
    /// own fit): the sky and the sun, which light a room, apart from the ground every capture
    /// sees and that dominates a whole-sphere figure. 0 in reports written before the field.
    #[serde(default)]
    pub log_rmse_upper: f64,
    /// `log_rmse_upper` of the best uniform map.
    #[serde(default)]
    pub log_rmse_upper_uniform: f64,
    /// Relative L1 error of the diffuse irradiance E(n) = ∫ L(ω) max(0, n·ω) dω over every
    /// normal n on the sphere, after a least-squares gain: what a Lambertian surface lit by the
    /// map sees, so it weighs the sun by the light it casts, not by its texel value.
    pub irradiance_error: f64,
    /// `irradiance_error` of a uniform map (constant irradiance): the bar to clear.
    pub irradiance_error_uniform: f64,
}

/// Map size on which irradiance is integrated, and the grid of normals it is evaluated at
/// (texel centres of a lat-long map of half that size): diffuse irradiance is a low-pass
/// function of the map (a cosine lobe), so a 64 × 32 area average loses nothing visible in it.
const IRRADIANCE_MAP: (usize, usize) = (64, 32);
const IRRADIANCE_NORMALS: (usize, usize) = (32, 16);

/// The map area-averaged to `IRRADIANCE_MAP`, as one light per texel: its direction and
/// Ω·L, so that E(n) = ∫ L(ω) max(0, n·ω) dω ≈ Σ Ω·L max(0, n·ω) ([`irradiance_at`]).
fn irradiance_lights(env: &Environment) -> Vec<([f64; 3], [f64; 3])> {
    let (mw, mh) = IRRADIANCE_MAP;
    let map = env.resample(mw, mh);
    (0..mh)
        .flat_map(|y| (0..mw).map(move |x| (x, y)))
        .map(|(x, y)| {
            let o = map.texel_solid_angle(y);
            let l = map.pixels[y * mw + x];
            (texel_dir(x, y, mw, mh), [0, 1, 2].map(|c| l[c] as f64 * o))
        })
        .collect()
}

/// The direction of texel (x, y)'s centre in a `w` × `h` lat-long map.
fn texel_dir(x: usize, y: usize, w: usize, h: usize) -> [f64; 3] {
    let d = crate::shade::envmap::uv_to_direction([
        (x as f32 + 0.5) / w as f32,
        (y as f32 + 0.5) / h as f32,
    ]);
    [d.x as f64, d.y as f64, d.z as f64]
}

/// E(n) per channel from [`irradiance_lights`].
fn irradiance_at(lights: &[([f64; 3], [f64; 3])], n: [f64; 3]) -> [f64; 3] {
    let mut e = [0.0f64; 3];
    for (d, l) in lights {
        let c = n[0] * d[0] + n[1] * d[1] + n[2] * d[2];
        if c > 0.0 {
            for k in 0..3 {
                e[k] += l[k] * c;
            }
        }
    }
    e
}

/// Irradiance E(n) per channel at the texel centres of a `IRRADIANCE_NORMALS` grid, from the
/// map area-averaged to `IRRADIANCE_MAP`; with each normal's solid angle.
fn irradiance(env: &Environment) -> Vec<([f64; 3], f64)> {
    let lights = irradiance_lights(env);
    let (nw, nh) = IRRADIANCE_NORMALS;
    (0..nh)
        .flat_map(|y| (0..nw).map(move |x| (x, y)))
        .map(|(x, y)| {
            let e = irradiance_at(&lights, texel_dir(x, y, nw, nh));
            (e, crate::scene::environment::texel_solid_angle(nw, nh, y))
        })
        .collect()
}

/// A white Lambertian sphere lit by `env`, as two orthographic views side by side (a
/// `2·size` × `size` image, row-major, top row first): from +X, the direction at the centre of
/// the lat-long map, then from −X; +Y (the zenith) up in both. Each pixel on a sphere holds its
/// radiance E(n) / π (the same irradiance as [`EnvFigures::irradiance_error`] judges); pixels
/// off the spheres are `None`. What a matte object placed in the scene would look like under the
/// map, which is the part of the lighting a diffuse surface can tell apart.
pub fn irradiance_sphere(env: &Environment, size: usize) -> Vec<Option<[f32; 3]>> {
    let lights = irradiance_lights(env);
    let mut out = vec![None; 2 * size * size];
    for (i, px) in out.iter_mut().enumerate() {
        let (x, y) = (i % (2 * size), i / (2 * size));
        let view = x / size;
        // Disc coordinates: a to the right, b up, both in [-1, 1].
        let a = 2.0 * ((x % size) as f64 + 0.5) / size as f64 - 1.0;
        let b = 1.0 - 2.0 * (y as f64 + 0.5) / size as f64;
        let r2 = a * a + b * b;
        if r2 > 1.0 {
            continue;
        }
        let c = (1.0 - r2).sqrt();
        // Seen from +X the camera's right is −Z; seen from −X it is +Z.
        let n = if view == 0 { [c, b, -a] } else { [-c, b, a] };
        let e = irradiance_at(&lights, n);
        *px = Some(e.map(|v| (v / std::f64::consts::PI) as f32));
    }
    out
}

/// Σ_n Ω_n Σ_c |g·a − b| / Σ_n Ω_n Σ_c b with g the least-squares gain of a onto b.
fn fitted_relative_l1(a: &[([f64; 3], f64)], b: &[([f64; 3], f64)]) -> f64 {
    let (mut ab, mut aa) = (0.0, 0.0);
    for ((x, o), (y, _)) in a.iter().zip(b) {
        for c in 0..3 {
            ab += o * x[c] * y[c];
            aa += o * x[c] * x[c];
        }
    }
    let g = if aa > 0.0 { ab / aa } else { 0.0 };
    let (mut num, mut den) = (0.0, 0.0);
    for ((x, o), (y, _)) in a.iter().zip(b) {
        for c in 0..3 {
            num += o * (g * x[c] - y[c]).abs();
            den += o * y[c];
        }
    }
    num / den
}

/// Solid-angle-weighted RMS of ln(s'·r + ε) − ln(t + ε) with the best s' (see
/// [`EnvFigures::log_rmse`]); `rec` and `truth` are luminances on the same grid, `omega` the
/// texels' solid angles. The best s' for a fixed ε has no closed form; the weighted mean of
/// ln(t + ε) − ln(r + ε) (exact when ε = 0) is used, then the RMS taken with ε in place.
fn log_rmse(rec: &[f64], truth: &[f64], omega: &[f64]) -> f64 {
    let osum: f64 = omega.iter().sum();
    let mean_t = truth.iter().zip(omega).map(|(t, o)| t * o).sum::<f64>() / osum;
    let eps = (0.01 * mean_t).max(f64::MIN_POSITIVE);
    let mean_r = rec.iter().zip(omega).map(|(r, o)| r * o).sum::<f64>() / osum;
    // Bring R to the truth's mean first so ε means the same on both sides, then fit in log.
    let pre = if mean_r > 0.0 { mean_t / mean_r } else { 1.0 };
    let diff = |s: f64| {
        rec.iter()
            .zip(truth)
            .map(move |(r, t)| (s * pre * r + eps).ln() - (t + eps).ln())
    };
    let offset = diff(1.0).zip(omega).map(|(d, o)| d * o).sum::<f64>() / osum;
    let s = (-offset).exp();
    (diff(s).zip(omega).map(|(d, o)| d * d * o).sum::<f64>() / osum).sqrt()
}

/// Area-averages `truth` onto a `width` × `height` lat-long grid: each target texel is the
/// solid-angle-weighted mean of the truth texels it overlaps ([`Environment::resample`]). When
/// the sizes are not integer multiples, a truth texel cut by a target texel's border counts with
/// the part of it inside (its overlap in φ times its overlap in cos θ), so ∫ L dΩ is kept for any
/// ratio. Same size: the truth itself.
pub fn resample_truth(truth: &Environment, width: usize, height: usize) -> Environment {
    if (truth.width, truth.height) == (width, height) {
        truth.clone()
    } else {
        truth.resample(width, height)
    }
}

/// ∫ luminance(L) dΩ over the sphere (Rec. 709 weights, [`LUMINANCE`]).
pub fn luminous_power(env: &Environment) -> f64 {
    env.integral()
        .iter()
        .zip(LUMINANCE)
        .map(|(e, w)| e * w)
        .sum()
}

/// Compares a recovered environment with the truth, both lat-long maps in the same frame.
/// The truth (any size, e.g. a 2k HDRI) is first area-averaged to the recovered map's size
/// ([`resample_truth`]); then, with Ω_i the solid angle of texel i
/// ([`Environment::texel_solid_angle`]), R the recovered and T the resampled truth:
///
/// - `scale` s = Σ Ω_i R_i·T_i / Σ Ω_i R_i·R_i (sums over texels and the three channels), the
///   least-squares fit of R to T; 0 when R is zero everywhere.
/// - MSE = Σ Ω_i |s·R_i − T_i|² / (3 Σ Ω_i) and `psnr_db` = 10 log10(peak² / MSE) with peak =
///   max over texels and channels of T. HDR maps have no natural peak; the truth's brightest
///   texel at the compared resolution makes the figure independent of the truth's exposure.
///   With a sun in the truth, the sun is both the peak and nearly all of the MSE, so this figure
///   says little more than whether the sun was recovered: a recovery without it scores
///   10 log10(12π / Ω_sun) whatever the rest of its sky is (measured: the same 47.81 dB on two
///   scenes). `log_rmse` and `irradiance_error` judge the rest.
/// - `log_rmse`, `irradiance_error` and their uniform-map bars: see [`EnvFigures`] and
///   `docs/lighting-metrics.md`.
/// - `power_error` = (P_R − P_T) / P_T with P = ∫ luminance dΩ ([`luminous_power`]), of R and
///   of the truth as given (before the fit; resampling keeps P).
///
/// Panics when either map is empty.
pub fn compare_environments(recovered: &Environment, truth: &Environment) -> EnvFigures {
    assert!(
        recovered.width * recovered.height > 0 && truth.width * truth.height > 0,
        "empty environment"
    );
    let t = resample_truth(truth, recovered.width, recovered.height);
    let w = recovered.width;
    let (mut rr, mut rt, mut omega_sum) = (0.0f64, 0.0f64, 0.0f64);
    for y in 0..recovered.height {
        let omega = recovered.texel_solid_angle(y);
        omega_sum += omega * w as f64;
        for x in 0..w {
            let (r, q) = (recovered.pixels[y * w + x], t.pixels[y * w + x]);
            for c in 0..3 {
                rr += omega * r[c] as f64 * r[c] as f64;
                rt += omega * r[c] as f64 * q[c] as f64;
            }
        }
    }
    let scale = if rr > 0.0 { rt / rr } else { 0.0 };
    let mut se = 0.0f64;
    for y in 0..recovered.height {
        let omega = recovered.texel_solid_angle(y);
        for x in 0..w {
            let (r, q) = (recovered.pixels[y * w + x], t.pixels[y * w + x]);
            for c in 0..3 {
                se += omega * (scale * r[c] as f64 - q[c] as f64).powi(2);
            }
        }
    }
    let mse = se / (3.0 * omega_sum);
    let peak = t
        .pixels
        .iter()
        .flatten()
        .fold(f64::NEG_INFINITY, |m, &v| m.max(v as f64));
    let p_t = luminous_power(truth);
    let luma = |e: &Environment| -> Vec<f64> {
        e.pixels
            .iter()
            .map(|p| (0..3).map(|c| LUMINANCE[c] * p[c] as f64).sum())
            .collect()
    };
    let omega: Vec<f64> = (0..recovered.height)
        .flat_map(|y| std::iter::repeat_n(recovered.texel_solid_angle(y), w))
        .collect();
    let (lr, lt) = (luma(recovered), luma(&t));
    // Row y's centre is above the horizon when y + 0.5 < height / 2 (row 0 is the zenith's).
    let upper: Vec<f64> = omega
        .iter()
        .enumerate()
        .map(|(i, &o)| {
            if 2 * (i / w) + 1 < recovered.height {
                o
            } else {
                0.0
            }
        })
        .collect();
    let e_t = irradiance(&t);
    // The best uniform map has the truth's mean colour; its irradiance is that colour times π
    // everywhere (only its colour matters: the gain is fitted).
    let mean_colour = truth.integral();
    let e_uniform: Vec<_> = e_t.iter().map(|&(_, o)| (mean_colour, o)).collect();
    EnvFigures {
        psnr_db: 10.0 * (peak * peak / mse).log10(),
        scale,
        power_error: (luminous_power(recovered) - p_t) / p_t,
        texels: recovered.width * recovered.height,
        log_rmse: log_rmse(&lr, &lt, &omega),
        log_rmse_uniform: log_rmse(&vec![1.0; lt.len()], &lt, &omega),
        log_rmse_upper: log_rmse(&lr, &lt, &upper),
        log_rmse_upper_uniform: log_rmse(&vec![1.0; lt.len()], &lt, &upper),
        irradiance_error: fitted_relative_l1(&irradiance(recovered), &e_t),
        irradiance_error_uniform: fitted_relative_l1(&e_uniform, &e_t),
    }
}

/// Recovered base colour against the albedo pass (see [`compare_albedo`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AlbedoFigures {
    /// Pixel pairs compared.
    pub pixels: usize,
    /// Relative error of the predictions as they are (definition at [`compare_albedo`]).
    pub raw_error: f64,
    /// The same after multiplying each channel of the predictions by `ratio`.
    pub scaled_error: f64,
    /// Per channel, the median over pixels of truth / predicted (pixels with predicted > 1e-4).
    pub ratio: [f64; 3],
    /// How uniform the recovered base colour is where the truth is ([`albedo_uniformity`]):
    /// shadows or highlights of the captures baked into it show here. Absent in reports
    /// written before the field, and when no surface qualifies.
    #[serde(default)]
    pub uniformity: Option<UniformityFigures>,
}

/// Over the surfaces whose true albedo is uniform, how much the recovered base colour varies
/// ([`albedo_uniformity`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct UniformityFigures {
    /// Uniform surfaces found: distinct true albedos covering at least [`UNIFORM_MIN_PIXELS`]
    /// pixels.
    pub surfaces: usize,
    /// Their pixels.
    pub pixels: usize,
    /// Share of those pixels whose recovered / true luminance ratio is more than
    /// [`GHOST_TOLERANCE`] off their surface's median ratio: ghost shadows (a capture's shadow
    /// painted into the base colour) and ghost highlights.
    pub ghost_share: f64,
    /// Mean over those pixels of |ratio / surface median − 1|.
    pub spread: f64,
}

/// A true albedo counts as a uniform surface when this many pixel pairs have it.
pub const UNIFORM_MIN_PIXELS: usize = 64;
/// A pixel's ratio more than this far from its surface's median (relative) is a ghost.
pub const GHOST_TOLERANCE: f64 = 0.15;

/// Ghost shadows, measured: (predicted, true) base colour pairs grouped by the true albedo
/// (quantised to 1/4096 per channel, so a uniform material's pixels fall together while
/// textures scatter over many values: a checker's two colours are two uniform surfaces); each
/// group of at least [`UNIFORM_MIN_PIXELS`] pixels is a surface whose recovered base colour
/// should be uniform too, up to one gain. Per pixel the luminance ratio r = p / t; the share of
/// pixels with |r / median_surface(r) − 1| > [`GHOST_TOLERANCE`], and the mean of that
/// deviation. Pixels with a true luminance below 1e-3 are left out (no ratio). `None` when no
/// surface qualifies.
pub fn albedo_uniformity(pairs: &[([f32; 3], [f32; 3])]) -> Option<UniformityFigures> {
    albedo_uniformity_over(pairs, |_| true)
}

/// [`albedo_uniformity`] counted over the pairs `keep` selects (by index into `pairs`), with
/// the same surfaces and each surface's median ratio from all its pairs: how far one part of a
/// surface strays from what the whole surface says (e.g. where a training state's shadow fell,
/// [`crate::eval::shadows`]). A surface counts when it qualifies by all its pairs and has a
/// kept one; `None` when no kept pair is on a surface that qualifies.
pub fn albedo_uniformity_over(
    pairs: &[([f32; 3], [f32; 3])],
    keep: impl Fn(usize) -> bool,
) -> Option<UniformityFigures> {
    uniformity_of(&albedo_deviation(pairs), keep)
}

/// [`albedo_uniformity_over`] from the pairs' [`albedo_deviation`], computed once: the figures
/// of several parts of one set of pairs (the report's per-view figures).
pub fn uniformity_of(
    deviations: &[Option<(usize, f64)>],
    keep: impl Fn(usize) -> bool,
) -> Option<UniformityFigures> {
    let mut surfaces = std::collections::BTreeSet::new();
    let (mut pixels, mut ghosts, mut deviation) = (0, 0, 0.0f64);
    for (i, dev) in deviations.iter().enumerate() {
        let Some((surface, d)) = *dev else { continue };
        if !keep(i) {
            continue;
        }
        surfaces.insert(surface);
        pixels += 1;
        deviation += d.abs();
        if d.abs() > GHOST_TOLERANCE {
            ghosts += 1;
        }
    }
    (pixels > 0).then(|| UniformityFigures {
        surfaces: surfaces.len(),
        pixels,
        ghost_share: ghosts as f64 / pixels as f64,
        spread: deviation / pixels as f64,
    })
}

/// A true albedo quantised to 1/4096 per channel: pixels with one key are one material.
pub fn albedo_key(t: [f32; 3]) -> [u32; 3] {
    t.map(|v| (v.clamp(0.0, 1.0) * 4096.0).round() as u32)
}

/// How far (pixels, in the max norm) a pixel must be from every pixel of another true albedo
/// to count as away from a seam ([`away_from_seams`]).
pub const SEAM_PIXELS: usize = 2;

/// Per pixel of an albedo pass (`w` wide, row-major): whether every pixel within
/// [`SEAM_PIXELS`] (the image's border aside) has its [`albedo_key`]. The ghost figure counted
/// over such pixels only tells a base colour painted by the light (a shadow is wider than
/// four pixels) from one blurred across a texture's edges, where a surfel straddling a
/// checker's seam puts one tile's colour on the other's pixels (issue 44: on the demo most
/// ghosts are there).
pub fn away_from_seams(truth: &[[f32; 3]], w: usize) -> Vec<bool> {
    let h = truth.len() / w.max(1);
    let keys: Vec<[u32; 3]> = truth.iter().map(|&t| albedo_key(t)).collect();
    let r = SEAM_PIXELS as i64;
    (0..truth.len())
        .map(|i| {
            let (x, y) = ((i % w) as i64, (i / w) as i64);
            (-r..=r).all(|dy| {
                (-r..=r).all(|dx| {
                    let (u, v) = (x + dx, y + dy);
                    u < 0
                        || v < 0
                        || u >= w as i64
                        || v >= h as i64
                        || keys[v as usize * w + u as usize] == keys[i]
                })
            })
        })
        .collect()
}

/// Each pair's place on the uniform surfaces of [`albedo_uniformity`]: the surface (its index
/// among the qualifying surfaces, in the order of their quantised true albedo) and the signed
/// deviation r / median_surface(r) − 1 of its luminance ratio r = p / t (below zero: darker
/// than the rest of its surface, as a painted shadow is); None for a pair on no qualifying
/// surface or with no ratio. The one definition behind the ghost figures and the report's
/// per-view ghost maps.
pub fn albedo_deviation(pairs: &[([f32; 3], [f32; 3])]) -> Vec<Option<(usize, f64)>> {
    let luma = |c: [f32; 3]| (0..3).map(|k| LUMINANCE[k] * c[k] as f64).sum::<f64>();
    let mut groups: std::collections::BTreeMap<[u32; 3], Vec<(usize, f64)>> = Default::default();
    for (i, (p, t)) in pairs.iter().enumerate() {
        let lt = luma(*t);
        if lt < 1e-3 {
            continue;
        }
        groups
            .entry(albedo_key(*t))
            .or_default()
            .push((i, luma(*p) / lt));
    }
    let mut out = vec![None; pairs.len()];
    let mut surface = 0;
    for members in groups.values() {
        if members.len() < UNIFORM_MIN_PIXELS {
            continue;
        }
        let mut ratios: Vec<f64> = members.iter().map(|m| m.1).collect();
        let m = crate::stats::median(&mut ratios).expect("a surface has pixels");
        if m <= 0.0 {
            continue;
        }
        for &(i, r) in members {
            out[i] = Some((surface, r / m - 1.0));
        }
        surface += 1;
    }
    out
}

/// Relative error per channel, Σ|p − t| / Σ t, averaged over the channels whose Σ t > 0.
fn relative_error(pairs: &[([f32; 3], [f32; 3])], gain: [f64; 3]) -> f64 {
    let (mut sum, mut n) = (0.0, 0);
    for c in 0..3 {
        let (mut abs, mut tot) = (0.0f64, 0.0f64);
        for (p, t) in pairs {
            abs += (gain[c] * p[c] as f64 - t[c] as f64).abs();
            tot += t[c] as f64;
        }
        if tot > 0.0 {
            sum += abs / tot;
            n += 1;
        }
    }
    if n == 0 {
        f64::NAN
    } else {
        sum / n as f64
    }
}

/// Compares (predicted, truth) base colours of surface pixels (the caller keeps only pixels
/// where the albedo pass hit something, i.e. is not 0, and where the prediction is defined).
///
/// The error of one channel is the mean absolute error divided by the mean truth,
/// Σ|p − t| / Σ t, and `raw_error` is its mean over the three channels. So "within 5 %" reads:
/// on average the prediction is off by 5 % of the typical albedo of that channel. A per-pixel
/// relative error |p − t| / t is not used because it explodes on dark materials (a black
/// plastic of 0.03 would dominate any mean), and any floor under t would be arbitrary. Channels
/// whose truth sums to 0 are left out of the mean; with none left, NaN.
///
/// `ratio[c]` is the median over pixels with p_c > 1e-4 of t_c / p_c (the upper median, as
/// [`crate::stats::median`]): the per-channel gain that inverse rendering cannot tell
/// from the light's colour and strength. It is NaN when no pixel qualifies, and `scaled_error`
/// then uses gain 1 for that channel. `scaled_error` is `raw_error`'s definition applied to
/// ratio ⊙ p.
pub fn compare_albedo(pairs: &[([f32; 3], [f32; 3])]) -> AlbedoFigures {
    let ratio: [f64; 3] = std::array::from_fn(|c| {
        let mut r: Vec<f64> = pairs
            .iter()
            .filter(|(p, _)| p[c] > 1e-4)
            .map(|(p, t)| t[c] as f64 / p[c] as f64)
            .collect();
        crate::stats::median(&mut r).unwrap_or(f64::NAN)
    });
    let gain = ratio.map(|r| if r.is_finite() { r } else { 1.0 });
    AlbedoFigures {
        pixels: pairs.len(),
        raw_error: relative_error(pairs, [1.0; 3]),
        scaled_error: relative_error(pairs, gain),
        ratio,
        uniformity: albedo_uniformity(pairs),
    }
}

/// One object's recovered metallic and roughness (see [`compare_materials`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MaterialFigures {
    pub object: String,
    /// Surface pixels of the object (by mask id) that were averaged.
    pub pixels: usize,
    /// Mean predicted metallic over those pixels (NaN when there are none).
    pub metallic: f64,
    /// Mean predicted roughness over those pixels (NaN when there are none).
    pub roughness: f64,
    /// The dataset's value (`objects[].material`), when recorded.
    pub metallic_truth: Option<f64>,
    pub roughness_truth: Option<f64>,
}

/// Per-object means of per-pixel (object id, predicted metallic, predicted roughness), one
/// entry per dataset object in the dataset's order, with its recorded truth. Pixels whose id
/// is 0 (background) or not an object's are ignored. The mean, not the median: the truth is
/// an area-weighted mean over the object's materials, and the mean over its visible pixels is
/// the matching (projected-area-weighted) figure, where a median would pick one material of a
/// two-material object.
pub fn compare_materials(
    samples: &[(u32, f32, f32)],
    objects: &[DatasetObject],
) -> Vec<MaterialFigures> {
    objects
        .iter()
        .map(|o| {
            let (mut n, mut m, mut r) = (0usize, 0.0f64, 0.0f64);
            for &(id, pm, pr) in samples {
                if id == o.id {
                    n += 1;
                    m += pm as f64;
                    r += pr as f64;
                }
            }
            MaterialFigures {
                object: o.name.clone(),
                pixels: n,
                metallic: m / n as f64,
                roughness: r / n as f64,
                metallic_truth: o.material.map(|t| t.metallic),
                roughness_truth: o.material.map(|t| t.roughness),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pattern(w: usize, h: usize) -> Environment {
        crate::scene::environment::test_pattern(w, h)
    }

    #[test]
    fn a_map_against_itself_times_three() {
        let truth = pattern(256, 128);
        let mut rec = truth.clone();
        for v in rec.pixels.iter_mut().flatten() {
            *v *= 3.0;
        }
        let f = compare_environments(&rec, &truth);
        // 3·T is rounded to f32: agreement to ~1e-8, not exactly.
        assert!((f.scale - 1.0 / 3.0).abs() < 1e-7, "{f:?}");
        assert!(f.psnr_db > 100.0, "{f:?}");
        assert!((f.power_error - 2.0).abs() < 1e-7, "{f:?}");
        assert_eq!(f.texels, 256 * 128);
        let same = compare_environments(&truth, &truth);
        assert_eq!(same.psnr_db, f64::INFINITY);
        assert_eq!((same.scale, same.power_error), (1.0, 0.0));
    }

    #[test]
    fn a_replicated_double_size_truth_resamples_back_exactly() {
        let small = pattern(256, 128);
        let big_px = (0..512 * 256)
            .map(|i| small.pixels[(i / 512 / 2) * 256 + (i % 512) / 2])
            .collect();
        let big = Environment::new("big", 512, 256, big_px);
        let back = resample_truth(&big, 256, 128);
        for (a, b) in back.pixels.iter().zip(&small.pixels) {
            for c in 0..3 {
                assert!((a[c] - b[c]).abs() <= 1e-6 * b[c].abs(), "{a:?} vs {b:?}");
            }
        }
        let f = compare_environments(&small, &big);
        assert!((f.scale - 1.0).abs() < 1e-6 && f.psnr_db > 120.0, "{f:?}");
        assert!(f.power_error.abs() < 1e-6, "{f:?}");
    }

    #[test]
    fn non_integer_ratios_keep_power_and_a_constant_stays_constant() {
        let truth = Environment::constant("c", 300, 170, [2.0, 1.0, 0.5]);
        let rec = Environment::constant("r", 256, 128, [1.0, 0.5, 0.25]);
        let f = compare_environments(&rec, &truth);
        assert!((f.scale - 2.0).abs() < 1e-6, "{f:?}");
        assert!(f.psnr_db > 100.0, "{f:?}");
        assert!((f.power_error + 0.5).abs() < 1e-6, "{f:?}");
    }

    /// A sky (brighter towards the zenith, bluish) with, optionally, a sun: one texel of
    /// 20,000 × the sky at (x, y), as an HDRI's sun is.
    fn sky(w: usize, h: usize, sun: Option<(usize, usize)>) -> Environment {
        let mut px: Vec<[f32; 3]> = (0..w * h)
            .map(|i| {
                let v = 1.0 - (i / w) as f32 / h as f32;
                [0.3 + 0.5 * v, 0.4 + 0.6 * v, 0.6 + 0.9 * v]
            })
            .collect();
        if let Some((x, y)) = sun {
            px[y * w + x] = [20_000.0, 19_000.0, 17_000.0];
        }
        Environment::new("sky", w, h, px)
    }

    #[test]
    fn the_irradiance_sphere_of_a_uniform_sky_and_of_a_sun() {
        // L = 1 everywhere: E(n) = π for every n, so every sphere pixel is 1 (the 64 × 32
        // midpoint quadrature of the clamped cosine is good to ~1e-3).
        let size = 16;
        let white = Environment::new("white", 64, 32, vec![[1.0; 3]; 64 * 32]);
        let px = irradiance_sphere(&white, size);
        assert_eq!(px.len(), 2 * size * size);
        let on: Vec<[f32; 3]> = px.iter().flatten().copied().collect();
        // Two discs of radius size / 2: π size² / 2 pixels, ± the rims'.
        let expect = std::f64::consts::PI * (size * size) as f64 / 2.0;
        assert!(
            (on.len() as f64 - expect).abs() < 0.1 * expect,
            "{}",
            on.len()
        );
        for p in &on {
            assert!(p.iter().all(|v| (v - 1.0).abs() < 5e-3), "{p:?}");
        }
        assert!(px[0].is_none() && px[2 * size - 1].is_none());
        // A sun in the map's centre (+X, on the horizon): the first view's centre faces it,
        // the second's faces away and gets only the sky.
        let (w, h) = (256, 128);
        let sunny = sky(w, h, Some((w / 2, h / 2)));
        let s = irradiance_sphere(&sunny, size);
        let centre = |view: usize| s[(size / 2) * 2 * size + view * size + size / 2].unwrap()[0];
        let sky_only = irradiance_sphere(&sky(w, h, None), size);
        let sky_centre = sky_only[(size / 2) * 2 * size + size + size / 2].unwrap()[0];
        assert!(centre(0) > 3.0 * centre(1), "{} {}", centre(0), centre(1));
        assert!((centre(1) - sky_centre).abs() < 1e-3 * sky_centre);
        // The sky is brighter at the zenith: a sphere's top is brighter than its bottom.
        let top = sky_only[2 * size + size / 2].unwrap()[2];
        let bottom = sky_only[(size - 2) * 2 * size + size / 2].unwrap()[2];
        assert!(top > bottom, "{top} {bottom}");
    }

    #[test]
    fn the_new_figures_are_zero_for_a_scaled_copy() {
        let truth = sky(256, 128, Some((40, 30)));
        let mut rec = truth.clone();
        for v in rec.pixels.iter_mut().flatten() {
            *v *= 7.0;
        }
        let f = compare_environments(&rec, &truth);
        // f32 rounding of 7·T, then f64 sums over 32k texels: ~1e-7 relative.
        assert!(f.log_rmse < 1e-5, "{f:?}");
        assert!(f.irradiance_error < 1e-5, "{f:?}");
        assert!(
            f.log_rmse_uniform > 0.1 && f.irradiance_error_uniform > 0.1,
            "{f:?}"
        );
    }

    #[test]
    fn a_uniform_map_has_irradiance_pi_everywhere() {
        let e = irradiance(&Environment::constant("c", 256, 128, [2.0, 1.0, 0.5]));
        assert_eq!(e.len(), IRRADIANCE_NORMALS.0 * IRRADIANCE_NORMALS.1);
        let pi = std::f64::consts::PI;
        for (v, _) in &e {
            // Σ Ω_i max(0, n·ω_i) over a 64 × 32 map is a midpoint rule for the cosine lobe:
            // within 0.5 % of π at every normal (measured worst 0.06 %).
            for (c, want) in [2.0 * pi, pi, 0.5 * pi].iter().enumerate() {
                assert!((v[c] / want - 1.0).abs() < 5e-3, "{v:?}");
            }
        }
        // The normals' solid angles tile the sphere.
        let total: f64 = e.iter().map(|(_, o)| o).sum();
        assert!((total - 4.0 * pi).abs() < 1e-9);
    }

    /// Why the figures exist: two recoveries that both miss the sun, one with the truth's sky
    /// and one with a sky upside down, score the same PSNR (the missing sun is all of it), while
    /// the log error and the irradiance error tell them apart. A recovery with the sun in the
    /// right place beats the uniform bar; with it on the other side of the sky it does not.
    #[test]
    fn psnr_sees_only_the_sun_and_the_new_figures_see_the_rest() {
        let (w, h) = (256, 128);
        let truth = sky(w, h, Some((40, 30)));
        let right_sky = sky(w, h, None);
        let mut wrong_sky = right_sky.clone();
        wrong_sky.pixels.reverse();
        let a = compare_environments(&right_sky, &truth);
        let b = compare_environments(&wrong_sky, &truth);
        assert!((a.psnr_db - b.psnr_db).abs() < 0.1, "{a:?} {b:?}");
        // The missing sun alone: one texel off by ln(20,000 / 1.3) ≈ 9.6 over a share
        // Ω_sun / 4π ≈ 3e-5 of the sphere gives an RMS of ~0.055 (measured 0.058); the upside-down
        // sky is off by up to ln 2.4 everywhere (measured 0.38, twice the uniform bar's 0.20).
        assert!(a.log_rmse < 0.1 && b.log_rmse > 0.3, "{a:?} {b:?}");
        assert!(b.log_rmse > b.log_rmse_uniform, "{b:?}");
        // The sun casts ~70 % of the irradiance, so neither sky is close; the right one is
        // nearer than the uniform bar (measured 0.47 against 0.54), the upside-down one not (0.60).
        assert!(a.irradiance_error < a.irradiance_error_uniform, "{a:?}");
        assert!(b.irradiance_error > b.irradiance_error_uniform, "{b:?}");

        let sun_right = compare_environments(&truth, &sky(w, h, Some((40, 30))));
        let sun_opposite = compare_environments(&sky(w, h, Some((168, 97))), &truth);
        assert!(sun_right.irradiance_error < 1e-9, "{sun_right:?}");
        assert!(
            sun_opposite.irradiance_error > sun_opposite.irradiance_error_uniform,
            "{sun_opposite:?}"
        );
    }

    /// The log error's floor for a map that is right only at a coarse grid: the truth itself,
    /// area-averaged to the light fit's 32×16 texels (11.25°) and read back at 256×128 as a
    /// piecewise-constant map, which lights a diffuse surface almost exactly. Its sun is spread
    /// over the 8×8 fine texels of its coarse one at ~1/64 of its value, each still ~300× the
    /// sky: ln 300 ≈ 5.7 over a share ~0.4 % of the upper hemisphere is an RMS of ~0.36 alone,
    /// above the uniform bar of a smooth sky. So on a sunny sky "worse than a uniform map above
    /// the horizon" does not by itself say the light is wrong (docs/lighting-metrics.md).
    #[test]
    fn a_sun_known_at_the_fits_resolution_scores_worse_than_a_uniform_map_in_log() {
        let (w, h) = (256, 128);
        let truth = sky(w, h, Some((40, 30)));
        let coarse = truth.resample(32, 16);
        // Up by whole factors, resample's area weights copy each coarse texel: piecewise constant.
        let f = compare_environments(&coarse.resample(w, h), &truth);
        // Measured: log error above the horizon 0.37 against the uniform bar's 0.12; irradiance
        // 2.5 % against the uniform map's 54 % (the sun's direction blurred by up to ~8°).
        assert!(f.log_rmse_upper > 2.0 * f.log_rmse_upper_uniform, "{f:?}");
        assert!(f.irradiance_error < 0.05, "{f:?}");
        // At the coarse grid itself the same map is exact: the floor is the grid's, not the map's.
        let at_grid = compare_environments(&coarse, &truth);
        assert!(at_grid.log_rmse_upper < 1e-6, "{at_grid:?}");
    }

    #[test]
    fn albedo_at_half_the_truth() {
        let truth = [[0.8f32, 0.4, 0.05], [0.2, 0.6, 0.9], [0.03, 0.03, 0.035]];
        let pairs: Vec<_> = truth.iter().map(|t| (t.map(|v| v / 2.0), *t)).collect();
        let f = compare_albedo(&pairs);
        assert_eq!(f.pixels, 3);
        for r in f.ratio {
            assert!((r - 2.0).abs() < 1e-6, "{f:?}");
        }
        assert!((f.raw_error - 0.5).abs() < 1e-6, "{f:?}");
        assert!(f.scaled_error < 1e-6, "{f:?}");
    }

    #[test]
    fn albedo_without_usable_pixels() {
        let f = compare_albedo(&[([0.0, 0.5, 0.5], [0.2, 0.5, 0.5])]);
        assert!(f.ratio[0].is_nan() && f.ratio[1] == 1.0);
        // Channel 0 keeps gain 1: |0 − 0.2| / 0.2 = 1, the others are exact.
        assert!((f.scaled_error - 1.0 / 3.0).abs() < 1e-6, "{f:?}");
        assert!(compare_albedo(&[]).raw_error.is_nan());
    }

    #[test]
    fn materials_are_averaged_per_object() {
        let objects: Vec<DatasetObject> = serde_json::from_value(serde_json::json!([
            {"id": 1, "name": "cup", "material": {"metallic": 0.0, "roughness": 0.2}},
            {"id": 2, "name": "bowl"},
            {"id": 3, "name": "unseen"}
        ]))
        .unwrap();
        let samples = [
            (1, 0.1, 0.2),
            (1, 0.3, 0.4),
            (2, 1.0, 0.5),
            (0, 9.0, 9.0),
            (7, 9.0, 9.0),
        ];
        let f = compare_materials(&samples, &objects);
        assert_eq!(f.len(), 3);
        assert_eq!((f[0].object.as_str(), f[0].pixels), ("cup", 2));
        assert!((f[0].metallic - 0.2).abs() < 1e-6 && (f[0].roughness - 0.3).abs() < 1e-6);
        assert_eq!(
            (f[0].metallic_truth, f[0].roughness_truth),
            (Some(0.0), Some(0.2))
        );
        assert_eq!(
            (f[1].pixels, f[1].metallic, f[1].metallic_truth),
            (1, 1.0, None)
        );
        assert!(f[2].pixels == 0 && f[2].metallic.is_nan());
    }

    #[test]
    fn ghost_shadows_are_the_pixels_off_their_uniform_surfaces_median() {
        // A uniform grey floor (1,000 pixels) recovered at 0.9x its albedo but for a dark blob
        // of 120 pixels at 0.5x (a baked shadow), a uniform red wall (200 pixels, exact), and a
        // texture whose 300 pixels all differ (no uniform surface: left out).
        let mut pairs = Vec::new();
        for i in 0..1000 {
            let k = if i < 120 { 0.5 } else { 0.9 };
            pairs.push(([0.4 * k; 3], [0.4f32; 3]));
        }
        for _ in 0..200 {
            pairs.push(([0.6, 0.1, 0.1], [0.6, 0.1, 0.1]));
        }
        for i in 0..300 {
            let t = 0.05 + i as f32 * 0.0005;
            pairs.push(([0.1; 3], [t; 3]));
        }
        let u = albedo_uniformity(&pairs).expect("two uniform surfaces");
        assert_eq!((u.surfaces, u.pixels), (2, 1200));
        assert!((u.ghost_share - 120.0 / 1200.0).abs() < 1e-12, "{u:?}");
        // The blob's pixels are 0.5 / 0.9 − 1 off the floor's median 0.9.
        let blob = (1.0 - 0.5f64 / 0.9) * 120.0 / 1200.0;
        assert!((u.spread - blob).abs() < 1e-6, "{u:?}");
        // A uniform gain alone is no ghost; nothing uniform at all is no figure.
        let scaled: Vec<_> = pairs[120..1000]
            .iter()
            .map(|&(p, t)| (p.map(|v| v * 3.0), t))
            .collect();
        assert_eq!(albedo_uniformity(&scaled).unwrap().ghost_share, 0.0);
        assert!(albedo_uniformity(&pairs[1200..]).is_none());

        // Per pair: the blob below its floor's median, the rest of the floor and the wall on
        // it, the texture on no surface; surfaces numbered in their true albedo's order.
        let dev = albedo_deviation(&pairs);
        let blob = 0.5f64 / 0.9 - 1.0;
        let (floor, _) = dev[0].expect("the blob is on the floor");
        assert!((dev[0].unwrap().1 - blob).abs() < 1e-6, "{:?}", dev[0]);
        assert_eq!(
            dev[500].map(|d| (d.0, d.1.abs() < 1e-6)),
            Some((floor, true))
        );
        let (wall, d) = dev[1100].expect("the wall");
        assert!(wall != floor && d.abs() < 1e-6);
        assert!(dev[1200..].iter().all(Option::is_none));
        // Seams: in a 12×1 image of two albedos (6 pixels each), only the pixels more than
        // SEAM_PIXELS (2) from the other are away from the seam.
        let strip: Vec<[f32; 3]> = (0..12)
            .map(|i| [if i % 12 < 6 { 0.2 } else { 0.8 }; 3])
            .collect();
        let away = away_from_seams(&strip, 12);
        let want: Vec<bool> = (0..12).map(|i| !(4..=7).contains(&i)).collect();
        assert_eq!(away, want);
        // Counted over one part (the blob's half): its surfaces and pixels only.
        let half = albedo_uniformity_over(&pairs, |i| i < 60).unwrap();
        assert_eq!((half.surfaces, half.pixels, half.ghost_share), (1, 60, 1.0));
    }
}
