//! Refitting a compressed wide BVH to moved primitives, keeping its tree.
//!
//! Stage 2 moves, turns, scales and fades every surfel a little at each step and traces a few
//! thousand rays through the result; rebuilding the BVH each time made the build, not the
//! tracing, the step's cost. A refit keeps the tree (which primitives share a leaf, which
//! leaves share a node) and recomputes only the boxes, bottom up: one pass over the nodes, no
//! sorting, no search. The tree's quality decays as surfels drift from where it was built, so
//! the caller rebuilds now and then ([`crate::stages`]' refine loop: every 100 steps and
//! whenever surfels are added or removed).
//!
//! `obvhs` 0.4 refits its binary BVH but not the compressed wide one we trace, whose child boxes
//! are stored as 8-bit offsets from the node's corner; this writes them exactly as its
//! `bvh2_to_cwbvh` conversion does (the same `p`, the same power-of-two exponent `e`, floor for
//! the minima and ceil for the maxima, clamped to 0..=255), so a refit to unchanged bounds gives
//! the built nodes back bit for bit (the tests below; `tests/trace.rs` checks what a refitted
//! scene composites).
//!
//! The layout read here is obvhs's (`cwbvh::node::CwBvhNode`): a node's internal children are
//! stored at `child_base_idx` onwards in slot order (the k-th set bit of `imask` is node
//! `child_base_idx + k`); a leaf slot's `child_meta` holds its first primitive's offset from
//! `primitive_base_idx` in the low five bits and its primitive count in unary in the high three;
//! an empty slot's meta is 0.

use obvhs::aabb::Aabb;
use obvhs::cwbvh::node::CwBvhNode;
use obvhs::cwbvh::CwBvh;
use obvhs_glam::Vec3A;

/// obvhs's `DENOM`: a child plane is `p + q·e` with `q` in 0..=255.
const DENOM: f32 = 1.0 / 255.0;

/// Recomputes every node's boxes from `bounds` (one per primitive, indexed as the primitives
/// given to the build: `bvh.primitive_indices` maps leaf slots to them) and the total box.
/// The tree is unchanged; so are the primitives' leaf order and everything indexed by it.
pub(crate) fn refit(bvh: &mut CwBvh, bounds: &[Aabb]) {
    if bvh.nodes.is_empty() {
        return;
    }
    let total = refit_node(&mut bvh.nodes, &bvh.primitive_indices, bounds, 0);
    bvh.total_aabb = total;
    // Exact node boxes are only kept on request and nothing here asks; drop them rather than
    // leave stale ones.
    bvh.exact_node_aabbs = None;
}

