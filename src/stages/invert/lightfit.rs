//! Lighting from shadows: a linear first fit of each state's environment and of a few base
//! colours, before stage 3's loop (`--light-fit`; not in the paper).
//!
//! **Why.** The paper starts stage 3 from grey materials and lets gradient descent find the
//! environments (eq. training-objectives). On a plain floor under a sun the loop never finds
//! the sun: an environment texel only gets a gradient from the few path samples that reach it,
//! a broad glow gets one from every sample, so the glow wins, the moved shadows cannot be cast
//! and the base colour takes them (`tests/separation.rs`: the recovered suns carry 2-12 % of
//! the light where the truth's carry 85 %). Yet with the geometry fixed, what a diffuse surface
//! receives is *linear* in the environment, and a shadow says which directions are blocked:
//! the classic inverse-lighting argument (Marschner & Greenberg 1997; Sato, Sato & Ikeuchi,
//! "Illumination from shadows", 1999). Solved directly, the sun appears where the shadows
//! point, whatever few samples would have reached it.
//!
//! **The model.** For a surface point x with normal n seen in state k, Lambertian and
//! direct light only,
//!
//! ```text
//! I_k(x) ≈ ρ_g · Σ_t T_k(x)_t E_k,t,   T_k(x)_t = (1/π) ∫_texel t V_k(x, ω) max(0, n·ω) dω
//! ```
//!
//! with E_k a coarse lat-long map (piecewise constant: exactly what its resampling to the
//! loop's resolution gives), V_k the transmittance through the stage-2 surfels placed as state
//! k, and ρ_g one base colour per *group*: the surfels of one component whose normals share a
//! dominant axis (a floor, a pair of walls, a box's pair of faces). One colour per group is
//! the prior here: it is what makes a shadow on a plain plane an effect of the light and not
//! of the paint. Textures are noise to this fit (the robust weights below), not errors: stage 3
//! then learns each surfel's own colour, starting from the group's.
//!
//! The pixels that see no surface look at the environment itself, so each texel they land in
//! gets the row E_k,t = their mean (a direct measurement; it pins the scale that ρ and E
//! otherwise trade). What remains unobserved is filled by a small smoothness term (the
//! graph Laplacian of the lat-long grid, wrapping in longitude) and a ridge.
//!
//! **The solve.** Alternating least squares, both steps exact: E_k (per channel, E ≥ 0) from
//! the normal equations by projected Gauss-Seidel, then each ρ_g in closed form (clamped to
//! [0.02, 0.95]); rows reweighted each round by 1 / max(|r|, δ) on their luminance residual
//! (iteratively reweighted least squares for an L1 fit, so specular objects, textures and the
//! indirect light this model leaves out count as outliers rather than light).
//!
//! **What it leaves out**, on purpose: interreflections (surfaces lit by walls come out a
//! little brighter than ρ E says, so the fit puts a little more light where walls are), gloss
//! and metals. The loop that follows has all of them.

// Colour channels and states are indexed alike across several arrays (rgb, ρ, E).
#![allow(clippy::needless_range_loop)]

use super::cache::{PrimaryCache, TrainState};
use crate::scene::environment::{fill_by_rows, texel_solid_angle};
use crate::scene::synthetic::SplitMix;
use crate::scene::{Environment, Surfels};
use crate::shade::envmap::{direction_to_uv, uv_to_direction};
use crate::trace::TraceScene;
use glam::{Quat, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};

/// The fit's environment: 32×16 texels (11.25° each). A sun falls in one texel; finer maps
/// cost the square of their texel count in the normal equations.
pub const WIDTH: usize = 32;
pub const HEIGHT: usize = 16;
/// Surface points (each in every state that saw it) kept for the fit.
pub const POINTS: usize = 2400;
/// Visibility directions per texel and point (2×2 stratified).
const SUB: usize = 2;
/// Rounds of alternation (each: E for every state, then ρ, then the weights).
const ROUNDS: usize = 12;
/// Gauss-Seidel sweeps per E solve (warm-started).
const SWEEPS: usize = 150;
/// The Laplacian's weight against the data's mean diagonal.
const SMOOTH: f64 = 0.02;
/// A pixel looks at the sky when its composited opacity is below this.
const SKY_ALPHA: f32 = 0.05;
/// A pixel sees a surface when its composited opacity is above this.
const SURFACE_ALPHA: f32 = 0.5;

