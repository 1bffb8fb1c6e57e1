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
//! **The model.** For a surface point x with normal n seen in state k, Lambertian,
//!
//! ```text
//! I_k(x) ≈ τ_x ρ_g · ( Σ_t T_k(x)_t E_k,t + b_k(x) ),
//! T_k(x)_t = (1/π) ∫_texel t V_k(x, ω) max(0, n·ω) dω,
//! b_k(x)   = (1/π) ∫ (1 − V_k(x, ω)) L_k(hit(x, ω)) max(0, n·ω) dω
//! ```
//!
//! with E_k a coarse lat-long map (piecewise constant: exactly what its resampling to the
//! loop's resolution gives), V_k the transmittance through the stage-2 surfels placed as state
//! k, ρ_g one base colour per *group* (the surfels of one component whose normals share a
//! dominant axis: a floor, a pair of walls, a box's pair of faces; in the background, one
//! group per *layer* along that axis, [`layers`]) and τ_x the point's own
//! brightness against its group's, its *texture* (luminance; the group's median τ is 1).
//!
//! What tells paint from light is that paint is the same in every state and the light is not:
//! τ_x is shared by the rows of point x in every state that saw it, so a shadow that falls on
//! x in one state and not in another can only be cast (by E), while a dark tile, dark in every
//! state, is τ. A point seen in one state alone cannot tell the two apart; there a prior holds
//! τ toward 1 (the group's colour: a plain surface) with the weight of [`TEXTURE_PRIOR`] of its
//! rows, so half of what such a row shows is left to the light. Without τ (τ = 1: one colour
//! per group, textures left to the robust weights as outliers) a textured floor is a quarter
//! of the data unexplained (the demo's residual 0.27 against 0.11 with τ).
//!
//! τ is fitted only with `--light-fit-texture` (off by default). On the Cycles scenes it does
//! what it should to the shape of the light (the demo's irradiance error 7.8 % against 11.5 %,
//! training views +0.4-2.6 dB, Table 1 after the median albedo rescale 27.73 against 26.37 dB;
//! on the sunroom 9.8 % against 11.6 %, +0.6-0.7 dB, 29.58 against 29.45), but the loop then
//! ends with a base colour 8-20 % too dark everywhere (the evaluation's truth / recovered ratio
//! 1.08 sunroom, 1.25 demo, against 0.94-0.98 without), which costs Table 1 without the
//! rescale 3 dB; what sets that scale with τ free is not yet understood (the seen sky should
//! pin it, as it does on `tests/separation.rs`'s floor, where the fit's ρ is within 1 % of the
//! truth). Stage 3 learns each surfel's own colour, starting from the group's (ρ_g; τ only
//! shapes the fit's light).
//!
//! b_k is the light the point gets from the surfaces around it (eq. rendering-equation's
//! indirect term, one bounce), and it is *measured*, not modelled: in the directions a surface
//! blocks, the radiance leaving that surface toward x is what the cameras saw of it in state k
//! (a diffuse surface sends the same radiance every way), so `composite_hits` along the
//! transport's own directions gives Σ_j w_j L_j with L_j the mean of the pixels whose front
//! surfel j is (not seen: its component's mean in that state, then the state's). Without it a
//! floor beside a lit wall comes out brighter than ρ E says, and the fit could only explain
//! that with more light (where the wall is) or brighter paint.
//!
//! **Sky and suns, E = S + P.** A few texels hold nearly all the power of a sunny sky; the rest
//! is smooth. The fit says so: S is a smooth map (a graph Laplacian on the lat-long grid,
//! wrapping in longitude and across each pole, not across the horizon, [`SMOOTH`] × the data's
//! mean diagonal) held near the seen sky's level where no data reach ([`PRIOR`]), and P = κ p
//! a sparse one: a magnitude p ≥ 0 per texel under a reweighted L1 penalty (Candès, Wakin &
//! Boyd 2008: each texel pays [`SUN_COST`] × diag × level² · p / (p + δ level) in the limit, a
//! near-constant price per sun) times one colour κ per state for all its suns (luminance 1,
//! fitted in closed form each round). A single map with a weak smoothness term, as before, let
//! the non-negative solve leave every texel no shadow points at near black: the zenith that no
//! view sees came out at a twentieth of the truth and the held-out views' backgrounds and the
//! loop's start paid for it. Here a texel the data do not ask for stays at the smooth sky's
//! value, and a sun costs what it costs, wherever the shadows put it. Suns of one colour,
//! because a sun per channel (the version before) could explain a red patch of texture by a
//! red sun that only that patch saw: the demo's maps came out with pure red, green and blue
//! suns scattered over the sky. The suns' colour is seen only through what they light, so it
//! trades with the colour of the surfaces they light most: on `tests/separation.rs`'s plain
//! floor (the truth 0.55 / 0.50 / 0.45 under a white sun) the fit's floor keeps the
//! chromaticity of its grey start, 0.503 / 0.504 / 0.503 (the luminance within 1 %), κ and the
//! unseen zenith taking the warmth; with κ held white it gets halfway, 0.521 / 0.501 / 0.475,
//! and the box's blue falls to 0.549 for 0.60 (measured 2026-12-06, not kept). What would pin
//! it (a prior on the suns' colour, the box's sunlit faces weighed more) is open.
//!
//! The pixels that see no surface look at the environment itself, so each texel they land in
//! gets the row E_k,t = their mean (a direct measurement; it pins the scale that ρ and E
//! otherwise trade).
//!
//! **The solve.** Alternating, each step exact: (S_k, P_k) by block coordinate descent on the
//! convex objective, texel by texel, each texel's block (the three channels of s and the sun's
//! p, all ≥ 0) solved in closed form ([`SunTexel`]), then κ_k; then each ρ_g in closed form
//! (clamped to [0.02, 0.95]); then each τ_x (`texture_step`, with `--light-fit-texture`); rows
//! reweighted each round by 1 / max(|r|, δ) on their luminance residual (iteratively
//! reweighted least squares for an L1 fit, so specular objects and the light paths this model
//! leaves out count as outliers rather than light), and the sun penalty's weights
//! 1 / (p + δ level) likewise. Once, before the last rounds, each cluster of suns is put to a
//! backward test ([`SUN_KEEP`]): taken out, the sky fitted again without it, and kept only if
//! the fit is clearly worse without it. The descent texel by texel cannot make that move (a
//! sun and the smooth sky fitted around it are a local minimum together), and without it the
//! demo's soft skies came out as a few bright texels over a sky too dim.
//!
//! **Ties between a component's groups** (`--light-fit-tie`, off by default; not in the
//! paper). A group that alone sees some part of the sky (the back wall, facing the open side
//! no camera looks out of) can trade its ρ against that part's light: only their product is
//! seen. On the sunroom the back wall's ρ came out 1.08× the side walls' (one paint in the
//! truth) and stage 3 widened it to 1.13×, a quarter of its training views' ghosts. With the
//! tie, the ρ step minimises per channel, over the groups g with data-only estimates ρ̂_g =
//! num_g / den_g,
//!
//! ```text
//! Σ_g den_g (ρ_g − ρ̂_g)²  +  Σ_{g<h, one component} w_gh (ρ_g − ρ_h)²,
//! w_gh = TIE · min(den_g, den_h) · exp(−(d_gh / TIE_SPREAD)²),  d_gh = max_c |ln ρ̂_g / ρ̂_h|
//! ```
//!
//! a truncated (Welsch) pull between groups whose own data give nearly one colour, as the
//! piecewise-constant reflectance priors of intrinsic-image methods tie pixels of one
//! chromaticity: two paints a third apart (the sunroom's floor and walls, 1.33×) pull at 3 %
//! of full strength, 20 % apart at 23 %, 8 % apart at 77 %, and as the light follows the tied
//! ρ round after round, closer pulls harder. The weights are the IRLS weights of a Welsch
//! penalty, recomputed each round from that round's ρ̂. [`tie_groups`].
//!
//! **What it leaves out**, on purpose: bounces past the first (the measured radiance of the
//! surroundings already holds them), gloss and metals. The loop that follows has all of them.

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
/// Rounds of alternation (each: S, P for every state, then ρ, then the weights). Many and
/// short: ρ and the map's scale trade along a valley that only the seen sky pins, and the
/// alternation walks it slowly (the module's test with a known bounce: ρ 10 % off after 12
/// rounds of 150 sweeps, 0.4 % after 40 of 50).
const ROUNDS: usize = 40;
/// Coordinate-descent sweeps per (S, P) solve (warm-started).
const SWEEPS: usize = 50;
/// The smooth sky's Laplacian weight against the data's mean diagonal: strong, so the smooth
/// part has no say in how light a shadow is cut (the sparse part has), and unseen texels take
/// their neighbours' level.
pub const SMOOTH: f64 = 50.0;
/// The price of a sun texel against the data's mean diagonal × the sky's level² (the
/// reweighted L1 term's limit).
///
/// A texel-by-texel descent under this price keeps suns a smooth sky would carry nearly as
/// well (taking one out is a single-texel move, and the smooth sky around it, fitted to the
/// sun, cannot follow in the same move); [`SUN_KEEP`]'s backward test takes those out.
///
/// Raising the price instead does not work (issue 44, measured 2026-12-06, before the
/// backward test): on the demo (an open-topped room under soft HDRIs whose brightest regions
/// carry a third of the light; the fit alone, `lightfuse invert --iterations 1`) the suns at
/// 10 carried 71 / 88 / 34 % of the three states' light, and the maps' log error above the
/// horizon was 1.32 / 1.84 / 1.24 where a uniform map scores 0.97 / 1.40 / 1.12; at 30, 100
/// and 300: 0.96 / 1.67 / 1.10, 0.77 / 1.28 / 1.07 and 0.76 / 1.41 / 1.07 (suns 34 / 85 / 2 %,
/// 0 / 37 / 2 %, 0 / 0 / 1 %). But at 100 `tests/separation.rs`'s plain floor loses its real
/// suns (12 % and 7 % of the light for a truth of 85 %; its ghost comes back, 0.89): the
/// plain L1 of the first round prices a bright sun by its magnitude, and a texel set to zero
/// there is dearer still under the reweighting, so it never returns. Keeping the first
/// round's price at 10 and raising only the reweighted rounds' does not separate the two
/// either: 100 keeps the floor's suns (the ghost 0.96) but most of the demo's (61 / 86 / 12 %;
/// log error 1.13 / 1.68 / 1.17), 1000 takes more of the demo's (28 / 62 / 0 %; 0.90 / 1.46 /
/// 1.10) and lets the floor's ghost back (0.94).
pub const SUN_COST: f64 = 10.0;
/// The backward test's price of a cluster of suns (`prune`, in the last penalised round):
/// a cluster whose removal, with the smooth sky and the other suns fitted again, raises the
/// objective by less than this × the data's mean luminance diagonal × the sky's luminance
/// level² is taken out. An L0 price per sun, where [`SUN_COST`]'s reweighted L1 is a price
/// per texel that a descent texel by texel cannot act on.
///
/// Where it sits (measured 2026-12-07, same units): `tests/separation.rs`'s plain floor under
/// two hard suns, removal costs 83 000 and 19 000 for the real suns and 2 800 for the one
/// spurious cluster; on the demo's fit, 23 clusters over three states from 120 to 3 300 and
/// six from 17 000 to 90 000, the six on the brightest regions of the true maps (state 0's
/// glow at the horizon, state 1's two low bright patches). 5 000 sits in that gap, ×3.8 below
/// the smallest real sun's cost. On the demo the fit alone then gives log errors above the
/// horizon of 1.02 / 1.64 / 1.11 for 1.25 / 1.76 / 1.33 without the test (a uniform map 0.97 /
/// 1.40 / 1.12), irradiance errors 8.2 / 12.5 / 13.6 % for 8.9 / 13.0 / 13.9 %, suns 38 /
/// 70 / 2 % of the light for 70 / 86 / 45 %. State 2's true map has two small suns (31 % of
/// its light, at 11°-texel scale) whose clusters cost 760 and 270 to remove: no shadow in its
/// captures points at them, and the test takes them out with the rest (its errors still fall).
/// At 15 000 the demo's figures are the same to 0.01 (1.03 / 1.64 / 1.11).
///
/// What it does not test (open): a cluster is kept or cut whole, so spurious texels joined to
/// a real sun stay with it. On the atelier (measured 2026-12-07, the fit alone) state 0's true
/// sun sits in texel (7, 4) and the fit puts three more above it, (6, 1), (6, 2), (7, 3), each
/// at about a third of the sun's value: the same azimuth at a higher elevation, shadows along
/// the same line but shorter. Tested one texel at a time (the cluster's brightest kept, the
/// same price) they cost 430-940 and go; that state's maps then light a diffuse surface
/// better (irradiance 8.9 → 4.9 % at 32×16) but their log error above the horizon rises (1.20
/// → 1.40 at 32×16) as the sky below the sun's azimuth, already 10-50× too dark near the
/// horizon, goes darker. Not adopted: not measured end to end. (That dark band was the walls'
/// tops sharing the floor's group, fixed since by [`groups`]' layers.) The same test with the
/// layers, on the demo (measured 2026-12-07, the fit alone, every kept cluster of two or more
/// texels tested texel by texel, its brightest kept): it cuts 7 / 6 / 2 more texels, the soft
/// skies' bright glows, each costing 11-2 600 where a glow's whole cluster costs 17 000 or more;
/// irradiance 6.9 / 9.0 / 12.6 → 9.2 / 8.8 / 11.7 %, log error above the horizon 0.95 / 1.36 /
/// 1.10 → 0.96 / 1.35 / 1.08. A glow's texels and a streak's are alike to this test (a third
/// to two thirds of their cluster's peak, cheap one by one), so it is not adopted.
pub const SUN_KEEP: f64 = 5000.0;
/// The reweighted L1 term's δ, relative to the sky's level.
const SUN_DELTA: f64 = 0.05;
/// The last rounds, in which the suns found are free of the penalty (least squares on the
/// support the L1 chose, "debiasing").
const DEBIAS: usize = 4;
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
    /// Groups and their fitted base colours: (component, normal axis 0-2, ρ); the background
    /// has one per layer ([`groups`]), in order along the axis.
    pub groups: Vec<(u32, u32, [f32; 3])>,
    /// Visibility rays traced (one per direction above a row's horizon).
    pub rays: u64,
    /// Mean absolute luminance residual over the mean luminance, first and last round.
    pub residual: [f64; 2],
    /// The share of the modelled light that is the surroundings' (Σ ρ b / Σ ρ (T E + b) over
    /// the rows, luminance).
    #[serde(default)]
    pub bounce_share: f64,
    /// Per state, the sparse part's share of the recovered map's radiant power (luminance):
    /// how much of the light the fit put in suns.
    #[serde(default)]
    pub sun_share: Vec<f64>,
    /// Per state, the clusters of suns the backward test ([`SUN_KEEP`]) took out.
    #[serde(default)]
    pub suns_pruned: Vec<usize>,
    pub seconds: f64,
}

