//! Object surfels beneath the surface the object stands on. A glossy floor or table shows a
//! mirror image of what stands on it; training explains that image with geometry grown under
//! the surface (initialisation puts every surfel on observed depth, densification moves them
//! there), and since the image lies in or beside the object's mask those surfels carry the
//! object's label. They then move with the object, leave its purity low (livingroom's metal
//! ring: 866 of its 1243 surfels more than 5 mm below its lowest observed point, purity 15.5 %),
//! and are nothing a relit or rearranged scene should keep.
//!
//! The test is geometric and local: a surfel is beneath a support when the lowest observed
//! point above it (along +Y, within [`RADIUS`] horizontally, any label) is the background's,
//! faces up and lies more than [`MARGIN`] higher. The object's own underside is not caught (what
//! lies above it is the object), nor is an object on a lower shelf (the first thing above it is
//! the object itself or the upper shelf's underside, which faces down), nor the surfels of an
//! object's base sitting a few millimetres into the floor by reconstruction noise ([`MARGIN`]).

use super::init::PointCloud;
use std::collections::HashMap;

/// Horizontal search radius, metres: about two pixels' footprint of a default-size capture at
/// 2 m (320×240, ~1 cm voxels), so a surfel finds the observed surface above it.
pub const RADIUS: f32 = 0.015;

/// How far above the surfel the support's surface must lie, metres: more than a
/// reconstruction's depth noise at an object's base (stage 1's held-out median depth error is
/// 0.6-0.9 cm over the whole image, far less at a well-seen floor).
pub const MARGIN: f32 = 0.005;

/// The support's observed normal must be this close to +Y (cos 45°).
pub const UP_FACING: f32 = 0.7;

/// For each of `positions` (world frame of the state `cloud` was observed in, +Y up), whether
/// it lies beneath an observed up-facing background surface (see the module docs).
pub fn beneath_support(cloud: &PointCloud, positions: &[[f32; 3]]) -> Vec<bool> {
    let cell = |x: f32, z: f32| ((x / RADIUS).floor() as i32, (z / RADIUS).floor() as i32);
    let mut grid: HashMap<(i32, i32), Vec<u32>> = HashMap::new();
    for (i, p) in cloud.position.iter().enumerate() {
        grid.entry(cell(p[0], p[2])).or_default().push(i as u32);
    }
    positions
        .iter()
        .map(|p| {
            let (cx, cz) = cell(p[0], p[2]);
            // The lowest observed point above p within RADIUS horizontally.
            let mut lowest: Option<(f32, usize)> = None;
            for dx in -1..=1 {
                for dz in -1..=1 {
                    let Some(ids) = grid.get(&(cx + dx, cz + dz)) else {
                        continue;
                    };
                    for &k in ids {
                        let q = cloud.position[k as usize];
                        let (hx, hz) = (q[0] - p[0], q[2] - p[2]);
                        if q[1] <= p[1] || hx * hx + hz * hz > RADIUS * RADIUS {
                            continue;
                        }
                        if lowest.is_none_or(|(h, _)| q[1] < h) {
                            lowest = Some((q[1], k as usize));
                        }
                    }
                }
            }
            lowest.is_some_and(|(h, k)| {
                cloud.mask[k] == 0 && cloud.normal[k][1] >= UP_FACING && h - p[1] > MARGIN
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn push(c: &mut PointCloud, p: [f32; 3], n: [f32; 3], id: u8) {
        c.position.push(p);
        c.normal.push(n);
        c.rgb.push([0.5; 3]);
        c.mask.push(id);
        c.state.push(0);
        c.footprint.push(0.005);
    }

    /// A floor at y = 0 observed every 5 mm (but under the object, which hides it), an object
    /// (id 1): a 10 cm box on the floor seen on its top and sides, and an upper shelf
    /// (background) at y = 0.5 m over part of the floor, seen on its top and underside.
    fn scene() -> PointCloud {
        let mut c = PointCloud::default();
        let step = 0.005;
        for i in -60..=60 {
            for j in -60..=60 {
                let (x, z) = (i as f32 * step, j as f32 * step);
                let under_box = x.abs() < 0.05 && z.abs() < 0.05;
                if !under_box {
                    push(&mut c, [x, 0.0, z], [0.0, 1.0, 0.0], 0);
                }
                if x.abs() <= 0.05 && z.abs() <= 0.05 {
                    push(&mut c, [x, 0.1, z], [0.0, 1.0, 0.0], 1);
                }
                if x > 0.15 {
                    push(&mut c, [x, 0.5, z], [0.0, 1.0, 0.0], 0);
                    push(&mut c, [x, 0.48, z], [0.0, -1.0, 0.0], 0);
                }
            }
        }
        // The box's sides.
        for k in 0..=20 {
            let y = k as f32 * 0.005;
            for t in -10..=10 {
                let s = t as f32 * 0.005;
                push(&mut c, [0.05, y, s], [1.0, 0.0, 0.0], 1);
                push(&mut c, [-0.05, y, s], [-1.0, 0.0, 0.0], 1);
            }
        }
        c
    }

    #[test]
    fn mirror_images_under_the_floor_are_caught_and_nothing_else() {
        let c = scene();
        let cases: [([f32; 3], bool, &str); 8] = [
            (
                [0.1, -0.05, 0.0],
                true,
                "a mirror image under the floor beside the box",
            ),
            (
                [-0.2, -0.01, 0.1],
                true,
                "one just under the floor, farther off",
            ),
            (
                [0.0, 0.05, 0.0],
                false,
                "inside the box: the box is above it",
            ),
            (
                [0.02, 0.0, 0.01],
                false,
                "the box's underside: the box is above it",
            ),
            (
                [0.06, -0.003, 0.0],
                false,
                "the base sunk 3 mm into the floor: within the margin",
            ),
            (
                [0.3, 0.1, 0.0],
                false,
                "on the floor under the shelf: the shelf's underside is first",
            ),
            (
                [0.3, 0.49, 0.0],
                true,
                "inside the shelf board: its top is first above it",
            ),
            ([2.0, -0.5, 0.0], false, "nothing observed above it"),
        ];
        let positions: Vec<[f32; 3]> = cases.iter().map(|c| c.0).collect();
        let flags = beneath_support(&c, &positions);
        for ((p, want, what), got) in cases.iter().zip(flags) {
            assert_eq!(got, *want, "{what} at {p:?}");
        }
    }
}