/// What the fit found and cost (in the stage's report).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitFigures {
    /// Surface rows (points × the states that saw them) and texels measured directly.
    pub rows: usize,
    pub sky_texels: usize,
    /// Groups and their fitted base colours: (component, normal axis 0-2, ρ).
    pub groups: Vec<(u32, u32, [f32; 3])>,
    /// Visibility rays traced (one per direction above a row's horizon).
    pub rays: u64,
    /// Mean absolute luminance residual over the mean luminance, first and last round.
    pub residual: [f64; 2],
    pub seconds: f64,
}

/// The fit: one coarse environment per training state and a base colour per group.
pub struct LightFit {
    pub envs: Vec<Environment>,
    /// Per component, per normal axis: ρ (None: no point of that group was seen).
    pub base_colors: Vec<[Option<[f32; 3]>; 3]>,
    pub figures: FitFigures,
}

impl LightFit {
    /// Each surfel's base colour from its group (components without a fitted group keep
    /// `fallback`).
    pub fn surfel_colors(&self, components: &[&Surfels], fallback: f32) -> Vec<Vec<[f32; 3]>> {
        components
            .iter()
            .enumerate()
            .map(|(c, s)| {
                (0..s.len())
                    .map(|i| {
                        let axis = dominant_axis(local_normal(s, i));
                        self.base_colors
                            .get(c)
                            .and_then(|g| g[axis])
                            .unwrap_or([fallback; 3])
                    })
                    .collect()
            })
            .collect()
    }
}

fn local_normal(s: &Surfels, i: usize) -> Vec3 {
    Quat::from_array(s.rotation[i]).normalize() * Vec3::Z
}

fn dominant_axis(n: Vec3) -> usize {
    let a = n.abs();
    if a.x >= a.y && a.x >= a.z {
        0
    } else if a.y >= a.z {
        1
    } else {
        2
    }
}

const LUMINANCE: [f64; 3] = [0.2126, 0.7152, 0.0722];

fn luminance(c: [f64; 3]) -> f64 {
    (0..3).map(|k| LUMINANCE[k] * c[k]).sum()
}

/// One surface point as one state saw it: mean colour, position and (camera-facing) normal
/// over the pixels whose front surfel it is.
#[derive(Clone, Copy, Default)]
struct Seen {
    rgb: [f64; 3],
    x: [f64; 3],
    n: [f64; 3],
    count: u32,
}

/// One row of the fit: state, group, observed colour and the transport to each texel
/// (sparse: texel index and weight).
pub struct Row {
    pub state: usize,
    pub group: usize,
    pub rgb: [f64; 3],
    pub t: Vec<(u16, f32)>,
}