/// The fit: one coarse environment per training state and a base colour per group.
pub struct LightFit {
    pub envs: Vec<Environment>,
    /// Per component, each surfel's group ([`Groups`]).
    pub group_of: Vec<Vec<usize>>,
    /// Per group: ρ (None: no point of that group was seen).
    pub base_colors: Vec<Option<[f32; 3]>>,
    pub figures: FitFigures,
}

impl LightFit {
    /// Each surfel's base colour from its group (surfels of groups no point was seen in keep
    /// `fallback`).
    pub fn surfel_colors(&self, fallback: f32) -> Vec<Vec<[f32; 3]>> {
        self.group_of
            .iter()
            .map(|g| {
                g.iter()
                    .map(|&g| self.base_colors[g].unwrap_or([fallback; 3]))
                    .collect()
            })
            .collect()
    }
}

/// The fit's groups of surfels that share one base colour ρ_g: per component, each surfel's
/// group, and per group its component and normal axis.
pub struct Groups {
    pub of: Vec<Vec<usize>>,
    pub info: Vec<(u32, u32)>,
}

/// How far apart (relative to the extent of the background's surfels along an axis) two
/// surfaces must lie to be two [`layers`]; and the share of that axis's surfels a bin must
/// hold to count as a surface rather than a stray surfel.
pub const LAYER_GAP: f32 = 0.02;
pub const LAYER_MIN_SHARE: f64 = 0.002;

/// Each surfel's group: its component and its normal's dominant axis, and in the background
/// (component 0) also its layer along that axis ([`layers`]).
///
/// Why layers, in the background only (issue 44, measured 2026-12-07): the background is one
/// component holding every static surface, so "the floor's group" also held the walls' tops
/// (and in other rooms a table's or a bench's top), a different material at a different
/// height. On the atelier (a linen floor, albedo luminance 0.83, slate walls 0.26 whose tops
/// the orbiting cameras see) each row's colour over what the *true* lighting gives it (the
/// truth area-averaged to the fit's 32×16, its sun traced as a point) is 0.75-0.81 on the
/// floor and 0.18-0.31 on the walls' tops; with one ρ for both the fit made the tops dark
/// with the one thing only they see, the sky low above the walls, and that band came out
/// 10-50× too dark behind them. An object stays one group per axis: it is one material far
/// more often, and its pair of opposite faces sharing ρ is what tells a lit face from a
/// shadowed one.
pub fn groups(components: &[&Surfels]) -> Groups {
    let mut of = Vec::with_capacity(components.len());
    let mut info = Vec::new();
    for (c, s) in components.iter().enumerate() {
        let axis: Vec<usize> = (0..s.len())
            .map(|i| dominant_axis(local_normal(s, i)))
            .collect();
        let mut layer = vec![0usize; s.len()];
        let mut first = [0usize; 3];
        for a in 0..3 {
            first[a] = info.len();
            let n = if c == 0 {
                let members: Vec<usize> = (0..s.len()).filter(|&i| axis[i] == a).collect();
                let coords: Vec<f32> = members.iter().map(|&i| s.position[i][a]).collect();
                let (n, of_member) = layers(&coords);
                for (&i, l) in members.iter().zip(of_member) {
                    layer[i] = l;
                }
                n
            } else {
                1
            };
            info.extend((0..n).map(|_| (c as u32, a as u32)));
        }
        of.push((0..s.len()).map(|i| first[axis[i]] + layer[i]).collect());
    }
    Groups { of, info }
}

/// Splits coordinates along one axis into layers: bins [`LAYER_GAP`] × their extent wide, a
/// bin holding at least [`LAYER_MIN_SHARE`] of them (and 3) a surface's, runs of such bins one
/// layer each, every coordinate in the layer nearest to it. Returns the number of layers
/// (at least 1) and each coordinate's layer. A curved surface or a floor whose surfels spread
/// leaves no empty bin and stays one layer.
pub fn layers(coords: &[f32]) -> (usize, Vec<usize>) {
    let (lo, hi) = coords
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    if coords.is_empty() || hi.partial_cmp(&lo) != Some(std::cmp::Ordering::Greater) {
        return (1, vec![0; coords.len()]);
    }
    let width = (LAYER_GAP * (hi - lo)).max(f32::MIN_POSITIVE);
    let nbins = ((hi - lo) / width) as usize + 1;
    let bin = |v: f32| (((v - lo) / width) as usize).min(nbins - 1);
    let mut count = vec![0usize; nbins];
    for &v in coords {
        count[bin(v)] += 1;
    }
    let min = ((LAYER_MIN_SHARE * coords.len() as f64).ceil() as usize).max(3);
    // Each occupied bin's layer; empty bins None.
    let mut of_bin: Vec<Option<usize>> = vec![None; nbins];
    let mut n = 0usize;
    for b in 0..nbins {
        if count[b] >= min {
            if b == 0 || of_bin[b - 1].is_none() {
                n += 1;
            }
            of_bin[b] = Some(n - 1);
        }
    }
    if n == 0 {
        return (1, vec![0; coords.len()]);
    }
    // Bins that hold too few: the nearest occupied bin's layer (the lower on a tie).
    let occupied: Vec<usize> = (0..nbins).filter(|&b| of_bin[b].is_some()).collect();
    let layer_of_bin: Vec<usize> = (0..nbins)
        .map(|b| {
            of_bin[b].unwrap_or_else(|| {
                let near = *occupied
                    .iter()
                    .min_by_key(|&&o| (o as i64 - b as i64).unsigned_abs())
                    .expect("an occupied bin");
                of_bin[near].expect("occupied")
            })
        })
        .collect();
    (n, coords.iter().map(|&v| layer_of_bin[bin(v)]).collect())
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

/// One row of the fit: state, group, observed colour, the transport to each texel (sparse:
/// texel index and weight) and the irradiance the surroundings give (the module's b, RGB).
pub struct Row {
    pub state: usize,
    pub group: usize,
    /// The surface point (rows of one point, one per state that saw it, share its texture
    /// factor τ).
    pub point: usize,
    pub rgb: [f64; 3],
    pub t: Vec<(u16, f32)>,
    pub b: [f64; 3],
}

/// What the cameras saw of each surfel in one state: the radiance b's directions meet
/// (the module's L_k), with the fallbacks for surfels no pixel had in front.
struct Radiance {
    surfel: HashMap<(u32, u32), [f64; 3]>,
    component: Vec<Option<[f64; 3]>>,
    state: [f64; 3],
}

impl Radiance {
    fn new(seen: &HashMap<(u32, u32), Seen>, ncomponents: usize) -> Radiance {
        let mut sums = vec![([0.0f64; 3], 0u64); ncomponents];
        let mut all = ([0.0f64; 3], 0u64);
        let mut surfel = HashMap::with_capacity(seen.len());
        // In key order: the sums must not depend on the map's iteration order (determinism).
        let mut keys: Vec<(u32, u32)> = seen.keys().copied().collect();
        keys.sort_unstable();
        for (c, i) in keys {
            let s = &seen[&(c, i)];
            for acc in [&mut sums[c as usize], &mut all] {
                for ch in 0..3 {
                    acc.0[ch] += s.rgb[ch];
                }
                acc.1 += s.count as u64;
            }
            surfel.insert((c, i), s.rgb.map(|x| x / s.count as f64));
        }
        let mean = |(s, n): ([f64; 3], u64)| (n > 0).then(|| s.map(|x| x / n as f64));
        Radiance {
            surfel,
            component: sums.into_iter().map(mean).collect(),
            state: mean(all).unwrap_or([0.0; 3]),
        }
    }

    fn of(&self, c: u32, i: u32) -> [f64; 3] {
        self.surfel
            .get(&(c, i))
            .copied()
            .or_else(|| self.component.get(c as usize).copied().flatten())
            .unwrap_or(self.state)
    }
}

/// The fit's switches: `texture` fits each point's τ (`--light-fit-texture`), `tie` pulls a
/// component's groups of nearly one colour together ([`tie_groups`], `--light-fit-tie`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FitOptions {
    pub texture: bool,
    pub tie: bool,
}

