//! Stage 2 repairs damaged geometry. A surfel room (floor, two walls, a box that moves between
//! two states) stands for true shapes whose "captures" (planar depth, normals and object masks,
//! as a dataset holds them) are ray cast analytically; the surfel scene is then damaged the ways splat-trained surfels go wrong for ray tracing
//! (holes punched, discs inflated, normals tilted, opacities lowered) and refined by the stage-2
//! loop on the training views of both states. Every one of the five figures of
//! `docs/geometry-metrics.md`, measured on held-out views, must improve by the stated factor.
//!
//! The captures are rendered from the true shapes (rectangles and a box), as Cycles' pixel-centre
//! depth and normal passes are, so the intact surfel scene is not perfect either: its discs reach
//! past the true edges (false occlusion 42% of the few environment pixels, all at silhouettes)
//! and corners leak a little (0.5% of blocked shadow rays).
//!
//! Measured with these seeds (`cargo test --test refine -- --nocapture` prints them), damaged →
//! refined: median depth error 7.8 → 0.57 mm (13.6×), mean normal error 11.4° → 4.6° (2.5×),
//! holes 1.74% → 0.29% of surface pixels (5.9×), false occlusion 46.9% → 27.5% (1.7×), light
//! leaks 3.5% → 2.9% of 1,155 blocked shadow rays (1.2×). The asserted factors are about half
//! the measured ones (in log scale), so the test fails if the repair loses half its effect and
//! not on float reordering. Light leaks are the exception: what is left after the holes are
//! filled sits where the box meets the floor and a shadow ray runs along a face, which the
//! refinement does not restore to the intact scene's 0.5%; the test asks that no more rays leak
//! than before.

use glam::{Quat, Vec3};
use lightfuse::eval::geometry::{tally_state, GeometryFigures, LeakOptions};
use lightfuse::io::dataset::Observation;
use lightfuse::scene::synthetic::SplitMix;
use lightfuse::scene::{Camera, Component, Rigid, Surfels};
use lightfuse::stages::refine::train::{Refiner, Settings, TrainState};
use lightfuse::trace::TraceScene;

const SPACING: f32 = 0.04;

fn plane(
    s: &mut Surfels,
    rng: &mut SplitMix,
    origin: Vec3,
    a: Vec3,
    b: Vec3,
    (na, nb): (usize, usize),
) {
    let n = a.cross(b).normalize();
    let rot = Quat::from_mat3(&glam::Mat3::from_cols(a.normalize(), b.normalize(), n));
    for i in 0..na {
        for j in 0..nb {
            let ja = rng.range(-0.2, 0.2);
            let jb = rng.range(-0.2, 0.2);
            let p = origin
                + a.normalize() * (SPACING * (i as f32 + 0.5 + ja))
                + b.normalize() * (SPACING * (j as f32 + 0.5 + jb));
            s.push(
                p.to_array(),
                rot.normalize().to_array(),
                [SPACING, SPACING],
                0.95,
                &[[0.5, 0.5, 0.5]],
                [0.5; 3],
                0.0,
                0.5,
            );
        }
    }
}

/// Floor, back wall and left wall (background) and a 0.4 m box (object 1).
fn room() -> Vec<Component> {
    let mut rng = SplitMix(3);
    let mut bg = Surfels::with_sh_degree(0);
    plane(
        &mut bg,
        &mut rng,
        Vec3::new(-1.0, 0.0, 1.0),
        Vec3::X,
        Vec3::NEG_Z,
        (50, 50),
    );
    plane(
        &mut bg,
        &mut rng,
        Vec3::new(-1.0, 0.0, -1.0),
        Vec3::X,
        Vec3::Y,
        (50, 25),
    );
    plane(
        &mut bg,
        &mut rng,
        Vec3::new(-1.0, 0.0, -1.0),
        Vec3::Y,
        Vec3::Z,
        (25, 50),
    );
    let mut obj = Surfels::with_sh_degree(0);
    let c = Vec3::new(0.2, 0.2, 0.0);
    let h = 0.2;
    let k = (10, 10);
    for (o, a, b) in [
        (Vec3::new(-h, -h, h), Vec3::X, Vec3::Y),     // +Z face
        (Vec3::new(h, -h, -h), Vec3::NEG_X, Vec3::Y), // −Z face
        (Vec3::new(h, -h, h), Vec3::NEG_Z, Vec3::Y),  // +X face
        (Vec3::new(-h, -h, -h), Vec3::Z, Vec3::Y),    // −X face
        (Vec3::new(-h, h, h), Vec3::X, Vec3::NEG_Z),  // top
    ] {
        plane(&mut obj, &mut rng, c + o, a, b, k);
    }
    vec![
        Component {
            name: "background".into(),
            id: 0,
            surfels: bg,
        },
        Component {
            name: "box".into(),
            id: 1,
            surfels: obj,
        },
    ]
}

