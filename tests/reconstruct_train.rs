//! The stage-1 training loop on a synthetic two-state capture made by the splatting kernel
//! itself: a textured floor and a textured box that moves between the states. Because the
//! observations are exactly what the model can render, the loop must (1) recover an object pose
//! that starts off by centimetres and degrees from the splatting gradients alone, and (2) fix a
//! corrupted appearance and geometry well beyond its starting error.

use glam::{Quat, Vec3};
use lightfuse::io::dataset::Observation;
use lightfuse::scene::synthetic::SplitMix;
use lightfuse::scene::transform;
use lightfuse::scene::{Camera, Component, Rigid, Surfels, SH_C0};
use lightfuse::splat::{self, Placement};
use lightfuse::stages::reconstruct::train::{Model, PoseGradient, RawComponent, Settings, Trainer};

fn push_patch(s: &mut Surfels, rng: &mut SplitMix, centre: Vec3, normal: Vec3, half: f32, h: f32) {
    let q = Quat::from_rotation_arc(Vec3::Z, normal.normalize());
    let n = (2.0 * half / h).round() as i32;
    for i in 0..n {
        for j in 0..n {
            let u = -half + (i as f32 + 0.5) * h;
            let v = -half + (j as f32 + 0.5) * h;
            let p = centre + q * Vec3::new(u, v, 0.0);
            // Blocky texture (4×4 cells per patch) so poses are observable from colour.
            let cell = ((i * 4 / n) + (j * 4 / n)) % 2;
            let base = if cell == 0 { 0.8 } else { 0.2 };
            let c = [base, rng.range(0.2, 0.8), 1.0 - base];
            s.push(
                p.to_array(),
                q.to_array(),
                [h, h],
                0.95,
                &[c.map(|x| (x - 0.5) / SH_C0)],
                c,
                0.0,
                0.5,
            );
        }
    }
}

fn scene() -> Vec<Component> {
    let mut rng = SplitMix(3);
    let mut floor = Surfels::with_sh_degree(0);
    push_patch(&mut floor, &mut rng, Vec3::ZERO, Vec3::Y, 1.0, 0.04);
    let mut boxy = Surfels::with_sh_degree(0);
    let c = Vec3::new(0.0, 0.15, 0.0);
    for n in [Vec3::X, -Vec3::X, Vec3::Y, Vec3::Z, -Vec3::Z] {
        push_patch(&mut boxy, &mut rng, c + 0.15 * n, n, 0.15, 0.02);
    }
    vec![
        Component {
            name: "background".into(),
            id: 0,
            surfels: floor,
        },
        Component {
            name: "box".into(),
            id: 1,
            surfels: boxy,
        },
    ]
}

fn camera(angle: f32, w: u32, h: u32) -> Camera {
    let eye = [1.6 * angle.cos(), 1.2, 1.6 * angle.sin()];
    Camera::look_at(eye, [0.0, 0.1, 0.0], w, h, 60.0)
}

/// What a capture of the components placed by `pose` would hold.
fn observe(
    components: &[Component],
    pose: Rigid,
    state: usize,
    view: usize,
    cam: Camera,
) -> Observation {
    let place = [
        Placement::world(&components[0].surfels),
        Placement {
            surfels: &components[1].surfels,
            transform: pose,
        },
    ];
    let full = splat::forward(&place, &cam).image;
    let object = splat::forward(&place[1..], &cam).image;
    let n = full.pixels();
    let covered = |i: usize| full.alpha[i] > 0.5;
    Observation {
        state,
        view,
        camera: cam,
        rgb: full.color.clone(),
        depth: (0..n)
            .map(|i| if covered(i) { full.depth[i] } else { 0.0 })
            .collect(),
        normal: (0..n)
            .map(|i| {
                let v = Vec3::from_array(full.normal[i]);
                if covered(i) {
                    v.normalize_or_zero().to_array()
                } else {
                    [0.0; 3]
                }
            })
            .collect(),
        mask: (0..n)
            .map(|i| {
                let front = object.alpha[i] > 0.5 && object.depth[i] <= full.depth[i] + 1e-3;
                (covered(i) && front) as u8
            })
            .collect(),
    }
}