/// Fits the lighting (see the module) from `states`' captures through `cache`'s primary
/// records; `trace` holds the stage-2 geometry; `components` are its surfels (for the groups).
pub fn fit(
    trace: &TraceScene,
    states: &[TrainState],
    cache: &PrimaryCache,
    components: &[&Surfels],
    seed: u64,
    options: FitOptions,
) -> LightFit {
    let t0 = std::time::Instant::now();
    let ntex = WIDTH * HEIGHT;
    let grouping = groups(components);
    let ngroups = grouping.info.len();

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
    let radiance: Vec<Radiance> = seen
        .iter()
        .map(|m| Radiance::new(m, components.len()))
        .collect();

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
    let mut jobs: Vec<(usize, usize, usize, Seen)> = Vec::new();
    for (point, &(c, i)) in keys.iter().enumerate() {
        let group = grouping.of[c as usize][i as usize];
        for (k, m) in seen.iter().enumerate() {
            if let Some(s) = m.get(&(c, i)).filter(|s| s.count >= 2) {
                jobs.push((k, group, point, *s));
            }
        }
    }

    // 3. Each row's transport and bounce: SUB² directions per texel, composited through the
    // state's placement: what passes is transport to the texel, what the hits block is the
    // hit surfels' measured radiance.
    let placed: Vec<_> = states.iter().map(|s| trace.place(&s.transforms)).collect();
    let traced = AtomicU64::new(0);
    let rows: Vec<Row> = jobs
        .par_iter()
        .map(|&(k, group, point, s)| {
            let inv = 1.0 / s.count as f64;
            let x = Vec3::from_array(s.x.map(|v| (v * inv) as f32));
            let n = Vec3::from_array(s.n.map(|v| v as f32)).normalize_or_zero();
            let origin = (x + states[k].eps * n).to_array();
            let mut hits = Vec::new();
            let (t, b) = transport(n, |d| {
                traced.fetch_add(1, Ordering::Relaxed);
                hits.clear();
                let rec =
                    placed[k].composite_hits(origin, d.to_array(), 0.0, f32::INFINITY, &mut hits);
                let mut l = [0.0f64; 3];
                for h in &hits {
                    let r = radiance[k].of(h.component, h.index);
                    for c in 0..3 {
                        l[c] += h.w as f64 * r[c];
                    }
                }
                (1.0 - rec.alpha.clamp(0.0, 1.0), l)
            });
            Row {
                state: k,
                group,
                point,
                rgb: s.rgb.map(|v| v * inv),
                t,
                b,
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
    let component: Vec<u32> = grouping.info.iter().map(|&(c, _)| c).collect();
    let solved = solve(&rows, &sky_rows, &component, states.len(), options);

    let mut groups_seen = vec![false; ngroups];
    for r in &rows {
        groups_seen[r.group] = true;
    }
    let base_colors: Vec<Option<[f32; 3]>> = (0..ngroups)
        .map(|g| groups_seen[g].then(|| solved.rho[g].map(|v| v as f32)))
        .collect();
    let groups = (0..ngroups)
        .filter(|&g| groups_seen[g])
        .map(|g| {
            (
                grouping.info[g].0,
                grouping.info[g].1,
                solved.rho[g].map(|v| v as f32),
            )
        })
        .collect();
    let envs = solved
        .env
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
        group_of: grouping.of,
        base_colors,
        figures: FitFigures {
            rows: rows.len(),
            sky_texels: sky_rows.iter().flatten().filter(|s| s.2).count(),
            groups,
            rays,
            residual: solved.residual,
            bounce_share: solved.bounce_share,
            sun_share: solved.sun_share,
            suns_pruned: solved.pruned,
            seconds: t0.elapsed().as_secs_f64(),
        },
    }
}

/// A point's transport to each texel and the irradiance its surroundings give (eq.
/// rendering-equation's diffuse term, texel by texel): T_t = (1/π) Σ_j V(ω_j) max(0, n·ω_j)
/// Δω_t / SUB² over SUB × SUB directions stratified in the texel, and b = (1/π) Σ over the
/// same directions of the blocked radiance × max(0, n·ω_j) Δω_t / SUB². `look` gives, toward a
/// direction, the transmittance V and the radiance the blocking surfaces send back weighted by
/// how much they block (Σ_j w_j L_j, so (1 − V) × their mean radiance). Texels with T_t = 0
/// are left out.
pub fn transport(
    n: Vec3,
    mut look: impl FnMut(Vec3) -> (f32, [f64; 3]),
) -> (Vec<(u16, f32)>, [f64; 3]) {
    let mut t = Vec::new();
    let mut b = [0.0f64; 3];
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
                    let (vis, blocked) = look(d);
                    acc += (vis * c) as f64 * dw;
                    for ch in 0..3 {
                        b[ch] += blocked[ch] * c as f64 * dw;
                    }
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
    (t, b.map(|v| v / std::f64::consts::PI))
}

/// A row on one texel of a state's environment: its index, radiance, and whether it was seen
/// directly (the pixels' mean, weighted as one surface row, on S + P) or is [`fill`]'s guess
/// (weighted [`PRIOR`] × the data's mean diagonal, on the smooth part S, and only on texels
/// whose own data weigh less: a guess must not outweigh the shadows that point at a sun).
pub type SkyTexel = (usize, [f64; 3], bool);

/// The weight of [`fill`]'s rows against the data's mean diagonal.
pub const PRIOR: f64 = 0.1;

/// Weak rows for the texels no view saw: the mean of their row's seen texels, or the nearest
/// row's with any (what the loop's own start, `train::initial_environment`, puts there). A
/// texel that few surface points see gets next to no say in the normal equations; a view of
/// a new arrangement, or one held out, may look straight at it (the demo's held-out
/// backgrounds fell to 7.5 dB without this).
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

/// A coarse map's texels (RGB, row-major).
type Map = Vec<[f64; 3]>;

/// [`solve`]'s result: each state's coarse environment E = S + P and its sparse part P
/// (texels, RGB), each group's ρ, the relative L1 residual of the first and last round, and
/// [`FitFigures`]' bounce and sun shares.
pub struct Solved {
    pub env: Vec<Vec<[f64; 3]>>,
    pub sun: Vec<Vec<[f64; 3]>>,
    pub rho: Vec<[f64; 3]>,
    pub residual: [f64; 2],
    pub bounce_share: f64,
    pub sun_share: Vec<f64>,
    /// Per state, the clusters of suns the backward test ([`SUN_KEEP`]) took out.
    pub pruned: Vec<usize>,
}

/// The texels' links of the smooth part's Laplacian: each texel to its right neighbour
/// (wrapping in longitude) and the one below (except across the horizon), and across each pole to the texel half a turn
/// away (the top row's texels all meet at the zenith).
fn links() -> Vec<Vec<usize>> {
    let mut n = vec![Vec::new(); WIDTH * HEIGHT];
    let mut link = |i: usize, j: usize| {
        n[i].push(j);
        n[j].push(i);
    };
    for y in 0..HEIGHT {
        for x in 0..WIDTH {
            let i = y * WIDTH + x;
            link(i, y * WIDTH + (x + 1) % WIDTH);
            // Not across the horizon (+Y up, v = ½): ground and sky are different things,
            // and a link there would pull the sky toward the ground's level.
            if y + 1 < HEIGHT && y + 1 != HEIGHT / 2 {
                link(i, (y + 1) * WIDTH + x);
            }
        }
    }
    for y in [0, HEIGHT - 1] {
        for x in 0..WIDTH / 2 {
            link(y * WIDTH + x, y * WIDTH + x + WIDTH / 2);
        }
    }
    n
}

/// The range of each channel of a state's sun colour κ (luminance 1).
const KAPPA_RANGE: (f64, f64) = (0.1, 10.0);

/// `a · v` for a dense `n × n` matrix `a`, row-major.
fn mat_vec(a: &[f64], v: &[f64], n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| {
            a[i * n..(i + 1) * n]
                .iter()
                .zip(v)
                .map(|(x, y)| x * y)
                .sum()
        })
        .collect()
}

/// One texel's block of the (S, P) objective with the other texels held: over the smooth
/// part's three channels s_c ≥ 0 and the sun magnitude p ≥ 0 (the sun's colour κ fixed),
/// minimises
///
/// ```text
/// F(s, p) = Σ_c [ ½ a_c (s_c + κ_c p)² + gx_c (s_c + κ_c p) + ½ l_c s_c² + gs_c s_c ] + cost · p,
/// ```
///
/// a_c the data's (and seen sky's) diagonal in channel c, gx_c their gradient at s = p = 0
/// given the other texels, l_c the Laplacian's and prior's diagonal, gs_c likewise, cost the
/// sun penalty's weight. One magnitude for the three channels: a sun is one colour, so a
/// texture's colour cannot be explained by a sun of its own colour (the per-channel suns of
/// the first version put pure red, green and blue suns above the demo's textured floor).
#[derive(Clone, Copy, Debug, Default)]
pub struct SunTexel {
    pub kappa: [f64; 3],
    pub a: [f64; 3],
    pub gx: [f64; 3],
    pub l: [f64; 3],
    pub gs: [f64; 3],
    pub cost: f64,
}

impl SunTexel {
    /// F at (s, p).
    pub fn value(&self, s: [f64; 3], p: f64) -> f64 {
        (0..3)
            .map(|c| {
                let x = s[c] + self.kappa[c] * p;
                0.5 * self.a[c] * x * x
                    + self.gx[c] * x
                    + 0.5 * self.l[c] * s[c] * s[c]
                    + self.gs[c] * s[c]
            })
            .sum::<f64>()
            + self.cost * p
    }

    /// Each s_c minimising F for a given p (a clamped 1-D minimum).
    fn s_at(&self, p: f64) -> [f64; 3] {
        [0, 1, 2].map(|c| {
            let d = self.a[c] + self.l[c];
            if d <= 0.0 {
                0.0
            } else {
                (-(self.a[c] * self.kappa[c] * p + self.gx[c] + self.gs[c]) / d).max(0.0)
            }
        })
    }

    /// The block's minimum. With s eliminated, φ(p) = min_s F(s, p) is convex and piecewise
    /// quadratic: its derivative φ′(p) = Σ_c κ_c (a_c (s_c(p) + κ_c p) + gx_c) + cost
    /// (envelope theorem) is piecewise linear and nondecreasing, with a kink where some
    /// s_c(p) reaches 0; the minimum is φ′'s root on p ≥ 0, found interval by interval
    /// (exact).
    pub fn solve(&self) -> ([f64; 3], f64) {
        let dphi = |p: f64| {
            let s = self.s_at(p);
            (0..3)
                .map(|c| self.kappa[c] * (self.a[c] * (s[c] + self.kappa[c] * p) + self.gx[c]))
                .sum::<f64>()
                + self.cost
        };
        let curv: f64 = (0..3)
            .map(|c| self.a[c] * self.kappa[c] * self.kappa[c])
            .sum();
        if curv <= 0.0 || dphi(0.0) >= 0.0 {
            return (self.s_at(0.0), 0.0);
        }
        // The kinks: s_c(p) = 0 at p_c = −(gx_c + gs_c) / (a_c κ_c).
        let mut knots: Vec<f64> = (0..3)
            .filter(|&c| self.a[c] * self.kappa[c] > 0.0)
            .map(|c| -(self.gx[c] + self.gs[c]) / (self.a[c] * self.kappa[c]))
            .filter(|&k| k > 0.0)
            .collect();
        knots.sort_by(f64::total_cmp);
        knots.push(f64::INFINITY);
        let mut lo = 0.0;
        for &hi in &knots {
            // φ′ is linear on [lo, hi]: its value and slope at lo.
            let d_lo = dphi(lo);
            if d_lo >= 0.0 {
                break;
            }
            let probe = if hi.is_finite() {
                0.5 * (lo + hi)
            } else {
                lo + 1.0
            };
            let slope = (dphi(probe) - d_lo) / (probe - lo);
            if slope > 0.0 {
                let root = lo - d_lo / slope;
                if root <= hi {
                    return (self.s_at(root), root);
                }
            }
            if !hi.is_finite() {
                break;
            }
            lo = hi;
        }
        (self.s_at(lo), lo)
    }
}

/// One state's (S, P) problem with ρ, the weights and κ held: per channel the data's (and the
/// seen sky's) normal matrix `a` and right-hand side `r`, the smooth part's Laplacian weight
/// and the fill prior's weights and values.
struct StateProblem<'a> {
    a: &'a [Vec<f64>],
    r: &'a [Vec<f64>],
    lam: [f64; 3],
    prior_w: &'a [Vec<f64>],
    prior_v: &'a [Vec<f64>],
    nbrs: &'a [Vec<usize>],
    kappa: [f64; 3],
}

