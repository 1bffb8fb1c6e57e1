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
//!
//! [`label_purity`] asks the other way round: of an object's surfels, the share whose nearest
//! observed surface point (any label's, the background's included) is the object's. Below 1,
//! the object carries surfels of something else (a patch of the floor it stands on), which
//! then move with it and leave a hole where they were.

use crate::io::dataset::Observation;
use crate::scene::surfels::quat_axes;
use crate::scene::Component;
use crate::spatial::KdTree;

/// λ of the 6-D distance, metres: opposite-facing or perpendicular normals (|Δn|² = 2 at 90°)
/// cost as much as ~2.8 cm of distance, several surfel spacings of a stage-1 reconstruction
/// (1 cm voxels), while surfels of one surface (|Δn| small) compete by position alone.
pub const NORMAL_WEIGHT: f32 = 0.02;

/// Pixels whose mask id is the same as their four neighbours': at a mask's edge the depth and
/// normal of a pixel mix the object with what is behind it (both are filtered like the
/// colour). Each with its world point, capture normal and id.
fn interior_points(o: &Observation) -> impl Iterator<Item = ([f32; 3], [f32; 3], u32)> + '_ {
    let (w, h) = (o.camera.w as usize, o.camera.h as usize);
    o.depth.iter().enumerate().filter_map(move |(i, &z)| {
        let (x, y) = (i % w, i / w);
        let id = o.mask[i];
        let interior = z > 0.0
            && x > 0
            && y > 0
            && x + 1 < w
            && y + 1 < h
            && [(x - 1, y), (x + 1, y), (x, y - 1), (x, y + 1)]
                .iter()
                .all(|&(x, y)| o.mask[y * w + x] == id);
        interior.then(|| {
            let p = o.camera.pixel_to_world(x as f32 + 0.5, y as f32 + 0.5, z);
            (p, o.normal[i], id as u32)
        })
    })
}

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
                for (p, n, _) in interior_points(o).filter(|q| q.2 == *id) {
                    let n = n.map(|x| x * NORMAL_WEIGHT);
                    if let Some((k, _)) = tree.nearest(&[p[0], p[1], p[2], n[0], n[1], n[2]]) {
                        all += 1;
                        good += (owner[k] == *id) as usize;
                    }
                }
            }
            (name.clone(), good as f64 / all.max(1) as f64)
        })
        .collect()
}

/// How far (in the 6-D distance of the module docs, metres) a surfel may lie from every
/// observed surface point and still be judged: an object's underside or the back of a shelf
/// that no view saw has no observed point near it, and is left out.
pub const OBSERVED: f32 = 0.02;

/// For each `(name, id)` of `objects`, the share of the object's surfels (of `components`,
/// placed in the state of `views`) whose nearest observed surface point (interior mask pixels
/// of every label, lifted by their depth; nearest in position and normal, see the module docs)
/// carries the object's id; surfels farther than [`OBSERVED`] from every observed point are
/// left out. 0 where the object has no judged surfel.
pub fn label_purity(
    components: &[Component],
    views: &[&Observation],
    objects: &[(String, u32)],
) -> Vec<(String, f64)> {
    let mut keys: Vec<[f32; 6]> = Vec::new();
    let mut owner: Vec<u32> = Vec::new();
    for o in views {
        for (p, n, id) in interior_points(o) {
            let l = n.map(|x| x * NORMAL_WEIGHT);
            keys.push([p[0], p[1], p[2], l[0], l[1], l[2]]);
            owner.push(id);
        }
    }
    let tree = KdTree::new(&keys);
    objects
        .iter()
        .map(|(name, id)| {
            let (mut good, mut all) = (0usize, 0usize);
            for c in components.iter().filter(|c| c.id == *id) {
                for (p, q) in c.surfels.position.iter().zip(&c.surfels.rotation) {
                    let n = quat_axes(*q)[2];
                    // A disc has no front: the nearer of its two orientations.
                    let nearest = [1.0, -1.0]
                        .iter()
                        .filter_map(|s| {
                            let l = s * NORMAL_WEIGHT;
                            let key = [p[0], p[1], p[2], l * n[0], l * n[1], l * n[2]];
                            tree.nearest_within(&key, OBSERVED * OBSERVED)
                        })
                        .min_by(|a, b| a.1.total_cmp(&b.1));
                    if let Some((k, _)) = nearest {
                        all += 1;
                        good += (owner[k] == *id) as usize;
                    }
                }
            }
            (
                name.clone(),
                if all == 0 {
                    0.0
                } else {
                    good as f64 / all as f64
                },
            )
        })
        .collect()
}