/// Fits the lighting (see the module) from `states`' captures through `cache`'s primary
/// records; `trace` holds the stage-2 geometry; `components` are its surfels (for the groups).
pub fn fit(
    trace: &TraceScene,
    states: &[TrainState],
    cache: &PrimaryCache,
    components: &[&Surfels],
    seed: u64,
) -> LightFit {
    let t0 = std::time::Instant::now();
    let ntex = WIDTH * HEIGHT;
    let ngroups = 3 * components.len();

    // 1. Per state: each front surfel's pixels, and the sky's texels.
    let mut seen: Vec<HashMap<(u32, u32), Seen>> = vec![HashMap::new(); states.len()];
    let mut sky: Vec<Vec<([f64; 3], u32)>> = vec![vec![([0.0; 3], 0); ntex]; states.len()];
    let mut image = 0usize;
    for (k, st) in states.iter().enumerate() {
        for obs in &st.views {
            let npix = obs.camera.w * obs.camera.h;
            for p in 0..npix {
                let e = cache.entry(image, p, 0);
                let (ray, rec) = cache.geometry(e);
                let rgb = obs.rgb[p as usize].map(|v| v.max(0.0) as f64);
                if rec.alpha < SKY_ALPHA {
                    let [u, v] = direction_to_uv(Vec3::from_array(ray.dir));
                    let tx = ((u * WIDTH as f32).floor() as i64).rem_euclid(WIDTH as i64) as usize;
                    let ty = ((v * HEIGHT as f32) as usize).min(HEIGHT - 1);
                    let s = &mut sky[k][ty * WIDTH + tx];
                    for c in 0..3 {
                        s.0[c] += rgb[c];
                    }
                    s.1 += 1;
                    continue;
                }
                if rec.alpha < SURFACE_ALPHA {
                    continue;
                }
                let Some(front) = cache
                    .hits(e)
                    .iter()
                    .max_by(|a, b| a.w.total_cmp(&b.w))
                    .copied()
                else {
                    continue;
                };
                let x = rec.mean_position();
                let n = rec.unit_normal();
                let acc = seen[k].entry((front.component, front.index)).or_default();
                for c in 0..3 {
                    acc.rgb[c] += rgb[c];
                    acc.x[c] += x[c] as f64;
                    acc.n[c] += n[c] as f64;
                }
                acc.count += 1;
            }
            image += 1;
        }
    }

    // 2. The points: surfels seen (by 2 pixels or more) in any state, a fixed-seed draw of
    // POINTS of them, each a row in every state that saw it (so the states' rows share ρ).
    let mut keys: Vec<(u32, u32)> = seen
        .iter()
        .flat_map(|m| m.iter().filter(|(_, s)| s.count >= 2).map(|(k, _)| *k))
        .collect();
    keys.sort_unstable();
    keys.dedup();
    let mut rng = SplitMix(seed ^ 0x6c69_6768_7466_6974);
    for i in (1..keys.len()).rev() {
        let j = (rng.f32() * (i + 1) as f32) as usize;
        keys.swap(i, j.min(i));
    }
    keys.truncate(POINTS);
    keys.sort_unstable();
    let mut jobs: Vec<(usize, usize, Seen)> = Vec::new();
    for &(c, i) in &keys {
        let group =
            3 * c as usize + dominant_axis(local_normal(components[c as usize], i as usize));
        for (k, m) in seen.iter().enumerate() {
            if let Some(s) = m.get(&(c, i)).filter(|s| s.count >= 2) {
                jobs.push((k, group, *s));
            }
        }
    }

    // 3. Each row's transport: SUB² directions per texel, visibility through the state's
    // placement, cosine, solid angle / π.
    let placed: Vec<_> = states.iter().map(|s| trace.place(&s.transforms)).collect();
    let traced = AtomicU64::new(0);
    let rows: Vec<Row> = jobs
        .par_iter()
        .map(|&(k, group, s)| {
            let inv = 1.0 / s.count as f64;
            let x = Vec3::from_array(s.x.map(|v| (v * inv) as f32));
            let n = Vec3::from_array(s.n.map(|v| v as f32)).normalize_or_zero();
            let origin = (x + states[k].eps * n).to_array();
            let t = transport(n, |d| {
                traced.fetch_add(1, Ordering::Relaxed);
                placed[k].transmittance(origin, d.to_array(), 0.0, f32::INFINITY)
            });
            Row {
                state: k,
                group,
                rgb: s.rgb.map(|v| v * inv),
                t,
            }
        })
        .collect();
    let rays = traced.into_inner();

    // 4. The sky's texels, measured directly, and the weak prior on the others.
    let sky_rows: Vec<Vec<SkyTexel>> = sky
        .iter()
        .map(|m| {
            let seen: Vec<SkyTexel> = m
                .iter()
                .enumerate()
                .filter(|(_, s)| s.1 > 0)
                .map(|(t, s)| (t, s.0.map(|v| v / s.1 as f64), true))
                .collect();
            let mut all = fill(&seen);
            all.extend(seen);
            all
        })
        .collect();
    // 5. Alternate.
    let solved = solve(&rows, &sky_rows, ngroups, states.len());
    let (env, rho, residual) = (solved.env, solved.rho, solved.residual);

    let mut groups_seen = vec![false; ngroups];
    for r in &rows {
        groups_seen[r.group] = true;
    }
    let base_colors = (0..components.len())
        .map(|c| {
            [0, 1, 2].map(|a| {
                let g = 3 * c + a;
                groups_seen[g].then(|| rho[g].map(|v| v as f32))
            })
        })
        .collect();
    let groups = (0..ngroups)
        .filter(|&g| groups_seen[g])
        .map(|g| ((g / 3) as u32, (g % 3) as u32, rho[g].map(|v| v as f32)))
        .collect();
    let envs = env
        .iter()
        .enumerate()
        .map(|(k, e)| {
            Environment::new(
                format!("light-fit-{k}"),
                WIDTH,
                HEIGHT,
                e.iter().map(|v| v.map(|x| (x as f32).max(1e-4))).collect(),
            )
        })
        .collect();
    LightFit {
        envs,
        base_colors,
        figures: FitFigures {
            rows: rows.len(),
            sky_texels: sky_rows.iter().flatten().filter(|s| s.2).count(),
            groups,
            rays,
            residual,
            seconds: t0.elapsed().as_secs_f64(),
        },
    }
}

