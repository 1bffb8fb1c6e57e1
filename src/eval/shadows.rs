//! Where the training states' shadows fell, seen from the test views (evaluation only): the
//! measure that tells a ghost shadow (a training capture's shadow painted into the base colour,
//! issue 44) from the base colour's noise. The ghost share of [`albedo_uniformity`] counts both;
//! here it is taken apart by what each pixel's surface point was in the training states.
//!
//! A point's *lit share* under training state k is the part of that state's true lighting that
//! reaches it,
//!
//!   s_k(x) = ∫ Y(L_k(ω)) max(0, n·ω) T_k(x, ω) dω / ∫ Y(L_k(ω)) max(0, n·ω) dω,
//!
//! with L_k the environment that lit state k (the dataset's file), Y luminance, and T_k the
//! transmittance from x toward ω through the relightable scene placed as state k (the geometry
//! and object poses stage 3 fitted under). Both integrals are estimated from the same
//! [`SAMPLES`] directions drawn from L_k ([`EnvMap::sample`]): an unoccluded point scores
//! exactly 1, and a point under a sun that carries most of the light scores about the sun's
//! share when the sun is blocked. The point and its normal are the test view's first hit at the
//! pixel centre; pixels on movable objects are left out (an object moves with its shadow: it
//! has no fixed "shadow of another state").
//!
//! A pixel is *in state k's shadow* when s_k < [`SHADOWED`] and lit (s_j > [`LIT`]) in some
//! other training state j: a shadow that moved, which a shared base colour cannot explain and
//! the environment and the occluders must. A pixel lit in every state (all s_k > [`LIT`]) is
//! the baseline: how far the base colour strays where no shadow ever fell.
//!
//! [`albedo_uniformity`]: crate::eval::lighting::albedo_uniformity

use crate::eval::lighting::{albedo_uniformity_over, UniformityFigures, LUMINANCE};
use crate::scene::synthetic::SplitMix;
use crate::shade::EnvMap;
use crate::trace::Placed;
use glam::Vec3;
use serde::{Deserialize, Serialize};

/// Directions per point and state: the lit share's standard error is at most 1/(2√64) ≈ 0.06,
/// well inside the gap between [`SHADOWED`] and [`LIT`].
pub const SAMPLES: usize = 64;
/// Below this lit share a point is in shadow.
pub const SHADOWED: f32 = 0.5;
/// Above this lit share a point is lit.
pub const LIT: f32 = 0.8;

/// The lit share s(x) of one point under one state (see the module), from [`SAMPLES`]
/// directions drawn from `env` with a generator seeded by `seed`; `eps` the self-hit offset
/// along the normal. None when no drawn direction is above the surface (no light to share).
pub fn lit_share(
    placed: &Placed,
    env: &EnvMap,
    x: Vec3,
    n: Vec3,
    eps: f32,
    seed: u64,
) -> Option<f32> {
    let mut rng = SplitMix(seed);
    let origin = (x + eps * n).to_array();
    let (mut all, mut lit) = (0.0f64, 0.0f64);
    for _ in 0..SAMPLES {
        let s = env.sample([rng.f32(), rng.f32()]);
        let c = n.dot(s.dir);
        if c <= 0.0 || s.pdf <= 0.0 {
            continue;
        }
        let y: f64 = (0..3).map(|k| LUMINANCE[k] * s.radiance[k] as f64).sum();
        let w = y * c as f64 / s.pdf as f64;
        all += w;
        lit += w * placed.transmittance(origin, s.dir.to_array(), 0.0, f32::INFINITY) as f64;
    }
    (all > 0.0).then(|| (lit / all) as f32)
}

/// What a test-view pixel was in the training states: its lit share under each, in the
/// dataset's order of training states (None where it has none).
pub type Shares = Vec<Option<f32>>;

/// Ghost shadows taken apart (see the module), in `eval.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShadowGhosts {
    /// Background pixels of uniform surfaces lit in every training state.
    pub lit: Option<UniformityFigures>,
    /// Per training state, the background pixels of uniform surfaces in its shadow and lit in
    /// another state.
    pub states: Vec<StateShadow>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StateShadow {
    pub state: String,
    pub figures: Option<UniformityFigures>,
}

/// The ghost figures of (predicted, true) base colour `pairs` by their pixels' lit shares
/// (`shares[i]` for `pairs[i]`; None for a pixel left out: not on the background), with each
/// surface's median from every pair ([`albedo_uniformity_over`]). `states` names the training
/// states in the order of the shares.
pub fn shadow_ghosts(
    pairs: &[([f32; 3], [f32; 3])],
    shares: &[Option<Shares>],
    states: &[String],
) -> ShadowGhosts {
    assert_eq!(pairs.len(), shares.len(), "one share list a pair");
    let lit_everywhere = |i: usize| {
        shares[i]
            .as_ref()
            .is_some_and(|s| s.iter().all(|v| v.is_some_and(|v| v > LIT)))
    };
    let in_shadow_of = |k: usize, i: usize| {
        shares[i].as_ref().is_some_and(|s| {
            s[k].is_some_and(|v| v < SHADOWED)
                && s.iter()
                    .enumerate()
                    .any(|(j, v)| j != k && v.is_some_and(|v| v > LIT))
        })
    };
    ShadowGhosts {
        lit: albedo_uniformity_over(pairs, lit_everywhere),
        states: states
            .iter()
            .enumerate()
            .map(|(k, name)| StateShadow {
                state: name.clone(),
                figures: albedo_uniformity_over(pairs, |i| in_shadow_of(k, i)),
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ghosts_split_by_where_the_shadows_fell() {
        // One uniform surface of true albedo 0.5: 300 pixels lit in both states (base colour
        // 0.5), 100 in state a's shadow and lit in state b (painted: 0.3), 50 in shadow in
        // both (a static shadow, painted too: in neither figure) and 50 on an object (None).
        let mut pairs = Vec::new();
        let mut shares: Vec<Option<Shares>> = Vec::new();
        let mut add = |n: usize, base: f32, s: Option<Shares>| {
            for _ in 0..n {
                pairs.push(([base; 3], [0.5; 3]));
                shares.push(s.clone());
            }
        };
        add(300, 0.5, Some(vec![Some(0.95), Some(0.9)]));
        add(100, 0.3, Some(vec![Some(0.2), Some(0.95)]));
        add(50, 0.3, Some(vec![Some(0.2), Some(0.3)]));
        add(50, 0.5, None);
        let g = shadow_ghosts(&pairs, &shares, &["a".into(), "b".into()]);
        // The surface's median ratio, over all 500 pixels, is 1: the lit pixels are on it and
        // state a's shadow is 40 % below it.
        let lit = g.lit.unwrap();
        assert_eq!((lit.surfaces, lit.pixels, lit.ghost_share), (1, 300, 0.0));
        let a = g.states[0].figures.as_ref().unwrap();
        assert_eq!((a.pixels, a.ghost_share), (100, 1.0));
        assert!((a.spread - 0.4).abs() < 1e-6, "{}", a.spread);
        // Nothing is in b's shadow and lit in a.
        assert!(g.states[1].figures.is_none());
        assert_eq!(g.states[1].state, "b");
    }
}