fn frozen_surfels(iterations: u32) -> Settings {
    Settings {
        iterations,
        lr_position_init: 1e-20,
        lr_position_final: 1e-20,
        lr_rotation: 0.0,
        lr_scale: 0.0,
        lr_opacity: 0.0,
        lr_sh_dc: 0.0,
        lr_pose_translation: 1e-3,
        lr_pose_rotation: 2e-3,
        lr_colour: 0.0,
        pose_from: 0,
        depth_normal_from: u32::MAX,
        densify_from: u32::MAX,
        ..Settings::fast()
    }
}

fn angle_deg(a: &Rigid, b: &Rigid) -> f32 {
    let q = a.quat().normalize().inverse() * b.quat().normalize();
    2.0 * q.w.abs().min(1.0).acos().to_degrees()
}

fn distance(a: &Rigid, b: &Rigid) -> f32 {
    (Vec3::from_array(a.translation) - Vec3::from_array(b.translation)).length()
}

/// The box's pose in state 1 (state 0 is the reference), and six views of each state around
/// the scene at 64×48; state k's cameras turned by `turn`·k radians from state 0's.
fn two_states(comps: &[Component], turn: f32) -> (Rigid, Vec<Vec<Observation>>) {
    let truth = Rigid {
        rotation: Quat::from_rotation_y(0.7).to_array(),
        translation: [0.3, 0.0, -0.2],
    };
    let obs = [Rigid::IDENTITY, truth]
        .iter()
        .enumerate()
        .map(|(k, &pose)| {
            (0..6)
                .map(|v| {
                    let a = v as f32 * 1.047 + turn * k as f32;
                    observe(comps, pose, k, v, camera(a, 64, 48))
                })
                .collect()
        })
        .collect();
    (truth, obs)
}

/// Adds an opaque grey 1 cm surfel at `p` oriented `q` to `s` (a label test's hand-over).
fn push_grey(s: &mut Surfels, p: [f32; 3], q: [f32; 4]) {
    let sh = vec![[0.0; 3]; s.sh_stride()];
    s.push(p, q, [0.01; 2], 1.0, &sh, [0.5; 3], 0.0, 0.5);
}

/// The box's poses in both states after training `comps` on `obs` with `settings` from
/// `start` (its pose in state 1; identity in the reference state 0).
fn trained_poses(
    comps: &[Component],
    obs: &[Vec<Observation>],
    start: Rigid,
    settings: Settings,
) -> [Rigid; 2] {
    let model = Model::new(
        comps
            .iter()
            .map(|c| RawComponent::from_component(c, 2))
            .collect(),
        vec![vec![Rigid::IDENTITY], vec![start]],
    );
    let iterations = settings.iterations;
    let mut trainer = Trainer::new(settings, model);
    let views: Vec<Vec<&Observation>> = obs.iter().map(|v| v.iter().collect()).collect();
    for _ in 0..iterations {
        trainer.step(&views);
    }
    [trainer.model.poses[0][0], trainer.model.poses[1][0]]
}

#[test]
fn poses_are_recovered_from_splatting_gradients() {
    let comps = scene();
    let (truth, obs) = two_states(&comps, 0.0);
    let start = transform::perturb(&truth, [0.02, 0.0, -0.015], [0.0, 0.05, 0.0]);
    let (e_t0, e_r0) = (distance(&start, &truth), angle_deg(&start, &truth));
    let [reference, est] = trained_poses(&comps, &obs, start, frozen_surfels(600));
    let (e_t, e_r) = (distance(&est, &truth), angle_deg(&est, &truth));
    eprintln!("pose error: {e_t0:.4} m / {e_r0:.2}° -> {e_t:.4} m / {e_r:.2}°");
    // Started 2.5 cm / 2.9° off (measured end: 0.5 mm / 0.00°; 0.5 mm / 0.06° turning about the
    // placed origin rather than the box's centre). The captures are exact renders,
    // so the optimum is the truth; what is left is Adam's step size (lr 1e-3 m, 2e-3 rad)
    // jittering about it: bounded by a few mm and a few tenths of a degree.
    assert!(
        e_t < 0.005 && e_r < 0.5,
        "from {e_t0:.4} m / {e_r0:.2}° to {e_t:.4} m / {e_r:.2}°"
    );
    // The reference state's poses never move.
    assert_eq!(reference, Rigid::IDENTITY);
}