/// A point's transport to each texel (eq. rendering-equation's diffuse term, texel by texel):
/// T_t = (1/π) Σ_j V(ω_j) max(0, n·ω_j) Δω_t / SUB², over SUB × SUB directions stratified in
/// the texel; `visibility` the transmittance toward a direction. Texels with T_t = 0 are left
/// out.
pub fn transport(n: Vec3, visibility: impl Fn(Vec3) -> f32) -> Vec<(u16, f32)> {
    let mut t = Vec::new();
    for ty in 0..HEIGHT {
        let dw = texel_solid_angle(WIDTH, HEIGHT, ty) / (SUB * SUB) as f64;
        for tx in 0..WIDTH {
            let mut acc = 0.0f64;
            for j in 0..SUB * SUB {
                let u = (tx as f32 + ((j % SUB) as f32 + 0.5) / SUB as f32) / WIDTH as f32;
                let v = (ty as f32 + ((j / SUB) as f32 + 0.5) / SUB as f32) / HEIGHT as f32;
                let d = uv_to_direction([u, v]);
                let c = n.dot(d);
                if c > 0.0 {
                    acc += (visibility(d) * c) as f64 * dw;
                }
            }
            if acc > 0.0 {
                t.push((
                    (ty * WIDTH + tx) as u16,
                    (acc / std::f64::consts::PI) as f32,
                ));
            }
        }
    }
    t
}

/// A row on one texel of a state's environment: its index, radiance, and whether it was seen
/// directly (the pixels' mean, weighted as one surface row) or is [`fill`]'s guess (weighted
/// [`PRIOR`] × the data's mean diagonal, and only on texels whose own data weigh less: a
/// guess must not outweigh the shadows that point at a sun).
pub type SkyTexel = (usize, [f64; 3], bool);

/// The weight of [`fill`]'s rows against the data's mean diagonal.
pub const PRIOR: f64 = 0.1;

/// Weak rows for the texels no view saw: the mean of their row's seen texels, or the nearest
/// row's with any (what the loop's own start, `train::initial_environment`, puts there). A
/// texel that few surface points see gets next to no say in the normal equations, and the
/// solve is free to leave it black; a view of a new arrangement, or one held out, may look
/// straight at it (the demo's held-out backgrounds fell to 7.5 dB without this).
pub fn fill(seen: &[SkyTexel]) -> Vec<SkyTexel> {
    let mut texels: Vec<Option<[f64; 3]>> = vec![None; WIDTH * HEIGHT];
    for &(t, v, _) in seen {
        texels[t] = Some(v);
    }
    let Some(filled) = fill_by_rows(WIDTH, &texels) else {
        return Vec::new();
    };
    (0..WIDTH * HEIGHT)
        .filter(|&t| texels[t].is_none())
        .map(|t| (t, filled[t], false))
        .collect()
}

/// [`solve`]'s result: each state's coarse environment (texels, RGB), each group's ρ, and the
/// relative L1 residual of the first and last round.
pub struct Solved {
    pub env: Vec<Vec<[f64; 3]>>,
    pub rho: Vec<[f64; 3]>,
    pub residual: [f64; 2],
}

