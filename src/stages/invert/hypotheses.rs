//! Which objects are metals or glossy: a few material hypotheses tested per object before
//! stage 3's loop (`--material-search`; not in the paper).
//!
//! **Why.** The paper starts every surfel at one material (grey, metallic 0.02, roughness 0.7)
//! and lets gradient descent find the rest. A chrome object does not get there. At roughness
//! 0.7 a metal's lobe is about as broad as a diffuse one, so raising metallic alone changes the
//! image little; lowering roughness on a dielectric (its specular F0 is 0.04) changes it little
//! too. The mirror lies past a ridge that neither coordinate climbs on its own. Measured on the
//! plain-family sunroom, every variant's chrome bottle ends at metallic 0.15-0.20, roughness
//! about 0.5 (truth 1 / 0.05), and the glossy ball keeps roughness 0.64 (truth 0.2).
//!
//! **The test.** For each object (component ≥ 1) and each hypothesis h = (metallic,
//! roughness) of [`HYPOTHESES`] (the preset's start first), the object's training pixels are
//! rendered with every surfel of the object at h by the loop's own estimator, its bounces and
//! the environments the loop starts from (the light fit's with `--light-fit`). An object's
//! pixels are those whose primary record (the stage-2 geometry, [`PrimaryCache`]) is at least
//! [`OWN_WEIGHT`] that object's: no mask is needed. Each sample is replayed with the primary
//! record's base colour at 0 and at 1 ([`PathReplay::radiance_with`]: the same directions,
//! so the estimate is exactly affine in it: the BRDF is, diffuse (1 − m) a/π and F0 =
//! mix(0.04, a, m)), which gives each hypothesis its base colour per channel in closed form
//! (the median ratio over the pixels). The hypothesis whose fit leaves the smallest L1
//! residual (the loop's image term, over the best-fitting [`KEEP`] of the pixels: both robust
//! to the sun glints a few samples catch) wins, if it beats the preset's by [`MARGIN`]; the object's
//! surfels then start at it, and at its base colour. The loop refines both per surfel.
//!
//! **What it assumes.** One material per object at the start (the loop then departs from it
//! surfel by surfel); the background keeps the preset's start (its walls and floors are
//! several materials: one hypothesis cannot stand for them). A hypothesis is judged under the
//! starting environments, so a wrong sky can favour a wrong material: the margin and the
//! report's residuals (`invert/report.json`, `material_search`) say how clear each choice was.

use super::cache::{PrimaryCache, TrainState};
use super::train::{Inverter, Passes};
use crate::scene::synthetic::SplitMix;
use crate::scene::{Material, Surfels};
use crate::shade::estimator::Estimator;
use crate::shade::replay::PathReplay;
use crate::shade::{EnvMap, Sampler};
use crate::trace::TraceScene;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// A starting material: metallic and roughness.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hypothesis {
    pub name: &'static str,
    pub metallic: f32,
    pub roughness: f32,
}

/// The hypotheses after the preset's start: a glossy dielectric (plastic, glaze), a brushed
/// metal and a polished one. Coarse on purpose: the loop refines the winner.
pub const HYPOTHESES: [Hypothesis; 3] = [
    Hypothesis {
        name: "glossy",
        metallic: 0.02,
        roughness: 0.2,
    },
    Hypothesis {
        name: "brushed metal",
        metallic: 1.0,
        roughness: 0.35,
    },
    Hypothesis {
        name: "polished metal",
        metallic: 1.0,
        roughness: 0.08,
    },
];

/// A pixel belongs to an object when its primary record's compositing weight is at least this
/// share that object's (and the record is at least half opaque).
pub const OWN_WEIGHT: f32 = 0.9;
/// Pixels kept per object (drawn evenly from all its training pixels).
pub const PIXELS: usize = 2048;
/// Path samples per pixel and hypothesis.
pub const SPP: u32 = 8;
/// The share of an object's pixels its residual is measured over (the best fitting: see
/// `Rendered::fit`).
pub const KEEP: f64 = 0.9;
/// Another hypothesis replaces the preset's start only when its residual is at least this much
/// (relative) below the preset's: a choice the data clearly make.
pub const MARGIN: f64 = 0.05;