impl StateProblem<'_> {
    /// One sweep of block coordinate descent, texel by texel ([`SunTexel`]); a banned texel's
    /// sun is held at 0.
    fn sweep(&self, cost: &[f64], banned: &[bool], sm: &mut [Vec<f64>], p: &mut [f64]) {
        let ntex = p.len();
        let kap = self.kappa;
        let mut x: Vec<Vec<f64>> = (0..3)
            .map(|c| (0..ntex).map(|i| sm[c][i] + kap[c] * p[i]).collect())
            .collect();
        for i in 0..ntex {
            let mut blk = SunTexel {
                kappa: kap,
                cost: cost[i],
                ..SunTexel::default()
            };
            for c in 0..3 {
                let row = &self.a[c][i * ntex..(i + 1) * ntex];
                let aii = row[i];
                blk.a[c] = aii;
                blk.gx[c] = row.iter().zip(&x[c]).map(|(u, v)| u * v).sum::<f64>()
                    - aii * x[c][i]
                    - self.r[c][i];
                blk.l[c] = self.lam[c] * self.nbrs[i].len() as f64 + self.prior_w[c][i];
                blk.gs[c] = -self.lam[c] * self.nbrs[i].iter().map(|&j| sm[c][j]).sum::<f64>()
                    - self.prior_w[c][i] * self.prior_v[c][i];
            }
            let (si, pi) = if banned[i] {
                (blk.s_at(0.0), 0.0)
            } else {
                blk.solve()
            };
            p[i] = pi;
            for c in 0..3 {
                sm[c][i] = si[c];
                x[c][i] = si[c] + kap[c] * pi;
            }
        }
    }

    /// The objective the sweeps descend (up to a constant): Σ_c ½ xᵀA_c x − r_cᵀx + the
    /// Laplacian's ½ λ_c Σ_links (s_i − s_j)² + the prior's ½ w (s − v)², x = S + κ P, plus
    /// Σ cost · p.
    fn value(&self, cost: &[f64], sm: &[Vec<f64>], p: &[f64]) -> f64 {
        let ntex = p.len();
        let mut f: f64 = cost.iter().zip(p).map(|(c, v)| c * v).sum();
        for c in 0..3 {
            let x: Vec<f64> = (0..ntex).map(|i| sm[c][i] + self.kappa[c] * p[i]).collect();
            let ax = mat_vec(&self.a[c], &x, ntex);
            for i in 0..ntex {
                f += 0.5 * x[i] * ax[i] - self.r[c][i] * x[i];
                let d = sm[c][i] - self.prior_v[c][i];
                f += 0.5 * self.prior_w[c][i] * d * d;
                for &j in &self.nbrs[i] {
                    let e = sm[c][i] - sm[c][j];
                    // Each link is in both texels' lists.
                    f += 0.25 * self.lam[c] * e * e;
                }
            }
        }
        f
    }
}

/// Texels within one step (8 neighbours, wrapping in longitude) of each other, as clusters,
/// among `on`.
fn clusters(on: &[bool]) -> Vec<Vec<usize>> {
    let mut label = vec![usize::MAX; on.len()];
    let mut out: Vec<Vec<usize>> = Vec::new();
    for start in 0..on.len() {
        if !on[start] || label[start] != usize::MAX {
            continue;
        }
        let id = out.len();
        let mut stack = vec![start];
        label[start] = id;
        let mut members = Vec::new();
        while let Some(i) = stack.pop() {
            members.push(i);
            let (x, y) = ((i % WIDTH) as i64, (i / WIDTH) as i64);
            for dy in -1..=1i64 {
                for dx in -1..=1i64 {
                    let ny = y + dy;
                    if ny < 0 || ny >= HEIGHT as i64 {
                        continue;
                    }
                    let j = ny as usize * WIDTH + (x + dx).rem_euclid(WIDTH as i64) as usize;
                    if on[j] && label[j] == usize::MAX {
                        label[j] = id;
                        stack.push(j);
                    }
                }
            }
        }
        members.sort_unstable();
        out.push(members);
    }
    out
}

/// One state's (S, P) step of a round: the smooth part, the suns' magnitudes and colour, the
/// texels banned from holding a sun, and the clusters [`prune`] took out this round.
struct StateStep {
    smooth: Map,
    mag: Vec<f64>,
    kappa: [f64; 3],
    banned: Vec<bool>,
    pruned: usize,
}

/// The backward test of each sun ([`SUN_KEEP`]): every cluster of sun texels brighter than the
/// sky's level (8-connected, wrapping in longitude) is taken out (its texels banned) and the
/// state's (S, P) swept again [`SWEEPS`] times; if the objective rises by less than
/// [`SUN_KEEP`] × the data's mean luminance diagonal × the sky's luminance level², the smooth
/// sky carries that light nearly as well and the cluster stays out for the rounds after. Each
/// cluster is judged against the same baseline (the current solution swept as long), not one
/// after another. Returns the clusters taken out.
fn prune(
    problem: &StateProblem,
    cost: &[f64],
    banned: &mut [bool],
    sm: &mut [Vec<f64>],
    p: &mut [f64],
    unit: f64,
    lev_lum: f64,
) -> usize {
    let (mut sm0, mut p0) = (sm.to_vec(), p.to_vec());
    for _ in 0..SWEEPS {
        problem.sweep(cost, banned, &mut sm0, &mut p0);
    }
    let f0 = problem.value(cost, &sm0, &p0);
    let on: Vec<bool> = p.iter().map(|&v| v > lev_lum).collect();
    let mut cut = Vec::new();
    let mut taken = 0;
    for cl in clusters(&on) {
        let (mut sm1, mut p1) = (sm.to_vec(), p.to_vec());
        let mut ban1 = banned.to_vec();
        for &i in &cl {
            ban1[i] = true;
            p1[i] = 0.0;
        }
        for _ in 0..SWEEPS {
            problem.sweep(cost, &ban1, &mut sm1, &mut p1);
        }
        if problem.value(cost, &sm1, &p1) - f0 < SUN_KEEP * unit {
            cut.extend(cl);
            taken += 1;
        }
    }
    if taken > 0 {
        for i in cut {
            banned[i] = true;
            p[i] = 0.0;
        }
        for _ in 0..SWEEPS {
            problem.sweep(cost, banned, sm, p);
        }
    }
    taken
}

/// The weight of a point's texture prior (τ = 1) in units of one of its rows at τ = 1.
pub const TEXTURE_PRIOR: f64 = 1.0;
/// The range of a group's fitted base colour.
const RHO_RANGE: (f64, f64) = (0.02, 0.95);
/// The tie's weight between two groups at zero distance, in units of the lesser group's own
/// data (its `den`, the curvature of its rows' squared error in ρ): with both groups' data
/// alike, one ρ step closes two thirds of their gap.
pub const TIE: f64 = 1.0;
/// The tie's scale on the log-ratio of two groups' colours (the worst channel): an 8 % gap
/// keeps 77 % of the weight, 20 % 23 %, a third 3 %. Narrower (0.08) left a 17.6 % gap from
/// a lone patch of sky untied (`a_wall_that_alone_sees_a_patch_of_sky_keeps_its_paint_with_
/// the_tie`: 1.154× with the tie against 1.176× without); wider (0.2) closes it alike (1.021×
/// against 1.025× here) but ties a third's gap at 13 %.
pub const TIE_SPREAD: f64 = 0.15;

/// The ρ step with [`TIE`]s (see the module): per channel, the minimiser of Σ_g den_g (ρ_g −
/// ρ̂_g)² + Σ_{g<h} w_gh (ρ_g − ρ_h)² over the groups, `hat` the data-only ρ̂ (unclamped: the
/// caller clamps), `component` each group's. Groups without data (`den` 0 in a channel) keep
/// ρ̂ and take part in no tie. Gauss–Seidel: the system is symmetric and diagonally dominant
/// (each row's diagonal den_g + Σ_h w_gh), so it converges; 200 sweeps or a change below
/// 1e-12.
pub fn tie_groups(hat: &[[f64; 3]], den: &[[f64; 3]], component: &[u32]) -> Vec<[f64; 3]> {
    let n = hat.len();
    let seen = |g: usize| (0..3).all(|c| den[g][c] > 1e-12 && hat[g][c] > 0.0);
    // Each group's ties: (other group, weight per channel).
    let mut ties: Vec<Vec<(usize, [f64; 3])>> = vec![Vec::new(); n];
    for g in 0..n {
        for h in g + 1..n {
            if component[g] != component[h] || !seen(g) || !seen(h) {
                continue;
            }
            let d = (0..3)
                .map(|c| (hat[g][c] / hat[h][c]).ln().abs())
                .fold(0.0f64, f64::max);
            let k = (-(d / TIE_SPREAD).powi(2)).exp();
            if k < 1e-9 {
                continue;
            }
            let w = [0, 1, 2].map(|c| TIE * den[g][c].min(den[h][c]) * k);
            ties[g].push((h, w));
            ties[h].push((g, w));
        }
    }
    let mut rho = hat.to_vec();
    for _ in 0..200 {
        let mut change = 0.0f64;
        for g in 0..n {
            if ties[g].is_empty() {
                continue;
            }
            for c in 0..3 {
                let (mut num, mut sum) = (den[g][c] * hat[g][c], den[g][c]);
                for &(h, w) in &ties[g] {
                    num += w[c] * rho[h][c];
                    sum += w[c];
                }
                let v = num / sum;
                change = change.max((v - rho[g][c]).abs());
                rho[g][c] = v;
            }
        }
        if change < 1e-12 {
            break;
        }
    }
    rho
}

