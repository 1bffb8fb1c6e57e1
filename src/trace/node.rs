//! Which children of a compressed wide BVH node a ray segment enters.
//!
//! `obvhs`'s own node test (`CwBvhNode::intersect_ray`) clips every child's slab interval to
//! `[1e-4, ray.tmax]`: it ignores the ray's `tmin`. A composite that needs a second batch of hits
//! resumes strictly after the last hit of the first (`t > t_resume`), yet with that test every
//! node in front of `t_resume` is entered again and each of its surfels tested again, only for
//! the hit test to reject them all. On stage 1's reconstructions a camera ray needs ~2 batches, so
//! its second traversal repeated most of the first. This test is the same slab test on the
//! node's 8-bit child planes, clipped to `[t_lo, t_hi]` instead; written here because obvhs takes
//! the node test as an expression in its `traverse!` macro but offers none with a lower bound.
//!
//! The arithmetic per child is obvhs's own (`q · (e / d) + (p − o) / d` with its `safe_inverse`
//! directions, in that order, no fused multiply-add), so for `t_lo ≤ 1e-4` the mask is the one
//! obvhs computes bit for bit; above it, a child is dropped only when its whole box lies before
//! `t_lo` (minus a rounding slack, so a hit at exactly `t_lo`, which a tie-break may still accept,
//! is never lost). Four children at a time in glam's `Vec4` (SSE on x86-64), safe code.

use glam::Vec4;
use obvhs::cwbvh::node::{extract_byte64, CwBvhNode};
use obvhs::ray::Ray;

/// What the node test needs of a ray, computed once per traversal.
#[derive(Clone, Copy, Debug)]
pub(super) struct NodeRay {
    origin: [f32; 3],
    /// obvhs's `safe_inverse` of the direction: finite for axis-parallel rays.
    inv_dir: [f32; 3],
    /// Whether the direction is negative along each axis: the child's max plane is then met first.
    negative: [bool; 3],
}

impl NodeRay {
    pub fn new(ray: &Ray) -> Self {
        NodeRay {
            origin: ray.origin.to_array(),
            inv_dir: ray.inv_direction.to_array(),
            negative: [
                ray.direction.x < 0.0,
                ray.direction.y < 0.0,
                ray.direction.z < 0.0,
            ],
        }
    }
}

/// The lower clip for a traversal that only takes hits after `t`: `t` less a relative slack of 1e-6, far
/// above the rounding of the slab arithmetic (a few ulps) and far below any gap between hits
/// that matters.
#[inline(always)]
pub(super) fn lower_clip(t: f32) -> f32 {
    t - 1e-6 * t.abs()
}

/// Traverses `$bvh` (an obvhs `CwBvh`) along the local ray `$o + t $d` for `t_min < t`, running
/// `$leaves` with `$base` bound to the node's first primitive slot and `$bits` to the mask of its
/// primitives (leaf slots `$base + bit`) whose leaf box the ray enters: obvhs's own traversal loop,
/// its `traverse!` macro, with [`node_hits`] as the node test, clipped below at
/// [`lower_clip`]`($t_min)` and above at `$t_far`, an expression evaluated at every node so that a
/// far bound that shrinks while the traversal runs (a filling batch) prunes at once. The leaves
/// are handled in the node test itself, which returns only the internal children: that is where
/// obvhs's loop would take them one by one next, highest bit first, before any other node, so
/// the order is the same, and a node's leaves can be tested together ([`LeafGroups`]). `$tally` (a
/// `super::Tally`) counts the nodes. A macro, not a function taking a closure: `$leaves` may
/// `return` from the enclosing function (a blocked visibility ray) and borrows what `$t_far`
/// reads. One copy for the composite's and the visibility ray's traversals.
macro_rules! traverse_clipped {
    ($bvh:expr, $o:expr, $d:expr, $t_min:expr, $t_far:expr, $tally:expr, |$base:ident, $bits:ident| $leaves:block) => {{
        let ray = obvhs::ray::Ray::new($o.to_array().into(), $d.to_array().into(), $t_min, $t_far);
        let node_ray = $crate::trace::node::NodeRay::new(&ray);
        let t_lo = $crate::trace::node::lower_clip($t_min);
        let mut state = $bvh.new_traversal(ray.direction);
        let mut node;
        obvhs::traverse!(
            $bvh,
            node,
            state,
            {
                $tally.node();
                let mask =
                    $crate::trace::node::node_hits(node, &node_ray, state.oct_inv4, t_lo, $t_far);
                let $bits = mask & 0x00ff_ffff;
                if $bits != 0 {
                    let $base = node.primitive_base_idx as usize;
                    $leaves
                }
                mask & 0xff00_0000
            },
            {}
        );
    }};
}
pub(super) use traverse_clipped;