/// One object's test (in the report).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObjectTest {
    pub object: String,
    /// Training pixels tested (of those the object owns).
    pub pixels: usize,
    pub owned_pixels: usize,
    /// Per hypothesis (the preset's start first): its name, metallic, roughness, the fitted
    /// base colour and the L1 residual relative to the pixels' mean |I|.
    pub hypotheses: Vec<HypothesisFit>,
    /// The hypothesis the object starts from.
    pub chosen: String,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HypothesisFit {
    pub name: String,
    pub metallic: f32,
    pub roughness: f32,
    pub base_color: [f32; 3],
    pub residual: f64,
}

/// What the search found and cost.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SearchFigures {
    pub objects: Vec<ObjectTest>,
    pub seconds: f64,
}

/// Per object (component ≥ 1): the (image, pixel) pairs it owns, every one, in image order.
fn owned_pixels(
    cache: &PrimaryCache,
    states: &[TrainState],
    components: usize,
) -> Vec<Vec<(usize, u32)>> {
    let images: Vec<usize> = states
        .iter()
        .flat_map(|s| s.views.iter().map(|v| (v.camera.w * v.camera.h) as usize))
        .collect();
    let per_image: Vec<Vec<(usize, u32)>> = images
        .par_iter()
        .enumerate()
        .map(|(image, &n)| {
            let mut out = Vec::new();
            let mut w = vec![0.0f32; components];
            for p in 0..n as u32 {
                w.iter_mut().for_each(|v| *v = 0.0);
                for h in cache.hits(cache.entry(image, p, 0)) {
                    w[h.component as usize] += h.w;
                }
                let total: f32 = w.iter().sum();
                if total < 0.5 {
                    continue;
                }
                if let Some(c) = (1..components).find(|&c| w[c] >= OWN_WEIGHT * total) {
                    out.push((c, p));
                }
            }
            out
        })
        .collect();
    let mut owned = vec![Vec::new(); components];
    for (image, list) in per_image.into_iter().enumerate() {
        for (c, p) in list {
            owned[c].push((image, p));
        }
    }
    owned
}

/// The image index of each (state, view), as the cache numbers them.
fn image_of(states: &[TrainState]) -> Vec<(usize, usize)> {
    states
        .iter()
        .enumerate()
        .flat_map(|(k, s)| (0..s.views.len()).map(move |v| (k, v)))
        .collect()
}

/// One object's pixels under one hypothesis: per pixel the capture I and the estimates at
/// base colour 0 and 1 (L0, L1; the estimate at a is L0 + a (L1 − L0)).
struct Rendered {
    rows: Vec<([f32; 3], [f32; 3], [f32; 3])>,
}

