//! The bottom level: one BVH per component, built once in the component's own frame.

use super::surfel::{surfel_bounds, HitSurfel};
use crate::scene::Material;
use crate::scene::{Scene, Surfels};
use obvhs::aabb::Aabb;
use obvhs::cwbvh::{builder::build_cwbvh, CwBvh};
use obvhs::BvhBuildParams;
use rayon::prelude::*;
use std::time::Duration;

/// One component ready for tracing: its BVH and, in the BVH's leaf order, what the hit test
/// and the compositing read.
pub(crate) struct Blas {
    /// `None` for a component without surfels.
    pub bvh: Option<CwBvh>,
    pub hit: Vec<HitSurfel>,
    /// The material a hit contributes, in leaf order next to the hit data.
    pub material: Vec<Material>,
    /// The surfel's index in the component, for the tie-break and for callers.
    pub index: Vec<u32>,
    /// Bounds of all supports, component frame (meaningless when empty).
    pub lo: [f32; 3],
    pub hi: [f32; 3],
}

impl Blas {
    fn build(s: &Surfels, params: BvhBuildParams) -> Blas {
        let n = s.len();
        assert!(
            n < u32::MAX as usize,
            "a component holds at most 2³² − 1 surfels"
        );
        if n == 0 {
            return Blas {
                bvh: None,
                hit: Vec::new(),
                material: Vec::new(),
                index: Vec::new(),
                lo: [0.0; 3],
                hi: [0.0; 3],
            };
        }
        let bounds = bounds_of(s);
        let (lo, hi) = extent(&bounds);
        let bvh = build_cwbvh(&bounds, params, &mut Duration::default());
        let index = bvh.primitive_indices.clone();
        Blas {
            bvh: Some(bvh),
            hit: hit_data(s, &index),
            material: index.iter().map(|&i| material_of(s, i)).collect(),
            index,
            lo,
            hi,
        }
    }

    /// The same surfels (same count and order) moved: new boxes in the old tree
    /// ([`super::refit`]), new hit data and materials in the old leaf order.
    fn refit(&mut self, s: &Surfels) {
        assert_eq!(self.index.len(), s.len(), "refit: surfel count changed");
        let Some(bvh) = self.bvh.as_mut() else {
            return;
        };
        let bounds = bounds_of(s);
        (self.lo, self.hi) = extent(&bounds);
        super::refit::refit(bvh, &bounds);
        self.hit = hit_data(s, &self.index);
        for (m, &i) in self.material.iter_mut().zip(&self.index) {
            *m = material_of(s, i);
        }
    }
}

/// Each surfel's box ([`surfel_bounds`]), in the component's order.
fn bounds_of(s: &Surfels) -> Vec<Aabb> {
    (0..s.len())
        .into_par_iter()
        .map(|i| {
            let (lo, hi) = surfel_bounds(s.position[i], s.rotation[i], s.scale[i], s.opacity[i]);
            Aabb::new(lo.into(), hi.into())
        })
        .collect()
}

/// The box around all of `bounds`.
fn extent(bounds: &[Aabb]) -> ([f32; 3], [f32; 3]) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for b in bounds {
        for k in 0..3 {
            lo[k] = lo[k].min(b.min[k]);
            hi[k] = hi[k].max(b.max[k]);
        }
    }
    (lo, hi)
}

/// What the hit test reads, in leaf order (`index`: the surfel at each leaf slot).
fn hit_data(s: &Surfels, index: &[u32]) -> Vec<HitSurfel> {
    index
        .par_iter()
        .map(|&i| {
            let k = i as usize;
            HitSurfel::new(s.position[k], s.rotation[k], s.scale[k], s.opacity[k], i)
        })
        .collect()
}

fn material_of(s: &Surfels, i: u32) -> Material {
    let i = i as usize;
    Material {
        base_color: s.base_color[i],
        metallic: s.metallic[i],
        roughness: s.roughness[i],
    }
}

/// Surfel components ready to be traced in any placement: build once per scene geometry, then
/// [`TraceScene::place`] for each state or layout.
pub struct TraceScene {
    pub(crate) blas: Vec<Blas>,
}

impl TraceScene {
    /// Builds a BVH for every component of the scene.
    pub fn new(scene: &Scene) -> TraceScene {
        let parts: Vec<&Surfels> = scene.components.iter().map(|c| &c.surfels).collect();
        TraceScene::from_components(&parts)
    }

    /// Builds a BVH for each group of surfels (component order = instance order in `place`).
    pub fn from_components(components: &[&Surfels]) -> TraceScene {
        // obvhs's medium quality: build time stays within a few times a fast build, and
        // traversal is what a path tracer pays for, millions of times per build.
        TraceScene::with_params(components, BvhBuildParams::medium_build())
    }

    /// [`TraceScene::from_components`] with BVHs built faster and traversed slower (obvhs's
    /// very fast build: the shortest PLOC search, little reinsertion): for a scene rebuilt at
    /// every optimisation step and traced by a few thousand rays, as in stage 2's loop. There,
    /// on the kitchen preset (0.70 M surfels, 4,096 rays a step), 60 steps took 23-25 s against
    /// 31-32 s with the medium build (alternating, idle machine), to the same held-out figures
    /// (`lightfuse refine data/kitchen W --iterations 60`). The hits a ray composites are the
    /// same whatever the tree: only the order they are found in changes, which moves the
    /// batch's running transmittance by rounding alone (`tests/trace.rs`).
    pub fn from_components_for_few_rays(components: &[&Surfels]) -> TraceScene {
        TraceScene::with_params(components, BvhBuildParams::very_fast_build())
    }

    fn with_params(components: &[&Surfels], params: BvhBuildParams) -> TraceScene {
        TraceScene {
            blas: components.iter().map(|s| Blas::build(s, params)).collect(),
        }
    }

    /// Replaces every surfel's material by `components`' (the surfels this scene was built from,
    /// same order and counts, geometry unchanged), keeping the BVHs: what inverse rendering
    /// changes each iteration. Panics if the counts differ.
    pub fn set_materials(&mut self, components: &[&Surfels]) {
        assert_eq!(
            components.len(),
            self.blas.len(),
            "set_materials: one Surfels per component"
        );
        for (b, s) in self.blas.iter_mut().zip(components) {
            assert_eq!(
                b.index.len(),
                s.len(),
                "set_materials: surfel count changed"
            );
            for (m, &i) in b.material.iter_mut().zip(&b.index) {
                *m = material_of(s, i);
            }
        }
    }

    /// Moves the surfels of the scene to `components`' (the surfels it was built from, same
    /// order and counts, any of position, rotation, scale, opacity or material changed) by
    /// refitting each BVH's boxes rather than building it again: a fraction of a build's time,
    /// for a tree that is slower to traverse the further the surfels have drifted since it was
    /// built. What a ray composites is the same either way up to the order in which its hits are
    /// found, i.e. rounding (`tests/trace.rs`). Panics if the counts differ.
    pub fn refit(&mut self, components: &[&Surfels]) {
        assert_eq!(
            components.len(),
            self.blas.len(),
            "refit: one Surfels per component"
        );
        for (b, s) in self.blas.iter_mut().zip(components) {
            b.refit(s);
        }
    }

    pub fn component_count(&self) -> usize {
        self.blas.len()
    }
}