/// A node's primitive mask in groups of up to four slots, highest bit first (the order obvhs's
/// loop takes them in): `(slots, live)`, the unused lanes repeating the first slot with their
/// `live` bit clear.
pub(super) struct LeafGroups {
    base: usize,
    bits: u32,
}

impl LeafGroups {
    #[inline(always)]
    pub fn new(base: usize, bits: u32) -> Self {
        LeafGroups { base, bits }
    }
}

impl Iterator for LeafGroups {
    type Item = ([usize; 4], u32);

    #[inline(always)]
    fn next(&mut self) -> Option<Self::Item> {
        if self.bits == 0 {
            return None;
        }
        let mut slots = [0usize; 4];
        let mut live = 0u32;
        for (lane, slot) in slots.iter_mut().enumerate() {
            if self.bits == 0 {
                break;
            }
            let bit = 31 - self.bits.leading_zeros();
            self.bits &= !(1u32 << bit);
            *slot = self.base + bit as usize;
            live |= 1 << lane;
        }
        let first = slots[0];
        for (lane, slot) in slots.iter_mut().enumerate() {
            if live & (1 << lane) == 0 {
                *slot = first;
            }
        }
        Some((slots, live))
    }
}

/// The quantised planes of children `4i..4i+4` along one axis.
#[inline(always)]
fn quads(q: &[u8; 8], i: usize) -> Vec4 {
    Vec4::new(
        q[4 * i] as f32,
        q[4 * i + 1] as f32,
        q[4 * i + 2] as f32,
        q[4 * i + 3] as f32,
    )
}