impl Rendered {
    /// The base colour per channel, the median over the pixels of (I − L0) / (L1 − L0)
    /// (clamped to [0.02, 0.98]), and the residual it leaves: the mean of each pixel's
    /// |I − L0 − a (L1 − L0)| over its channels, over the best [`KEEP`] of the pixels, relative
    /// to the mean |I|. Robust on purpose: where a mirror reflects a small sun, a few of the
    /// search's 8 samples (or the capture's) catch it in one pixel and miss it in the next,
    /// and those pixels would otherwise decide both the colour and the verdict.
    fn fit(&self) -> ([f32; 3], f64) {
        let mut a = [0.5f32; 3];
        for c in 0..3 {
            let mut d: Vec<f32> = self.rows.iter().map(|(_, l0, l1)| l1[c] - l0[c]).collect();
            d.sort_by(f32::total_cmp);
            // Pixels the base colour barely changes (in shadow, at grazing angles) say
            // nothing about it.
            let floor = 0.05 * d.get(d.len() / 2).copied().unwrap_or(0.0).max(0.0);
            let mut ratios: Vec<f32> = self
                .rows
                .iter()
                .filter(|(_, l0, l1)| l1[c] - l0[c] > floor.max(1e-9))
                .map(|(i, l0, l1)| (i[c] - l0[c]) / (l1[c] - l0[c]))
                .collect();
            if ratios.is_empty() {
                continue;
            }
            ratios.sort_by(f32::total_cmp);
            a[c] = ratios[ratios.len() / 2].clamp(0.02, 0.98);
        }
        let mut res: Vec<f64> = self
            .rows
            .iter()
            .map(|(i, l0, l1)| {
                (0..3)
                    .map(|c| (i[c] - l0[c] - a[c] * (l1[c] - l0[c])).abs() as f64)
                    .sum::<f64>()
            })
            .collect();
        res.sort_by(f64::total_cmp);
        let keep = ((res.len() as f64 * KEEP).ceil() as usize).clamp(1, res.len().max(1));
        let norm = self
            .rows
            .iter()
            .map(|(i, _, _)| i.iter().map(|v| v.abs() as f64).sum::<f64>())
            .sum::<f64>()
            / self.rows.len().max(1) as f64;
        let mean = res.iter().take(keep).sum::<f64>() / keep as f64;
        (a, mean / norm.max(1e-12))
    }
}