/// The range of a point's texture factor.
const TAU_RANGE: (f64, f64) = (0.1, 10.0);

/// Each point's texture factor τ in closed form on luminance, its rows' weights and the
/// prior toward 1 ([`TEXTURE_PRIOR`] rows' worth), then each group's τ renormalised to a
/// median of 1 (the factor moved into ρ_g, so ρ_g stays the group's typical colour).
fn texture_step(
    rows: &[Row],
    irr: &[[f64; 3]],
    weight: &[f64],
    rho: &mut [[f64; 3]],
    tau: &mut [f64],
) {
    let n = tau.len();
    let (mut num, mut den, mut rows_of) = (vec![0.0f64; n], vec![0.0f64; n], vec![0u32; n]);
    let mut group_of = vec![usize::MAX; n];
    for (r, row) in rows.iter().enumerate() {
        let a = luminance([0, 1, 2].map(|c| rho[row.group][c] * irr[r][c]));
        let y = luminance(row.rgb);
        num[row.point] += weight[r] * y * a;
        den[row.point] += weight[r] * a * a;
        rows_of[row.point] += 1;
        group_of[row.point] = row.group;
    }
    let ngroups = rho.len();
    let mut of_group: Vec<Vec<f64>> = vec![Vec::new(); ngroups];
    for x in 0..n {
        if rows_of[x] == 0 || den[x] <= 1e-300 {
            continue;
        }
        let lam = TEXTURE_PRIOR * den[x] / rows_of[x] as f64;
        tau[x] = ((num[x] + lam) / (den[x] + lam)).clamp(TAU_RANGE.0, TAU_RANGE.1);
        of_group[group_of[x]].push(tau[x]);
    }
    // Each group's factor moved from its points' τ into ρ_g (1: none).
    let mut moved = vec![1.0f64; ngroups];
    for g in 0..ngroups {
        if of_group[g].is_empty() {
            continue;
        }
        // The median: a few strongly textured (or glossy) points must not set the group's
        // colour.
        let v = &mut of_group[g];
        let mid = v.len() / 2;
        let median = *v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1;
        // Only as far as ρ_g's range lets it take the factor: every point's τ ρ_g must stay
        // as it is (a clamped ρ_g would darken the group and the light would make up for it).
        let gm = if median > 1.0 {
            let most = (0..3)
                .map(|c| RHO_RANGE.1 / rho[g][c].max(1e-12))
                .fold(f64::INFINITY, f64::min);
            median.min(most.max(1.0))
        } else {
            let least = (0..3)
                .map(|c| RHO_RANGE.0 / rho[g][c].max(1e-12))
                .fold(0.0, f64::max);
            median.max(least.min(1.0))
        };
        for c in 0..3 {
            rho[g][c] *= gm;
        }
        moved[g] = gm;
    }
    for x in (0..n).filter(|&x| group_of[x] != usize::MAX) {
        tau[x] /= moved[group_of[x]];
    }
}

/// Each state's sparse map P_t = κ p_t from its magnitudes `mag` and its suns' colour `kappa`.
fn suns(mag: &[Vec<f64>], kappa: &[[f64; 3]]) -> Vec<Map> {
    mag.iter()
        .zip(kappa)
        .map(|(m, kap)| m.iter().map(|&p| kap.map(|c| c * p)).collect())
        .collect()
}