/// The traversal's hit mask for `node` (child bits in obvhs's layout: internal children in the
/// high byte by traversal priority, leaf primitives in the low 24 bits) for the children whose
/// box the ray meets for some `t` in `[t_lo, t_hi]`.
#[inline(always)]
pub(super) fn node_hits(
    node: &CwBvhNode,
    ray: &NodeRay,
    oct_inv4: u32,
    t_lo: f32,
    t_hi: f32,
) -> u32 {
    let ext = node.compute_extent();
    let ext = [ext.x, ext.y, ext.z];
    let p = node.p.to_array();
    // Per axis: t = q · scale + offset.
    let mut scale = [0.0f32; 3];
    let mut offset = [0.0f32; 3];
    for k in 0..3 {
        scale[k] = ext[k] * ray.inv_dir[k];
        offset[k] = (p[k] - ray.origin[k]) * ray.inv_dir[k];
    }
    let planes = [
        (&node.child_min_x, &node.child_max_x),
        (&node.child_min_y, &node.child_max_y),
        (&node.child_min_z, &node.child_max_z),
    ];
    let (child_bits8, bit_index8) = node.get_child_and_index_bits(oct_inv4);
    let mut mask = 0u32;
    for i in 0..2 {
        let mut near = Vec4::splat(t_lo);
        let mut far = Vec4::splat(t_hi);
        for k in 0..3 {
            let (lo, hi) = (quads(planes[k].0, i), quads(planes[k].1, i));
            let (first, last) = if ray.negative[k] { (hi, lo) } else { (lo, hi) };
            let (s, o) = (Vec4::splat(scale[k]), Vec4::splat(offset[k]));
            near = near.max(first * s + o);
            far = far.min(last * s + o);
        }
        let entered = near.cmple(far).bitmask();
        for j in 0..4 {
            if entered & (1 << j) != 0 {
                let child = 4 * i + j;
                mask |= extract_byte64(child_bits8, child) << extract_byte64(bit_index8, child);
            }
        }
    }
    mask
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::synthetic::SplitMix;
    use obvhs::aabb::Aabb;
    use obvhs::cwbvh::builder::build_cwbvh;
    use obvhs::BvhBuildParams;
    use std::time::Duration;

    fn bvh(rng: &mut SplitMix) -> obvhs::cwbvh::CwBvh {
        let boxes: Vec<Aabb> = (0..3000)
            .map(|_| {
                let c = [
                    rng.range(-2.0, 2.0),
                    rng.range(-2.0, 2.0),
                    rng.range(-2.0, 2.0),
                ];
                let h = [
                    rng.range(0.0, 0.2),
                    rng.range(0.0, 0.2),
                    rng.range(0.0, 0.01),
                ];
                Aabb::new(
                    [c[0] - h[0], c[1] - h[1], c[2] - h[2]].into(),
                    [c[0] + h[0], c[1] + h[1], c[2] + h[2]].into(),
                )
            })
            .collect();
        build_cwbvh(
            &boxes,
            BvhBuildParams::medium_build(),
            &mut Duration::default(),
        )
    }

    fn ray(rng: &mut SplitMix, axis_parallel: bool) -> Ray {
        let o = [
            rng.range(-3.0, 3.0),
            rng.range(-3.0, 3.0),
            rng.range(-3.0, 3.0),
        ];
        let mut d = [
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
            rng.range(-1.0, 1.0),
        ];
        if axis_parallel {
            d[(rng.range(0.0, 2.99)) as usize] = 0.0;
        }
        Ray::new(o.into(), d.into(), 0.0, rng.range(0.5, 8.0))
    }

    /// The groups take every bit once, highest first (obvhs's `firstbithigh` order, which a
    /// visibility ray's product follows), four to a group, unused lanes off.
    #[test]
    fn leaf_groups_take_the_bits_highest_first() {
        for bits in [0u32, 1, 0b1011, 0x00ff_ffff, 0x0080_0001, 0x0012_3456] {
            let mut seen = Vec::new();
            for (slots, live) in LeafGroups::new(100, bits) {
                assert!(
                    live != 0 && live & !0xf == 0 && (live + 1) & live == 0,
                    "{live:b}"
                );
                for (lane, &slot) in slots.iter().enumerate() {
                    if live & (1 << lane) != 0 {
                        seen.push(slot - 100);
                    } else {
                        assert_eq!(slot, slots[0]);
                    }
                }
            }
            let want: Vec<usize> = (0..32).rev().filter(|b| bits & (1 << b) != 0).collect();
            assert_eq!(seen, want, "{bits:#x}");
        }
    }

    /// With no lower clip beyond obvhs's own, every node's mask is obvhs's, bit for bit, axis-
    /// parallel rays included.
    #[test]
    fn matches_obvhs_without_a_lower_clip() {
        let mut rng = SplitMix(11);
        let bvh = bvh(&mut rng);
        let mut nonzero = 0;
        for r in 0..200 {
            let ray = ray(&mut rng, r % 4 == 0);
            let nr = NodeRay::new(&ray);
            let oct = bvh.new_traversal(ray.direction).oct_inv4;
            for node in &bvh.nodes {
                let ours = node_hits(node, &nr, oct, 1e-4, ray.tmax);
                assert_eq!(ours, node.intersect_ray(&ray, oct));
                nonzero += (ours != 0) as usize;
            }
        }
        assert!(nonzero > 300, "the rays should enter nodes: {nonzero}");
    }

    /// With a lower clip, a child is kept exactly when its (dequantised, f64) box meets the ray
    /// for some t in [t_lo, t_hi], up to the rounding at the box's faces.
    #[test]
    fn a_lower_clip_drops_only_children_wholly_before_it() {
        let mut rng = SplitMix(12);
        let bvh = bvh(&mut rng);
        let (mut dropped, mut kept) = (0, 0);
        for r in 0..200 {
            let ray = ray(&mut rng, r % 4 == 0);
            let nr = NodeRay::new(&ray);
            let oct = bvh.new_traversal(ray.direction).oct_inv4;
            let t_lo = rng.range(0.0, 4.0);
            for node in &bvh.nodes {
                let all = node_hits(node, &nr, oct, f32::NEG_INFINITY, ray.tmax);
                let clipped = node_hits(node, &nr, oct, t_lo, ray.tmax);
                assert_eq!(clipped & !all, 0, "a clip only removes children");
                let ext = node.compute_extent();
                let (child_bits8, bit_index8) = node.get_child_and_index_bits(oct);
                for child in 0..8 {
                    let bits =
                        extract_byte64(child_bits8, child) << extract_byte64(bit_index8, child);
                    if bits == 0 || all & bits == 0 {
                        continue;
                    }
                    // The child's box and the ray's exit from it, in f64.
                    let q = |v: &[u8; 8]| v[child] as f64;
                    let lo = [
                        node.p.x as f64 + q(&node.child_min_x) * ext.x as f64,
                        node.p.y as f64 + q(&node.child_min_y) * ext.y as f64,
                        node.p.z as f64 + q(&node.child_min_z) * ext.z as f64,
                    ];
                    let hi = [
                        node.p.x as f64 + q(&node.child_max_x) * ext.x as f64,
                        node.p.y as f64 + q(&node.child_max_y) * ext.y as f64,
                        node.p.z as f64 + q(&node.child_max_z) * ext.z as f64,
                    ];
                    let mut exit = ray.tmax as f64;
                    for k in 0..3 {
                        let inv = ray.inv_direction[k] as f64;
                        let (a, b) = (
                            (lo[k] - ray.origin[k] as f64) * inv,
                            (hi[k] - ray.origin[k] as f64) * inv,
                        );
                        exit = exit.min(a.max(b));
                    }
                    let slack = 1e-5 * (1.0 + exit.abs());
                    if clipped & bits == 0 {
                        dropped += 1;
                        assert!(
                            exit < t_lo as f64 + slack,
                            "dropped a child left at {exit} > {t_lo}"
                        );
                    } else {
                        kept += 1;
                        assert!(
                            exit > t_lo as f64 - slack,
                            "kept a child left at {exit} < {t_lo}"
                        );
                    }
                }
            }
        }
        assert!(
            dropped > 100 && kept > 100,
            "both cases: {dropped} dropped, {kept} kept"
        );
    }
}