/// Tests every object's hypotheses and sets the winners as the inverter's starting materials
/// (see the module doc). `surfels` are the scene's components: the inverter's current
/// materials are written into them first, so the caller passes a scratch copy; each hypothesis
/// then copies only the objects' surfels and shares the background's. `names` name the
/// components. `trace` is left holding the last hypothesis' materials: `Inverter::step` sets
/// the inverter's at its start, as it does every iteration.
pub fn search(
    inv: &mut Inverter,
    trace: &mut TraceScene,
    surfels: &mut [Surfels],
    states: &[TrainState],
    names: &[String],
) -> SearchFigures {
    let t0 = std::time::Instant::now();
    let settings = inv.settings.clone();
    let preset = Hypothesis {
        name: "preset",
        metallic: settings.init_metallic,
        roughness: settings.init_roughness,
    };
    let hypotheses: Vec<Hypothesis> = std::iter::once(preset).chain(HYPOTHESES).collect();
    inv.ensure_cache(trace, states);
    inv.write_materials(surfels);
    let envs: Vec<EnvMap> = (0..states.len())
        .map(|k| EnvMap::new(&inv.environment(k, ""), 0.0))
        .collect();
    let cache = inv.cache().expect("built above");
    let owned = owned_pixels(cache, states, surfels.len());
    let images = image_of(states);
    // Each object's pixels: PIXELS of them, evenly spaced after a fixed shuffle.
    let mut rng = SplitMix(settings.seed ^ 0x6d61_7465_7269_616c);
    let tested: Vec<Vec<(usize, u32)>> = owned
        .iter()
        .map(|all| {
            let mut v = all.clone();
            for i in (1..v.len()).rev() {
                let j = (rng.next_u64() % (i as u64 + 1)) as usize;
                v.swap(i, j);
            }
            v.truncate(PIXELS);
            v.sort_unstable();
            v
        })
        .collect();
    let objects: Vec<usize> = (1..surfels.len())
        .filter(|&c| !tested[c].is_empty())
        .collect();

    // rendered[h][c]: object c's pixels under hypothesis h (every object at h at once: what
    // one object reflects of another is second order here).
    let mut rendered: Vec<Vec<Rendered>> = Vec::new();
    for h in &hypotheses {
        // Only the objects change: copy theirs, and share the rest (the background's are most).
        let hyp: Vec<(usize, Surfels)> = objects
            .iter()
            .map(|&c| {
                let mut s = surfels[c].clone();
                s.metallic.iter_mut().for_each(|m| *m = h.metallic);
                s.roughness.iter_mut().for_each(|r| *r = h.roughness);
                s.base_color.iter_mut().for_each(|a| *a = [0.5; 3]);
                (c, s)
            })
            .collect();
        let refs: Vec<&Surfels> = (0..surfels.len())
            .map(|c| {
                hyp.iter()
                    .find(|(k, _)| *k == c)
                    .map_or(&surfels[c], |(_, s)| s)
            })
            .collect();
        trace.set_materials(&refs);
        let mut per_object: Vec<Rendered> = (0..surfels.len())
            .map(|_| Rendered { rows: Vec::new() })
            .collect();
        for (k, state) in states.iter().enumerate() {
            let placed = trace.place(&state.transforms);
            let est = Estimator::new(&placed, &envs[k], state.eps)
                .with_strategy(settings.estimator)
                .with_bounces(settings.bounces);
            for &c in &objects {
                let rows: Vec<([f32; 3], [f32; 3], [f32; 3])> = tested[c]
                    .par_iter()
                    .filter(|(image, _)| images[*image].0 == k)
                    .map_init(Vec::new, |records, &(image, p)| {
                        let passes = Passes {
                            estimator: &est,
                            env: &envs[k],
                            cache,
                            image,
                            components: &refs,
                            spp: SPP,
                        };
                        passes.primaries(p, records);
                        let sampler = Sampler::new(p, settings.seed as u32 ^ 0x5eed);
                        let jitters = records.len();
                        let (mut l0, mut l1) = ([0.0f32; 3], [0.0f32; 3]);
                        for i in 0..SPP {
                            let (ray, rec) = records[i as usize % jitters];
                            let path = est.replay_from(ray, rec, &sampler, i);
                            let (r0, r1) = at_base_colours(&path, &envs[k]);
                            for ch in 0..3 {
                                l0[ch] += r0[ch] / SPP as f32;
                                l1[ch] += r1[ch] / SPP as f32;
                            }
                        }
                        let (state, view) = images[image];
                        let obs = states[state].views[view];
                        (obs.rgb[p as usize], l0, l1)
                    })
                    .collect();
                per_object[c].rows.extend(rows);
            }
        }
        rendered.push(per_object);
    }

    let mut tests = Vec::new();
    for &c in &objects {
        let fits: Vec<HypothesisFit> = hypotheses
            .iter()
            .zip(&rendered)
            .map(|(h, r)| {
                let (base_color, residual) = r[c].fit();
                HypothesisFit {
                    name: h.name.to_string(),
                    metallic: h.metallic,
                    roughness: h.roughness,
                    base_color,
                    residual,
                }
            })
            .collect();
        let best = (1..fits.len())
            .min_by(|&a, &b| fits[a].residual.total_cmp(&fits[b].residual))
            .filter(|&b| fits[b].residual < (1.0 - MARGIN) * fits[0].residual)
            .unwrap_or(0);
        if best != 0 {
            let f = &fits[best];
            let n = surfels[c].len();
            inv.set_base_colors(c, &vec![f.base_color; n]);
            inv.set_lobes(c, f.metallic, f.roughness);
        }
        tests.push(ObjectTest {
            object: names
                .get(c)
                .cloned()
                .unwrap_or_else(|| format!("component {c}")),
            pixels: tested[c].len(),
            owned_pixels: owned[c].len(),
            chosen: fits[best].name.clone(),
            hypotheses: fits,
        });
    }
    SearchFigures {
        objects: tests,
        seconds: t0.elapsed().as_secs_f64(),
    }
}

/// A replayed sample's radiance with the primary record's base colour at 0 and at 1, its
/// other materials as traced.
fn at_base_colours(path: &PathReplay, env: &EnvMap) -> ([f32; 3], [f32; 3]) {
    let [m0, m1] = path.materials;
    let with = |a: f32| {
        let primary = Material {
            base_color: [a; 3],
            ..m0
        };
        path.radiance_with(&[primary, m1], env)
    };
    (with(0.0), with(1.0))
}