/// State 1 lit so that no colour matrix explains it: a shadow whose edge stands still in the
/// world (x > 0.3: across the middle of the moved box and the floor beside it) darkens its
/// captures to a quarter, as a lamp's or the sun's shadow does when an object is moved into
/// it. From the start of the test above, the lighting-free pose gradient
/// ([`PoseGradient::Geometry`]: coverage, depth, normal terms) recovers the pose as well as it
/// is recovered without the shadow (measured: 0.2 mm / 0.00°; the photometric gradient, every
/// term, 0.8 mm / 0.19°: with the surfels frozen at the truth the shadow's pull is small).
/// The bound is the test above's. (On a real capture the geometry gradient did worse than the
/// photometric one: `Settings::fast`.)
#[test]
fn a_moved_shadow_does_not_pull_the_pose_with_the_lighting_free_gradient() {
    let comps = scene();
    let (truth, mut obs) = two_states(&comps, 0.0);
    for o in &mut obs[1] {
        let w = o.camera.w as usize;
        for i in 0..o.rgb.len() {
            let z = o.depth[i];
            let (x, y) = ((i % w) as f32 + 0.5, (i / w) as f32 + 0.5);
            if z > 0.0 && o.camera.pixel_to_world(x, y, z)[0] > 0.3 {
                o.rgb[i] = o.rgb[i].map(|c| 0.25 * c);
            }
        }
    }
    let start = transform::perturb(&truth, [0.02, 0.0, -0.015], [0.0, 0.05, 0.0]);
    let run = |gradient: PoseGradient| {
        let settings = Settings {
            pose_gradient: gradient,
            ..frozen_surfels(600)
        };
        let [_, est] = trained_poses(&comps, &obs, start, settings);
        (distance(&est, &truth), angle_deg(&est, &truth))
    };
    let (t_geo, r_geo) = run(PoseGradient::Geometry);
    let (t_pho, r_pho) = run(PoseGradient::Photometric);
    eprintln!(
        "from {:.4} m / {:.2}°: geometry {t_geo:.4} m / {r_geo:.2}°, photometric {t_pho:.4} m / {r_pho:.2}°",
        distance(&start, &truth),
        angle_deg(&start, &truth)
    );
    assert!(
        t_geo < 0.005 && r_geo < 0.5,
        "geometry: {t_geo} m / {r_geo}°"
    );
}

/// A state lit differently overall (captures = the reference appearance through a colour
/// matrix): the state's colour matrix learns it from the rendered-image gradient alone, and the
/// other state is untouched.
#[test]
fn a_states_colour_matrix_is_recovered() {
    let comps = scene();
    // Warmer and darker, with some cross-talk between channels.
    let truth: [f32; 9] = [1.2, 0.1, 0.0, 0.0, 0.9, 0.05, 0.0, 0.0, 0.7];
    let obs: Vec<Vec<Observation>> = (0..2)
        .map(|k| {
            (0..6)
                .map(|v| {
                    let mut o = observe(
                        &comps,
                        Rigid::IDENTITY,
                        k,
                        v,
                        camera(v as f32 * 1.047, 64, 48),
                    );
                    if k == 1 {
                        for c in &mut o.rgb {
                            *c = [0, 1, 2].map(|r| {
                                truth[3 * r] * c[0]
                                    + truth[3 * r + 1] * c[1]
                                    + truth[3 * r + 2] * c[2]
                            });
                        }
                    }
                    o
                })
                .collect()
        })
        .collect();
    let model = Model::new(
        comps
            .iter()
            .map(|c| RawComponent::from_component(c, 2))
            .collect(),
        vec![vec![Rigid::IDENTITY]; 2],
    );
    let settings = Settings {
        lr_pose_translation: 0.0,
        lr_pose_rotation: 0.0,
        lr_colour: 5e-3,
        ..frozen_surfels(600)
    };
    let mut trainer = Trainer::new(settings, model);
    let views: Vec<Vec<&Observation>> = obs.iter().map(|v| v.iter().collect()).collect();
    for _ in 0..600 {
        trainer.step(&views);
    }
    let m = trainer.model.colour[1];
    let worst = m
        .iter()
        .zip(&truth)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    eprintln!("colour matrix {m:?} (truth {truth:?}), worst entry error {worst:.4}");
    // Started 0.3 off at worst; Adam (lr 5e-3) jitters about the optimum by a few steps, and the
    // L1 + D-SSIM optimum is the truth, since the captures are exact renders.
    assert!(worst < 0.03, "{m:?} vs {truth:?}");
    assert_eq!(
        trainer.model.colour[0],
        lightfuse::stages::reconstruct::train::IDENTITY3
    );
}