/// Refits node `n` and its subtree; returns the node's exact box (the union of its primitives').
fn refit_node(nodes: &mut [CwBvhNode], prims: &[u32], bounds: &[Aabb], n: usize) -> Aabb {
    let node = nodes[n];
    // Each occupied slot's exact box; an empty slot's meta is 0.
    let mut child_box: [Option<Aabb>; 8] = [None; 8];
    let mut aabb = Aabb::empty();
    let mut internal_seen = 0;
    for (slot, child) in child_box.iter_mut().enumerate() {
        let meta = node.child_meta[slot];
        if meta == 0 {
            continue;
        }
        let b = if node.imask & (1 << slot) != 0 {
            let child = node.child_base_idx as usize + internal_seen;
            internal_seen += 1;
            refit_node(nodes, prims, bounds, child)
        } else {
            let first = node.primitive_base_idx as usize + (meta & 0b1_1111) as usize;
            let count = (meta >> 5).count_ones() as usize;
            let mut b = Aabb::empty();
            for &p in &prims[first..first + count] {
                b = b.union(&bounds[p as usize]);
            }
            b
        };
        aabb = aabb.union(&b);
        *child = Some(b);
    }

    // The quantisation of obvhs's bvh2_to_cwbvh, operation for operation.
    let p = aabb.min;
    let e = ((aabb.max - aabb.min).max(Vec3A::splat(1e-20)) * DENOM)
        .log2()
        .ceil()
        .exp2();
    let rcp_e = 1.0 / e;
    let exponent = |c: f32| (c.to_bits() >> 23) as u8;
    let node = &mut nodes[n];
    node.p = p.into();
    node.e = [exponent(e.x), exponent(e.y), exponent(e.z)];
    for (slot, child) in child_box.iter().enumerate() {
        // An empty slot's planes are zero, as the conversion leaves them.
        let (lo, hi) = if let Some(c) = child {
            let lo = ((c.min - p) * rcp_e)
                .floor()
                .clamp(Vec3A::ZERO, Vec3A::splat(255.0));
            let hi = ((c.max - p) * rcp_e)
                .ceil()
                .clamp(Vec3A::ZERO, Vec3A::splat(255.0));
            (lo, hi)
        } else {
            (Vec3A::ZERO, Vec3A::ZERO)
        };
        node.child_min_x[slot] = lo.x as u8;
        node.child_min_y[slot] = lo.y as u8;
        node.child_min_z[slot] = lo.z as u8;
        node.child_max_x[slot] = hi.x as u8;
        node.child_max_y[slot] = hi.y as u8;
        node.child_max_z[slot] = hi.z as u8;
    }
    aabb
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::synthetic::SplitMix;
    use obvhs::cwbvh::builder::build_cwbvh;
    use obvhs::BvhBuildParams;
    use std::time::Duration;

    /// Random boxes, some of them points (a surfel too faint ever to be hit has a point box),
    /// some sharing a corner, over a few orders of magnitude of size.
    fn boxes(seed: u64, n: usize) -> Vec<Aabb> {
        let mut rng = SplitMix(seed);
        (0..n)
            .map(|i| {
                let c = Vec3A::new(
                    rng.f32() * 4.0 - 2.0,
                    rng.f32() * 3.0,
                    rng.f32() * 4.0 - 2.0,
                );
                let r = match i % 7 {
                    0 => Vec3A::ZERO,
                    1 => Vec3A::splat(1e-4),
                    _ => Vec3A::new(rng.f32(), rng.f32(), rng.f32()) * 0.05,
                };
                Aabb::new(c - r, c + r)
            })
            .collect()
    }

    /// Refitting a freshly built tree to the bounds it was built from changes nothing, bit for
    /// bit: the refit computes each node's box and quantisation exactly as obvhs's conversion
    /// does. Both builds stage 2 and stage 3 use, from one primitive to thousands.
    #[test]
    fn refitting_to_the_built_bounds_gives_the_built_nodes() {
        for params in [
            BvhBuildParams::very_fast_build(),
            BvhBuildParams::medium_build(),
        ] {
            for (seed, n) in [(1u64, 1usize), (2, 2), (3, 9), (4, 300), (5, 5000)] {
                let b = boxes(seed, n);
                let built = build_cwbvh(&b, params, &mut Duration::default());
                let mut refitted = built.clone();
                // Scramble the boxes first so the refit has to write every field.
                for node in &mut refitted.nodes {
                    node.p = glam_zero();
                    node.e = [0; 3];
                    node.child_min_x = [7; 8];
                    node.child_max_z = [1; 8];
                }
                refit(&mut refitted, &b);
                assert_eq!(refitted.nodes.len(), built.nodes.len());
                for (k, (x, y)) in refitted.nodes.iter().zip(&built.nodes).enumerate() {
                    assert!(
                        bytemuck::bytes_of(x) == bytemuck::bytes_of(y),
                        "n {n}: node {k} refitted {x:?}\nbuilt {y:?}"
                    );
                }
                assert_eq!(refitted.total_aabb, built.total_aabb, "n {n}");
                assert_eq!(refitted.primitive_indices, built.primitive_indices);
            }
        }
    }

    fn glam_zero() -> obvhs_glam::Vec3 {
        obvhs_glam::Vec3::ZERO
    }

    /// After the primitives move, every node's child planes enclose the child's true box (each
    /// primitive lies inside the planes of every node above it), and the root's box is exact.
    #[test]
    fn refitted_boxes_enclose_the_moved_primitives() {
        let b = boxes(11, 4000);
        let mut bvh = build_cwbvh(
            &b,
            BvhBuildParams::very_fast_build(),
            &mut Duration::default(),
        );
        // Move every box by up to 0.5 (a tenth of the scene) and grow some.
        let mut rng = SplitMix(12);
        let moved: Vec<Aabb> = b
            .iter()
            .map(|a| {
                let d = Vec3A::new(rng.f32(), rng.f32(), rng.f32()) - 0.5;
                let g = Vec3A::splat(rng.f32() * 0.02);
                Aabb::new(a.min + d - g, a.max + d + g)
            })
            .collect();
        refit(&mut bvh, &moved);
        let mut total = Aabb::empty();
        for a in &moved {
            total = total.union(a);
        }
        assert_eq!(bvh.total_aabb, total);
        // Walk down from the root with each node's decoded child boxes.
        let mut seen = 0;
        let mut stack = vec![(0usize, Aabb::LARGEST)];
        while let Some((n, outer)) = stack.pop() {
            let node = bvh.nodes[n];
            let e = Vec3A::new(
                f32::from_bits((node.e[0] as u32) << 23),
                f32::from_bits((node.e[1] as u32) << 23),
                f32::from_bits((node.e[2] as u32) << 23),
            );
            let p: Vec3A = node.p.into();
            let mut internal = 0;
            for slot in 0..8 {
                let meta = node.child_meta[slot];
                if meta == 0 {
                    continue;
                }
                let q_lo = Vec3A::new(
                    node.child_min_x[slot] as f32,
                    node.child_min_y[slot] as f32,
                    node.child_min_z[slot] as f32,
                );
                let q_hi = Vec3A::new(
                    node.child_max_x[slot] as f32,
                    node.child_max_y[slot] as f32,
                    node.child_max_z[slot] as f32,
                );
                // Decoded in f64-free f32 as the traversal does; a rounding of one ulp of
                // the scene's size is allowed.
                let slack = Vec3A::splat(1e-6 * 4.0);
                let child = Aabb::new(p + q_lo * e - slack, p + q_hi * e + slack);
                if node.imask & (1 << slot) != 0 {
                    stack.push((node.child_base_idx as usize + internal, child));
                    internal += 1;
                } else {
                    let first = node.primitive_base_idx as usize + (meta & 0x1f) as usize;
                    for k in 0..(meta >> 5).count_ones() as usize {
                        let a = moved[bvh.primitive_indices[first + k] as usize];
                        for box_ in [child, outer] {
                            assert!(
                                box_.min.cmple(a.min).all() && a.max.cmple(box_.max).all(),
                                "node {n} slot {slot}: {a:?} outside {box_:?}"
                            );
                        }
                        seen += 1;
                    }
                }
            }
        }
        assert_eq!(seen, moved.len(), "every primitive in exactly one leaf");
    }
}
