//! How well stage 1's background/object split covers each object: the share of an object's
//! true surface whose nearest surfel carries the object's label.
//!
//! The truth is the capture itself: every pixel of a view whose mask names the object (and
//! its four neighbours': edge pixels mix the object's depth with the background's), lifted
//! to the world by its depth, is a point of the object's surface, with the capture's normal.
//! Its nearest surfel (of every component, as placed in that view's state) either belongs to
//! the object or not. "Nearest" weighs orientation as well as position, in a 6-D distance
//! |Δp|² + λ²|Δn|² (λ = [`NORMAL_WEIGHT`], a surfel's normal taken with either sign): at a seam
//! where an object stands on a floor, the floor's surfels lie as close to the object's lowest
//! centimetre as the object's own surfels do, and which is nearer by position alone depends on
//! how densely each side is sampled rather than on which surface the point is on. A share
//! below 1 means some of the object's surface is explained by surfels of another component
//! (usually the background grown into it, or the object's own surfels pruned), which then stay
//! behind when the object moves.

use crate::io::dataset::Observation;
use crate::scene::surfels::quat_axes;
use crate::scene::Component;
use crate::stages::reconstruct::register::KdTree;

/// λ of the 6-D distance, metres: opposite-facing or perpendicular normals (|Δn|² = 2 at 90°)
/// cost as much as ~2.8 cm of distance, several surfel spacings of a stage-1 reconstruction
/// (1 cm voxels), while surfels of one surface (|Δn| small) compete by position alone.
pub const NORMAL_WEIGHT: f32 = 0.02;

/// For each `(name, id)` of `objects`, the share of the masked surface points of `views` (all
/// of one state, whose surfels are `components`, placed) whose nearest surfel (position and
/// normal, see the module docs) belongs to the component with that id; 0 where no view sees
/// the object.
pub fn label_shares(
    components: &[Component],
    views: &[&Observation],
    objects: &[(String, u32)],
) -> Vec<(String, f64)> {
    // Each surfel twice, once per sign of its normal (a disc has no front).
    let mut keys: Vec<[f32; 6]> = Vec::new();
    let mut owner: Vec<u32> = Vec::new();
    for c in components {
        for (p, q) in c.surfels.position.iter().zip(&c.surfels.rotation) {
            let n = quat_axes(*q)[2];
            for s in [1.0, -1.0] {
                let l = s * NORMAL_WEIGHT;
                keys.push([p[0], p[1], p[2], l * n[0], l * n[1], l * n[2]]);
                owner.push(c.id);
            }
        }
    }
    let tree = KdTree::new(&keys);
    objects
        .iter()
        .map(|(name, id)| {
            let (mut good, mut all) = (0usize, 0usize);
            for o in views {
                let (w, h) = (o.camera.w as usize, o.camera.h as usize);
                // Interior pixels only: at a mask's edge the depth and normal of a pixel mix
                // the object with what is behind it (both are filtered like the colour).
                let inside = |x: usize, y: usize| o.mask[y * w + x] as u32 == *id;
                let interior = |i: usize| {
                    let (x, y) = (i % w, i / w);
                    x > 0
                        && y > 0
                        && x + 1 < w
                        && y + 1 < h
                        && [(x - 1, y), (x + 1, y), (x, y - 1), (x, y + 1), (x, y)]
                            .iter()
                            .all(|&(x, y)| inside(x, y))
                };
                for (i, &z) in o.depth.iter().enumerate() {
                    if z > 0.0 && interior(i) {
                        let p =
                            o.camera
                                .pixel_to_world((i % w) as f32 + 0.5, (i / w) as f32 + 0.5, z);
                        let n = o.normal[i].map(|x| x * NORMAL_WEIGHT);
                        let key = [p[0], p[1], p[2], n[0], n[1], n[2]];
                        if let Some((n, _)) = tree.nearest(&key) {
                            all += 1;
                            good += (owner[n] == *id) as usize;
                        }
                    }
                }
            }
            (name.clone(), good as f64 / all.max(1) as f64)
        })
        .collect()
}