fn psnr(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    let se: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| (0..3).map(|k| ((x[k] - y[k]) as f64).powi(2)).sum::<f64>())
        .sum();
    -10.0 * (se / (3 * a.len()) as f64).log10()
}

#[test]
fn training_repairs_a_corrupted_reconstruction() {
    let comps = scene();
    let obs: Vec<Vec<Observation>> = vec![(0..7)
        .map(|v| {
            observe(
                &comps,
                Rigid::IDENTITY,
                0,
                v,
                camera(v as f32 * 0.9, 64, 48),
            )
        })
        .collect()];
    let held = observe(&comps, Rigid::IDENTITY, 0, 99, camera(0.45, 64, 48));
    // Corrupt: colours scrambled, centres jittered by up to 1 cm, opacities halved.
    let mut rng = SplitMix(9);
    let mut bad = comps.clone();
    for c in &mut bad {
        let s = &mut c.surfels;
        for i in 0..s.len() {
            s.sh[i] = [
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
            ];
            for k in 0..3 {
                s.position[i][k] += rng.range(-0.01, 0.01);
            }
            s.opacity[i] *= 0.5;
        }
    }
    let model = Model::new(
        bad.iter()
            .map(|c| RawComponent::from_component(c, 1))
            .collect(),
        vec![vec![Rigid::IDENTITY]],
    );
    let render =
        |m: &Model| lightfuse::stages::reconstruct::train::render_state(m, 0, &held.camera);
    let before = psnr(&render(&model).color, &held.rgb);
    let settings = Settings {
        iterations: 400,
        densify_from: u32::MAX,
        ..Settings::fast()
    };
    let mut trainer = Trainer::new(settings, model);
    let views: Vec<Vec<&Observation>> = obs.iter().map(|v| v.iter().collect()).collect();
    let first = trainer.step(&views).total;
    let mut last = first;
    for _ in 1..400 {
        last = trainer.step(&views).total;
    }
    let after = psnr(&render(&trainer.model).color, &held.rgb);
    eprintln!("held-out PSNR {before:.2} -> {after:.2} dB, loss {first:.4} -> {last:.4}");
    // A view no iteration saw must improve a lot: measured 14.9 -> 28.6 dB here (display-space
    // L_RGB); +10 dB leaves room for other seeds and thread counts without letting a loop that
    // barely learns pass.
    assert!(
        after > before + 10.0,
        "held-out PSNR {before:.2} -> {after:.2} dB"
    );
    assert!(last < 0.5 * first, "loss {first} -> {last}");
}