/// The alternation of the module's model on given rows (exposed for its tests): `rows` the
/// surface points (state, group, colour, sparse transport over `WIDTH × HEIGHT` texels),
/// `sky` each state's directly seen texels.
pub fn solve(rows: &[Row], sky: &[Vec<SkyTexel>], ngroups: usize, nstates: usize) -> Solved {
    let ntex = WIDTH * HEIGHT;
    let sky_rows = sky;
    let mean_lum = rows.iter().map(|r| luminance(r.rgb)).sum::<f64>() / rows.len().max(1) as f64;
    let delta = 0.05 * mean_lum.max(1e-6);
    let mut rho = vec![[0.5f64; 3]; ngroups];
    let mut weight = vec![1.0f64; rows.len()];
    // Start each environment at its sky's mean (or the captures' level where none is seen).
    let mut env: Vec<Vec<[f64; 3]>> = sky_rows
        .iter()
        .map(|s| {
            let m = if s.is_empty() {
                [2.0 * mean_lum; 3]
            } else {
                let mut a = [0.0; 3];
                for (_, v, _) in s {
                    for c in 0..3 {
                        a[c] += v[c] / s.len() as f64;
                    }
                }
                a
            };
            vec![m; ntex]
        })
        .collect();
    let by_state: Vec<Vec<usize>> = (0..nstates)
        .map(|k| (0..rows.len()).filter(|&r| rows[r].state == k).collect())
        .collect();
    let mut residual = [0.0f64; 2];
    for round in 0..ROUNDS {
        // E step: per state, A_c = Σ_g ρ_gc² M_g + sky + smoothness, b_c likewise. A sky
        // texel's row is one measurement of it (transport 1 to that texel), weighted as the
        // mean surface row.
        let w_sky = weight.iter().sum::<f64>() / weight.len().max(1) as f64;
        let solved: Vec<Vec<[f64; 3]>> = (0..nstates)
            .into_par_iter()
            .map(|k| {
                let mut m = vec![vec![0.0f64; ntex * ntex]; ngroups];
                let mut b = vec![[0.0f64; 3]; ntex];
                for &r in &by_state[k] {
                    let row = &rows[r];
                    let w = weight[r];
                    let mg = &mut m[row.group];
                    for &(i, ti) in &row.t {
                        let wi = w * ti as f64;
                        for &(j, tj) in &row.t {
                            mg[i as usize * ntex + j as usize] += wi * tj as f64;
                        }
                        for c in 0..3 {
                            b[i as usize][c] += wi * rho[row.group][c] * row.rgb[c];
                        }
                    }
                }
                let mut out = env[k].clone();
                for c in 0..3 {
                    let mut a = vec![0.0f64; ntex * ntex];
                    for (g, mg) in m.iter().enumerate() {
                        let r2 = rho[g][c] * rho[g][c];
                        if r2 > 0.0 && mg.iter().any(|&v| v != 0.0) {
                            for (av, mv) in a.iter_mut().zip(mg) {
                                *av += r2 * mv;
                            }
                        }
                    }
                    let mut bc: Vec<f64> = b.iter().map(|v| v[c]).collect();
                    let diag = (0..ntex).map(|i| a[i * ntex + i]).sum::<f64>() / ntex as f64;
                    let diag = diag.max(1e-12);
                    for &(t, v, seen) in &sky_rows[k] {
                        let w = if seen {
                            w_sky
                        } else if a[t * ntex + t] < PRIOR * diag {
                            PRIOR * diag
                        } else {
                            continue;
                        };
                        a[t * ntex + t] += w;
                        bc[t] += w * v[c];
                    }
                    let lam = SMOOTH * diag;
                    for y in 0..HEIGHT {
                        for x in 0..WIDTH {
                            let i = y * WIDTH + x;
                            let mut link = |j: usize| {
                                a[i * ntex + i] += lam;
                                a[j * ntex + j] += lam;
                                a[i * ntex + j] -= lam;
                                a[j * ntex + i] -= lam;
                            };
                            link(y * WIDTH + (x + 1) % WIDTH);
                            if y + 1 < HEIGHT {
                                link((y + 1) * WIDTH + x);
                            }
                        }
                    }
                    for i in 0..ntex {
                        a[i * ntex + i] += 1e-6 * diag;
                    }
                    let mut e: Vec<f64> = out.iter().map(|v| v[c]).collect();
                    for _ in 0..SWEEPS {
                        for i in 0..ntex {
                            let row = &a[i * ntex..(i + 1) * ntex];
                            let s: f64 =
                                row.iter().zip(&e).map(|(x, y)| x * y).sum::<f64>() - row[i] * e[i];
                            e[i] = ((bc[i] - s) / row[i]).max(0.0);
                        }
                    }
                    for (o, v) in out.iter_mut().zip(e) {
                        o[c] = v;
                    }
                }
                out
            })
            .collect();
        env = solved;

        // ρ step and the new weights.
        let irr: Vec<[f64; 3]> = rows
            .iter()
            .map(|r| {
                let mut p = [0.0f64; 3];
                for &(t, w) in &r.t {
                    for c in 0..3 {
                        p[c] += w as f64 * env[r.state][t as usize][c];
                    }
                }
                p
            })
            .collect();
        let mut num = vec![[0.0f64; 3]; ngroups];
        let mut den = vec![[0.0f64; 3]; ngroups];
        for (r, row) in rows.iter().enumerate() {
            for c in 0..3 {
                num[row.group][c] += weight[r] * row.rgb[c] * irr[r][c];
                den[row.group][c] += weight[r] * irr[r][c] * irr[r][c];
            }
        }
        for g in 0..ngroups {
            for c in 0..3 {
                if den[g][c] > 1e-12 {
                    rho[g][c] = (num[g][c] / den[g][c]).clamp(0.02, 0.95);
                }
            }
        }
        let mut abs = 0.0;
        for (r, row) in rows.iter().enumerate() {
            let pred = [0, 1, 2].map(|c| rho[row.group][c] * irr[r][c]);
            let res = (luminance(row.rgb) - luminance(pred)).abs();
            abs += res;
            weight[r] = 1.0 / res.max(delta);
        }
        let rel = abs / rows.len().max(1) as f64 / mean_lum.max(1e-12);
        if round == 0 {
            residual[0] = rel;
        }
        residual[1] = rel;
    }

    Solved { env, rho, residual }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An unoccluded point's transport, dense.
    fn open_row(n: Vec3) -> Vec<f64> {
        let mut t = vec![0.0; WIDTH * HEIGHT];
        for (i, v) in transport(n, |_| 1.0) {
            t[i as usize] = v as f64;
        }
        t
    }

    /// (1/π) ∫ max(0, n·ω) dω = 1: the quadrature within 1 % for any normal (measured 0.3 %
    /// off at 32×16 with 2×2 directions per texel); a point blocked toward every direction
    /// with x > 0 receives half.
    #[test]
    fn an_open_point_receives_the_whole_cosine_lobe() {
        for n in [Vec3::Y, Vec3::X, Vec3::new(0.3, 0.8, -0.5).normalize()] {
            let sum: f64 = open_row(n).iter().sum();
            assert!((sum - 1.0).abs() < 0.01, "normal {n}: Σ T = {sum}");
        }
        let half: f32 = transport(Vec3::Y, |d| if d.x > 0.0 { 0.0 } else { 1.0 })
            .iter()
            .map(|&(_, v)| v)
            .sum();
        assert!((half - 0.5).abs() < 0.01, "half-blocked: Σ T = {half}");
    }

    /// Rows made from a known model: two states, each a sky of 0.25-0.4 (bluish) plus a sun
    /// in one texel (its own per state), two groups of known ρ, upward points whose sun is
    /// blocked for a quarter of them (the shadows) and whose sky is cut in a random azimuth
    /// wedge; the horizon band of the sky seen, the zenith and the suns not.
    /// The fit, the true maps, the true ρ and an open upward point's transport.
    type Synthetic = (Solved, Vec<Vec<[f64; 3]>>, [[f64; 3]; 2], Vec<f64>);

    fn synthetic(outliers: bool) -> Synthetic {
        let ntex = WIDTH * HEIGHT;
        let up = open_row(Vec3::Y);
        let sun_texel = [3 * WIDTH + 5, 5 * WIDTH + 20];
        let truth: Vec<Vec<[f64; 3]>> = (0..2)
            .map(|k| {
                (0..ntex)
                    .map(|t| {
                        if t == sun_texel[k] {
                            [60.0, 55.0, 45.0]
                        } else if t / WIDTH < HEIGHT / 2 {
                            [0.25, 0.3, 0.4]
                        } else {
                            [0.1, 0.1, 0.1]
                        }
                    })
                    .collect()
            })
            .collect();
        let rho = [[0.6, 0.5, 0.4], [0.2, 0.35, 0.6]];
        let mut rng = SplitMix(7);
        let mut rows = Vec::new();
        for k in 0..2 {
            for i in 0..400 {
                let group = i % 2;
                let shadowed = i % 4 < 1;
                let wedge = (rng.f32() * WIDTH as f32) as usize;
                let t: Vec<(u16, f32)> = up
                    .iter()
                    .enumerate()
                    .filter(|&(t, &v)| {
                        let x = t % WIDTH;
                        let cut = (x + WIDTH - wedge) % WIDTH < 4;
                        v > 0.0 && !(shadowed && t == sun_texel[k]) && !cut
                    })
                    .map(|(t, &v)| (t as u16, v as f32))
                    .collect();
                let mut rgb = [0.0; 3];
                for &(j, w) in &t {
                    for c in 0..3 {
                        rgb[c] += rho[group][c] * w as f64 * truth[k][j as usize][c];
                    }
                }
                if outliers && i % 10 == 3 {
                    rgb = rgb.map(|v| 2.0 * v);
                }
                rows.push(Row {
                    state: k,
                    group,
                    rgb,
                    t,
                });
            }
        }
        let sky: Vec<Vec<SkyTexel>> = (0..2)
            .map(|k| {
                let seen: Vec<SkyTexel> = (5 * WIDTH..8 * WIDTH)
                    .filter(|&t| t != sun_texel[k])
                    .map(|t| (t, truth[k][t], true))
                    .collect();
                let mut all = fill(&seen);
                all.extend(seen);
                all
            })
            .collect();
        (solve(&rows, &sky, 2, 2), truth, rho, up)
    }

    /// What the data determine: each sun's texel (the shadows point at it), the seen sky
    /// (kept to 1 %), the groups' colours relative to each other (within 5 %: measured 3.1-3.2 %,
    /// the smoothness term's pull on the suns weighs the groups' rows a little differently) and
    /// a fit of the rows (relative L1 residual below 5 %: measured 2.9 %, the same pull; with
    /// the outliers below 15 %: they alone are ~10 %, measured 11.2 %). Not the common scale
    /// and colour of ρ: the suns' colour is never seen and the unseen zenith sky trades with
    /// it (measured: ρ 1.45 / 1.28 / 0.95 × the truth per channel, the suns whiter and
    /// dimmer). The robust weights hold the same with a tenth of the rows' colours doubled.
    fn check(outliers: bool, max_residual: f64) {
        let (got, truth, rho, _) = synthetic(outliers);
        let lum = |v: &[f64; 3]| luminance(*v);
        let argmax = |e: &Vec<[f64; 3]>| {
            (0..e.len())
                .max_by(|&a, &b| lum(&e[a]).total_cmp(&lum(&e[b])))
                .unwrap()
        };
        for k in 0..2 {
            assert_eq!(
                argmax(&got.env[k]),
                argmax(&truth[k]),
                "state {k}: sun texel"
            );
            for t in 5 * WIDTH..8 * WIDTH {
                if t == argmax(&truth[k]) {
                    continue;
                }
                for c in 0..3 {
                    let r = got.env[k][t][c] / truth[k][t][c];
                    assert!(
                        (r - 1.0).abs() < 0.01,
                        "state {k}, seen texel {t}: {r:.4}× the truth"
                    );
                }
            }
        }
        for c in 0..3 {
            let r = (got.rho[1][c] / got.rho[0][c]) / (rho[1][c] / rho[0][c]);
            assert!(
                (r - 1.0).abs() < 0.05,
                "channel {c}: ρ_1 / ρ_0 {r:.3}× the truth's"
            );
        }
        assert!(
            got.residual[1] < max_residual,
            "relative L1 residual {:?} (first, last round)",
            got.residual
        );
    }

    #[test]
    fn the_fit_finds_suns_and_relative_colours_from_shadows() {
        check(false, 0.05);
    }

    #[test]
    fn the_fit_shrugs_off_outliers() {
        check(true, 0.15);
    }
}