fn states() -> Vec<Vec<Rigid>> {
    let moved = Rigid {
        rotation: Quat::from_rotation_y(0.5).to_array(),
        translation: [-0.3, 0.0, 0.35],
    };
    vec![
        vec![Rigid::IDENTITY, Rigid::IDENTITY],
        vec![Rigid::IDENTITY, moved],
    ]
}

fn cameras() -> Vec<Camera> {
    let eyes = [
        [0.9, 0.8, 0.9],
        [0.2, 1.0, 0.95],
        [0.95, 0.6, 0.1],
        [-0.5, 0.9, 0.9],
        [0.6, 1.2, 0.5],
        [0.9, 0.4, 0.6],
        [0.0, 0.7, 0.9],
        [0.7, 0.9, -0.3],
        [0.95, 1.0, 0.95],
    ];
    eyes.iter()
        .map(|&e| Camera::look_at(e, [-0.3, 0.15, -0.4], 64, 48, 45.0))
        .collect()
}

/// The first hit of a ray with the true shapes the surfels stand for: the floor, the two walls
/// and the box placed by `boxt` (distance along the unit direction, world normal).
fn true_hit(o: Vec3, d: Vec3, boxt: &Rigid) -> Option<(f32, Vec3, u8)> {
    let mut best: Option<(f32, Vec3, u8)> = None;
    let mut take = |t: f32, n: Vec3, id: u8| {
        if t > 1e-4 && best.is_none_or(|(b, _, _)| t < b) {
            best = Some((t, n, id));
        }
    };
    // Axis-aligned rectangles of the background: (axis, plane value, ranges of the other two).
    let rects = [
        (1, 0.0, [(-1.0, 1.0), (-1.0, 1.0)]), // floor y = 0 (x, z)
        (2, -1.0, [(-1.0, 1.0), (0.0, 1.0)]), // back wall z = −1 (x, y)
        (0, -1.0, [(0.0, 1.0), (-1.0, 1.0)]), // left wall x = −1 (y, z)
    ];
    for (axis, value, ranges) in rects {
        let t = (value - o[axis]) / d[axis];
        let p = o + t * d;
        let others: Vec<usize> = (0..3).filter(|&k| k != axis).collect();
        if (0..2).all(|k| p[others[k]] >= ranges[k].0 && p[others[k]] <= ranges[k].1) {
            let mut n = Vec3::ZERO;
            n[axis] = 1.0;
            take(t, n, 0);
        }
    }
    // The box, slab test in its own frame.
    let inv = boxt.inverse();
    let q = Quat::from_array(inv.rotation);
    let (lo_o, lo_d) = (Vec3::from_array(inv.transform_point(o.to_array())), q * d);
    let (lo, hi) = (Vec3::new(0.0, 0.0, -0.2), Vec3::new(0.4, 0.4, 0.2));
    let (mut t0, mut t1, mut axis) = (f32::NEG_INFINITY, f32::INFINITY, 0);
    for k in 0..3 {
        let (a, b) = ((lo[k] - lo_o[k]) / lo_d[k], (hi[k] - lo_o[k]) / lo_d[k]);
        let (near, far) = (a.min(b), a.max(b));
        if near > t0 {
            t0 = near;
            axis = k;
        }
        t1 = t1.min(far);
    }
    if t0 <= t1 && t0 > 0.0 {
        let mut n = Vec3::ZERO;
        n[axis] = 1.0;
        take(t0, Quat::from_array(boxt.rotation) * n, 1);
    }
    best
}

/// Captures of the true shapes (as Cycles' pixel-centre depth and normal passes are): planar
/// depth and the normal facing the camera; 0 where the ray escapes.
fn capture(transforms: &[Rigid], state: usize) -> Vec<Observation> {
    cameras()
        .into_iter()
        .enumerate()
        .map(|(v, camera)| {
            let n = (camera.w * camera.h) as usize;
            let mut depth = vec![0.0; n];
            let mut normal = vec![[0.0; 3]; n];
            let mut mask = vec![0u8; n];
            for i in 0..n {
                let (x, y) = (i % camera.w as usize, i / camera.w as usize);
                let (o, d) = camera.planar_ray(x as f32 + 0.5, y as f32 + 0.5);
                let (o, d) = (Vec3::from_array(o), Vec3::from_array(d));
                if let Some((t, nn, id)) = true_hit(o, d, &transforms[1]) {
                    depth[i] = t;
                    mask[i] = id;
                    normal[i] = (if nn.dot(d) > 0.0 { -nn } else { nn }).to_array();
                }
            }
            Observation {
                state,
                view: v,
                camera,
                rgb: vec![[0.0; 3]; n],
                depth,
                normal,
                mask,
            }
        })
        .collect()
}