/// Labels over training (issue 15): the share of the box's true surface whose nearest surfel
/// is a box surfel ([`lightfuse::eval::labels::label_shares`]) must not fall while the loop
/// trains everything, densifies and prunes. Two starts of the moved state's pose: 1.5 cm and
/// 3° off with pose refinement (the rendered alignment's errors before the polish), and 4 cm
/// and 8.6° off without it (a pose stage 1 got wrong: the box's surfels are then pulled by two
/// inconsistent states, where a background could grow into it). The box stands on the floor,
/// so floor surfels touch its sides. The start is corrupted (colours, centres, opacities) so
/// every surfel moves.
#[test]
fn labels_hold_over_training() {
    let comps = scene();
    let (truth, obs) = two_states(&comps, 0.3);
    let mut rng = SplitMix(21);
    let mut bad = comps.clone();
    for c in &mut bad {
        let s = &mut c.surfels;
        for i in 0..s.len() {
            for k in 0..3 {
                s.sh[i][k] += rng.range(-0.5, 0.5);
                s.position[i][k] += rng.range(-0.005, 0.005);
            }
            s.opacity[i] *= 0.7;
        }
    }
    let objects = [("box".to_string(), 1)];
    let reference: Vec<&Observation> = obs[0].iter().collect();
    let share =
        |c: &[Component]| lightfuse::eval::labels::label_shares(c, &reference, &objects)[0].1;
    let near = transform::perturb(&truth, [0.01, 0.0, -0.011], [0.0, 0.052, 0.0]);
    let far = transform::perturb(&truth, [0.03, 0.0, -0.03], [0.0, 0.15, 0.0]);
    for (start, pose_from) in [(near, 100), (far, u32::MAX)] {
        let model = Model::new(
            bad.iter()
                .map(|c| RawComponent::from_component(c, 2))
                .collect(),
            vec![vec![Rigid::IDENTITY], vec![start]],
        );
        let iterations = 600;
        let settings = Settings {
            iterations,
            densify_from: 100,
            densify_until: 400,
            densify_every: 100,
            pose_from,
            ..Settings::fast()
        };
        let mut trainer = Trainer::new(settings, model);
        let views: Vec<Vec<&Observation>> = obs.iter().map(|v| v.iter().collect()).collect();
        let mut shares = vec![share(&trainer.model.scene_components())];
        for it in 1..=iterations {
            trainer.step(&views);
            if it % 100 == 0 {
                shares.push(share(&trainer.model.scene_components()));
            }
        }
        let pose = trainer.model.poses[1][0];
        eprintln!(
            "label share every 100 iterations: {shares:.4?}; {} surfels; pose {:.4} m / {:.2}° off",
            trainer.model.surfel_count(),
            distance(&pose, &truth),
            angle_deg(&pose, &truth)
        );
        // Measured: 1.0 at the start and 0.9989-1.0 at every checkpoint in both cases (edge
        // pixels are left out and orientation counts, so the seam is not ambiguous). 1 % below
        // the start allows a few seam surfels cloned or pruned on either side.
        for s in &shares {
            assert!(*s >= shares[0] - 0.01, "label share fell: {shares:?}");
        }
        // The measure sees a fall when there is one: the box's lowest 10 cm handed to the floor
        // (measured 0.868; a fall of 3 points is asked).
        let mut moved = trainer.model.scene_components();
        let (floor, boxy) = moved.split_at_mut(1);
        let (floor, boxy) = (&mut floor[0].surfels, &mut boxy[0].surfels);
        for i in 0..boxy.len() {
            if boxy.position[i][1] < 0.1 {
                push_grey(floor, boxy.position[i], boxy.rotation[i]);
                boxy.position[i][1] += 100.0;
            }
        }
        let fallen = share(&moved);
        eprintln!("the lowest 10 cm handed to the floor: share {fallen:.4}");
        assert!(
            fallen < shares[0] - 0.03,
            "a handed-over strip went unseen: {fallen}"
        );
        // The other direction: the box's surfels lie on its own surface (purity), and a ring
        // of floor 20 cm wide around its foot handed to the box is seen (measured: 1.0 clean,
        // 0.595 and 0.646 with the ring; a fall of 3 points is asked).
        let purity =
            |c: &[Component]| lightfuse::eval::labels::label_purity(c, &reference, &objects)[0].1;
        let trained = trainer.model.scene_components();
        let clean = purity(&trained);
        let mut grabbed = trained.clone();
        let (floor, boxy) = grabbed.split_at_mut(1);
        let (floor, boxy) = (&floor[0].surfels, &mut boxy[0].surfels);
        for i in 0..floor.len() {
            let p = floor.position[i];
            let r = p[0].abs().max(p[2].abs());
            if r > 0.15 && r < 0.35 {
                push_grey(boxy, p, floor.rotation[i]);
            }
        }
        let impure = purity(&grabbed);
        eprintln!("purity {clean:.4}; with a 20 cm ring of floor handed to the box {impure:.4}");
        assert!(clean > 0.99, "the box's surfels off its surface: {clean}");
        assert!(
            impure < clean - 0.03,
            "a grabbed ring of floor went unseen: {impure}"
        );
    }
}