/// The alternation of the module's model on given rows (exposed for its tests): `rows` the
/// surface points (state, group, colour, sparse transport over `WIDTH × HEIGHT` texels,
/// bounce), `sky` each state's directly seen texels and [`fill`]'s guesses.
/// With `texture`, each point's τ is fitted too (else τ = 1: one colour per group).
pub fn solve(
    rows: &[Row],
    sky: &[Vec<SkyTexel>],
    component: &[u32],
    nstates: usize,
    options: FitOptions,
) -> Solved {
    let FitOptions { texture, tie } = options;
    let ngroups = component.len();
    let ntex = WIDTH * HEIGHT;
    let mean_lum = rows.iter().map(|r| luminance(r.rgb)).sum::<f64>() / rows.len().max(1) as f64;
    let delta = 0.05 * mean_lum.max(1e-6);
    let mut rho = vec![[0.5f64; 3]; ngroups];
    let mut weight = vec![1.0f64; rows.len()];
    let npoints = rows.iter().map(|r| r.point + 1).max().unwrap_or(0);
    let mut tau = vec![1.0f64; npoints];
    let nbrs = links();
    // Each state's sky level (its sky rows' mean, or the captures' level where none is
    // seen): the smooth part's start and the sun penalty's scale.
    let level: Vec<[f64; 3]> = sky
        .iter()
        .map(|s| {
            if s.is_empty() {
                [2.0 * mean_lum; 3]
            } else {
                let mut a = [0.0; 3];
                for (_, v, _) in s {
                    for c in 0..3 {
                        a[c] += v[c] / s.len() as f64;
                    }
                }
                a
            }
        })
        .collect();
    // S starts at the sky rows' values (seen, or filled), P at zero.
    let mut smooth: Vec<Vec<[f64; 3]>> = (0..nstates)
        .map(|k| {
            let mut s = vec![level[k]; ntex];
            for &(t, v, _) in &sky[k] {
                s[t] = v;
            }
            s
        })
        .collect();
    // The sparse part: per texel one magnitude p ≥ 0 (luminance), times the state's sun
    // colour κ (luminance 1), shared by its suns: P_t = κ p_t.
    let mut mag: Vec<Vec<f64>> = vec![vec![0.0; ntex]; nstates];
    let mut kappa: Vec<[f64; 3]> = vec![[1.0; 3]; nstates];
    // Texels whose sun [`prune`] took out: no sun there in the rounds after.
    let mut banned: Vec<Vec<bool>> = vec![vec![false; ntex]; nstates];
    let mut pruned = vec![0usize; nstates];
    let by_state: Vec<Vec<usize>> = (0..nstates)
        .map(|k| (0..rows.len()).filter(|&r| rows[r].state == k).collect())
        .collect();
    let mut residual = [0.0f64; 2];
    for round in 0..ROUNDS {
        // (S, P) step: per state, A_c = Σ_g ρ_gc² M_g (+ the seen sky), rhs_c = Σ_rows w ρ_c
        // T (I_c − ρ_c b_c) (+ the seen sky). A sky texel's row is one measurement of it
        // (transport 1 to that texel), weighted as the mean surface row.
        let w_sky = weight.iter().sum::<f64>() / weight.len().max(1) as f64;
        let solved: Vec<StateStep> = (0..nstates)
            .into_par_iter()
            .map(|k| {
                let mut m = vec![vec![0.0f64; ntex * ntex]; ngroups];
                let mut rhs = vec![[0.0f64; 3]; ntex];
                for &r in &by_state[k] {
                    let row = &rows[r];
                    let w = weight[r];
                    let tx = tau[row.point];
                    let rg = rho[row.group];
                    let mg = &mut m[row.group];
                    for &(i, ti) in &row.t {
                        let wi = w * ti as f64;
                        let wm = wi * tx * tx;
                        for &(j, tj) in &row.t {
                            mg[i as usize * ntex + j as usize] += wm * tj as f64;
                        }
                        for c in 0..3 {
                            rhs[i as usize][c] +=
                                wi * tx * rg[c] * (row.rgb[c] - tx * rg[c] * row.b[c]);
                        }
                    }
                }
                let mut a = vec![vec![0.0f64; ntex * ntex]; 3];
                let mut r = vec![vec![0.0f64; ntex]; 3];
                let mut prior_w = vec![vec![0.0f64; ntex]; 3];
                let mut prior_v = vec![vec![0.0f64; ntex]; 3];
                let mut lam = [0.0f64; 3];
                let mut diag = [0.0f64; 3];
                for c in 0..3 {
                    let ac = &mut a[c];
                    for (g, mg) in m.iter().enumerate() {
                        let r2 = rho[g][c] * rho[g][c];
                        if r2 > 0.0 && mg.iter().any(|&v| v != 0.0) {
                            for (av, mv) in ac.iter_mut().zip(mg) {
                                *av += r2 * mv;
                            }
                        }
                    }
                    r[c] = rhs.iter().map(|v| v[c]).collect();
                    let d = (0..ntex).map(|i| ac[i * ntex + i]).sum::<f64>() / ntex as f64;
                    diag[c] = d.max(1e-12);
                    for &(t, v, seen) in &sky[k] {
                        if seen {
                            ac[t * ntex + t] += w_sky;
                            r[c][t] += w_sky * v[c];
                        } else if ac[t * ntex + t] < PRIOR * diag[c] {
                            prior_w[c][t] = PRIOR * diag[c];
                            prior_v[c][t] = v[c];
                        }
                    }
                    for i in 0..ntex {
                        ac[i * ntex + i] += 1e-6 * diag[c];
                    }
                    lam[c] = SMOOTH * diag[c];
                }
                let lev = level[k].map(|v| v.max(1e-6));
                let lev_lum = luminance(lev).max(1e-6);
                let kap = kappa[k];
                // The reweighted L1's price per unit of p: each channel's, Σ_c κ_c λ_c /
                // (κ_c p + δ lev_c) with λ_c = SUN_COST diag_c lev_c² (plain L1 in the first
                // round); in the last DEBIAS rounds none on the suns found (p above the
                // level), whose power then comes from the data alone (the L1 chose where the
                // suns are, not how bright: its pull would dim them and brighten ρ to match).
                let p_old = &mag[k];
                let cost: Vec<f64> = (0..ntex)
                    .map(|i| {
                        let p = p_old[i];
                        if round + DEBIAS >= ROUNDS && p > lev_lum {
                            return 0.0;
                        }
                        (0..3)
                            .map(|c| {
                                let lam_p = SUN_COST * diag[c] * lev[c] * lev[c];
                                if round == 0 {
                                    kap[c] * lam_p / lev[c]
                                } else {
                                    kap[c] * lam_p / (kap[c] * p + SUN_DELTA * lev[c])
                                }
                            })
                            .sum()
                    })
                    .collect();
                let problem = StateProblem {
                    a: &a,
                    r: &r,
                    lam,
                    prior_w: &prior_w,
                    prior_v: &prior_v,
                    nbrs: &nbrs,
                    kappa: kap,
                };
                let mut sm: Vec<Vec<f64>> = (0..3)
                    .map(|c| smooth[k].iter().map(|v| v[c]).collect())
                    .collect();
                let mut p = mag[k].clone();
                let mut ban = banned[k].clone();
                for _ in 0..SWEEPS {
                    problem.sweep(&cost, &ban, &mut sm, &mut p);
                }
                let mut taken = 0;
                if round + DEBIAS + 1 == ROUNDS {
                    let unit = luminance(diag) * lev_lum * lev_lum;
                    taken = prune(&problem, &cost, &mut ban, &mut sm, &mut p, unit, lev_lum);
                }
                // The suns' colour given where they are and how bright: per channel the
                // least-squares factor on p (the data's quadratic in κ_c), then luminance 1
                // (p takes the scale).
                let mut kap_new = kap;
                let ptap: Vec<f64> = (0..3)
                    .map(|c| {
                        let ap = mat_vec(&a[c], &p, ntex);
                        p.iter().zip(&ap).map(|(u, v)| u * v).sum::<f64>()
                    })
                    .collect();
                if ptap.iter().all(|&v| v > 1e-12) {
                    for c in 0..3 {
                        let asm = mat_vec(&a[c], &sm[c], ntex);
                        let num: f64 = (0..ntex).map(|i| p[i] * (r[c][i] - asm[i])).sum();
                        kap_new[c] = (num / ptap[c]).max(0.0);
                    }
                    let l = luminance(kap_new);
                    if l > 1e-9 {
                        kap_new = kap_new.map(|v| (v / l).clamp(KAPPA_RANGE.0, KAPPA_RANGE.1));
                        let l2 = luminance(kap_new);
                        kap_new = kap_new.map(|v| v / l2);
                        p.iter_mut().for_each(|v| *v *= l);
                    } else {
                        kap_new = kap;
                    }
                }
                let s_out: Map = (0..ntex).map(|i| [sm[0][i], sm[1][i], sm[2][i]]).collect();
                StateStep {
                    smooth: s_out,
                    mag: p,
                    kappa: kap_new,
                    banned: ban,
                    pruned: taken,
                }
            })
            .collect();
        for (k, step) in solved.into_iter().enumerate() {
            banned[k] = step.banned;
            pruned[k] += step.pruned;
            smooth[k] = step.smooth;
            mag[k] = step.mag;
            kappa[k] = step.kappa;
        }
        let sun = suns(&mag, &kappa);

        // ρ step and the new weights.
        let irr: Vec<[f64; 3]> = rows
            .iter()
            .map(|r| {
                let mut e = r.b;
                for &(t, w) in &r.t {
                    for c in 0..3 {
                        e[c] += w as f64
                            * (smooth[r.state][t as usize][c] + sun[r.state][t as usize][c]);
                    }
                }
                e
            })
            .collect();
        let mut num = vec![[0.0f64; 3]; ngroups];
        let mut den = vec![[0.0f64; 3]; ngroups];
        for (r, row) in rows.iter().enumerate() {
            let tx = tau[row.point];
            for c in 0..3 {
                num[row.group][c] += weight[r] * tx * row.rgb[c] * irr[r][c];
                den[row.group][c] += weight[r] * tx * tx * irr[r][c] * irr[r][c];
            }
        }
        let mut hat = rho.clone();
        for g in 0..ngroups {
            for c in 0..3 {
                if den[g][c] > 1e-12 {
                    hat[g][c] = num[g][c] / den[g][c];
                }
            }
        }
        if tie {
            hat = tie_groups(&hat, &den, component);
        }
        for g in 0..ngroups {
            for c in 0..3 {
                rho[g][c] = hat[g][c].clamp(RHO_RANGE.0, RHO_RANGE.1);
            }
        }
        if texture {
            texture_step(rows, &irr, &weight, &mut rho, &mut tau);
        }
        let mut abs = 0.0;
        for (r, row) in rows.iter().enumerate() {
            let pred = [0, 1, 2].map(|c| tau[row.point] * rho[row.group][c] * irr[r][c]);
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

    let sun = suns(&mag, &kappa);
    let env: Vec<Vec<[f64; 3]>> = (0..nstates)
        .map(|k| {
            (0..ntex)
                .map(|t| [0, 1, 2].map(|c| smooth[k][t][c] + sun[k][t][c]))
                .collect()
        })
        .collect();
    let power = |e: &[[f64; 3]]| {
        (0..ntex)
            .map(|t| luminance(e[t]) * texel_solid_angle(WIDTH, HEIGHT, t / WIDTH))
            .sum::<f64>()
    };
    let sun_share = (0..nstates)
        .map(|k| power(&sun[k]) / power(&env[k]).max(1e-12))
        .collect();
    let (mut bounce, mut total) = (0.0, 0.0);
    for row in rows {
        let rg = rho[row.group].map(|v| v * tau[row.point]);
        let mut e = row.b;
        for &(t, w) in &row.t {
            for c in 0..3 {
                e[c] += w as f64 * env[row.state][t as usize][c];
            }
        }
        bounce += luminance([0, 1, 2].map(|c| rg[c] * row.b[c]));
        total += luminance([0, 1, 2].map(|c| rg[c] * e[c]));
    }
    Solved {
        env,
        sun,
        rho,
        residual,
        bounce_share: bounce / total.max(1e-12),
        sun_share,
        pruned,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two surfaces apart along an axis are two layers, whatever a few stray surfels between
    /// them; one surface spread over the whole extent (a curved wall) stays one; nothing to
    /// split is one layer.
    #[test]
    fn layers_split_surfaces_apart_and_keep_a_spread_one_whole() {
        let mut rng = SplitMix(7);
        // A floor at 0 (1,000 surfels, ±2 mm), walls' tops at 0.55 (100), two strays between.
        let mut coords: Vec<f32> = (0..1000).map(|_| (rng.f32() - 0.5) * 0.004).collect();
        coords.extend((0..100).map(|_| 0.55 + (rng.f32() - 0.5) * 0.004));
        coords.extend([0.2, 0.4]);
        let (n, of) = layers(&coords);
        assert_eq!(n, 2);
        assert!(
            of[..1000].iter().all(|&l| l == 0),
            "the floor is the first layer"
        );
        assert!(
            of[1000..1100].iter().all(|&l| l == 1),
            "the tops are the second"
        );
        assert_eq!(&of[1100..], &[0, 1], "each stray joins the nearer surface");
        let spread: Vec<f32> = (0..1000).map(|i| i as f32 / 999.0).collect();
        assert_eq!(layers(&spread).0, 1);
        assert_eq!(layers(&[]), (1, vec![]));
        assert_eq!(layers(&[0.3; 5]), (1, vec![0; 5]));
    }

    /// The background is grouped by axis and layer, an object by axis alone (its two opposite
    /// faces, apart along the axis, share one group).
    #[test]
    fn the_background_is_grouped_by_layer_and_an_object_by_axis() {
        let up = Quat::from_rotation_arc(Vec3::Z, Vec3::Y).to_array();
        let side = Quat::from_rotation_arc(Vec3::Z, Vec3::X).to_array();
        let surfels = |pts: &[([f32; 3], [f32; 4])]| {
            let mut s = Surfels::with_sh_degree(0);
            for &(p, q) in pts {
                s.push(p, q, [0.01; 2], 1.0, &[[0.5; 3]], [0.5; 3], 0.0, 0.5);
            }
            s
        };
        let mut bg = Vec::new();
        for i in 0..50 {
            bg.push(([i as f32 * 0.01, 0.0, 0.0], up)); // floor
        }
        for i in 0..10 {
            bg.push(([i as f32 * 0.01, 0.55, 0.0], up)); // a wall's top
        }
        for i in 0..10 {
            bg.push(([-0.75, 0.1 + i as f32 * 0.01, 0.0], side)); // the wall's face
        }
        let obj: Vec<_> = (0..20)
            .map(|i| ([if i % 2 == 0 { -0.1 } else { 0.1 }, 0.05, 0.0], side))
            .collect();
        let g = groups(&[&surfels(&bg), &surfels(&obj)]);
        // Background: x (one layer), y (two), z (none seen: one); the object: x, y, z.
        assert_eq!(
            g.info,
            vec![(0, 0), (0, 1), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2)]
        );
        assert!(g.of[0][..50].iter().all(|&x| x == 1));
        assert!(g.of[0][50..60].iter().all(|&x| x == 2));
        assert!(g.of[0][60..].iter().all(|&x| x == 0));
        assert!(g.of[1].iter().all(|&x| x == 4));
    }

    /// An unoccluded point's transport, dense.
    fn open_row(n: Vec3) -> Vec<f64> {
        let mut t = vec![0.0; WIDTH * HEIGHT];
        for (i, v) in transport(n, |_| (1.0, [0.0; 3])).0 {
            t[i as usize] = v as f64;
        }
        t
    }

    /// (1/π) ∫ max(0, n·ω) dω = 1: the quadrature within 1 % for any normal (measured 0.3 %
    /// off at 32×16 with 2×2 directions per texel); a point blocked toward every direction
    /// with x > 0 by surfaces of radiance L receives half through the texels and L / 2 from
    /// those surfaces (b: what they send back, over what they cover).
    #[test]
    fn an_open_point_receives_the_whole_cosine_lobe() {
        for n in [Vec3::Y, Vec3::X, Vec3::new(0.3, 0.8, -0.5).normalize()] {
            let sum: f64 = open_row(n).iter().sum();
            assert!((sum - 1.0).abs() < 0.01, "normal {n}: Σ T = {sum}");
            assert_eq!(transport(n, |_| (1.0, [0.0; 3])).1, [0.0; 3]);
        }
        let wall = [0.3, 0.2, 0.1];
        let (t, b) = transport(Vec3::Y, |d| {
            if d.x > 0.0 {
                (0.0, wall)
            } else {
                (1.0, [0.0; 3])
            }
        });
        let half: f32 = t.iter().map(|&(_, v)| v).sum();
        assert!((half - 0.5).abs() < 0.01, "half-blocked: Σ T = {half}");
        for c in 0..3 {
            let r = b[c] / (0.5 * wall[c]);
            assert!(
                (r - 1.0).abs() < 0.02,
                "channel {c}: b {:.4} = {r:.4} × L / 2",
                b[c]
            );
        }
    }

    /// The block's closed form against a slow reference: cyclic coordinate descent on the four
    /// variables (each an exact clamped 1-D minimum) run to convergence, and a grid; in each of
    /// its cases (interior, a channel's s at 0, p at 0, a sun dearer than its light, a coloured
    /// sun, a channel without data).
    #[test]
    fn a_sun_texel_step_is_its_block_minimum() {
        let base = SunTexel {
            kappa: [1.0, 1.0, 1.0],
            a: [2.0, 2.0, 2.0],
            gx: [-3.0, -3.0, -3.0],
            l: [1.0, 1.0, 1.0],
            gs: [-0.5, -0.5, -0.5],
            cost: 0.2,
        };
        let cases = [
            base,
            SunTexel { cost: 5.0, ..base },
            SunTexel {
                gs: [2.5, -0.5, 0.3],
                ..base
            },
            SunTexel {
                gx: [3.0, 3.0, 3.0],
                ..base
            },
            SunTexel {
                kappa: [1.6, 0.9, 0.4],
                gx: [-4.0, -2.0, -0.5],
                ..base
            },
            SunTexel {
                a: [0.5, 0.0, 3.0],
                l: [4.0, 1.0, 0.1],
                gs: [-1.0, 0.2, -0.1],
                cost: 0.05,
                ..base
            },
        ];
        for (n, t) in cases.iter().enumerate() {
            let (s, p) = t.solve();
            assert!(s.iter().all(|&v| v >= 0.0) && p >= 0.0);
            let got = t.value(s, p);
            // The reference: coordinate descent from zero.
            let (mut rs, mut rp) = ([0.0f64; 3], 0.0f64);
            for _ in 0..20_000 {
                rs = t.s_at(rp);
                let curv: f64 = (0..3).map(|c| t.a[c] * t.kappa[c] * t.kappa[c]).sum();
                let lin: f64 = (0..3)
                    .map(|c| t.kappa[c] * (t.a[c] * rs[c] + t.gx[c]))
                    .sum::<f64>()
                    + t.cost;
                rp = if curv > 0.0 {
                    (-lin / curv).max(0.0)
                } else {
                    0.0
                };
            }
            let reference = t.value(rs, rp);
            let mut grid = f64::INFINITY;
            for i in 0..=30 {
                for j in 0..=30 {
                    let pp = j as f64 * 0.1;
                    let mut ss = t.s_at(pp);
                    ss[0] = i as f64 * 0.1;
                    grid = grid.min(t.value(ss, pp));
                }
            }
            assert!(
                got <= reference + 1e-9 && got <= grid + 1e-9,
                "case {n}: F {got} against the reference's {reference} and the grid's {grid}"
            );
        }
    }

    /// Rows made from a known model: two states, each a sky of 0.25-0.4 (bluish) plus a sun
    /// in one texel (its own per state), two groups of known ρ, upward points whose sun is
    /// blocked for a quarter of them (the shadows) and whose sky is cut in a random azimuth
    /// wedge by a wall of known radiance (their bounce light); the horizon band of the sky
    /// seen, the zenith and the suns not. The fit, the true maps, the true ρ.
    type Synthetic = (Solved, Vec<Vec<[f64; 3]>>, [[f64; 3]; 2]);

    const WALL: [f64; 3] = [0.9, 0.7, 0.5];

    fn synthetic(outliers: bool, with_bounce: bool, seen_from: usize) -> Synthetic {
        synthetic_with(outliers, with_bounce, seen_from, None)
    }

    /// [`synthetic`], or with `texture`: each point seen in both states (the same 400 points,
    /// moved shadows and bounces per state) with its own brightness factor, 0.6-1.4 around its
    /// group's colour, and the fit told to fit one (`true`) or not (`false`).
    fn synthetic_with(
        outliers: bool,
        with_bounce: bool,
        seen_from: usize,
        texture: Option<bool>,
    ) -> Synthetic {
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
        let tau: Vec<f64> = (0..400)
            .map(|_| match texture {
                Some(_) => 0.6 + 0.8 * rng.f32() as f64,
                None => 1.0,
            })
            .collect();
        let mut rows = Vec::new();
        for k in 0..2 {
            for i in 0..400 {
                let group = i % 2;
                // With texture, the shadowed quarter differs per state (the box moved).
                let shadowed = match texture {
                    Some(_) => (i + k) % 4 < 1,
                    None => i % 4 < 1,
                };
                let wedge = (rng.f32() * WIDTH as f32) as usize;
                let cut = |t: usize| (t % WIDTH + WIDTH - wedge) % WIDTH < 4 && t / WIDTH >= 4;
                let t: Vec<(u16, f32)> = up
                    .iter()
                    .enumerate()
                    .filter(|&(t, &v)| v > 0.0 && !(shadowed && t == sun_texel[k]) && !cut(t))
                    .map(|(t, &v)| (t as u16, v as f32))
                    .collect();
                let covered: f64 = (0..ntex).filter(|&t| cut(t)).map(|t| up[t]).sum();
                let b = WALL.map(|v| v * covered);
                let mut rgb = [0.0; 3];
                for c in 0..3 {
                    rgb[c] = rho[group][c] * b[c];
                }
                for &(j, w) in &t {
                    for c in 0..3 {
                        rgb[c] += rho[group][c] * w as f64 * truth[k][j as usize][c];
                    }
                }
                if outliers && i % 10 == 3 {
                    rgb = rgb.map(|v| 2.0 * v);
                }
                rgb = rgb.map(|v| v * tau[i]);
                rows.push(Row {
                    state: k,
                    group,
                    point: if texture.is_some() { i } else { k * 400 + i },
                    rgb,
                    t,
                    b: if with_bounce { b } else { [0.0; 3] },
                });
            }
        }
        let sky: Vec<Vec<SkyTexel>> = (0..2)
            .map(|k| {
                let seen: Vec<SkyTexel> = (seen_from * WIDTH..8 * WIDTH)
                    .filter(|&t| t != sun_texel[k])
                    .map(|t| (t, truth[k][t], true))
                    .collect();
                let mut all = fill(&seen);
                all.extend(seen);
                all
            })
            .collect();
        let fit_texture = texture.unwrap_or(false);
        let options = FitOptions {
            texture: fit_texture,
            tie: false,
        };
        (solve(&rows, &sky, &[0, 1], 2, options), truth, rho)
    }

    fn lum(v: &[f64; 3]) -> f64 {
        luminance(*v)
    }

    fn argmax(e: &[[f64; 3]]) -> usize {
        (0..e.len())
            .max_by(|&a, &b| lum(&e[a]).total_cmp(&lum(&e[b])))
            .unwrap()
    }

    /// What the data determine: each sun's texel (the shadows point at it), the seen sky
    /// (kept to 3 %: the smooth part's Laplacian pulls the seen band toward the unseen rows
    /// above it; measured 1.1 / 1.3 %, with the outliers 0.8 / 0.9 %), the groups' colours
    /// relative to each other (within 5 %: measured 0.2 %, with the outliers 1.6 %) and a fit
    /// of the rows (relative L1 residual below 5 %: measured 0.19 %; with the outliers below
    /// 15 %: they alone are ~10 %, measured 9.1 %). The robust weights hold the same with a
    /// tenth of the rows' colours doubled. Not the common scale and colour of ρ here: the
    /// suns' colour is never seen and the unseen zenith trades with it (measured: ρ 1.24 /
    /// 1.17 / 0.97 × the truth per channel; [`known_bounce_light_is_not_painted`] sees more
    /// of the sky and gets it).
    fn check(outliers: bool, max_residual: f64) {
        let (got, truth, rho) = synthetic(outliers, true, 5);
        for k in 0..2 {
            let sun = argmax(&truth[k]);
            assert_eq!(argmax(&got.env[k]), sun, "state {k}: sun texel");
            let mut worst = 0.0f64;
            for t in 5 * WIDTH..8 * WIDTH {
                if t == sun {
                    continue;
                }
                for c in 0..3 {
                    worst = worst.max((got.env[k][t][c] / truth[k][t][c] - 1.0).abs());
                }
            }
            eprintln!("state {k}: seen sky off by ≤ {worst:.4}");
            assert!(
                worst < 0.03,
                "state {k}: a seen texel {worst:.4} off the truth"
            );
        }
        for c in 0..3 {
            let r = (got.rho[1][c] / got.rho[0][c]) / (rho[1][c] / rho[0][c]);
            eprintln!(
                "channel {c}: ρ_1 / ρ_0 {r:.4}× the truth's; ρ {:.4}, {:.4}× the truth",
                got.rho[0][c] / rho[0][c],
                got.rho[1][c] / rho[1][c]
            );
            assert!(
                (r - 1.0).abs() < 0.05,
                "channel {c}: ρ_1 / ρ_0 {r:.3}× the truth's"
            );
        }
        eprintln!("residual {:?}", got.residual);
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

    /// The zenith no view sees and no shadow points at is a sky, not a hole: each of its
    /// texels (rows 0-4, the sun's left out) within a factor 2 of the truth (measured 1.43×
    /// at worst, both states; the old single map with a weak smoothness term left such
    /// texels near black).
    #[test]
    fn the_unseen_sky_stays_a_sky() {
        let (got, truth, _) = synthetic(false, true, 5);
        for k in 0..2 {
            let sun = argmax(&truth[k]);
            let mut worst = 0.0f64;
            for t in 0..5 * WIDTH {
                if t == sun {
                    continue;
                }
                worst = worst.max((lum(&got.env[k][t]) / lum(&truth[k][t])).ln().abs());
            }
            eprintln!(
                "state {k}: zenith |log ratio| ≤ {worst:.3}, sun share {:.3}",
                got.sun_share[k]
            );
            assert!(
                worst < 2f64.ln(),
                "state {k}: a zenith texel {:.2}× off",
                worst.exp()
            );
        }
    }

    /// The surroundings' light is not painted: with each row's bounce given, the groups'
    /// colours come out at their own scale (within 5 %, measured 0.4 %) when the sky is seen
    /// down from row 1; with it left out the fit must explain the wall's light with paint or
    /// sky, and misses by more (measured 24 %: ρ too bright).
    #[test]
    fn known_bounce_light_is_not_painted() {
        let err = |with: bool| {
            let (got, _, rho) = synthetic(false, with, 1);
            (0..2)
                .flat_map(|g| (0..3).map(move |c| (g, c)))
                .map(|(g, c)| (got.rho[g][c] / rho[g][c] - 1.0).abs())
                .fold(0.0f64, f64::max)
        };
        let (with, without) = (err(true), err(false));
        eprintln!("ρ off by ≤ {with:.4} with the bounce, {without:.4} without");
        assert!(with < 0.05, "with the bounce: ρ {with:.3} off");
        assert!(
            without > 2.0 * with,
            "without: {without:.3} against {with:.3}"
        );
    }

    /// A textured surface (each point 0.6-1.4× its group's colour, seen in both states with the
    /// shadows moved): with τ (`--light-fit-texture`) each sun is in its texel and the texture
    /// is mostly τ's (relative L1 residual below 10 %, measured 6.6 %: the prior, one row's
    /// worth toward τ = 1 against a point's two rows, keeps about a third of each point's
    /// texture out of τ); with one colour per group the texture is left in the residual
    /// (measured 19.7 %: above twice τ's).
    #[test]
    fn a_texture_factor_takes_the_texture() {
        let (with, truth, _) = synthetic_with(false, true, 5, Some(true));
        let (without, _, _) = synthetic_with(false, true, 5, Some(false));
        eprintln!(
            "residual with τ {:?}, without {:?}",
            with.residual, without.residual
        );
        for k in 0..2 {
            assert_eq!(
                argmax(&with.env[k]),
                argmax(&truth[k]),
                "state {k}: sun texel"
            );
        }
        assert!(with.residual[1] < 0.10, "with τ: {:?}", with.residual);
        assert!(
            without.residual[1] > 2.0 * with.residual[1],
            "without τ {:?}, with {:?}",
            without.residual,
            with.residual
        );
    }

    /// Clusters are 8-connected and wrap in longitude, not in latitude.
    #[test]
    fn sun_clusters_join_diagonals_and_wrap_in_longitude() {
        let mut on = vec![false; WIDTH * HEIGHT];
        for (x, y) in [
            (0, 3),
            (WIDTH - 1, 4),
            (5, 5),
            (6, 6),
            (9, 0),
            (9, HEIGHT - 1),
        ] {
            on[y * WIDTH + x] = true;
        }
        let mut got: Vec<Vec<(usize, usize)>> = clusters(&on)
            .into_iter()
            .map(|c| c.into_iter().map(|i| (i % WIDTH, i / WIDTH)).collect())
            .collect();
        got.sort();
        assert_eq!(
            got,
            vec![
                vec![(0, 3), (WIDTH - 1, 4)],
                vec![(5, 5), (6, 6)],
                vec![(9, 0)],
                vec![(9, HEIGHT - 1)],
            ]
        );
    }

    /// The backward test on a state whose texels are each measured directly (weight `w`, 100×
    /// at the centre, a direction many rows see; the smooth part's Laplacian at [`SMOOTH`] ×
    /// w, the fit's own scale; [`SUN_KEEP`]'s unit w × a level² of 1). A sun planted on a
    /// broad bump of the sky (4× the sky's level at its centre, σ 1.5 texels), which the
    /// descent keeps (checked first: without the test it would stay), is taken out and the
    /// smooth part carries the bump (above 2.5 at the centre); a sun 200× the sky's level on
    /// one texel (what a real sun is at 11° texels) is kept.
    #[test]
    fn the_backward_test_takes_out_suns_the_sky_can_carry() {
        let ntex = WIDTH * HEIGHT;
        let w = 10.0;
        let nbrs = links();
        let centre = (HEIGHT / 4) * WIDTH + WIDTH / 2;
        let run = |spike: bool| {
            let target: Vec<f64> = (0..ntex)
                .map(|i| {
                    let (dx, dy) = (
                        (i % WIDTH) as f64 - (centre % WIDTH) as f64,
                        (i / WIDTH) as f64 - (centre / WIDTH) as f64,
                    );
                    if spike {
                        if i == centre {
                            200.0
                        } else {
                            1.0
                        }
                    } else {
                        1.0 + 3.0 * (-(dx * dx + dy * dy) / (2.0 * 1.5 * 1.5)).exp()
                    }
                })
                .collect();
            // Each texel measured with weight w, the centre 100× (a direction many rows see).
            let weight = |i: usize| if i == centre { 100.0 * w } else { w };
            let mut diag = vec![0.0; ntex * ntex];
            for i in 0..ntex {
                diag[i * ntex + i] = weight(i);
            }
            let a = vec![diag.clone(), diag.clone(), diag];
            let r: Vec<Vec<f64>> = (0..3)
                .map(|_| (0..ntex).map(|i| weight(i) * target[i]).collect())
                .collect();
            let zeros = vec![vec![0.0; ntex]; 3];
            let problem = StateProblem {
                a: &a,
                r: &r,
                lam: [SMOOTH * w; 3],
                prior_w: &zeros,
                prior_v: &zeros,
                nbrs: &nbrs,
                kappa: [1.0; 3],
            };
            // The descent's state: the sky at its level, the bump's excess (or the spike) in a
            // sun at the centre, priced as the fit prices a sun texel in its reweighted rounds.
            let cost = vec![SUN_COST * w; ntex];
            let mut sm = vec![vec![1.0; ntex]; 3];
            let mut p = vec![0.0; ntex];
            p[centre] = target[centre] - 1.0;
            let mut banned = vec![false; ntex];
            for _ in 0..SWEEPS {
                problem.sweep(&cost, &banned, &mut sm, &mut p);
            }
            let kept_by_descent = p[centre] > 0.5;
            let taken = prune(&problem, &cost, &mut banned, &mut sm, &mut p, w, 1.0);
            (kept_by_descent, taken, p[centre], sm[1][centre])
        };
        let (descent, taken, p, s) = run(false);
        assert!(
            descent,
            "the descent itself took the bump's sun out: the test shows nothing"
        );
        assert_eq!(taken, 1, "bump: p {p}, s {s}");
        assert!(
            p == 0.0 && s > 2.5,
            "bump: p {p}, s {s} (the bump's centre is 4)"
        );
        let (_, taken, p, _) = run(true);
        assert_eq!(taken, 0, "spike: p {p}");
        assert!(p > 150.0, "spike: p {p}");
    }

    /// [`tie_groups`] on two groups of one component and equal data is the closed form of the
    /// two-unknown least squares, x = a + w (b − a) / (d + 2w) with w = TIE d exp(−(ln(b/a) /
    /// TIE_SPREAD)²); groups of two components, groups 20 % or more apart and groups no data
    /// saw keep their own estimates.
    #[test]
    fn tie_groups_is_the_closed_form_and_leaves_different_paints_alone() {
        let den = [[4.0; 3]; 5];
        let (a, b) = (0.50, 0.54);
        let hat = [
            [a; 3],
            [b; 3],
            [0.2, 0.3, 0.4],
            [0.62, 0.62, 0.62],
            [0.5; 3],
        ];
        let mut den_unseen = den;
        den_unseen[4] = [0.0; 3];
        let got = tie_groups(&hat, &den_unseen, &[0, 0, 1, 1, 0]);
        let d = 4.0;
        let w = TIE * d * (-((b / a).ln() / TIE_SPREAD).powi(2)).exp();
        let x = a + w * (b - a) / (d + 2.0 * w);
        let y = b + w * (a - b) / (d + 2.0 * w);
        for c in 0..3 {
            assert!((got[0][c] - x).abs() < 1e-9, "{} against {x}", got[0][c]);
            assert!((got[1][c] - y).abs() < 1e-9, "{} against {y}", got[1][c]);
        }
        // Component 1: 0.2-0.4 against 0.62 (more than 20 % apart in every channel): untied.
        assert_eq!(got[2], hat[2]);
        assert!((got[3][0] - hat[3][0]).abs() < 1e-12);
        // Group 4 has no data: its estimate kept, and no pull on group 0 from it.
        assert_eq!(got[4], hat[4]);
    }

    /// The failure the tie is for, in the fit end to end. Two walls of one paint (ρ 0.35, one
    /// component), facing +x and −x, under a sky seen everywhere except a bright patch low on
    /// the −x side (2.0 against 0.3: the open side no camera looks out of) that only the −x
    /// wall sees. Without the tie the −x wall's ρ and the patch trade, the patch is held
    /// near the sky around it (the Laplacian) and the wall comes out too bright (measured
    /// 1.176× the +x wall's, the patch 1.38); with it, the walls' colours are within 3 % of
    /// each other (measured 1.025×) and 5 % of the truth (1.024×, 1.049×: the Laplacian still
    /// holds the patch below its truth), and the patch gets most of its light back (measured
    /// 1.66; asserted within 25 % of 2.0). A third group, another component's paint (0.5,
    /// 1.43× the walls'), facing −x too, keeps its ratio to the −x wall within 3 % either way.
    #[test]
    fn a_wall_that_alone_sees_a_patch_of_sky_keeps_its_paint_with_the_tie() {
        let ntex = WIDTH * HEIGHT;
        let dir = |t: usize| {
            uv_to_direction([
                ((t % WIDTH) as f32 + 0.5) / WIDTH as f32,
                ((t / WIDTH) as f32 + 0.5) / HEIGHT as f32,
            ])
        };
        let patch = |t: usize| {
            let d = dir(t);
            d.x < -0.6 && d.y > 0.0 && d.y < 0.4
        };
        let truth: Vec<[f64; 3]> = (0..ntex)
            .map(|t| if patch(t) { [2.0; 3] } else { [0.3; 3] })
            .collect();
        assert!((0..ntex).filter(|&t| patch(t)).count() >= 4);
        let rho = [0.35, 0.35, 0.5];
        let normals = [Vec3::X, -Vec3::X, -Vec3::X];
        let mut rows = Vec::new();
        for (g, n) in normals.iter().enumerate() {
            let t = open_row(*n);
            let lit: f64 = (0..ntex).map(|j| t[j] * truth[j][0]).sum();
            for i in 0..100 {
                rows.push(Row {
                    state: 0,
                    group: g,
                    point: g * 100 + i,
                    rgb: [rho[g] * lit; 3],
                    t: (0..ntex)
                        .filter(|&j| t[j] > 0.0)
                        .map(|j| (j as u16, t[j] as f32))
                        .collect(),
                    b: [0.0; 3],
                });
            }
        }
        let seen: Vec<SkyTexel> = (0..ntex)
            .filter(|&t| !patch(t))
            .map(|t| (t, truth[t], true))
            .collect();
        let mut sky = fill(&seen);
        sky.extend(seen);
        let run = |tie: bool| {
            let options = FitOptions {
                texture: false,
                tie,
            };
            solve(&rows, &[sky.clone()], &[0, 0, 1], 1, options)
        };
        let patch_mean = |got: &Solved| {
            let p: Vec<usize> = (0..ntex).filter(|&t| patch(t)).collect();
            p.iter().map(|&t| lum(&got.env[0][t])).sum::<f64>() / p.len() as f64
        };
        let without = run(false);
        let with = run(true);
        let ratio = |got: &Solved| lum(&got.rho[1]) / lum(&got.rho[0]);
        eprintln!(
            "without: ρ {:?}, −x / +x {:.3}, patch {:.3}; with: ρ {:?}, −x / +x {:.3}, patch {:.3}",
            without.rho,
            ratio(&without),
            patch_mean(&without),
            with.rho,
            ratio(&with),
            patch_mean(&with)
        );
        assert!(
            ratio(&without) > 1.1,
            "the failure: without the tie the −x wall {:.3}× the +x wall's",
            ratio(&without)
        );
        assert!(
            (ratio(&with) - 1.0).abs() < 0.03,
            "with the tie: {:.3}",
            ratio(&with)
        );
        for g in 0..2 {
            let r = lum(&with.rho[g]) / rho[g];
            assert!((r - 1.0).abs() < 0.05, "group {g}: {r:.3}× the truth");
        }
        assert!(
            (patch_mean(&with) / 2.0 - 1.0).abs() < 0.25,
            "the patch {:.3} for 2.0",
            patch_mean(&with)
        );
        // Another component's paint (0.5): as without the tie, near the −x wall's fit there.
        for got in [&without, &with] {
            let r = lum(&got.rho[2]) / lum(&got.rho[1]);
            assert!(
                (r / (0.5 / 0.35) - 1.0).abs() < 0.03,
                "the third group over the −x wall {r:.3}, truth {:.3}",
                0.5 / 0.35
            );
        }
    }
}