/// Holes punched, discs inflated, normals tilted and opacities lowered.
fn damage(components: &[Component]) -> Vec<Component> {
    let mut rng = SplitMix(11);
    components
        .iter()
        .map(|c| {
            let s = &c.surfels;
            // Holes: every surfel within 15 cm of ten random centres is removed.
            let centres: Vec<Vec3> = (0..10)
                .map(|_| Vec3::from_array(s.position[(rng.next_u64() % s.len() as u64) as usize]))
                .collect();
            let mut out = Surfels::with_sh_degree(0);
            for i in 0..s.len() {
                let p = Vec3::from_array(s.position[i]);
                if centres.iter().any(|q| q.distance(p) < 0.15) {
                    continue;
                }
                let mut rot = s.rotation[i];
                let mut scale = s.scale[i];
                let mut opacity = s.opacity[i];
                let r = rng.f32();
                if r < 0.05 {
                    scale = scale.map(|x| 2.5 * x);
                } else if r < 0.35 {
                    let axis = Vec3::new(rng.range(-1.0, 1.0), 0.0, rng.range(-1.0, 1.0));
                    let q = Quat::from_array(rot);
                    let tilt =
                        Quat::from_axis_angle(q * axis.normalize_or(Vec3::X), 25f32.to_radians());
                    rot = (tilt * q).normalize().to_array();
                } else if r < 0.55 {
                    opacity *= 0.3;
                }
                out.push(
                    s.position[i],
                    rot,
                    scale,
                    opacity,
                    s.sh_of(i),
                    s.base_color[i],
                    s.metallic[i],
                    s.roughness[i],
                );
            }
            Component {
                surfels: out,
                ..c.clone()
            }
        })
        .collect()
}

fn measure(components: &[Component], captures: &[Vec<Observation>]) -> GeometryFigures {
    let refs: Vec<&Surfels> = components.iter().map(|c| &c.surfels).collect();
    let scene = TraceScene::from_components(&refs);
    let mut all = lightfuse::eval::geometry::GeometryTally::default();
    for (k, tf) in states().iter().enumerate() {
        let placed = scene.place(tf);
        let every: Vec<&Observation> = captures[k].iter().collect();
        let held: Vec<&Observation> = captures[k].iter().filter(|o| o.view % 8 == 0).collect();
        all.merge(tally_state(
            &placed,
            &held,
            &every,
            4.0,
            &LeakOptions::default(),
        ));
    }
    all.figures()
}

#[test]
fn refine_repairs_a_damaged_scene() {
    let intact = room();
    let captures: Vec<Vec<Observation>> = states()
        .iter()
        .enumerate()
        .map(|(k, tf)| capture(tf, k))
        .collect();
    let damaged = damage(&intact);
    let truth = measure(&intact, &captures);
    let before = measure(&damaged, &captures);

    let mut settings = Settings::fast();
    settings.iterations = 300;
    settings.patches = 32;
    let mut refiner = Refiner::new(settings.clone(), &damaged);
    let train: Vec<TrainState> = states()
        .into_iter()
        .zip(&captures)
        .map(|(transforms, caps)| TrainState {
            views: caps.iter().filter(|o| o.view % 8 != 0).collect(),
            transforms,
        })
        .collect();
    for _ in 0..settings.iterations {
        refiner.step(&train);
    }
    let after = measure(&refiner.scene_components(), &captures);
    println!("intact  {truth:?}\ndamaged {before:?}\nrefined {after:?}");

    assert!(truth.holes < 0.01 && truth.light_leaks < 0.02, "{truth:?}");
    assert!(
        before.blocked_rays > 500,
        "too few blocked rays to judge: {before:?}"
    );
    assert!(after.depth_median_m < before.depth_median_m / 4.0, "depth");
    assert!(
        after.normal_mean_deg < before.normal_mean_deg / 1.6,
        "normals"
    );
    assert!(after.holes < before.holes / 2.5, "holes");
    assert!(
        after.false_occlusion < before.false_occlusion / 1.3,
        "false occlusion"
    );
    assert!(after.leaking_rays < before.leaking_rays, "leaks");
}
